"""The Markdown model card ``<name>.md`` of an exported checkpoint, and the commands it gives
(``scripts/export_checkpoint.py`` writes it beside the weights and ``<name>.json``; imported from there)."""

from __future__ import annotations

from pathlib import Path

from depthnerf import __version__
from depthnerf.data.synth.framing import card_framing
from depthnerf.depth.cache import depth_command
from depthnerf.depth.estimators import CACHED_ESTIMATORS
from depthnerf.pretrained.card import total_steps, warm_start_steps
from depthnerf.train.config import TrainConfig, inference_spec

LICENCE = "MIT (the depthnerf repository's licence, see pyproject.toml)"
"""Licence of the exported weights."""
METRIC_KEYS = ("psnr", "ssim", "lpips", "chamfer_l1", "fscore")
"""Metrics copied from the eval summary (null ones are left out), in the card's order."""


def eval_command(name: str, card: dict, train_res: int) -> str:
    """The ``depthnerf eval`` command that measures the card's metrics (its ``evaluation``) for a shipped checkpoint:
    on ``$DATA``, or on ``$EVAL_DATA`` when the evaluation read other data than the training
    (:func:`separate_eval_data`)."""
    ev = card["evaluation"]
    data = "$EVAL_DATA" if separate_eval_data(card) else "$DATA"
    parts = ["depthnerf eval", f"--checkpoint {name}", f"--data {data}", f"--split {ev['split']}",
             f"--out eval/{name}", f"--views-stride {ev['views_stride']}"]
    if ev.get("max_objects"):
        parts.append(f"--max-objects {ev['max_objects']}")
    if ev.get("resolution") and ev["resolution"] != train_res:
        parts.append(f"--resolution {ev['resolution']}")
    return " ".join(parts)


def separate_eval_data(card: dict) -> bool:
    """Whether the card's reproduce commands make the evaluation data apart from the training data: the evaluation
    read another dataset folder (its ``data_root`` and its dataset card are then in the card's ``evaluation``
    section, recorded by the export), and no ``--data-root`` given at export names one folder for both."""
    ev = card.get("evaluation") or {}
    return bool(not card.get("data_root") and ev.get("dataset") and ev.get("data_root")
                and ev.get("train_data_root") and ev["data_root"] != ev["train_data_root"])


def synth_command(dataset_card: dict | None, category: str, out: str = "$DATA") -> str:
    """The ``depthnerf synth`` command of a dataset (from its dataset card), written to ``out``."""
    if not dataset_card:
        return f"# dataset card missing: the {category} data's generation settings are unknown"
    counts = dataset_card.get("counts", {})
    family = dataset_card.get("family", "standard")
    return (f"depthnerf synth --category {category} --out {out} --train-objects {counts.get('train')} "
            f"--val-objects {counts.get('val')} --test-objects {counts.get('test')} --resolution "
            f"{dataset_card.get('resolution')} --seed {dataset_card.get('seed')} --framing "
            f"{card_framing(dataset_card)}" + (f" --family {family}" if family != "standard" else ""))


def file_rows(card: dict) -> list[str]:
    """The card table's rows naming the weights file: its size and SHA-256."""
    return [f"| weights | `{card['name']}.safetensors`, float16 ({card['size_bytes']:,} bytes), loaded as float32 |",
            f"| sha256 | `{card['sha256']}` |"]


INPUTS_TEXT = {"photo": ", each framed as `reconstruct` frames a photo",
               "both": ", each encoded both as it is and framed as `reconstruct` frames a photo"}
"""How the card says a head's views were encoded (``fit-facing --inputs``; ``dataset``, the first heads' way, says
nothing)."""


def facing_head_lines(fh: dict) -> list[str]:
    """The card's "Facing head" section (from the card's ``facing_head`` entry)."""
    text = (f"The weights carry a facing head (`depthnerf fit-facing`): ridge regression from the input view's "
            f"features pooled to {fh['grid']}x{fh['grid']} to the angle of the mirror plane, which "
            "`depthnerf reconstruct --facing auto` takes. Fitted on "
            f"{fh['views']} views of {fh['objects']} objects (`{fh['data']}`)"
            + (f"{INPUTS_TEXT[fh['inputs']]};" if fh.get("inputs") in INPUTS_TEXT else ",")
            + f" ridge weight {fh['lambda']:g}, "
            f"chosen on a held-out fifth of them: median angle error {fh['validation_median_deg']:.2f} "
            f"degrees, 90th percentile {fh['validation_p90_deg']:.2f}.")
    if fh.get("attached"):
        text += (" The head was added to the exported file afterwards (`scripts/attach_facing_head.py`), which "
                 "leaves the network's tensors and metadata as they were: the evaluation above is of this network.")
    return ["## Facing head", "", text]


def facing_fit_line(fh: dict, category: str) -> str:
    """The reproduce line that fits the facing head into the file ``HEAD``."""
    return ((fh.get("command") or f"depthnerf fit-facing --checkpoint RUN --data $DATA --category {category} "
             "--out HEAD") + "  # HEAD: the facing head's file")


def attach_line(name: str) -> str:
    """The reproduce line that adds the head of ``HEAD`` to the exported ``name``."""
    return f"python scripts/attach_facing_head.py --name {name} --facing-head HEAD"


def training_steps(card: dict) -> str:
    """The card's training steps: the run's own, and for a warm-started run those behind its source and the total
    (``total_steps``; cards written before that field give the source's own steps)."""
    behind = warm_start_steps(card)
    if behind is None:
        return str(card["step"])
    return (f"{total_steps(card, card['step'])} in all: {card['step']} on top of a warm start from a model trained "
            f"{behind} steps")


def model_card(card: dict, cfg: TrainConfig, data_card: dict, prior: dict | None) -> str:
    """The Markdown model card ``<name>.md``."""
    name, est, cat = card["name"], card["depth_estimator"], card["category"]
    kind = "pixelNeRF baseline (RGB encoder only)" if est == "none" else f"depth-aware pixelNeRF ({est} depth prior)"
    ds = data_card.get("dataset_card") or {}
    m, f = cfg.model, cfg.model.coarse
    s, r = cfg.schedule, cfg.render.sampler
    lines = [f"# {name}", "",
             f"A {kind} for single-image 3D reconstruction of **{cat}**, trained with the `{cfg.preset}` preset "
             f"on the CPU at {cfg.data.resolution}x{cfg.data.resolution}. Trained and evaluated on the project's "
             "**synthetic** SRN-format benchmark (`depthnerf synth`: procedural shapes, ray-traced) — **not** on "
             "real ShapeNet; the numbers below are not comparable with the paper's Table 1.", "",
             "| field | value |", "|---|---|",
             *file_rows(card),
             f"| training steps | {training_steps(card)} |",
             f"| source | run `{card['source']['run']}`, `{card['source']['file']}` (sha256 "
             f"`{card['source']['sha256'][:16]}...`) |",
             f"| fp16 round trip | max abs RGB difference {card['fp16_check']['max_abs_rgb']:.2e} "
             f"(PSNR {card['fp16_check']['psnr_db']:.1f} dB vs the fp32 weights) |", "",
             "## Training data", "",
             f"- {data_card.get('train_objects')} synthetic {cat} train objects (`{cat}_train`), images at "
             f"{data_card.get('resolution')} px for training, generator `{ds.get('generator', 'unknown')}`, "
             f"framing `{card.get('framing') or 'unknown'}` (docs/data.md), pixel centres read as "
             f"`data.pixel_center` {cfg.data.pixel_center}, "
             f"seed {ds.get('seed', 'unknown')}, {ds.get('protocol', {}).get('train_views', '?')} random "
             "upper-hemisphere views per object (exact z-depth, masks and meshes exist for every view).",
             f"- Dataset split sizes: {', '.join(f'{k} {v}' for k, v in ds.get('counts', {}).items()) or 'unknown'}"
             "; no val/test object is used for training.",
             f"- Depth prior: `{est}`" + (f", weights `{card['depth_weights']}`" if card.get("depth_weights") else "")
             + (f" (sha256 `{str(prior.get('weights_hash'))[:16]}...`, "
                f"licence {prior.get('licence')})" if prior and est != "none" else "")
             + ".", "",
             "## Model and preset", "",
             f"- Encoder: {m.encoder.backbone} trunk, {m.encoder.num_layers} feature stages"
             + (f", + 4th input channel and depth encoder ({m.encoder.depth_channels} channels)"
                if cfg.prior.enabled else "") + ".",
             f"- NeRF MLP: {f.n_blocks} residual blocks of width {f.d_hidden}; samples {r.n_coarse} coarse + "
             f"{r.n_importance} importance + {r.n_gaussian} Gaussian per ray; z-range {list(inference_spec(cfg).z_range)}.",
             *([f"- Mirror-symmetric conditioning (beyond the paper): each point also reads the features at its "
                f"mirror image's projection; trained with {s.mirror_dropout:g} of the items without a plane"
                + (f" and each plane turned by up to {s.mirror_jitter:g} degrees" if s.mirror_jitter else "") + ". "
                "`depthnerf eval` uses the dataset's plane (`--no-symmetry`: none), `depthnerf reconstruct "
                "--facing DEG` a photo's (default 90, a side view; `none`: none)."] if m.mirror else []),
             *(["- Depth prior at the point (beyond the paper, `--model.prior_at_point true`): the MLP input also "
                "gets the normalised prior read at full resolution at each point's projection"
                + (" and at its mirror image's" if m.mirror else "") + "."] if m.prior_at_point else []),
             *(["- Colour at the point (beyond the paper, `--model.rgb_at_point true`): the MLP input also gets the "
                "input's colour read at each point's projection" + (" and at its mirror image's" if m.mirror else "")
                + "."] if m.rgb_at_point else []),
             *(["- Global features (beyond the paper, `--model.global_features true`): each source view's feature "
                "maps averaged over the image enter the MLP's first hidden layer at every point."]
               if m.global_features else []),
             f"- Schedule: {s.max_steps} steps"
             + (f" (the run stopped at step {card['unfinished']['stopped_at']}: exported unfinished)"
                if card.get("unfinished") else "") + f", Adam lr {s.lr:g}"
             + (f" with a half-cosine decay to {s.lr_final:g}" if s.lr_schedule == "cosine" else "")
             + f", {s.objects_phase1}/{s.objects_phase2} objects x {s.rays_per_object} rays per step, bbox sampling "
             f"for {s.bbox_steps} steps; seed {cfg.seed}"
             + (f"; parameters held fixed (`--schedule.freeze {','.join(s.freeze)}`)" if s.freeze else "") + ".",
             *(["- Warm start (`--init-from`): these steps continue from the network weights of "
                + (f"the `{name}` shipped before this one" if card["init_from"]["source"] == name
                   else f"`{card['init_from']['source']}`")
                + f" (step {card['init_from']['step']}, sha256 "
                f"`{card['init_from']['sha256'][:16]}...`), with a fresh optimiser and schedule."]
               if card.get("init_from") else []),
             "- Full config: the `train_config` entry of the weights' metadata "
             f"(`depthnerf train --preset {cfg.preset} --print-config` prints the preset).", "",
             "## Evaluation", ""]
    metrics, ev = card.get("metrics"), card.get("evaluation")
    if metrics and ev:
        heads = [k for k in METRIC_KEYS if k in metrics]
        lines += ["| " + " | ".join(h.upper() if h != "chamfer_l1" else "Chamfer-L1" for h in heads) + " |",
                  "|" + "---:|" * len(heads),
                  "| " + " | ".join(f"{metrics[h]:.4f}" for h in heads) + " |", "",
                  f"Protocol: {card['protocol']}.", "",
                  f"- split `{ev['split']}`, {ev['objects']} objects, {ev['views']} scored views "
                  f"(view stride {ev['views_stride']}), {ev['resolution']}x{ev['resolution']} px, "
                  f"{ev['metrics_path']}; {ev['aggregation']}.",
                  f"- LPIPS: {ev['lpips_status']}." + (f" Mesh: {ev['mesh_status']}." if ev.get("mesh_status") else "")]
    else:
        lines += ["Not evaluated at export time (no `--eval-summary`)."]
    fh = card.get("facing_head")
    if fh:
        lines += ["", *facing_head_lines(fh)]
    separate = separate_eval_data(card)
    data_root = (card.get("data_root") or (ev["train_data_root"] if separate else (ev or {}).get("data_root"))
                 or data_card.get("root", "data/synth"))
    reproduce = [f"DATA={data_root}", synth_command(ds, cat)]
    if est in CACHED_ESTIMATORS:
        reproduce.append(depth_command(Path("$DATA"), est, card.get("depth_weights"), cfg.data.resolution,
                                       category=cat))
    reproduce.append(card.get("command") or f"depthnerf train --preset {cfg.preset} --data $DATA --depth {est} "
                     f"--out runs/{name}  # --command not given at export: check the config in the weights")
    if fh and not fh.get("attached"):
        reproduce.append(facing_fit_line(fh, cat))
    reproduce.append(f"python scripts/export_checkpoint.py --run {card.get('run_path') or 'runs/' + card['source']['run']} "
                     f"--name {name}"
                     + (" --eval-summary SUMMARY" if ev else "") + (" --facing-head HEAD" if fh and not fh.get("attached")
                                                                     else ""))
    if fh and fh.get("attached"):
        reproduce += [facing_fit_line(fh, cat), attach_line(name)]
    if separate:  # scored on a dataset folder of its own: made the same way
        reproduce += [f"EVAL_DATA={ev['data_root']}", synth_command(ev["dataset"], cat, "$EVAL_DATA")]
        if est in CACHED_ESTIMATORS:
            reproduce.append(depth_command(Path("$EVAL_DATA"), est, card.get("depth_weights"), cfg.data.resolution,
                                           category=cat))
    if ev:
        reproduce.append(eval_command(name, card, cfg.data.resolution))
    lines += ["", "## Reproduce", "", "```bash", *reproduce, "```", "",
              "## Intended use", "",
              f"Demonstrating and testing the depthnerf pipeline offline: `depthnerf demo`, `depthnerf eval "
              f"--checkpoint {name}` on the synthetic benchmark, and `depthnerf reconstruct` on renders that look "
              "like it (one object, centred, white background, SRN-like camera).", "",
              "## Limitations", "",
              "- Trained on procedural synthetic objects only: real photos (and real ShapeNet renders) are out of "
              "distribution, expect poor reconstructions.",
              f"- CPU preset: {cfg.data.resolution} px, a small MLP and few training steps; far below the paper's "
              "GPU settings.",
              "- Single object, centred, on white, camera at the category's SRN distance and focal length.",
              ("- The bundled depth network only knows the synthetic benchmark; for photos retrain with "
               "`depth-anything-v2`." if est == "bundled" else
               "- The oracle prior needs ground-truth depth, which only synthetic data has." if est == "oracle"
               else "- Baseline: no depth prior, the reference for the depth-aware model."), "",
              "## Licence", "", f"{LICENCE}. Exported with depthnerf {__version__}.", ""]
    return "\n".join(lines)
