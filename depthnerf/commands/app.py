"""``depthnerf app [--host 127.0.0.1] [--port 7860] [--checkpoint NAME_OR_PATH ...] [--share]``: serve the local
web page (Gradio) that turns one photo into novel views, a depth prior, a mesh and a point cloud through
:class:`~depthnerf.reconstruct.reconstructor.Reconstructor` (page: :mod:`depthnerf.app.page`; behaviour:
:mod:`depthnerf.app.logic`). Needs the optional extra ``pip install -e ".[app]"`` (gradio, imageio-ffmpeg);
without gradio the command prints that hint and exits 2. Binds 127.0.0.1 unless ``--host`` says otherwise; a
public share link only with ``--share``.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.files import make_folder

INSTALL_HINT = "depthnerf app needs gradio, which is not installed: pip install -e \".[app]\" (or 'depthnerf[app]')"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from depthnerf.pretrained.recommended import RECOMMENDED

    p.add_argument("--host", default="127.0.0.1", help="interface to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=7860, help="TCP port (default 7860)")
    p.add_argument("--checkpoint", nargs="+", action="extend", metavar="NAME_OR_PATH",
                   help="checkpoints offered in the model menu (default: the best shipped one per category, "
                        f"{' '.join(RECOMMENDED.values())})")
    p.add_argument("--share", action="store_true", help="also create a public Gradio share link (off by default)")
    p.add_argument("--views", type=int, default=8, help="default number of orbit views (default 8)")
    p.add_argument("--max-views", type=int, default=36, help="largest number of orbit views (default 36)")
    p.add_argument("--mesh-resolution", type=int, default=64,
                   help="marching-cubes samples along the mesh box's longest side (default 64; 0 = no mesh)")
    p.add_argument("--device", default="cpu", help="torch device of the models: cpu (default), cuda, cuda:N or auto")
    p.add_argument("--work-dir", type=Path,
                   help="where runs are written (default: a temporary folder, removed when the app stops)")
    p.add_argument("--background-model", metavar="NAME_OR_FILE",
                   help="background model when the page's field is empty: rembg model name or .onnx file "
                        "(default u2net from rembg's model folder; needs pip install 'depthnerf[bg]')")


def check_menu(checkpoints: tuple[str, ...]) -> None:
    """One line naming ``--checkpoint`` when a menu entry names no checkpoint (a shipped name, weights file,
    checkpoint or run folder; a Hub file is fetched when it is chosen): only the first one loads before the page
    serves."""
    from depthnerf.pretrained.hub import is_hub_reference
    from depthnerf.pretrained.load import resolve_checkpoint

    for checkpoint in checkpoints:
        if not is_hub_reference(checkpoint):
            try:
                resolve_checkpoint(checkpoint)
            except DepthnerfError as err:
                raise DepthnerfError(f"--checkpoint {err}") from None


def run(args: argparse.Namespace) -> int:
    if importlib.util.find_spec("gradio") is None:
        raise DepthnerfError(INSTALL_HINT)
    from depthnerf.app.logic import SHIPPED_MODELS, AppConfig, check_port
    from depthnerf.distributed import pick_device
    from depthnerf.render.mesh import check_mesh_resolution

    if not 1 <= args.views <= args.max_views:
        raise DepthnerfError(f"--views must be within 1..--max-views ({args.max_views}), got {args.views}")
    check_mesh_resolution(args.mesh_resolution)
    if not 0 < args.port < 65536:
        raise DepthnerfError(f"--port must be within 1..65535, got {args.port}")
    if args.background_model is not None:  # else the page served and every cut-out failed on it
        from depthnerf.reconstruct.background import check_model

        check_model(args.background_model)
    device = pick_device(args.device)  # a device that is not there: one line, not the first model's traceback
    checkpoints = tuple(args.checkpoint or SHIPPED_MODELS.values())
    check_menu(checkpoints)
    if args.work_dir is not None:  # a file or a folder that cannot be made: one line
        make_folder(args.work_dir, "--work-dir")
    check_port(args.host, args.port)  # before gradio is imported and the first model loaded
    config = AppConfig(host=args.host, port=args.port,
                       checkpoints=checkpoints, share=args.share,
                       views=args.views, max_views=args.max_views, mesh_resolution=args.mesh_resolution,
                       device=str(device), work_dir=args.work_dir, allow_checkpoint_paths=not args.share,
                       background_model=args.background_model)
    from depthnerf.app.page import serve

    serve(config)
    return 0
