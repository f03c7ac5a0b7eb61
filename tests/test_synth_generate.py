"""The ``depthnerf synth`` generator: SRN layout, geometry of the written files, determinism, resume, CLI."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from depthnerf.cli import main as cli_main
from depthnerf.data import srn_format
from depthnerf.data.cameras import pixel_directions
from depthnerf.data.synth.generate import MARKER, SynthConfig, generate
from depthnerf.errors import DepthnerfError


def _small(out: Path, category: str = "cars", **kw) -> SynthConfig:
    base = dict(category=category, out=out, train_objects=2, val_objects=1, test_objects=1, resolution=24,
                views_train=3, views_test=4, progress=False)
    base.update(kw)
    return SynthConfig(**base)


@pytest.fixture(scope="module", params=["srn", "legacy"])
def protocol_ds(tmp_path_factory, request) -> Path:
    """One train (50 views) and one test (251 views) car at 64 px (the real view protocol) and a chair, in each
    framing."""
    out = tmp_path_factory.mktemp(f"synth_protocol_{request.param}")
    generate(SynthConfig(category="cars", out=out, train_objects=1, val_objects=0, test_objects=1, resolution=64,
                         seed=3, progress=False, framing=request.param))
    generate(SynthConfig(category="chairs", out=out, train_objects=1, val_objects=0, test_objects=0, resolution=48,
                         views_train=6, seed=3, progress=False, framing=request.param))
    return out


def _pixel_center(root: Path) -> float:
    """The pixel-centre convention the dataset's card states (0.5 for the SRN framing, 0 for legacy)."""
    return json.loads((root / "cars_card.json").read_text())["camera"]["pixel_center"]


def _dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Dilation by a (2 pixels + 1)^2 square (8-neighbourhood for 1)."""
    return ndimage.binary_dilation(mask, structure=np.ones((3, 3), dtype=bool), iterations=pixels)


def _views(obj: Path) -> list[str]:
    return sorted(p.stem for p in (obj / "rgb").glob("*.png"))


def test_srn_layout_and_readers(protocol_ds: Path) -> None:
    train = protocol_ds / "cars_train" / "synth_cars_train_000000"
    test = protocol_ds / "cars_test" / "synth_cars_test_000000"
    assert _views(train) == [f"{i:06d}" for i in range(50)]
    assert _views(test) == [f"{i:06d}" for i in range(251)]
    assert (protocol_ds / "chairs_train" / "synth_chairs_train_000000" / "mesh.ply").is_file()  # flat chairs_train
    intr = srn_format.read_intrinsics(test / "intrinsics.txt")
    assert (intr.height, intr.width) == (64, 64)
    srn = _pixel_center(protocol_ds) == 0.5
    assert intr.focal == pytest.approx(131.25 / 2) and intr.cx == intr.cy == pytest.approx(32.0 if srn else 31.75)
    for obj in (train, test):
        for name in _views(obj)[:: 25]:
            rgb = srn_format.read_rgb(obj / "rgb" / f"{name}.png")
            depth = srn_format.read_depth(obj / "depth" / f"{name}.npz")
            mask = srn_format.read_mask(obj / "mask" / f"{name}.png")
            srn_format.read_pose(obj / "pose" / f"{name}.txt")  # rigid, or it raises
            assert rgb.shape == (64, 64, 3) and depth.shape == mask.shape == (64, 64)
            assert ((depth > 0) == mask).all() and mask.any()
            assert (rgb[~_dilate(mask, 1)] == 1.0).all()  # AA touches only 8-neighbours of the mask
    card = json.loads((protocol_ds / "cars_card.json").read_text())
    assert card["counts"] == {"train": 1, "val": 0, "test": 1} and card["seed"] == 3
    assert card["camera"]["radius"] == 1.3 and card["camera"]["focal"] == pytest.approx(131.25 / 2)
    zr = card["z_range"]
    assert zr["near"] == 0.8 and zr["far"] == 1.8
    assert 0.8 < zr["measured_z_depth_min"] < zr["measured_z_depth_max"] < 1.8
    assert sum(card["styles"]["train"]["style"].values()) == 1


def _load(obj: Path, name: str):
    """Integer-centred intrinsics (the card's pixel centres applied), pose, depth and mask of one view."""
    intr = srn_format.read_intrinsics(obj / "intrinsics.txt").with_pixel_center(_pixel_center(obj.parent.parent))
    return (intr, srn_format.read_pose(obj / "pose" / f"{name}.txt").astype(np.float64),
            srn_format.read_depth(obj / "depth" / f"{name}.npz"), srn_format.read_mask(obj / "mask" / f"{name}.png"))


def _project(points: np.ndarray, pose: np.ndarray, intr) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cam = (points - pose[:3, 3]) @ pose[:3, :3]
    return cam[:, 0] / cam[:, 2] * intr.focal + intr.cx, cam[:, 1] / cam[:, 2] * intr.focal + intr.cy, cam[:, 2]


@pytest.mark.parametrize("obj", ["cars_train/synth_cars_train_000000", "cars_test/synth_cars_test_000000",
                                 "chairs_train/synth_chairs_train_000000"])
def test_mesh_vertices_project_into_the_mask(protocol_ds: Path, obj: str) -> None:
    folder = protocol_ds / obj
    verts = np.asarray(trimesh.load(folder / "mesh.ply", process=False).vertices, dtype=np.float64)
    for name in _views(folder)[::7]:
        intr, pose, depth, mask = _load(folder, name)
        u, v, z = _project(verts, pose, intr)
        j, i = np.round(u).astype(int), np.round(v).astype(int)
        assert (z > 0).all() and (i >= 0).all() and (i < intr.height).all() and (j >= 0).all() and (j < intr.width).all()
        # the silhouette is the mesh's projection; vertices of sub-pixel details (mirrors, spindles, tubes) that
        # no pixel centre hits may stick out of the 1-px dilated mask (measured: 1-5% of vertices, which crowd on
        # small parts), never out of the 2-px one
        assert _dilate(mask, 1)[i, j].mean() > 0.9
        assert _dilate(mask, 2)[i, j].all()


def test_depth_back_projects_onto_the_mesh(protocol_ds: Path) -> None:
    folder = protocol_ds / "cars_test" / "synth_cars_test_000000"
    mesh = trimesh.load(folder / "mesh.ply", process=False)
    intr, pose, depth, mask = _load(folder, "000064")
    cam = pixel_directions(intr, normalize=False).numpy().astype(np.float64)[mask] * depth[mask][:, None]
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    _, dist, _ = trimesh.proximity.closest_point(mesh, world)
    assert dist.max() < 1e-5


@pytest.mark.parametrize("pair", [(64, 65), (64, 70), (100, 110)])
def test_depth_reprojects_between_views(protocol_ds: Path, pair: tuple[int, int]) -> None:
    """View A's depth, lifted to 3D and projected into view B, matches B's depth where both see the surface.

    B's depth is interpolated as *inverse* depth, which is affine in (u, v) on a plane, over pixel quads whose
    inverse depth is planar; there the comparison is exact to float32 rounding (a 0.1 px error in the camera
    model already gives a median error > 5e-5)."""
    folder = protocol_ds / "cars_test" / "synth_cars_test_000000"
    intr, pose_a, depth_a, mask_a = _load(folder, f"{pair[0]:06d}")
    _, pose_b, depth_b, _ = _load(folder, f"{pair[1]:06d}")
    cam = pixel_directions(intr, normalize=False).numpy().astype(np.float64)[mask_a] * depth_a[mask_a][:, None]
    u, v, z = _project(cam @ pose_a[:3, :3].T + pose_a[:3, 3], pose_b, intr)
    j0, i0 = np.floor(u).astype(int), np.floor(v).astype(int)
    inside = (i0 >= 0) & (j0 >= 0) & (i0 < intr.height - 1) & (j0 < intr.width - 1)
    u, v, z, i0, j0 = u[inside], v[inside], z[inside], i0[inside], j0[inside]
    quad = np.stack([depth_b[i0, j0], depth_b[i0, j0 + 1], depth_b[i0 + 1, j0], depth_b[i0 + 1, j0 + 1]], 1)
    valid = (quad > 0).all(1)
    inv = 1.0 / np.where(valid[:, None], quad, 1.0).astype(np.float64)
    planar = valid & (np.abs(inv[:, 0] + inv[:, 3] - inv[:, 1] - inv[:, 2]) < 1e-5 * inv.mean(1))
    fu, fv = u - j0, v - i0
    interp = (inv[:, 0] * (1 - fu) * (1 - fv) + inv[:, 1] * fu * (1 - fv) + inv[:, 2] * (1 - fu) * fv
              + inv[:, 3] * fu * fv)
    err = np.abs(1.0 / interp - z)[planar]
    visible = err < 0.01  # the rest is occluded in B
    assert visible.sum() > max(20, 0.05 * mask_a.sum())
    assert np.median(err[visible]) < 1e-5


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _assert_same_dataset(a: Path, b: Path) -> None:
    fa, fb = _files(a), _files(b)
    assert fa.keys() == fb.keys()
    for name, data in fa.items():
        if name.endswith(".npz"):  # np.savez_compressed stamps the zip entry with the wall-clock time
            np.testing.assert_array_equal(srn_format.read_depth(a / name), srn_format.read_depth(b / name))
        else:
            assert data == fb[name], name


def test_deterministic_and_independent_of_workers(tmp_path: Path) -> None:
    card1 = generate(_small(tmp_path / "w1", seed=5, workers=1))
    card2 = generate(_small(tmp_path / "w2", seed=5, workers=2))
    assert card1 == card2
    _assert_same_dataset(tmp_path / "w1", tmp_path / "w2")
    other = generate(_small(tmp_path / "s6", seed=6, train_objects=1, val_objects=0, test_objects=0))
    assert other != card1
    ply = "cars_train/synth_cars_train_000000/mesh.ply"
    assert (tmp_path / "s6" / ply).read_bytes() != (tmp_path / "w1" / ply).read_bytes()


def test_resume_skips_finished_and_redoes_partial(tmp_path: Path) -> None:
    cfg = _small(tmp_path / "ds", category="chairs", seed=2)
    generate(cfg)
    reference = tmp_path / "ref"
    shutil.copytree(tmp_path / "ds", reference)
    done = tmp_path / "ds" / "chairs_train" / "synth_chairs_train_000000"
    partial = tmp_path / "ds" / "chairs_train" / "synth_chairs_train_000001"
    (done / "sentinel").write_text("kept")  # a finished object is not touched again
    marker_time = (done / MARKER).stat().st_mtime_ns
    (partial / MARKER).unlink()  # crashed before the marker: garbage and missing files
    (partial / "rgb" / "000001.png").write_bytes(b"garbage")
    (partial / "depth" / "000002.npz").unlink()
    generate(cfg)
    assert (done / "sentinel").read_text() == "kept" and (done / MARKER).stat().st_mtime_ns == marker_time
    (done / "sentinel").unlink()
    _assert_same_dataset(tmp_path / "ds", reference)
    # growing a split keeps the existing objects and adds new ones
    card = generate(replace(cfg, train_objects=3))
    assert card["counts"]["train"] == 3 and (done / MARKER).stat().st_mtime_ns == marker_time
    with pytest.raises(DepthnerfError, match="different settings"):
        generate(replace(cfg, seed=99))


def test_cli(tmp_path: Path, capsys) -> None:
    args = ["synth", "--category", "cars", "--out", str(tmp_path / "cli"), "--train-objects", "1", "--val-objects",
            "0", "--test-objects", "0", "--resolution", "16", "--views-train", "2", "--quiet"]
    assert cli_main(args) == 0
    assert len(list((tmp_path / "cli" / "cars_train" / "synth_cars_train_000000" / "rgb").glob("*.png"))) == 2
    assert cli_main(args[:-1] + ["--workers", "0"]) == 2
    assert capsys.readouterr().err.strip().startswith("error: synth:")
    (tmp_path / "file").write_text("x")
    assert cli_main(["synth", "--category", "chairs", "--out", str(tmp_path / "file")]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'file'}: --out is a file, not a folder\n"


def test_no_progress_is_the_flag_every_command_shares_and_quiet_stays_its_alias(tmp_path: Path, capsys) -> None:
    base = ["synth", "--category", "cars", "--train-objects", "1", "--val-objects", "0", "--test-objects", "0",
            "--resolution", "16", "--views-train", "2"]
    assert cli_main(base + ["--out", str(tmp_path / "shown")]) == 0
    assert "synth cars" in capsys.readouterr().err  # the bar, by default
    for flag in ("--no-progress", "--quiet"):
        assert cli_main(base + ["--out", str(tmp_path / flag.strip("-")), flag]) == 0
        assert "synth cars" not in capsys.readouterr().err


def test_work_the_disk_cannot_hold_is_refused_before_anything_is_written(tmp_path: Path, capsys, monkeypatch):
    """10^8 views an object was the kernel's out-of-memory kill, without a message."""
    out = tmp_path / "huge" / "data"
    args = ["synth", "--category", "cars", "--out", str(out), "--train-objects", "2", "--val-objects", "0",
            "--test-objects", "1", "--resolution", "64", "--views-train", "100000000", "--views-test", "3", "--quiet"]
    free = shutil.disk_usage(tmp_path).free
    need = (2 * 100_000_000 + 3) * (1024 + 0.25 * 64 * 64)
    assert need > free  # 205 GB: more than this machine's disk
    assert cli_main(args) == 2
    assert capsys.readouterr().err == (f"error: {out}: 3 objects of 200,000,003 views in all need at least "
                                       f"{need / 1e9:,.1f} GB, and the disk has {free / 1e9:,.1f} GB free; lower "
                                       "--views-train, --views-test, --resolution or the object counts\n")
    assert not (tmp_path / "huge").exists()
    monkeypatch.setattr("shutil.disk_usage", lambda path: shutil._ntuple_diskusage(10**6, 10**6 - 4000, 4000))

    def small(name: str, views: int) -> list[str]:
        return ["synth", "--category", "cars", "--out", str(tmp_path / name), "--train-objects", "1",
                "--val-objects", "0", "--test-objects", "0", "--resolution", "16", "--views-train", str(views),
                "--quiet"]

    assert cli_main(small("fits", 2)) == 0  # 2 x (1024 + 64) bytes fit in 4000
    assert cli_main(small("fits", 2)) == 0  # nothing left to make: nothing to fit
    assert cli_main(small("four", 4)) == 2  # 4352 bytes do not
    assert "1 object of 4 views in all need at least 0.0 GB" in capsys.readouterr().err
    assert not (tmp_path / "four").exists()


def test_cli_out_of_memory_is_one_line(tmp_path: Path, capsys, monkeypatch) -> None:
    """A resolution too large for memory was the CPU allocator's traceback (rc 1)."""
    def too_big(config):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:121] data. DefaultCPUAllocator: can't allocate memory: "
                           "you tried to allocate 40000000000 bytes. Error code 12 (Cannot allocate memory)")

    monkeypatch.setattr("depthnerf.commands.synth.generate", too_big)
    args = ["synth", "--category", "cars", "--out", str(tmp_path / "big"), "--resolution", "100000", "--quiet"]
    assert cli_main(args) == 2
    err = capsys.readouterr().err
    assert err == (f"error: out of memory (could not allocate 37.3 GiB) rendering cars at --resolution 100000 "
                   f"(--views-train 50, --views-test 251); lower them (finished objects in {tmp_path / 'big'} are "
                   f"kept)\n")
