"""The package's structure: the import graph is the one-way stage chain, estimator names live in one registry,
every checkpoint carries an inference spec (older ones derive it), and a training config that asks for
something training does not do is rejected when it is built."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fixtures_scripts import load_script

from depthnerf.cli import main
from depthnerf.config_io import to_dict
from depthnerf.depth.estimators import CACHED_ESTIMATORS, ESTIMATORS, PHOTO_ESTIMATORS, estimator_entry
from depthnerf.depth.prior import PriorConfig, portable_prior
from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.load import load_pretrained, shipped_checkpoints
from depthnerf.pretrained.spec import SPEC_KEY, model_config_from_dict, spec_from_json, spec_from_metadata
from depthnerf.pretrained.weights import read_weights, save_weights
from depthnerf.train.config import from_dict_config, inference_spec, preset, with_prior

ROOT = Path(__file__).resolve().parent.parent


def _graph_module():
    return load_script("import_graph")


def test_import_graph_is_the_stage_chain():
    graph = _graph_module()
    full = graph.build_graph()
    assert graph.back_edges(full) == []
    assert graph.cycles(full) == []  # annotation-only (`if TYPE_CHECKING:`) cycles count too
    assert not {graph.stage_of(m) for m in full} - set(graph.STAGES)
    # eval, reconstruct and train never import each other, and nothing below them imports them
    for module, deps in full.items():
        stage = graph.stage_of(module)
        if stage in {"data", "depth", "model", "render", "pretrained"}:
            assert not {graph.stage_of(d) for d in deps} & {"train", "eval", "reconstruct", "commands"}, module


def test_cycle_finder_against_a_known_graph():
    graph = _graph_module()
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e2"}, "e2": set()}
    assert graph.cycles(g) == [["a", "b", "c"]]
    back = graph.back_edges({"depthnerf.data.x": {"depthnerf.render.y"}, "depthnerf.render.y": {"depthnerf.data.x"},
                             "depthnerf.eval.z": {"depthnerf.train.w"}, "depthnerf.train.w": set()})
    assert back == [("depthnerf.data.x", "depthnerf.render.y"), ("depthnerf.eval.z", "depthnerf.train.w")]


def test_import_graph_script_exits_clean():
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "import_graph.py")], capture_output=True, text=True,
                         cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "import cycles: 0" in out.stdout and "back-edges against the chain: 0" in out.stdout
    assert "annotation-only cycles (through `if TYPE_CHECKING:` imports): 0" in out.stdout


def test_import_graph_script_fails_on_an_annotation_only_cycle(tmp_path, capsys):
    graph = _graph_module()
    pkg = tmp_path / "depthnerf"
    (pkg / "data").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "data" / "__init__.py").write_text("")
    (pkg / "data" / "a.py").write_text("from depthnerf.data.b import B\n\nA = B\n")
    (pkg / "data" / "b.py").write_text("from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
                                       "    from depthnerf.data.a import A\n\nB = int\n")
    assert graph.cycles(graph.build_graph(pkg, runtime_only=True)) == []
    assert graph.cycles(graph.build_graph(pkg)) == [["depthnerf.data.a", "depthnerf.data.b"]]
    assert graph.main(["--root", str(pkg)]) == 1
    out = capsys.readouterr().out
    assert "import cycles: 0" in out
    assert "annotation-only cycles (through `if TYPE_CHECKING:` imports): 1" in out
    assert "cycle: depthnerf.data.a <-> depthnerf.data.b" in out
    (pkg / "data" / "b.py").write_text("B = int\n")  # the same package without the annotation import passes
    assert graph.main(["--root", str(pkg)]) == 0



def _text_writes(tree) -> list[int]:
    """Lines of ``x.write_text(...)``, ``x.write_bytes(...)``, ``json.dump(...)`` and ``open(..., "w"/"x")``: whole-file
    writes. (Appending to a log, ``open(..., "a")``, is allowed: ``train/run_log.py`` drops a torn last line.)"""
    import ast

    lines = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
        mode = node.args[1] if len(node.args) > 1 else next((k.value for k in node.keywords if k.arg == "mode"), None)
        opens_for_writing = (name == "open" and isinstance(mode, ast.Constant) and isinstance(mode.value, str)
                             and set(mode.value) & set("wx"))
        dumps = name == "dump" and isinstance(func, ast.Attribute) and getattr(func.value, "id", "") == "json"
        if name in {"write_text", "write_bytes"} or dumps or opens_for_writing:
            lines.append(node.lineno)
    return lines


def test_every_text_and_json_writer_goes_through_files_py():
    import ast

    assert _text_writes(ast.parse("p.write_text('x')\nopen(p, 'wb')\njson.dump(d, f)\nopen(p)\nopen(p, 'a')\n")) == [1, 2, 3]
    found = {}
    for path in sorted((ROOT / "depthnerf").rglob("*.py")):
        if path.name == "files.py" and path.parent.name == "depthnerf":
            continue
        if lines := _text_writes(ast.parse(path.read_text(), str(path))):
            found[str(path.relative_to(ROOT))] = lines
    assert found == {}, "write these through depthnerf.files (write_text_atomic / write_json_atomic / ...)"

def _undocumented_fields(tree) -> list[str]:
    """``Class.field`` of every dataclass (or bundle) field not followed by a docstring."""
    import ast

    missing = []
    for cls in (n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)):
        is_dataclass = any("dataclass" in ast.unparse(d) for d in cls.decorator_list)
        if not is_dataclass and not any(ast.unparse(b) in {"TensorBundle", "NamedTuple"} for b in cls.bases):
            continue
        for node, after in zip(cls.body, [*cls.body[1:], None], strict=True):
            if not isinstance(node, ast.AnnAssign) or "ClassVar" in ast.unparse(node.annotation):
                continue
            documented = (isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                          and isinstance(after.value.value, str))
            if not documented:
                missing.append(f"{cls.name}.{ast.unparse(node.target)}")
    return missing


def test_every_config_and_bundle_field_has_a_docstring():
    import ast

    example = "@dataclass\nclass A:\n    x: int = 1\n    \"\"\"Doc.\"\"\"\n    y: int = 2\n"
    assert _undocumented_fields(ast.parse(example)) == ["A.y"]
    found = {}
    for path in sorted((ROOT / "depthnerf").rglob("*.py")):
        if missing := _undocumented_fields(ast.parse(path.read_text(), str(path))):
            found[str(path.relative_to(ROOT))] = missing
    assert found == {}, "put a docstring under every field"


def test_nothing_unpickles():
    """``torch.load`` only with ``weights_only=True``, ``np.load`` never with ``allow_pickle=True``, no pickle."""
    import ast

    found = []
    for path in sorted((ROOT / "depthnerf").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}"
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] + ([node.module] if isinstance(node, ast.ImportFrom) else [])
                found += [where for n in names if n and n.split(".")[0] in {"pickle", "dill", "cloudpickle"}]
            if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Attribute):
                continue
            keywords = {k.arg: ast.unparse(k.value) for k in node.keywords}
            call = ast.unparse(node.func)
            if call == "torch.load" and keywords.get("weights_only") != "True":
                found.append(where)
            if call in {"np.load", "numpy.load"} and keywords.get("allow_pickle", "False") != "False":
                found.append(where)
    assert found == []


def test_one_estimator_registry_feeds_every_flag():
    assert ESTIMATORS == ("depth-anything-v2", "bundled", "oracle", "none")
    assert CACHED_ESTIMATORS == ("depth-anything-v2", "bundled") and PHOTO_ESTIMATORS == CACHED_ESTIMATORS
    assert estimator_entry("none").describe(None) is None
    with pytest.raises(DepthnerfError, match="unknown depth estimator 'midas'"):
        estimator_entry("midas")
    with pytest.raises(DepthnerfError, match="^unknown depth prior 'midas': choose depth-anything-v2, bundled"):
        PriorConfig("midas")
    assert not PriorConfig("none").enabled and all(PriorConfig(n).enabled for n in ESTIMATORS if n != "none")
    import argparse

    from depthnerf.commands import depth, depth_eval, evaluate, reconstruct, train
    for module, flag, names in ((train, "--depth", ESTIMATORS), (evaluate, "--depth", ESTIMATORS),
                                (depth, "--depth", ESTIMATORS), (depth_eval, "--estimator", ESTIMATORS),
                                (reconstruct, "--depth-estimator", PHOTO_ESTIMATORS)):
        parser = argparse.ArgumentParser()
        module.add_arguments(parser)
        action = next(a for a in parser._actions if flag in a.option_strings)
        assert tuple(action.choices) == names, (module.__name__, flag)


def test_spec_round_trip_and_depth_aware_derived():
    cfg = with_prior(preset("cpu-chairs"), "oracle")
    spec = inference_spec(cfg, "ab" * 32)
    again = spec_from_json(spec.to_json(), "x")
    assert again == spec and again.depth_aware and again.z_range == (1.25, 2.75) and again.resolution == 64
    assert "use_depth" not in json.dumps(to_dict(cfg))  # stored once: the prior
    assert inference_spec(with_prior(cfg, "none")).depth_aware is False
    older = {**json.loads(spec.to_json()), "extra": {"a convention": 1}}  # specs once held an unused mapping
    assert spec_from_json(json.dumps(older), "x") == spec


def test_legacy_use_depth_is_checked_then_dropped():
    cfg = preset("cpu-cars")
    legacy = to_dict(cfg)
    legacy["model"]["encoder"]["use_depth"] = True  # as configs written before the prior road stored it
    assert from_dict_config(legacy).model == cfg.model
    legacy["model"]["encoder"]["use_depth"] = False
    with pytest.raises(DepthnerfError, match="use_depth=False disagrees with the depth prior"):
        from_dict_config(legacy)
    with pytest.raises(DepthnerfError, match="disagrees"):
        model_config_from_dict({"encoder": {"use_depth": True}}, depth_aware=False, where="m")


@pytest.mark.parametrize("name", sorted(shipped_checkpoints()))
def test_shipped_checkpoints_derive_their_spec(name):
    """The stored spec equals the one derived from the training config, which is how checkpoints written before
    specs existed are read; the framing, which the -depth / -baseline specs predate, is derived once at load from
    the checkpoint card beside the weights when the spec predates it; the prior names its weights by their hash
    (``portable_prior``)."""
    pre = load_pretrained(name)
    meta = read_weights(pre.path)[1]
    derived = spec_from_metadata({k: v for k, v in meta.items() if k != SPEC_KEY}, "w")
    depth_aware = not name.endswith("-baseline")
    stored = json.loads(meta[SPEC_KEY])
    assert derived.framing is None and pre.spec.framing == "srn"
    if "framing" in stored:
        assert stored["framing"] == "srn" and pre.framing_origin == "the checkpoint's inference spec"
    else:
        assert pre.framing_origin == str(pre.path.with_suffix(".json"))
    named = portable_prior(derived.prior, pre.spec.prior_weights_hash)
    assert dataclasses.replace(derived, prior_weights_hash=pre.spec.prior_weights_hash, framing="srn",
                               prior=named) == pre.spec
    assert (pre.spec.prior_weights_hash is not None) == depth_aware  # only the stored spec has it
    train = from_dict_config(json.loads(meta["train_config"]))
    spec = pre.spec
    assert spec.category == train.data.category and spec.resolution == train.data.resolution == 64
    assert spec.prior == portable_prior(train.prior, spec.prior_weights_hash) and spec.depth_aware == depth_aware
    assert spec.model.mirror == ("-sym" in name)
    assert spec.model.prior_at_point == name.endswith("-pp")
    assert spec.render == train.render and spec.model == train.model and spec.preset == train.preset
    assert spec.z_range == {"cars": (0.8, 1.8), "chairs": (1.25, 2.75)}[spec.category]


def test_new_checkpoint_spec_wins_and_loads_the_same_model(tmp_path):
    pre = load_pretrained("cpu-chairs-depth")
    path = tmp_path / "spec_only.safetensors"
    save_weights(path, pre.model, to_dict(pre.spec.model), step=3, extra={SPEC_KEY: pre.spec.to_json()})
    again = load_pretrained(path)
    assert again.spec == pre.spec and again.step == 3 and again.data_root is None
    for (k, a), (_, b) in zip(pre.model.state_dict().items(), again.model.state_dict().items(), strict=True):
        assert torch.equal(a, b), k
    with pytest.raises(DepthnerfError, match="neither an inference spec nor a training config"):
        spec_from_metadata({"config": "{}"}, "w")


def test_training_rejects_guided_sampling_when_the_config_is_built(capsys):
    assert main(["train", "--preset", "cpu-cars", "--print-config", "--render.guided.enabled", "true"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--render.guided.enabled" in err and "eval/reconstruct --guided" in err


def test_model_needs_the_prior_exactly_when_depth_aware():
    cfg = preset("cpu-cars").model
    deep, base = PixelNeRF(cfg, depth_aware=True), PixelNeRF(cfg, depth_aware=False)
    assert deep.encoder.trunk.conv1.in_channels == 4 and base.encoder.trunk.conv1.in_channels == 3
    assert deep.coarse.cfg == base.coarse.cfg
    assert cfg.encoder.latent_size(True) - cfg.encoder.latent_size(False) == cfg.encoder.depth_channels


def test_top_level_public_api():
    import depthnerf

    assert depthnerf.Reconstructor.__module__ == "depthnerf.reconstruct.reconstructor"
    assert depthnerf.Reconstruction.__module__ == "depthnerf.reconstruct.result"
    assert set(depthnerf.__all__) >= {"Reconstructor", "ReconstructConfig", "Reconstruction", "prepare_photo"}
