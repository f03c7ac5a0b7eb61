"""The training loop: the paper's schedule, exact resume, rank-0 logging, PyTorch DDP across processes.

Per step: the global batch of objects comes from :class:`~depthnerf.train.batching.BatchPlan` (a function of
``(seed, step)``), each rank takes its contiguous share, and :func:`~depthnerf.train.step.train_step` encodes and
renders the rank's objects in one batch, each with its own BatchNorm statistics and generator (so a rank's result
does not depend on which other objects share its batch: 2 ranks x 2 objects equal 1 process x 4 objects). The
loss is pixelNeRF's: mean squared error of the coarse plus the fine colour (plus the optional depth loss);
gradients are averaged across ranks by DDP. BatchNorm running statistics (used only in eval mode) are merged
after each step as one process updating them with the whole batch would have them
(:class:`~depthnerf.distributed.NormMerge`), so they too do not depend on the number of ranks. A rank that stops
(its own error, a kill) stops the others with one line each (:func:`~depthnerf.distributed.peer_failure`).

On CUDA: bf16 autocast, fused Adam, channels-last encoder, pinned host batches, and the loss terms stay on the
device until a log step reads them (the only host synchronisation of the loop besides validation/checkpoints).

SIGTERM / SIGINT end the loop after the current step with a checkpoint of that step (:mod:`depthnerf.train.stop`);
the returned state then names the signal (``stopped_by``). A validation the signal skipped or abandoned is due in
that checkpoint (``validation_due``), and the resume runs it before its first step, so the validation records and
``best/`` are those of an uninterrupted run. Every start and resume appends one line to the run's
``launches.jsonl`` (:func:`~depthnerf.train.run_log.record_launch`: step, world size, device, determinism).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import inspect
import json
import math
import signal
import sys
import time
from pathlib import Path

import torch
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader
from tqdm import tqdm

from depthnerf.config_io import to_dict
from depthnerf.crash_hook import crash_point
from depthnerf.data.card import card_path, read_dataset_card
from depthnerf.data.protocol import check_validation_views, record_views, validation_views_note
from depthnerf.data.srn import index_split
from depthnerf.data.symmetry import dataset_plane
from depthnerf.data.synth.framing import dataset_framing
from depthnerf.data.view_store import ViewStore
from depthnerf.depth.prior import PriorSource, open_prior, portable_prior, weights_mismatch
from depthnerf.distributed import DistInfo, NormMerge, barrier, checked_together, peer_failure
from depthnerf.errors import DepthnerfError, refusal
from depthnerf.files import write_text_atomic
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.spec import InferenceSpec
from depthnerf.train import checkpoint as ckpt
from depthnerf.train import memory
from depthnerf.train.batching import BatchPlan, StepSampler, check_world_split, collate_packed, step_keys
from depthnerf.train.config import LogConfig, TrainConfig, inference_spec
from depthnerf.train.freeze import freeze_parameters, hold_frozen_modules, trainable_parameters
from depthnerf.train.items import TrainItems, ready_view_store
from depthnerf.train.run_log import RunLog, check_run_dir, read_run_record, record_launch, run_lock
from depthnerf.train.step import BatchLoss, compiled_fields, train_step
from depthnerf.train.stop import STOP_SIGNALS, StopRequest, exit_code, signal_name
from depthnerf.train.validator import ValidationPhase, Validator
from depthnerf.train.warm_start import warm_start

__all__ = ["learning_rate", "train"]


def learning_rate(cfg: TrainConfig, plan: BatchPlan, step: int) -> float:
    """The learning rate of ``step``: ``lr`` in phase 1; afterwards ``lr * decay^(whole epochs since phase 2
    began)`` (``exponential``) or ``lr_final + (lr - lr_final) * (1 + cos(pi * t)) / 2`` with
    ``t = (step - bbox_steps) / (max_steps - bbox_steps)`` (``cosine``)."""
    s = cfg.schedule
    if step < s.bbox_steps:
        return s.lr
    if s.lr_schedule == "cosine":
        t = min(1.0, (step - s.bbox_steps) / max(s.max_steps - s.bbox_steps, 1))
        return s.lr_final + (s.lr - s.lr_final) * 0.5 * (1.0 + math.cos(math.pi * t))
    if s.lr_decay == 1.0:
        return s.lr
    epochs = (plan.consumed(step) - plan.consumed(s.bbox_steps)) // plan.num_objects  # integers: exact at the ends
    return s.lr * s.lr_decay ** epochs


def _trained_weights_hash(run_dir: Path) -> str | None:
    """The prior's weights hash a run recorded in its ``prior.json`` (None: none recorded, or no prior)."""
    recorded = (read_run_record(run_dir / "prior.json") or {}).get("weights_hash")
    return recorded if isinstance(recorded, str) else None


def _object_ids_digest(records: list) -> str:
    """SHA-256 of the training objects' ids in the order the batches index them."""
    return hashlib.sha256("\n".join(r.object_id for r in records).encode()).hexdigest()


def _check_same_objects(run_dir: Path, root: Path, records: list) -> None:
    """On resume: the data must hold the training objects the run trained on (its ``data_card.json``: their number,
    and their ids where recorded), else its batches (a function of seed, step and object index) would silently
    change; a moved copy passes."""
    path = run_dir / "data_card.json"
    card = read_run_record(path)
    if card is None:
        return  # no record to compare with
    trained, ids = card.get("train_objects"), card.get("train_object_ids_sha256")
    again = "resume with --data naming the run's own data, or choose another --out for a new run"
    if isinstance(trained, int) and trained != len(records):
        raise DepthnerfError(f"{path}: the run trained on {trained} training objects, but {root} holds "
                             f"{len(records)}; {again}")
    if isinstance(ids, str) and ids != _object_ids_digest(records):
        raise DepthnerfError(f"{path}: the run trained on other training objects (other object ids) than {root} "
                             f"holds; {again}")


def _write_run_files(run_dir: Path, cfg: TrainConfig, prior_source: PriorSource, records: list,
                     card: dict | None) -> None:
    write_text_atomic(run_dir / "config.json", json.dumps(to_dict(cfg), indent=1) + "\n")
    prior = {"estimator": cfg.prior.estimator, **(prior_source.provenance or {})}
    write_text_atomic(run_dir / "prior.json", json.dumps(prior, indent=1, default=str) + "\n")
    root = Path(cfg.data.root)
    data_card = {"root": str(root.resolve()), "category": cfg.data.category, "train_objects": len(records),
                 "train_object_ids_sha256": _object_ids_digest(records), "resolution": cfg.data.resolution,
                 "dataset_card": card}
    write_text_atomic(run_dir / "data_card.json", json.dumps(data_card, indent=1) + "\n")


def train(cfg: TrainConfig, run_dir: Path, info: DistInfo, *, resume: bool = False, progress: bool = True,
          validate: Validator | None = None, compile: bool = False, compile_step: bool = False) -> dict:
    """Train (or resume) a run in ``run_dir``; returns the final state as a dict.

    ``run_dir`` must be new, empty or a run folder (:func:`~depthnerf.train.run_log.check_run_dir`); rank 0
    holds its lock (:func:`~depthnerf.train.run_log.run_lock`) from before it writes anything until it returns.

    ``compile``: the fields' MLPs run through ``torch.compile`` (:func:`depthnerf.train.step.compiled_fields`);
    ``compile_step``: the whole loss (encoder, render, loss terms; forward and backward) runs as one compiled graph
    (:func:`depthnerf.train.step.compiled_losses`; CUDA graphs on CUDA). Both are settings of how to run, not stored
    in the run's config (same results up to float rounding).

    ``validate`` scores the model on the val objects every ``log.val_every`` steps (``depthnerf train`` passes
    :func:`depthnerf.eval.validation.validate`; None: no validation).
    """
    with contextlib.ExitStack() as hold, peer_failure(info, "training (the run keeps its last checkpoint: "
                                                      "--resume continues it)"):
        return _train(cfg, Path(run_dir), info, hold, resume=resume, progress=progress, validate=validate,
                      compile=compile, compile_step=compile_step)


def _train(cfg: TrainConfig, run_dir: Path, info: DistInfo, hold: contextlib.ExitStack, *, resume: bool,
           progress: bool, validate: Validator | None, compile: bool, compile_step: bool) -> dict:
    """:func:`train`'s body; ``hold`` keeps the run's lock until :func:`train` returns."""
    sched = cfg.schedule
    try:  # from the config, the world size and the run's last checkpoint: every rank refuses alike, rank 0 prints it
        check_world_split(sched.bbox_steps, sched.objects_phase1, sched.objects_phase2, sched.max_steps, info.world,
                          start=ckpt.last_step(run_dir / "checkpoints") if resume else 0)
    except DepthnerfError as err:
        raise refusal(str(err), info.rank) from None
    with checked_together(info, "checking the run's settings, data and folder"):  # agreed by the ranks: one line
        memory.check_step_fits(cfg, info)
        ckpt_root = run_dir / "checkpoints"
        latest = ckpt.latest_checkpoint(ckpt_root) if ckpt_root.exists() else None
        if latest is not None and not resume:
            raise DepthnerfError(f"{run_dir}: already holds a run (last checkpoint {latest.name}); pass --resume to "
                                 "continue it or choose another --out")
        check_run_dir(run_dir, latest is not None)
        if cfg.data.view_store:  # before the run writes its folder
            ViewStore(cfg.data.view_store, cfg.data.resolution, cfg.data.pixel_center).check()
        root, cat = Path(cfg.data.root), cfg.data.category
        try:
            records = index_split(root, cat, "train", mesh_body=False).objects
        except DepthnerfError as err:
            if resume and latest is None:  # most likely a mistyped --out: say so, not only what the data lacks
                raise DepthnerfError(f"{err} (--resume found no checkpoint in {run_dir}, so a new run would start "
                                     "there: check --out)") from None
            raise
        most = max(cfg.data.source_views)
        least = most + 1  # pixelNeRF's items need their source views and another view as the target
        single = next((r for r in records if r.num_views < least), None)
        if single is not None:
            plural = "s" if single.num_views != 1 else ""
            counts = ",".join(map(str, cfg.data.source_views))
            raise DepthnerfError(f"{single.path}: has {single.num_views} view{plural}; a training object needs at "
                                 f"least {least} (--data.source_views {counts} conditions on up to {most}, and a "
                                 "target); remove it from the train split")
        if latest is not None:
            _check_same_objects(run_dir, root, records)
        trained_hash = _trained_weights_hash(run_dir) if latest is not None else None
        cfg = dataclasses.replace(cfg, prior=portable_prior(cfg.prior, trained_hash))
        prior_source = open_prior(cfg.prior, data_root=root, resolution=cfg.data.resolution, records=records)
        mismatch = weights_mismatch(prior_source, trained_hash, str(run_dir / "prior.json"))
        if mismatch is not None:
            raise DepthnerfError(f"{mismatch}; restore the weights the run began with to resume it")
        val_records = []
        if cfg.log.val_every > 0 and info.is_main and validate is not None:
            try:
                val_records = index_split(root, cat, "val", mesh_body=False).objects[: cfg.log.val_objects]
            except DepthnerfError as err:
                raise DepthnerfError(f"{err} (validation needs a val split; pass --log.val_every 0 to train without)"
                                     ) from None
            prior_source.check(val_records)
            inputs = cfg.log.val_input_views or None
            for record in val_records:  # a val object without the input views: one line now, not at the first validation
                record_views(record, inputs=inputs, flag="--log.val_input_views")
            val_counts = [(str(r.path), r.num_views) for r in val_records]
            if tuple(cfg.log.val_views) != LogConfig().val_views:  # the presets' (SRN's) fall back with the note
                check_validation_views(cfg.log.val_views, val_counts)
            views_note = validation_views_note(cfg.log.val_views, val_counts, inputs)
            if views_note is not None:
                print(views_note, file=sys.stderr, flush=True)
        plane = None
        if cfg.model.mirror:
            plane, plane_from = dataset_plane(root, cat, cfg.data.symmetry_plane)
            if info.is_main:
                print(f"mirror conditioning: symmetry plane {plane} ({plane_from})", file=sys.stderr, flush=True)
        if cfg.model.encoder.norm_stats == "batch" and info.world > 1 and info.is_main:
            print(f"note: --model.encoder.norm_stats batch pools the encoder's BatchNorm statistics over each rank's "
                  f"objects, so this run's result depends on its {info.world} ranks", file=sys.stderr, flush=True)
        card = read_dataset_card(root, cat)
        framing = dataset_framing(card, str(card_path(root, cat)))
        spec = inference_spec(cfg, (prior_source.provenance or {}).get("weights_hash"), framing)
        near, far = spec.z_range

        torch.manual_seed(cfg.seed)
        model = PixelNeRF(cfg.model, depth_aware=cfg.prior.enabled).to(info.device)
        warm = None
        if latest is None and cfg.init_from is not None:
            warm = warm_start(model, cfg.init_from, cfg.model, cfg.prior.enabled, cat)
        if info.device.type == "cuda":
            model.encoder.to(memory_format=torch.channels_last)
        cuda = info.device.type == "cuda"
        frozen = freeze_parameters(model, cfg.schedule.freeze)
        optimizer = torch.optim.Adam(trainable_parameters(model), lr=cfg.schedule.lr, fused=cuda or None)
        model_cfg = to_dict(cfg.model)
        state = ckpt.TrainingState(step=0, best_psnr=-math.inf)
        if latest is not None:
            state = ckpt.load_checkpoint(latest, model, optimizer, model_cfg)
        start = state.step
        if info.is_main:
            print(f"resumed from step {start} ({latest})" if latest is not None else
                  f"started a new run in {run_dir} ({'no checkpoint found' if resume else 'new folder'})",
                  file=sys.stderr, flush=True)
            if start >= cfg.schedule.max_steps:
                print(f"nothing to train: the run is at step {start}, --max-steps is {cfg.schedule.max_steps} (pass a "
                      "larger --max-steps to continue it)", file=sys.stderr, flush=True)
    if info.is_main:
        hold.enter_context(run_lock(run_dir))  # before the first write: a second process stops here
        restored = ckpt.restore_best(ckpt_root, state) if latest is not None else None
        if restored:
            print(restored, file=sys.stderr, flush=True)
        _write_run_files(run_dir, cfg, prior_source, records, card)
        if warm is not None:
            write_text_atomic(run_dir / "init_from.json", warm.to_json())
            in_all = f", {warm.total_steps} in all" if warm.total_steps != warm.step else ""
            print(f"warm start: the network's weights from {warm.path} (step {warm.step}{in_all})", file=sys.stderr,
                  flush=True)
        if frozen:
            held = sum(p.numel() for p in model.parameters() if not p.requires_grad)
            print(f"frozen (--schedule.freeze {','.join(cfg.schedule.freeze)}): {len(frozen)} parameter tensors, "
                  f"{held:,} of {sum(p.numel() for p in model.parameters()):,} values", file=sys.stderr, flush=True)
        note = record_launch(run_dir, start, info.world, str(info.device),
                             deterministic=torch.are_deterministic_algorithms_enabled())
        if note:
            print(note, file=sys.stderr, flush=True)
    barrier(info)

    loss_module = BatchLoss(model, cfg.render, cfg.schedule.depth_loss_weight, cfg.schedule.background_opacity_weight,
                            compiled_fields(model) if compile else None, "inductor" if compile_step else None,
                            foreground_weight=cfg.schedule.foreground_opacity_weight,
                            depth_min_opacity=cfg.schedule.depth_loss_min_opacity)
    # buffers: merged after each step (NormMerge), not rank 0's broadcast before each forward (the flag's newer name
    # where torch has it)
    no_sync = "forward_sync_buffers" if "forward_sync_buffers" in inspect.signature(
        DistributedDataParallel).parameters else "broadcast_buffers"
    runner = DistributedDataParallel(loss_module, **{no_sync: False}) if info.world > 1 else loss_module
    norms = NormMerge(model, info)
    s = cfg.schedule
    plan = BatchPlan(num_objects=len(records), seed=cfg.seed, bbox_steps=s.bbox_steps,
                     objects_phase1=s.objects_phase1, objects_phase2=s.objects_phase2,
                     source_views=cfg.data.source_views)
    items = TrainItems(records, prior_source, resolution=cfg.data.resolution, target_views=cfg.data.target_views,
                       rays_per_object=s.rays_per_object, target_priors=s.depth_loss_weight > 0,
                       pixel_center=cfg.data.pixel_center, symmetry_plane=plane,
                       mirror_dropout=s.mirror_dropout, mirror_jitter=s.mirror_jitter, view_store=ready_view_store(cfg.data, records, info),
                       channel_permute=cfg.data.channel_permute)
    loader = DataLoader(items, batch_sampler=StepSampler(plan, start, s.max_steps, info.rank, info.world),
                        collate_fn=collate_packed, num_workers=cfg.data.num_workers, pin_memory=cuda,
                        persistent_workers=False, prefetch_factor=4 if cfg.data.num_workers else None,
                        worker_init_fn=_ignore_stop_signals if cfg.data.num_workers else None)
    log = RunLog(run_dir, start, validation_due=state.validation_due) if info.is_main else None
    phase = ValidationPhase(validate, val_records, prior_source, spec, cfg, info, plane, progress and info.is_main)
    bar = tqdm(total=s.max_steps, initial=start, desc="train", unit="it", dynamic_ncols=True,
               disable=not (progress and info.is_main))
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if cuda else contextlib.nullcontext()
    per_object = s.step_shape == "per-object"
    model.train()
    hold_frozen_modules(model)
    step, best, best_step, last_saved = start, state.best_psnr, state.best_step, None
    saved_step, stopping, pending = None, False, state.validation_due and phase.enabled
    t_last, rays_since = time.perf_counter(), 0
    # out of memory: one line naming the step's settings, the step and the last checkpoint as they are then
    oom = memory.one_line_out_of_memory(info, lambda: memory.in_training_step(cfg, info.world, step,
                                                                               last_saved or latest))
    with StopRequest(info) as stop, oom, contextlib.ExitStack() as cleanup:
        if pending:  # the step's validation a stop signal skipped or abandoned, before the next step
            best, best_step, pending = (phase.due_on_resume(stop, model, state, log, latest) if info.is_main
                                        else (best, best_step, False))
            stopping = stop.requested()  # a signal during it: stop before training (its validation stays due)
        batches = iter(() if stopping else loader)
        cleanup.callback(_stop_workers, batches)  # also when a step raises: see _stop_workers
        for batch in batches:
            lr = learning_rate(cfg, plan, step)
            for group in optimizer.param_groups:
                group["lr"] = lr
            batch = batch.to(info.device, non_blocking=True)
            keys = step_keys(plan, step, info.rank, info.world)
            optimizer.zero_grad(set_to_none=True)
            before = norms.state()
            terms = train_step(runner, batch, keys, step, near, far, info.device, amp=amp, per_object=per_object,
                               distributed=info.world > 1)
            norms.merge(before)
            optimizer.step()
            step += 1
            crash_point("step", step)
            rays_since += len(keys) * s.rays_per_object * info.world
            bar.update(1)
            log_now = step % cfg.log.log_every == 0 or step == s.max_steps
            if log_now and info.world > 1:  # every rank reaches the same log steps
                torch.distributed.all_reduce(terms)
                terms /= info.world
            if info.is_main and log_now:
                # the one host sync per log interval
                total, coarse, fine, depth, background, foreground = terms.tolist()
                now = time.perf_counter()
                psnr = -10.0 * math.log10(max(fine, 1e-10))
                values = {"loss": total, "loss_coarse": coarse, "loss_fine": fine, "loss_depth": depth,
                          "loss_background": background, "loss_foreground": foreground, "psnr_train": psnr, "lr": lr,
                          "epoch": plan.epoch(step),
                          "rays_per_s": rays_since / max(now - t_last, 1e-9)}
                log.log(step, values)
                bar.set_postfix(loss=f"{values['loss']:.4f}", psnr=f"{psnr:.2f}")
                t_last, rays_since = now, 0
            due = info.is_main and phase.due(step)  # a signal skips it; one during it abandons it: due on resume
            res = phase.score(stop, model, step, log, last_saved or latest) if due and stop.signum is None else None
            improved = res is not None and res.psnr > best
            best, best_step = (res.psnr, step) if improved else (best, best_step)
            pending = due and res is None
            if info.is_main and (step % cfg.log.checkpoint_every == 0 or step == s.max_steps or improved):
                last_saved = _save(ckpt_root, model, optimizer, model_cfg, step, (best, best_step), cfg, spec, info,
                                   pending)
                saved_step = step
                if improved:
                    ckpt.mark_best(ckpt_root, last_saved)
            stopping = stop.requested()  # after the step's checkpoint: a signal during its write counts too
            if info.is_main and stopping and saved_step != step:
                last_saved = _save(ckpt_root, model, optimizer, model_cfg, step, (best, best_step), cfg, spec, info,
                                   pending)
                saved_step = step
            if stopping:
                break
        finished = step >= s.max_steps and not pending  # a signal after the last step and its validation: nothing
        stopped_by = signal_name(stop.signum) if stopping and stop.signum and not finished else None
    bar.close()
    if log is not None:
        log.close()
    barrier(info)
    return {"step": step, "best_val_psnr": best if math.isfinite(best) else None,  # strict JSON: no -Infinity
            "checkpoint": str(last_saved or latest) if (last_saved or latest) else None,  # nothing trained: the run's
            "stopped_by": stopped_by,
            "exit_code": exit_code(stop.signum) if stopped_by else 0}


def _save(ckpt_root: Path, model: PixelNeRF, optimizer: torch.optim.Optimizer, model_cfg: dict, step: int,
          best: tuple[float, int | None], cfg: TrainConfig, spec: InferenceSpec, info: DistInfo,
          validation_due: bool) -> Path:
    """The run checkpoint of ``step`` (:func:`depthnerf.train.checkpoint.save_checkpoint`); ``best``: the best
    validation PSNR so far and its step; ``validation_due``: the step's validation did not run."""
    state = ckpt.TrainingState(step=step, best_psnr=best[0], best_step=best[1], world_size=info.world,
                               validation_due=validation_due)
    return ckpt.save_checkpoint(ckpt_root, model, optimizer, model_cfg, state, keep_last=cfg.log.keep_last,
                                train_config=to_dict(cfg), spec_json=spec.to_json())


def _stop_workers(batches) -> None:
    """Shut down the DataLoader iterator's worker processes now. Left to garbage collection, a run that ends in an
    exception (out of memory in a worker, one line) keeps the iterator alive through the exception's traceback, and
    at interpreter exit multiprocessing's SIGTERM to its workers is ignored (:func:`_ignore_stop_signals`): the
    process would wait for them for ever."""
    shutdown = getattr(batches, "_shutdown_workers", None)  # torch's multi-process iterator; none with 0 workers
    if shutdown is not None:
        shutdown()


def _ignore_stop_signals(worker_id: int) -> None:
    """DataLoader workers ignore SIGTERM / SIGINT (sent to the whole process group): the main process stops
    cleanly and shuts them down; a worker that died first would abort it."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)

