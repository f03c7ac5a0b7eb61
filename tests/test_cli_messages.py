"""Cases a new user trips on get one clear line: a flag that cannot work, a checkpoint that cannot take what is
asked of it, an output folder that is not free, a file where a folder is expected, a corrupt depth map, a busy
port. Each goes through the CLI entry (``depthnerf.cli.main``) and checks the message and the exit status."""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures_srn import make_srn_fixture
from PIL import Image

from depthnerf.app.logic import EXAMPLES_DIR, check_port, collect_outputs
from depthnerf.app.messages import check_upload
from depthnerf.cli import main
from depthnerf.data.srn_format import read_depth
from depthnerf.errors import DepthnerfError

CAR = EXAMPLES_DIR / "car_rgba.png"
QUICK = ["--views", "2", "--no-progress"]


def reconstruct(*args: str | Path) -> int:
    return main(["reconstruct", *map(str, args)])


def one_error(capsys) -> str:
    """The single stderr line of a failed command (asserted to be exactly one ``error: ...`` line)."""
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err.strip()


def test_mesh_resolution_is_checked_and_0_writes_no_mesh(tmp_path, capsys):
    for value in ("-1", "5000"):  # 5000 ran the renders first, then sampled 10^11 densities
        assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "bad", "--mesh-resolution",
                           value, *QUICK) == 2
        assert one_error(capsys) == f"error: --mesh-resolution must be 0 (no mesh) or >= 2 and at most 1024 (up to 1024^3 density samples, 4.3 GB), got {value}"
        assert not (tmp_path / "bad").exists()
    for flag in ("--views", "--render-resolution", "--chunk"):
        assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "bad", flag, "0") == 2
        assert one_error(capsys) == f"error: {flag} must be >= 1, got 0"
    for value in ("-0.1", "nan", "inf"):
        assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "bad", "--mesh-fill", value) == 2
        assert one_error(capsys) == f"error: --mesh-fill must be a number >= 0, got {float(value)!r}"
    out = tmp_path / "out"
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--mesh-resolution", "0", *QUICK) == 0
    assert "no mesh (--mesh-resolution 0)" in capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["mesh"]["made"] is False and manifest["files"]["mesh_ply"] is manifest["files"]["mesh_glb"] is None
    assert not (out / "mesh.ply").exists() and not (out / "mesh.glb").exists()
    assert (out / "views" / "view_001.png").is_file()
    page = collect_outputs(out, manifest, "car_rgba.png")  # what the app shows for the same folder
    assert page.viewer_glb is None and page.downloads == [out / "points.ply"]
    assert "**Mesh** none (--mesh-resolution 0)" in page.details


def test_an_earlier_reconstruction_is_kept_unless_overwrite(tmp_path, capsys):
    out = tmp_path / "out"
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--mesh-resolution", "0", *QUICK) == 0
    (out / "notes.txt").write_text("mine")
    (out / "views" / "sketch.png").write_bytes(b"mine")
    before = (out / "manifest.json").read_bytes()
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, *QUICK) == 2
    err = one_error(capsys)
    assert err.startswith(f"error: {out}: holds an earlier reconstruction (") and "pass --overwrite" in err
    assert (out / "manifest.json").read_bytes() == before
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--overwrite", "--views", "1",
                       "--mesh-resolution", "4", "--no-progress") == 0
    assert sorted(p.name for p in (out / "views").iterdir()) == ["sketch.png", "view_000.png"]  # view_001 gone
    assert (out / "notes.txt").read_text() == "mine" and (out / "mesh.ply").is_file()
    assert json.loads((out / "manifest.json").read_text())["settings"]["views"] == 1


def test_a_failed_overwrite_leaves_the_earlier_reconstruction_as_it_was(tmp_path, capsys, monkeypatch):
    import errno

    import depthnerf.reconstruct.exports as exports

    out = tmp_path / "out"
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--mesh-resolution", "0", *QUICK) == 0
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}

    def disk_full(*args, **kwargs):  # the turntable comes after the views and depths: a half-written folder
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(exports.iio, "imwrite", disk_full)
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--overwrite", "--views", "3",
                       "--mesh-resolution", "0", "--no-progress") == 2
    err = one_error(capsys)
    assert err == (f"error: {out}: cannot write the reconstruction (No space left on device); the earlier "
                   "reconstruction there is left as it was")
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before  # no staging folder left, no file changed, no third view
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


def test_an_unusable_output_folder_fails_before_any_work(tmp_path, capsys, monkeypatch):
    import depthnerf.infer.session as session
    import depthnerf.pretrained.load as load

    def never(*args, **kwargs):
        raise AssertionError("the model was loaded before the output folder was checked")

    # patched where it is looked up as well: a module that first imports the name while the patch is on would keep
    # `never` for the rest of the process (the CUDA run's worker order found that)
    monkeypatch.setattr(load, "load_pretrained", never)
    monkeypatch.setattr(session, "load_pretrained", never)
    (tmp_path / "a_file").write_text("x")
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "a_file" / "out") == 2
    assert one_error(capsys) == (f"error: {tmp_path / 'a_file' / 'out'}: --out lies under "
                                 f"{tmp_path / 'a_file'}, which is a file, not a folder")
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "a_file") == 2
    assert one_error(capsys) == f"error: {tmp_path / 'a_file'}: --out is a file, not a folder"
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", locked / "out") == 2
        assert "cannot write the output folder" in one_error(capsys)


def test_overwrite_never_replaces_the_photo_or_mask_it_reads(tmp_path, capsys, monkeypatch):
    """A photo named ``input.png`` (or a mask named ``input_mask.png``) inside ``--out`` is one of the files a
    reconstruction writes there: ``--overwrite`` deleted the user's own photo and put the framed view in its
    place. It is refused before any work, with or without ``--overwrite``; files of the same name elsewhere are
    not."""
    import depthnerf.infer.session as session

    monkeypatch.setattr(session, "load_pretrained", lambda *a, **k: pytest.fail("loaded before --out was checked"))
    out = tmp_path / "car"
    (out / "views").mkdir(parents=True)
    photo, mask = out / "input.png", out / "views" / "view_000.png"
    photo.write_bytes(CAR.read_bytes())
    Image.fromarray(np.full((16, 16), 255, np.uint8)).save(mask)
    for args in ((photo,), (CAR, "--mask", mask)):
        for flags in ((), ("--overwrite",)):
            assert reconstruct(*args, "--checkpoint", "cpu-cars-depth", "--out", out, *flags) == 2
            name = "input.png" if args[0] == photo else "views/view_000.png"
            assert one_error(capsys) == (f"error: {out / name}: a reconstruction in {out} writes a file of this name; "
                                         "choose another --out, or move the file")
    assert photo.read_bytes() == CAR.read_bytes() and mask.is_file()


def test_precision_flags_the_device_cannot_run_are_refused_before_loading(tmp_path, capsys, monkeypatch):
    import depthnerf.infer.session as session

    monkeypatch.setattr(session, "load_pretrained", lambda *a, **k: pytest.fail("loaded before the flags' check"))
    out = tmp_path / "o"
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--device", "cpu", "--bf16-residual") == 2
    assert one_error(capsys) == ("error: --bf16-residual is a CUDA setting (bf16 autocast); on cpu the fields render "
                                 "in fp32")
    assert not out.exists()
    with pytest.raises(SystemExit):
        main(["eval", "--checkpoint", "cpu-cars-depth", "--data", str(tmp_path), "--compile-mode", "fast"])
    assert "argument --compile-mode: invalid choice: 'fast'" in capsys.readouterr().err


@pytest.mark.parametrize("flag, value, line", [
    ("--focal", "0", "--focal must be > 0, got 0.0"), ("--radius", "0", "--radius must be > 0, got 0.0"),
    ("--radius", "nan", "--radius must be > 0, got nan"),
    ("--elevation", "90", "--elevation must be within [-89, 89] degrees, got 90.0")])
def test_camera_flags_are_named_and_zero_is_not_the_default(tmp_path, capsys, flag, value, line):
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "o", flag, value, *QUICK) == 2
    assert one_error(capsys) == f"error: {line}"
    assert not (tmp_path / "o").exists()


def test_a_checkpoint_with_non_finite_weights_is_refused(tmp_path, capsys):
    """A damaged file (or a diverged run) would render black images: refused at load, naming the tensor."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    from depthnerf.pretrained.load import load_pretrained

    src = load_pretrained("cpu-cars-depth").path
    with safe_open(str(src), framework="pt") as f:
        meta = f.metadata()
    tensors = load_file(str(src))
    floats = sorted(k for k, t in tensors.items() if t.is_floating_point())
    name = floats[len(floats) // 2]
    tensors[name].view(-1)[:3] = float("nan")
    bad = tmp_path / "bad.safetensors"
    save_file(tensors, str(bad), metadata=meta)
    assert reconstruct(CAR, "--checkpoint", bad, "--out", tmp_path / "o", *QUICK) == 2
    assert one_error(capsys) == (f"error: {bad}: tensor {name} holds 3 non-finite values (NaN or inf): the file is "
                                 "damaged, or the run that wrote it diverged")


def test_resume_into_a_folder_without_a_run_says_so_when_the_data_is_missing(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the preset's default data root does not exist here
    assert main(["train", "--out", str(tmp_path / "runs" / "typo"), "--resume", "--device", "cpu"]) == 2
    err = one_error(capsys)
    assert err.endswith(f"(--resume found no checkpoint in {tmp_path / 'runs' / 'typo'}, so a new run would start "
                        "there: check --out)"), err



def test_resume_of_a_run_without_its_config_is_refused(tmp_path, capsys):
    """Its checkpoints were trained with settings only config.json holds: the preset's would silently replace them."""
    run = tmp_path / "run"
    (run / "checkpoints" / "step_00000002").mkdir(parents=True)
    assert main(["train", "--out", str(run), "--resume", "--device", "cpu", "--data", str(tmp_path)]) == 2
    assert one_error(capsys) == (f"error: {run / 'config.json'}: missing, so the run's checkpoints cannot be resumed "
                                 "with the settings they were trained with; restore it, or train a new run in "
                                 "another --out")
    assert not (run / "config.json").exists()

def test_guided_before_the_image_says_how_to_write_it(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["reconstruct", "--checkpoint", "cpu-cars-depth", "--out", str(tmp_path / "o"), "--guided", str(CAR)])
    assert (f"argument --guided: expected a sample budget (an integer), got '{CAR}'; for the default budget put "
            "--guided after the image, or write --guided 48") in capsys.readouterr().err


def test_facing_on_a_model_without_the_mirror_branch_is_a_note(tmp_path, capsys):
    for facing, noted in ((["--facing", "0"], True), ([], False)):
        out = tmp_path / f"o{len(facing)}"
        assert reconstruct(CAR, "--checkpoint", "cpu-cars-depth", "--out", out, "--mesh-resolution", "0",
                           *facing, *QUICK) == 0
        err = capsys.readouterr().err
        assert ("note: --facing has no effect: cpu-cars-depth has no mirror-symmetric conditioning" in err) == noted


def test_a_baseline_checkpoint_refuses_a_depth_prior(tmp_path, capsys):
    assert reconstruct(CAR, "--checkpoint", "cpu-cars-baseline", "--depth", "bundled", "--out", tmp_path / "o") == 2
    assert one_error(capsys) == ("error: cpu-cars-baseline: a baseline checkpoint (trained without a depth prior) "
                                 "takes no depth prior; drop --depth bundled, or use a depth-aware checkpoint")


def test_the_cli_and_the_app_refuse_the_same_formats(tmp_path, capsys):
    gif = tmp_path / "car.gif"
    Image.open(CAR).save(gif)
    assert reconstruct(gif, "--checkpoint", "cpu-cars-depth", "--out", tmp_path / "o", *QUICK) == 2
    line = f"{gif}: GIF images are not supported; use a PNG, JPEG or WebP photo"
    assert one_error(capsys) == f"error: {line}"
    with pytest.raises(DepthnerfError, match="car.gif: GIF images are not supported; use a PNG, JPEG or WebP"):
        check_upload(gif)
    webp = tmp_path / "car.webp"
    Image.open(CAR).save(webp, lossless=True)
    assert check_upload(webp) == webp  # what the app takes, reconstruct takes too (no error before the render)


@pytest.mark.parametrize(("flags", "line"), [
    (["--max-steps", "-5"], "--max-steps must be >= 1, got -5"),
    (["--max-steps", "0"], "--max-steps must be >= 1, got 0"),
    (["--checkpoint-every", "0"], "--checkpoint-every must be >= 1, got 0"),
    (["--seed", "-1"], "--seed must be >= 0, got -1"),  # as synth and demo refuse it
    (["--schedule.lr", "-1"], "--schedule.lr must be > 0, got -1.0"),
    (["--schedule.rays_per_object", "0"], "--schedule.rays_per_object must be >= 1, got 0"),
    (["--model.coarse.d_hidden", "-4"], "--model.coarse.d_hidden -4: model config: field.d_hidden must be >= 1, got -4"),
])
def test_train_numbers_are_checked_before_the_run_folder_exists(tmp_path, capsys, flags, line):
    assert main(["train", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "run"), *flags]) == 2
    assert one_error(capsys) == f"error: {line}"
    assert not (tmp_path / "run").exists()


def test_eval_names_a_category_mismatch(tmp_path, capsys):
    data = make_srn_fixture(tmp_path / "data", "cars", {"test": 1}, views=3, size=16)
    common = ["--checkpoint", "cpu-chairs-baseline", "--data", str(data), "--no-mesh", "--no-progress"]
    assert main(["eval", *common, "--out", str(tmp_path / "e1")]) == 2
    assert one_error(capsys) == (f"error: {data}: holds cars_test but no chairs_test, and cpu-chairs-baseline is a "
                                 "chairs model; pass a chairs dataset, or --category cars to score it on cars anyway")
    assert main(["eval", *common, "--category", "cars", "--out", str(tmp_path / "e2")]) == 0
    err = capsys.readouterr().err
    assert ("warning: scoring cpu-chairs-baseline, a chairs model, on cars data (--category cars); the figures "
            "measure a category it was not trained on\n") in err
    assert json.loads((tmp_path / "e2" / "summary.json").read_text())["category"] == "cars"


def test_a_corrupt_depth_map_is_named(tmp_path, capsys):
    data = make_srn_fixture(tmp_path / "data", "cars", {"train": 1}, views=2, with_depth=True)
    bad = sorted((data / "cars_train").glob("*/depth/*.npz"))[0]
    bad.write_bytes(b"\x00garbage that is no zip archive")
    assert main(["inspect", "--data", str(data), "--strict"]) == 2
    assert one_error(capsys) == (f"error: {bad}: unreadable depth map: the file is corrupt or not a NumPy .npz "
                                 "file; rewrite it with numpy.savez")
    cases = {"empty.npz": (b"", "the file is empty; rewrite it with numpy.savez"),
             "cut.npz": (b"PK\x03\x04 and then nothing", "a truncated or corrupt .npz file (File is not a zip file)"),
             "text.npy": (b"0.5 0.5\n", "the file is corrupt or not a NumPy .npy file; rewrite it with numpy.save")}
    for name, (content, text) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(DepthnerfError) as caught:
            read_depth(tmp_path / name)
        assert str(caught.value) == f"{tmp_path / name}: unreadable depth map: {text}"
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DepthnerfError, match=r"objects.npy: unreadable depth map: it holds Python objects, not a"):
        read_depth(tmp_path / "objects.npy")


def test_inspect_names_a_file_given_for_the_data_folder(tmp_path, capsys):
    (tmp_path / "cars_card.json").write_text("{}")
    assert main(["inspect", "--data", str(tmp_path / "cars_card.json")]) == 2
    assert one_error(capsys) == (f"error: {tmp_path / 'cars_card.json'}: is a file, not a dataset folder (pass the "
                                 "folder that holds the <category>_<split>/ folders)")


@pytest.mark.parametrize(("flag", "value", "least"), [("--resolution", "7", 8), ("--workers", "0", 1),
                                                      ("--views-test", "0", 1), ("--seed", "-1", 0)])
def test_synth_names_only_the_offending_flag(tmp_path, capsys, flag, value, least):
    assert main(["synth", "--category", "cars", "--out", str(tmp_path / "d"), flag, value]) == 2
    assert one_error(capsys) == f"error: synth: {flag} must be >= {least} (got {value})"


def test_synth_with_no_objects_at_all_is_refused(tmp_path, capsys):
    assert main(["synth", "--category", "cars", "--out", str(tmp_path / "d"), "--train-objects", "0",
                 "--val-objects", "0", "--test-objects", "0"]) == 2
    assert one_error(capsys) == ("error: synth: --train-objects, --val-objects and --test-objects are all 0: nothing "
                                 "to make")
    assert not (tmp_path / "d").exists()


def test_a_busy_port_is_refused_before_anything_is_served(capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        line = f"cannot serve on 127.0.0.1:{port} (Address already in use); pass another --port"
        with pytest.raises(DepthnerfError) as caught:
            check_port("127.0.0.1", port)
        assert str(caught.value) == line
        if importlib.util.find_spec("gradio") is not None:  # without gradio the command stops at its install hint
            assert main(["app", "--port", str(port)]) == 2
            out, err = capsys.readouterr()
            assert out == "" and err == f"error: {line}\n"  # nothing loaded, nothing "serving"
    check_port("127.0.0.1", port)  # free again


def test_an_unknown_flag_is_named_with_its_subcommand(capsys):
    """A flag the subcommand does not know is reported by that subcommand, not the top level, in one line like
    every other error (a value argparse refuses too)."""
    for argv, start, end in (
            (["checkpoints", "--bogus"], "error: depthnerf checkpoints: unrecognized arguments: --bogus ",
             "(depthnerf checkpoints --help lists its options)"),
            (["synth", "--category", "boats", "--out", "x"],  # argparse quotes the choices or not by Python version
             "error: depthnerf synth: argument --category: invalid choice: 'boats' (choose from ",
             ") (depthnerf synth --help lists its options)")):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
        line = one_error(capsys)
        assert line.startswith(start) and line.endswith(end), line


@pytest.mark.parametrize(("argv", "flag"), [
    (["reconstruct", "photo.png", "--checkpoint", "cpu-cars-sym-pp", "--out", ""], "--out"),
    (["reconstruct", "photo.png", "--checkpoint", "cpu-cars-sym-pp", "--out="], "--out"),
    (["eval", "--checkpoint", "cpu-cars-sym-pp", "--out", ""], "--out"), (["train", "--out", ""], "--out"),
    (["train", "--data", ""], "--data"), (["synth", "--category", "cars", "--out", ""], "--out"),
    (["compare", "x", "--out", ""], "--out"), (["demo", "--out", ""], "--out"),
    (["fit-facing", "--checkpoint", "x", "--data", "d", "--category", "cars", "--out", ""], "--out"),
    (["inspect", "d", "--json", ""], "--json"), (["depth-eval", "--data", "d", "--json", ""], "--json"),
    (["eval", "--checkpoint", "", "--out", "o"], "--checkpoint"),
    (["reconstruct", "photo.png", "--checkpoint", "", "--out", "o"], "--checkpoint"),
    (["reconstruct", "photo.png", "--checkpoint", "x", "--out", "o", "--background-model", ""],
     "--background-model"),
    (["fit-facing", "--checkpoint", "", "--data", "d", "--category", "cars", "--out", "o.safetensors"],
     "--checkpoint"),
    (["train", "--init-from", "", "--out", "r"], "--init-from"), (["train", "--config", ""], "--config"),
    (["train", "--depth-checkpoint", "", "--print-config"], "--depth-checkpoint"),
    (["depth", "--data", "d", "--for", ""], "--for"),
    (["depth", "--data", "d", "--depth", "bundled", "--checkpoint", ""], "--depth-checkpoint"),
    (["depth-eval", "--data", "d", "--depth", "bundled", "--depth-checkpoint", ""], "--depth-checkpoint")])
def test_an_empty_path_flag_is_refused_before_any_work(argv, flag, tmp_path, capsys, monkeypatch):
    """``--out ''`` would be ``Path('')``, the current folder, where ``reconstruct`` wrote its files, and
    ``--checkpoint ''`` the run folder the command was started in: every option naming a path or a checkpoint
    refuses an empty value while the flags are parsed (an alias's refusal names the flag's first name)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    assert one_error(capsys) == (f"error: depthnerf {argv[0]}: {flag} is empty (depthnerf {argv[0]} --help lists "
                                 "its options)")
    assert not list(tmp_path.iterdir())


def test_a_shortened_flag_is_refused_not_taken_for_a_longer_one(capsys):
    """Flags count as spelled in full: ``eval --views`` is not ``--views-stride`` (``reconstruct --views`` is the
    number of orbit views), nor ``train --max`` ``--max-steps``."""
    for argv, name in ((["eval", "--checkpoint", "x", "--views", "8"], "--views"),
                       (["inspect", "--data", "x", "--str"], "--str")):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
        line = one_error(capsys)
        assert f"unrecognized arguments: {name} " in line, line
    assert main(["train", "--preset", "cpu-cars", "--max", "5"]) == 2
    assert one_error(capsys).startswith("error: --max: neither a flag of this command (--help lists them) nor a "
                                        "config field (known: data, ")


def test_app_help_does_not_import_torch():
    """``depthnerf app`` builds its parser (the default models in its help) without torch, so ``--help`` and the
    missing-extra message stay instant."""
    probe = ("import sys; from depthnerf.cli import build_parser; build_parser(['app']); "
             "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_encoder_norm_names_live_once_in_a_torch_free_module():
    """``depthnerf eval --encoder-norm`` takes its choices from ``model.config.ENCODER_NORMS``, the names
    ``PixelNeRF.encode`` checks; importing that module (through the lazy ``depthnerf.model``) imports no torch."""
    from depthnerf.cli import build_parser
    from depthnerf.model import config, pixelnerf

    probe = "import sys; import depthnerf.model.config; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    sub = next(a for a in build_parser(["eval"])._actions if a.dest == "command").choices["eval"]
    action = next(a for a in sub._actions if a.dest == "encoder_norm")
    assert action.choices is config.ENCODER_NORMS is pixelnerf.ENCODER_NORMS


def test_a_closed_stdout_pipe_ends_the_command_quietly():
    """``depthnerf train --print-config | head``: the reader closes the pipe before the config is written; the
    command stops with 141 (128 + SIGPIPE) and no traceback, at the write or when Python flushes stdout."""
    proc = subprocess.Popen([sys.executable, "-m", "depthnerf", "train", "--print-config"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    proc.stdout.close()  # before the child has written anything: it imports torch first
    _, err = proc.communicate(timeout=120)
    assert (proc.returncode, err.decode()) == (141, "")
