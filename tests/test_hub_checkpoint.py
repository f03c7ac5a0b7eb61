"""Checkpoints on the Hugging Face Hub (``hf://OWNER/REPO[/FILE][@REVISION]``, depthnerf/pretrained/hub.py).

No network here: each test builds a Hugging Face cache by hand (``models--OWNER--REPO/refs/<rev>`` holding a commit
hash, ``snapshots/<hash>/<file>``, the layout ``huggingface_hub`` writes) and runs ``huggingface_hub``'s real
download code against it offline, so what is tested is the reference parsing, the cache lookup and the errors.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import save_tiny, tiny_config

from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.hub import parse_hub_reference
from depthnerf.pretrained.load import load_pretrained, resolve_checkpoint

hub_constants = pytest.importorskip("huggingface_hub.constants")

COMMIT = "0123456789abcdef0123456789abcdef01234567"


def cached_repo(cache: Path, repo_id: str, files: dict[str, Path], revision: str = "main") -> None:
    """``files`` (name in the repository -> local file) in ``cache`` as ``huggingface_hub`` lays out a download."""
    repo = cache / f"models--{repo_id.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True, exist_ok=True)
    (repo / "refs" / revision).write_text(COMMIT)
    for name, source in files.items():
        target = repo / "snapshots" / COMMIT / name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(source.read_bytes())


@pytest.fixture
def offline_cache(tmp_path, monkeypatch) -> Path:
    cache = tmp_path / "hf-cache"
    cache.mkdir()
    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(hub_constants, "HF_HUB_OFFLINE", True)
    return cache


@pytest.mark.parametrize(("reference", "expect"), [
    ("hf://alice/depthnerf-cars", ("alice/depthnerf-cars", "model.safetensors", None)),
    ("hf://alice/depthnerf-cars/", ("alice/depthnerf-cars", "model.safetensors", None)),
    ("hf://alice/dn/paper/cars.safetensors", ("alice/dn", "paper/cars.safetensors", None)),
    ("hf://alice/dn@v1.0", ("alice/dn", "model.safetensors", "v1.0")),
    ("hf://alice/dn/cars.safetensors@" + COMMIT, ("alice/dn", "cars.safetensors", COMMIT)),
])
def test_references_name_a_repository_file_and_revision(reference, expect):
    assert parse_hub_reference(reference) == expect


@pytest.mark.parametrize(("reference", "says"), [
    ("hf://alice", "hf://OWNER/REPO[/FILE][@REVISION]"),
    ("hf://", "hf://OWNER/REPO[/FILE][@REVISION]"),
    ("hf://alice/dn@", "empty revision"),
    ("hf://alice/dn/model.pt", "not a .safetensors file"),
    ("hf://alice/dn/pytorch_model.bin@main", "nothing is unpickled"),
])
def test_malformed_references_are_one_line(reference, says):
    with pytest.raises(DepthnerfError) as err:
        parse_hub_reference(reference)
    assert says in str(err.value) and str(err.value).startswith(reference) and "\n" not in str(err.value)


def test_a_cached_hub_checkpoint_loads_as_the_local_file(offline_cache, tmp_path):
    weights = save_tiny(tmp_path / "model.safetensors", tiny_config("cars", "none"))
    other = save_tiny(tmp_path / "other.safetensors", tiny_config("chairs", "none"), seed=3)
    cached_repo(offline_cache, "alice/depthnerf-cars", {"model.safetensors": weights, "v2/chairs.safetensors": other})
    path = resolve_checkpoint("hf://alice/depthnerf-cars")
    assert path.is_file() and path.read_bytes() == weights.read_bytes() and offline_cache in path.parents
    hub, local = load_pretrained("hf://alice/depthnerf-cars"), load_pretrained(weights)
    assert hub.sha256 == local.sha256 and hub.spec == local.spec and hub.step == local.step
    for (name, a), (_, b) in zip(hub.model.state_dict().items(), local.model.state_dict().items(), strict=True):
        assert torch.equal(a, b), name
    chairs = load_pretrained("hf://alice/depthnerf-cars/v2/chairs.safetensors@main")
    assert chairs.spec.category == "chairs" and chairs.sha256 == load_pretrained(other).sha256


def test_the_python_api_takes_a_hub_reference(offline_cache, tmp_path):
    from depthnerf import Reconstructor

    weights = save_tiny(tmp_path / "model.safetensors", tiny_config("cars", "none"))
    cached_repo(offline_cache, "alice/depthnerf-cars", {"model.safetensors": weights}, revision="v1")
    rec = Reconstructor.from_pretrained("hf://alice/depthnerf-cars@v1")
    assert rec.pretrained.sha256 == load_pretrained(weights).sha256


def test_missing_repository_file_or_revision_is_one_line(offline_cache, tmp_path):
    weights = save_tiny(tmp_path / "model.safetensors", tiny_config("cars", "none"))
    cached_repo(offline_cache, "alice/dn", {"model.safetensors": weights})
    for reference in ("hf://alice/elsewhere", "hf://alice/dn/cars.safetensors", "hf://alice/dn@v9"):
        with pytest.raises(DepthnerfError) as err:
            resolve_checkpoint(reference)
        message = str(err.value)
        assert message.startswith(reference + ": ") and "\n" not in message, message
        assert "not in the local Hugging Face cache" in message, message


def test_the_cli_names_the_reference_in_one_line(tmp_path):
    """``reconstruct --checkpoint hf://...`` offline with an empty cache: exit 2, one ``error:`` line naming it."""
    photo = Path(__file__).resolve().parents[1] / "depthnerf" / "app" / "examples" / "car_rgba.png"
    env = {"HF_HUB_OFFLINE": "1", "HF_HUB_CACHE": str(tmp_path / "empty-cache"), "PATH": "/usr/bin:/bin",
           "OMP_NUM_THREADS": "1", "HOME": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-m", "depthnerf", "reconstruct", str(photo), "--checkpoint",
                           "hf://alice/depthnerf-cars", "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert lines[-1].startswith("error: hf://alice/depthnerf-cars: not in the local Hugging Face cache"), lines


def test_a_hub_folder_round_trips_through_the_cache(offline_cache, tmp_path, capsys):
    """``scripts/hub_folder.py`` lays a checkpoint out as a model repository; that repository, as the Hub would
    serve it, loads as ``hf://OWNER/REPO`` to the same weights, with a card that starts with the Hub's header."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "hub_folder", Path(__file__).resolve().parents[1] / "scripts" / "hub_folder.py")
    hub_folder = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hub_folder)
    weights = save_tiny(tmp_path / "tiny-chairs.safetensors", tiny_config("chairs", "none"))
    folder = tmp_path / "repo"
    assert hub_folder.main([str(weights), str(folder)]) == 0
    card = (folder / "README.md").read_text()
    assert card.startswith("---\nlibrary_name: depthnerf\nlicense: mit\n") and "- chairs\n- baseline\n---" in card
    assert "# tiny-chairs" in card  # no card beside the weights: one made from the spec
    cached_repo(offline_cache, "alice/tiny-chairs", {p.name: p for p in folder.iterdir()})
    assert load_pretrained("hf://alice/tiny-chairs").sha256 == load_pretrained(weights).sha256
    assert hub_folder.main([str(weights), str(folder)]) == 2
    assert "already exists" in capsys.readouterr().err
    (tmp_path / "tiny-chairs.md").write_text("# my card\n")
    assert hub_folder.main([str(weights), str(tmp_path / "repo2")]) == 0
    assert (tmp_path / "repo2" / "README.md").read_text().endswith("---\n\n# my card\n")
