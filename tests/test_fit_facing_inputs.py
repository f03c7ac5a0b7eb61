"""``depthnerf fit-facing`` refusing bad input in one line before any view is encoded: ``--out`` and ``--json``
that cannot be written (each named), an existing ``--out`` without ``--overwrite``, ``--out`` naming the
checkpoint itself, data of another category than the model's, and a ``--grid`` finer than the encoder's feature
maps (which ran out of memory at ``--grid 1000``)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from depthnerf.cli import main
from depthnerf.config_io import apply_overrides
from tests.fixtures_checkpoints import save_tiny, tiny_config, tiny_model
from tests.fixtures_srn import make_srn_fixture


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp("fit_facing_inputs")
    root = make_srn_fixture(tmp / "data", "cars", splits={"train": 6}, views=4, size=16)
    mirror = ["--model.mirror", "true"]
    return {"tmp": tmp, "root": root,
            "cars": save_tiny(tmp / "cars.safetensors", apply_overrides(tiny_config("cars", "none"), mirror)),
            "chairs": save_tiny(tmp / "chairs.safetensors", apply_overrides(tiny_config("chairs", "none"), mirror))}


@pytest.fixture
def no_fit(monkeypatch):
    """Fitting fails the test: a refusal must come before any work."""
    import depthnerf.train.facing_head as facing_head

    def fail(*args, **kwargs):
        raise AssertionError("fit-facing started fitting")

    monkeypatch.setattr(facing_head, "fit_facing_head", fail)
    monkeypatch.setattr(facing_head, "gather", fail)


def _fit(case: dict, out: Path, *flags: str, checkpoint: str = "cars") -> int:
    return main(["fit-facing", "--checkpoint", str(case[checkpoint]), "--data", str(case["root"]), "--category",
                 "cars", "--views-per-object", "1", "--grid", "2", "--out", str(out), *flags])


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def test_unwritable_json_is_named_before_any_work(case, tmp_path, capsys, no_fit):
    out = tmp_path / "h.safetensors"
    (tmp_path / "afile").write_text("x")
    assert _fit(case, out, "--json", str(tmp_path)) == 2
    assert _one_error_line(capsys) == f"error: {tmp_path}: --json is a folder; name the file to write\n"
    json_path = tmp_path / "afile" / "x.json"
    assert _fit(case, out, "--json", str(json_path)) == 2
    assert _one_error_line(capsys) == (f"error: {json_path}: --json lies under {tmp_path / 'afile'}, which is a "
                                       "file, not a folder\n")
    assert _fit(case, out, "--json", str(out)) == 2
    assert "--json names the --out file" in _one_error_line(capsys)
    assert not out.exists()


def test_unwritable_out_is_named_before_any_work(case, tmp_path, capsys, no_fit):
    (tmp_path / "afile").write_text("x")
    folder = tmp_path / "dir.safetensors"
    folder.mkdir()
    assert _fit(case, folder) == 2
    assert _one_error_line(capsys) == f"error: {folder}: --out is a folder; name the file to write\n"
    under = tmp_path / "afile" / "h.safetensors"
    assert _fit(case, under) == 2
    assert f"{under}: --out lies under {tmp_path / 'afile'}, which is a file" in _one_error_line(capsys)


def test_existing_out_needs_overwrite_and_the_checkpoint_is_never_replaced(case, tmp_path, capsys, no_fit):
    out = tmp_path / "h.safetensors"
    out.write_bytes(b"earlier")
    assert _fit(case, out) == 2
    assert _one_error_line(capsys) == (f"error: {out}: exists; pass --overwrite to replace it, or choose another "
                                       "--out\n")
    assert out.read_bytes() == b"earlier"
    before = case["cars"].read_bytes()
    for flags in ((), ("--overwrite",)):
        assert _fit(case, case["cars"], *flags) == 2
        assert "--out is the checkpoint's own weights file" in _one_error_line(capsys)
    link = tmp_path / "link.safetensors"  # another name of the same file
    link.symlink_to(case["cars"])
    assert _fit(case, link, "--overwrite") == 2
    assert "--out is the checkpoint's own weights file" in _one_error_line(capsys)
    assert case["cars"].read_bytes() == before


def test_overwrite_replaces_an_existing_out(case, tmp_path, capsys):
    out = tmp_path / "h.safetensors"
    out.write_bytes(b"earlier")
    assert _fit(case, out, "--overwrite") == 0
    assert f"wrote {out}" in capsys.readouterr().out and out.read_bytes() != b"earlier"


def test_data_of_another_category_is_refused(case, tmp_path, capsys, monkeypatch):
    import depthnerf.train.facing_head as facing_head

    monkeypatch.setattr(facing_head, "gather", lambda *a, **k: pytest.fail("views encoded"))
    assert _fit(case, tmp_path / "h.safetensors", checkpoint="chairs") == 2
    assert _one_error_line(capsys) == (f"error: {case['chairs']}: a chairs model, given cars data (--category "
                                       "cars); fit its facing head on chairs views\n")


def test_grid_finer_than_the_feature_maps_is_refused(case, tmp_path, capsys, monkeypatch):
    import depthnerf.train.facing_head as facing_head

    monkeypatch.setattr(facing_head, "gather", lambda *a, **k: pytest.fail("views encoded"))
    out = tmp_path / "h.safetensors"
    for grid in ("9", "1000"):
        assert main(["fit-facing", "--checkpoint", str(case["cars"]), "--data", str(case["root"]), "--category",
                     "cars", "--grid", grid, "--out", str(out)]) == 2
        assert _one_error_line(capsys) == (f"error: --grid must be <= 8 (the encoder's feature maps are 8 x 8 at the "
                                           f"model's resolution 16), got {grid}\n")
    assert not out.exists()


def test_a_fit_larger_than_the_host_memory_is_refused(case, tmp_path, capsys, monkeypatch):
    """The fit's memory (``FIT_BYTES_PER_VALUE`` a pooled value) is sized before any view is encoded: above all of
    the host's memory, one line naming the settings that size it."""
    import depthnerf.train.facing_head as facing_head

    monkeypatch.setattr(facing_head, "gather", lambda *a, **k: pytest.fail("views encoded"))
    dim = tiny_model(apply_overrides(tiny_config("cars", "none"), [])).encoder.latent_size * 4
    need = facing_head.fit_memory(6 * 2, dim)  # 6 objects x 1 view x 2 (--inputs both); --grid 2
    monkeypatch.setattr(facing_head, "device_memory", lambda device: need - 1)
    out = tmp_path / "h.safetensors"
    assert _fit(case, out) == 2
    err = _one_error_line(capsys)
    assert err.startswith(f"error: 12 encoded views (6 objects x up to 1 (--views-per-object) x 2 for --inputs "
                          f"both) x {dim:,} pooled values (--grid 2: {dim // 4} channels x 2^2): the fit would need "
                          "about "), err
    assert "more than all the host's memory" in err and "lower --grid" in err and not out.exists()
    monkeypatch.setattr(facing_head, "device_memory", lambda device: need)
    monkeypatch.setattr(facing_head, "gather", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("sized")))
    with pytest.raises(RuntimeError, match="sized"):  # at the bound the fit goes on to encode the views
        _fit(case, out)
    assert capsys.readouterr().err.startswith("fitting on 12 encoded views")


@pytest.mark.parametrize("scale", [1.0, 0.5, 1.5])
def test_feature_side_is_the_encoded_maps_side(scale):
    cfg = apply_overrides(tiny_config("cars", "none"), ["--model.encoder.image_scale", str(scale)])
    encoder = tiny_model(cfg).encoder.eval()
    for resolution in (16, 17, 30):
        with torch.no_grad():
            features = encoder(torch.rand(1, 3, resolution, resolution))
        assert features.shape[-2:] == (cfg.model.encoder.feature_side(resolution),) * 2
