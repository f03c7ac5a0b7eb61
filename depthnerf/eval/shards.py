"""Evaluation at scale: objects shared out over ``torchrun`` ranks, one result file per object, exact resume.

Files (under ``OUT_DIR/objects/``)
    ``settings.json``: everything a per-object result depends on (checkpoint hash, data, views, resolution,
    chunk, prior, protocol choices, mesh and geometry settings, device type and render precision; not
    ``--max-objects``, ``--method`` or the number of processes). ``<object_id>.json``: one object's metrics, mesh
    level, timings and ``renders.csv`` rows, written atomically (:func:`depthnerf.files.write_json_atomic`, a
    temporary sibling renamed into place) after its PNGs and mesh, with the settings' hash and the fingerprint
    of the object's files (``data_fingerprint``: :mod:`depthnerf.data.fingerprint`, taken before it was read)
    inside. A reader only ever sees whole files; a stray ``.NAME.PID.tmp`` of a killed process is never read, and
    a file that does not parse or carries another settings hash counts as not done.

Resume
    :func:`evaluate_objects` skips the objects whose file is there, so a killed evaluation restarted with the same
    arguments computes only the rest, and the merged outputs equal an uninterrupted run's (the stored floats
    round-trip exactly through JSON; only timings differ). A restart with other settings, once an object is
    finished, is a one-line error naming what differs, and so is one on data that changed since (a finished
    object whose files' fingerprint is not the stored one: a dataset generated again in place under the same
    object ids; result files without a fingerprint, of earlier versions, are not checked), unless
    ``--overwrite``, which first deletes everything an earlier evaluation wrote there (:func:`remove_outputs`: the
    object files, ``summary.json``, ``per_object.csv``, ``renders.csv`` and the PNGs and meshes of
    ``--save-renders``), and nothing else.

Sharding
    Rank 0 checks the folder and sends every rank the same list of unfinished objects (in dataset order); rank
    ``r`` of ``N`` takes every ``N``-th of them starting at ``r``, writes each object's file as it finishes, and
    sends its results to rank 0 (over the process group, so the merge does not need a shared file system; rank 0
    writes the files of objects it did not compute when they are missing, so a restart resumes them too). Rank 0
    returns every object in dataset order; the summary's means are then the one-process means, bit for bit.
    ``--save-renders`` PNGs and meshes are written by the rank that computed the object: with several machines,
    ``OUT_DIR`` should be on a file system they share.

Test hook: with ``DEPTHNERF_CRASH_AT=eval-object@K`` in the environment a process SIGKILLs itself right after
writing the result file of its K-th object (:mod:`depthnerf.crash_hook`).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from depthnerf.config_io import differences
from depthnerf.crash_hook import crash_point
from depthnerf.data.protocol import ProtocolViews
from depthnerf.data.srn import ObjectRecord
from depthnerf.distributed import DistInfo, broadcast_from_main, gather_to_main
from depthnerf.errors import DepthnerfError, refusal
from depthnerf.eval.geometry_metrics import GeometryMetrics
from depthnerf.eval.metrics import ObjectMetrics, ViewMetrics
from depthnerf.files import make_folder, write_json_atomic
from depthnerf.render.mesh_level import MeshLevel

OBJECTS_DIR = "objects"
"""Folder of the per-object result files, inside the evaluation's output folder."""
SETTINGS_FILE = "settings.json"
"""What the results in :data:`OBJECTS_DIR` were computed with."""
FORMAT = "depthnerf-eval-object-1"
"""Format tag of a per-object result file."""
OUTPUT_FILES = ("summary.json", "per_object.csv", "renders.csv")
"""Files an evaluation writes at the top of its output folder (:mod:`depthnerf.eval.protocol`)."""
OUTPUT_TREES = (("renders", "*/*.png"), ("gt", "*/*.png"), ("meshes", "*.ply"))
"""(folder, pattern) of the files ``--save-renders`` writes in the output folder: ``renders/<object_id>/<view>.png``,
``gt/<object_id>/<view>.png`` and ``meshes/<object_id>.ply``."""
CRASH_STAGE = "eval-object"
"""``DEPTHNERF_CRASH_AT`` stage of the test hook (module docstring)."""


@dataclass
class ObjectResult:
    """Everything measured on one object."""

    record: ObjectRecord
    """The object."""
    views: ProtocolViews
    """Which views were used."""
    metrics: ObjectMetrics
    """Image metrics."""
    geometry: GeometryMetrics | None
    """3D metrics; None without a GT mesh or with meshing off."""
    mesh_level: MeshLevel | None
    """The density level the mesh was extracted at (None without a mesh)."""
    seconds: dict[str, float]
    """Wall-clock seconds of ``render`` (encode + render), ``metrics`` and ``mesh``."""
    renders: list[dict] = field(default_factory=list)
    """Its ``renders.csv`` rows (with ``save_renders``)."""


def settings_hash(settings: dict) -> str:
    """Short stable hash of a settings mapping (sorted-key JSON)."""
    import hashlib

    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]


def encode(result: ObjectResult, settings_sha: str, data_fingerprint: str | None = None) -> dict:
    """The JSON content of an object's result file (``data_fingerprint``: of its files, None: not taken)."""
    m = result.metrics
    return {"format": FORMAT, "object_id": result.record.object_id, "settings_sha": settings_sha,
            "data_fingerprint": data_fingerprint,
            "metrics": {"psnr": m.psnr, "ssim": m.ssim, "lpips": m.lpips,
                        "views": [dataclasses.asdict(v) for v in m.views]},
            "geometry": None if result.geometry is None else dataclasses.asdict(result.geometry),
            "mesh_level": None if result.mesh_level is None else dataclasses.asdict(result.mesh_level),
            "seconds": result.seconds, "renders": result.renders}


ViewsOf = Callable[[ObjectRecord], ProtocolViews]
"""An object's input and target views under the evaluation's settings (``views_of(record)``)."""


def decode(payload: dict, record: ObjectRecord, views_of: ViewsOf) -> ObjectResult:
    """An :class:`ObjectResult` back from :func:`encode`'s mapping (``KeyError``/``TypeError`` when malformed)."""
    m = payload["metrics"]
    metrics = ObjectMetrics(object_id=record.object_id, views=[ViewMetrics(**v) for v in m["views"]],
                            psnr=m["psnr"], ssim=m["ssim"], lpips=m["lpips"])
    geo, level = payload["geometry"], payload["mesh_level"]
    return ObjectResult(record=record, views=views_of(record), metrics=metrics,
                        geometry=None if geo is None else GeometryMetrics(**geo),
                        mesh_level=None if level is None else MeshLevel(**level),
                        seconds=dict(payload["seconds"]), renders=list(payload["renders"]))


def _differences(old: dict, new: dict) -> list[str]:
    """``"key OLD there, NEW now"`` for every setting that differs (nested keys dotted)."""
    return [f"{k} {json.dumps(there)} there, {json.dumps(now)} now" for k, (there, now) in differences(old, new).items()]


def prepare_output_folder(out_dir: Path) -> None:
    """Make ``out_dir`` (a one-line error when it cannot be used as the output folder, and when a name the
    evaluation writes there, :data:`OUTPUT_FILES`, :data:`OBJECTS_DIR` or an :data:`OUTPUT_TREES` folder, is taken
    by a folder or a file of the other kind)."""
    out_dir = make_folder(Path(out_dir), "--out")
    folders = (OBJECTS_DIR, *(name for name, _ in OUTPUT_TREES))
    for name in (*OUTPUT_FILES, *folders):
        path, folder = out_dir / name, name in folders
        if path.exists() and path.is_dir() != folder:
            raise DepthnerfError(f"{path}: is a {'file' if folder else 'folder'}, where the evaluation writes its "
                                 f"{'folder' if folder else 'file'} {name}; move it away or choose another --out")


def remove_outputs(out_dir: Path) -> int:
    """Delete what an evaluation writes in ``out_dir`` (:data:`OBJECTS_DIR`'s result, settings and stray
    temporary files, :data:`OUTPUT_FILES`, the :data:`OUTPUT_TREES` files) and the folders that leaves empty;
    any other file stays. Returns how many files were deleted."""
    out_dir = Path(out_dir)
    doomed = [p for name in OUTPUT_FILES for p in (out_dir / name, *out_dir.glob(f".{name}.*.tmp"))]
    objects = out_dir / OBJECTS_DIR
    doomed += [*objects.glob("*.json"), *objects.glob(".*.tmp")]
    folders = [objects]
    for name, pattern in OUTPUT_TREES:
        doomed += (out_dir / name).glob(pattern)
        folders += [*(p for p in (out_dir / name).glob("*") if p.is_dir()), out_dir / name]
    removed = 0
    for path in doomed:
        if path.is_file() or path.is_symlink():
            path.unlink()
            removed += 1
    for folder in folders:  # deepest first: object folders before their parents
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    return removed


class ObjectStore:
    """The per-object result files of one evaluation (module docstring)."""

    def __init__(self, out_dir: Path, settings: dict,
                 fingerprint: Callable[[ObjectRecord], str] | None = None) -> None:
        self.dir = Path(out_dir) / OBJECTS_DIR
        self.settings = json.loads(json.dumps(settings))  # as it reads back from disk
        self.sha = settings_hash(self.settings)
        self.fingerprint = fingerprint
        """An object's data fingerprint (:class:`depthnerf.data.fingerprint.DataFingerprint`); None: not kept."""

    def data_fingerprint(self, record: ObjectRecord) -> str | None:
        """``record``'s data fingerprint now (None without :attr:`fingerprint`)."""
        return None if self.fingerprint is None else self.fingerprint(record)

    def path(self, object_id: str) -> Path:
        return self.dir / f"{object_id}.json"

    def _object_files(self) -> list[Path]:
        return sorted(p for p in self.dir.glob("*.json") if p.name != SETTINGS_FILE) if self.dir.is_dir() else []

    def prepare(self, overwrite: bool) -> None:
        """Check an earlier evaluation's settings (a one-line error when they differ and objects are finished,
        unless ``overwrite``), delete all its outputs with ``overwrite`` (:func:`remove_outputs`), and record the
        current settings."""
        settings_path = self.dir / SETTINGS_FILE
        files = self._object_files()
        if overwrite:
            remove_outputs(self.dir.parent)
        elif files and settings_path.is_file():
            try:
                old = json.loads(settings_path.read_text(encoding="utf-8"))
            except (OSError, ValueError) as err:  # ValueError: not JSON, or not UTF-8 text
                raise DepthnerfError(f"{settings_path}: unreadable ({err}); pass --overwrite to start "
                                     "over") from None
            diff = _differences(old, self.settings) if isinstance(old, dict) else ["not a JSON object"]
            if diff:
                raise DepthnerfError(
                    f"{self.dir.parent}: holds {len(files)} objects evaluated with other settings ("
                    f"{'; '.join(diff[:3])}{'; ...' if len(diff) > 3 else ''}); pass --overwrite to start over or "
                    "choose another --out")
        write_json_atomic(settings_path, self.settings)

    def finished(self, records: Sequence[ObjectRecord], views_of: ViewsOf) -> dict[str, ObjectResult]:
        """The objects of ``records`` whose result file is complete and was made with these settings; a one-line
        error when the files of a finished object are not those it was computed from (:meth:`check_data`)."""
        done, stored = {}, {}
        for record in records:
            path = self.path(record.object_id)
            if not path.is_file():
                continue
            try:
                payload = json.loads(path.read_text())
                if payload.get("format") != FORMAT or payload.get("settings_sha") != self.sha:
                    continue
                done[record.object_id] = decode(payload, record, views_of)
                stored[record.object_id] = payload.get("data_fingerprint")
            except (OSError, ValueError, KeyError, TypeError, AttributeError):
                continue  # not a result of this evaluation: computed again
        self.check_data([r for r in records if r.object_id in done], stored)
        return done

    def check_data(self, records: Sequence[ObjectRecord], stored: dict[str, str | None]) -> None:
        """A one-line error when a finished object's files changed since its result was computed (its stored
        fingerprint, by id in ``stored``, is not the one of its files now); an object without one (a result file
        of an earlier version) is not checked."""
        if self.fingerprint is None:
            return
        changed = [r for r in records if stored.get(r.object_id) is not None
                   and stored[r.object_id] != self._current(r)]
        if changed:
            more = f" and {len(changed) - 1} more of the {len(records)} finished objects" if len(changed) > 1 else ""
            raise DepthnerfError(
                f"{self.dir.parent}: the data changed since the evaluation there started ({changed[0].path}{more}: "
                "other cameras, image sizes or dataset card than its result was computed from); pass --overwrite "
                "to start over or choose another --out")

    def _current(self, record: ObjectRecord) -> str | None:
        try:
            return self.data_fingerprint(record)
        except DepthnerfError:
            return None  # a file gone or unreadable: changed

    def save(self, payload: dict, *, only_if_missing: bool = False) -> None:
        """Write an object's result file atomically (:func:`encode`'s mapping)."""
        path = self.path(payload["object_id"])
        if not (only_if_missing and path.is_file()):
            write_json_atomic(path, payload)


@dataclass(frozen=True)
class RunCounts:
    """How many objects this invocation computed and how many it took from an earlier one."""

    computed: int
    """Objects scored now (all ranks)."""
    resumed: int
    """Objects whose result file was already there."""


def _plan(store: ObjectStore, records: Sequence[ObjectRecord], views_of: ViewsOf, info: DistInfo,
          overwrite: bool) -> tuple[dict[str, ObjectResult], list[str]]:
    """Rank 0 prepares the store and finds the finished objects; every rank gets the unfinished ids."""
    done: dict[str, ObjectResult] = {}
    message = None
    if info.is_main:
        try:
            store.prepare(overwrite)
            done = store.finished(records, views_of)
        except DepthnerfError as err:
            message = str(err)
    todo = [r.object_id for r in records if r.object_id not in done]
    message, todo = broadcast_from_main((message, todo), info)
    if message is not None:
        raise refusal(message, info.rank)
    return done, todo


def evaluate_objects(records: Sequence[ObjectRecord], evaluate: Callable[[ObjectRecord], ObjectResult],
                     store: ObjectStore, info: DistInfo, views_of: ViewsOf, *, overwrite: bool = False,
                     progress: bool = True) -> tuple[list[ObjectResult] | None, RunCounts]:
    """Score ``records`` over the ranks of ``info`` with resume (module docstring). Rank 0 gets every object's
    result in ``records`` order; the other ranks get None."""
    done, todo = _plan(store, records, views_of, info, overwrite)
    by_id = {r.object_id: r for r in records}
    mine = [by_id[i] for i in todo[info.rank::info.world]]
    if info.is_main and done:
        print(f"resuming {store.dir.parent}: {len(done)} of {len(records)} objects already evaluated, "
              f"{len(todo)} to go", file=sys.stderr, flush=True)
    desc = "eval" if info.world == 1 else f"eval (rank 0 of {info.world}, {len(todo)} objects in all)"
    bar = tqdm(total=len(mine) + (len(done) if info.world == 1 else 0),
               initial=len(done) if info.world == 1 else 0, desc=desc, unit="obj", file=sys.stderr,
               disable=not (progress and info.is_main), dynamic_ncols=True)
    payloads, views, start, where = [], 0, time.perf_counter(), "" if info.world == 1 else " on rank 0"
    for k, record in enumerate(mine, start=1):
        fingerprint = store.data_fingerprint(record)  # of the files as they are read
        result = evaluate(record)
        payload = encode(result, store.sha, fingerprint)
        store.save(payload)
        payloads.append(payload)
        crash_point(CRASH_STAGE, k)
        views += len(result.views.targets)
        rate = views / max(time.perf_counter() - start, 1e-9)
        bar.set_postfix_str(f"{rate:.2f} views/s{where}", refresh=False)
        bar.update(1)
    bar.close()
    gathered = gather_to_main(payloads, info)
    counts = RunCounts(computed=len(todo), resumed=len(done))
    if not info.is_main:
        return None, counts
    results = dict(done)
    for part in gathered:
        for payload in part:
            store.save(payload, only_if_missing=True)  # objects other machines computed, for a later resume
            results[payload["object_id"]] = decode(payload, by_id[payload["object_id"]], views_of)
    missing = [r.object_id for r in records if r.object_id not in results]
    if missing:
        raise DepthnerfError(f"{store.dir}: no result for {len(missing)} objects (first {missing[0]})")
    return [results[r.object_id] for r in records], counts
