"""The ``depthnerf app`` page: Gradio widgets wired to :mod:`depthnerf.app.logic` (which holds all behaviour).

Imports Gradio (the ``[app]`` extra); nothing else in the package does. Requests go through Gradio's queue with
one worker (``queue(default_concurrency_limit=1)``): one reconstruction at a time, and a second tab sees its
place in the queue on its outputs. The server binds ``AppConfig.host`` (127.0.0.1 by default) and asks for a
public share link only with ``AppConfig.share``. A shared page hides its path fields, and the session refuses
local paths in any request (``AppConfig.allow_checkpoint_paths``), since its HTTP API takes every field.

A new upload clears every output of the previous one (the preview fills in the preprocessed input; errors leave
nothing stale). On exit (Ctrl+C or SIGTERM) the server closes, Gradio deletes the files it cached for this page
(uploads included; ``delete_cache``) and the temporary run folder is removed (a ``--work-dir`` is kept).
"""

from __future__ import annotations

import shutil
import signal
import threading
from pathlib import Path

import gradio as gr

from depthnerf.app.logic import (
    SHIPPED_MODELS,
    AppConfig,
    AppSession,
    RunOutputs,
    RunRequest,
    background_installed,
    check_port,
    examples,
)
from depthnerf.app.messages import prior_description
from depthnerf.errors import DepthnerfError

INTRO = """# depthnerf: one photo in, 3D out
Upload a photo of **one object** (PNG, JPEG or WebP; RGB or RGBA, any size) or pick an example, then press
**Reconstruct**. The page removes the background (the alpha channel if the image has one, else a background model
when "Remove background" is ticked and one is installed, else everything that differs from the border colour),
recentres the object at the foreground ratio, puts it on white and resizes it to the model's input; then a
depth-aware pixelNeRF renders an orbit of novel views and extracts a mesh.

**Honest note.** The shipped CPU models (`cpu-cars-sym-pp` and `cpu-chairs-sym-pp`, both with mirror-symmetric
conditioning) are small, were trained at 64 px on procedurally *synthesised* cars and chairs with the bundled depth network as
their prior, and have never seen a real photo: expect coarse shapes, and better results on clean renders than on
photographs. Both models read the side they cannot see from its mirror image, so set the object's facing. `depth-anything-v2`
(when its weights are in the local Hugging Face cache, a local directory, or reachable) is a different prior
from the one these models were trained with.
"""

CLUTTER_HINT = """**Cluttered background?** The border-colour mask only works on a plain background. Cut the object out
(a PNG or WebP with a transparent background) and upload that RGBA image above, or let a background model do it:
install it where the page runs (`pip install 'depthnerf[bg]'`, then
`python -c "from rembg.bg import download_models; download_models(['u2net'])"` for its weights) and tick
**Remove background**."""

LOCAL = ("127.0.0.1", "localhost", "::1")
"""Host names that only this machine can reach."""
MAX_UPLOAD = "100mb"
"""Largest upload Gradio accepts (a 6000x4000 PNG is well below)."""
PRIOR_CHOICES = [("as the model was trained", "trained"), ("bundled (MIT)", "bundled"),
                 ("Depth Anything V2 (Base by default, as the paper; Base/Large CC-BY-NC-4.0, Small Apache-2.0)",
                  "depth-anything-v2")]
"""(label, value) of the depth prior choice; the line under it names the exact weights and licence."""
DELETE_CACHE = (3600, 86400)
"""Gradio's cache of this page: files older than a day deleted hourly, and all of them when the server stops."""
RATIO_INFO = ("object's longer side / frame side (TripoSR's foreground ratio; TripoSR's 0.85 suits its own "
              "model; the default is the fill of the chosen model's training data)")
FACING_DEFAULT = 90.0
"""The facing slider's start: a side view with the front to the right (``ReconstructConfig.facing``)."""
FACING_INFO = ("which way the object's front points: 0 = towards the camera, 90 = right (a side view, the "
               "default), 180 = away, 270 = left; sets the mirror plane of models with mirror-symmetric conditioning")
FACING_AUTO_INFO = ("instead of the slider: read from the photo by the model's facing head when it has one "
                    "(ticked then; depthnerf fit-facing), else the plane whose render of the photo is closest, or "
                    "none; for a side view untick it, the slider's 90 is right (docs/reconstruction.md, \"Facing\")")
MESH_LEVEL_INFO = ("local: each part at its own half-maximum, outlined by the photo's mask, which keeps thin parts "
                   "(legs, frames) in a looser surface; auto: one tight piece at half the object's typical density "
                   "(docs/RESULTS.md, \"Mesh level rules\")")
MESH_COLORS_INFO = ("photo: the photo's own colours where it sees the surface (and its mirror image), spread into "
                    "the rest; normal-ray: the model's colour along each vertex normal (docs/RESULTS.md, \"Mesh "
                    "vertex colours\")")
GUIDED_INFO = ("samples each ray where the depth prior puts the surface: about twice as fast, within 0.04 dB of "
               "the model's own sampler on the shipped models (docs/RESULTS.md, \"Depth-guided sampling\")")
SYMMETRY_INFO = ("models with mirror-symmetric conditioning also read each point's mirror image; untick for none "
                 "(the details below say which plane was used)")


CSS = """
#prepared img, #prior-image img, #gif img { width: 100%; height: 100%; object-fit: contain;
  image-rendering: pixelated; }
"""
"""The model works at 64 px: show its images scaled up to the boxes, pixels kept sharp."""


def model_choices(config: AppConfig) -> list[tuple[str, str]]:
    """(label, checkpoint) pairs of the model menu."""
    by_name = {name: label for label, name in SHIPPED_MODELS.items()}
    return [(f"{by_name[c]} ({c})" if c in by_name else c, c) for c in config.checkpoints]


def _cleared(prepared, message: str, clutter: bool) -> tuple:
    """The preview's outputs: the preprocessed input (or nothing) and its message; every result of an earlier
    run cleared."""
    return (prepared, message, gr.Markdown(visible=clutter), None, None, None, None, None, "")


def _outputs(out: RunOutputs) -> tuple:
    clutter = not out.ok and "background is not a plain colour" in out.message
    return (out.message, None if out.input_image is None else str(out.input_image),
            None if out.depth_prior is None else str(out.depth_prior),
            None if out.video is None else str(out.video), None if out.gif is None else str(out.gif),
            None if out.viewer_glb is None else str(out.viewer_glb), [str(p) for p in out.downloads] or None,
            out.details, gr.Markdown(visible=clutter))


def build_page(session: AppSession) -> gr.Blocks:
    """The Blocks page over one :class:`AppSession`."""
    config = session.config
    choices = model_choices(config)
    first = choices[0][1]
    start_fill, start_auto = session.model_defaults(first)

    def preview(image, model, ckpt_path, ratio, remove_bg, bg_model):
        if not image:  # the upload was cleared: nothing to complain about yet
            return _cleared(None, "upload a PNG, JPEG or WebP photo, or pick an example", False)
        img, message = session.preview(RunRequest(image, model, ckpt_path or "", foreground_ratio=ratio,
                                                  remove_background=bool(remove_bg),
                                                  background_model=bg_model or ""))
        return _cleared(img, message, img is None and "background is not a plain colour" in message)

    def defaults_for(model, ckpt_path):
        try:
            return session.model_defaults(model, ckpt_path or "")
        except DepthnerfError:  # a bad path or model shows up (one line) when the user runs it; a bug surfaces
            return gr.Slider(), gr.Checkbox()

    def reconstruct(image, model, ckpt_path, prior, prior_ckpt, ratio, elevation, views, remove_bg, bg_model,
                    facing=FACING_DEFAULT, use_symmetry=True, mesh_level="local", guided=True, mesh_colors="photo",
                    facing_auto=False, progress=gr.Progress(track_tqdm=True)):  # noqa: B008 - Gradio's way to ask for a progress bar
        from depthnerf.infer.facing import AUTO  # torch loads on the first run, not with the page

        request = RunRequest(image=image, model=model, checkpoint_path=ckpt_path or "", depth_prior=prior,
                             depth_checkpoint=prior_ckpt or "", foreground_ratio=ratio, elevation=elevation,
                             views=int(views), remove_background=bool(remove_bg), background_model=bg_model or "",
                             facing=(AUTO if facing_auto else float(facing)) if use_symmetry else None,
                             mesh_level=mesh_level,
                             guided=bool(guided), mesh_colors=mesh_colors)
        return _outputs(session.run(request, lambda frac, text: progress(frac, desc=text)))

    with gr.Blocks(title="depthnerf app", analytics_enabled=False, delete_cache=DELETE_CACHE) as page:
        gr.Markdown(INTRO)
        with gr.Row():
            with gr.Column(scale=1):
                upload = gr.File(label="Photo (PNG / JPEG / WebP; RGBA cut-outs welcome)", type="filepath",
                                 elem_id="upload")
                gr.Examples([[str(p)] for p in examples()], inputs=[upload],
                            label="Examples (synthesised by depthnerf synth)")
                clutter = gr.Markdown(CLUTTER_HINT, visible=False, elem_id="clutter-hint")
                model = gr.Dropdown(choices, value=first, label="Model (category -> shipped checkpoint)",
                                    elem_id="model")
                ckpt_path = gr.Textbox(label="or a local checkpoint (weights file, checkpoint or run folder)",
                                       placeholder="runs/cars/checkpoints/best", visible=config.allow_checkpoint_paths,
                                       elem_id="checkpoint-path")
                installed = background_installed()
                remove_bg = gr.Checkbox(value=installed, label="Remove background (rembg)", elem_id="remove-bg",
                                        info="for photos without transparency" if installed else
                                        "not installed where the page runs: pip install 'depthnerf[bg]'")
                bg_model = gr.Textbox(label="Background model (rembg name in its model folder, or an .onnx file)",
                                      placeholder="u2net", visible=config.allow_checkpoint_paths,
                                      elem_id="background-model")
                prior = gr.Radio(PRIOR_CHOICES, value="trained", label="Depth prior", elem_id="prior")
                prior_ckpt = gr.Textbox(label="Depth Anything V2 weights (hub id in the local cache"
                                        + (", or a folder)" if config.allow_checkpoint_paths else ")"),
                                        placeholder="depth-anything/Depth-Anything-V2-Base-hf (default)",
                                        elem_id="prior-checkpoint")
                prior_info = gr.Markdown(prior_description("trained"), elem_id="prior-info")
                ratio = gr.Slider(0.3, 1.0, value=start_fill, step=0.01, label="Foreground ratio", info=RATIO_INFO,
                                  elem_id="ratio")
                elevation = gr.Slider(-10, 60, value=20, step=1, label="Elevation (degrees)", elem_id="elevation")
                views = gr.Slider(1, config.max_views, value=config.views, step=1, label="Orbit views",
                                  elem_id="views")
                use_symmetry = gr.Checkbox(value=True, label="Use mirror symmetry", info=SYMMETRY_INFO,
                                           elem_id="use-symmetry")
                facing = gr.Slider(0, 359, value=FACING_DEFAULT, step=1, label="Object facing (degrees)",
                                   info=FACING_INFO, elem_id="facing")
                facing_auto = gr.Checkbox(value=start_auto, label="Estimate the facing from the photo",
                                          info=FACING_AUTO_INFO, elem_id="facing-auto")
                mesh_level = gr.Radio(["local", "auto"], value="local", label="Mesh surface", info=MESH_LEVEL_INFO,
                                      elem_id="mesh-level")
                mesh_colors = gr.Radio(["photo", "normal-ray"], value="photo", label="Mesh colours",
                                       info=MESH_COLORS_INFO, elem_id="mesh-colors")
                guided = gr.Checkbox(value=True, label="Depth-guided rendering", info=GUIDED_INFO, elem_id="guided")
                run = gr.Button("Reconstruct", variant="primary", elem_id="run")
            with gr.Column(scale=2):
                status = gr.Textbox(label="Status", interactive=False, elem_id="status")
                with gr.Row():
                    prepared = gr.Image(label="Preprocessed input (what the model sees)", interactive=False,
                                        elem_id="prepared", height=220)
                    prior_img = gr.Image(label="Depth prior used (brighter = nearer)", interactive=False,
                                         elem_id="prior-image", height=220)
                with gr.Row():
                    video = gr.Video(label="Orbit (MP4)", interactive=False, autoplay=True, loop=True,
                                     elem_id="video", height=260)
                    gif = gr.Image(label="Orbit (GIF)", interactive=False, elem_id="gif", height=260)
                viewer = gr.Model3D(label="Mesh (drag to rotate)", clear_color=(1.0, 1.0, 1.0, 1.0),
                                    camera_position=(45, 65, None),  # a three-quarter view from above
                                    elem_id="viewer", height=360)
                downloads = gr.File(label="Downloads: mesh GLB, mesh PLY, point cloud PLY", file_count="multiple",
                                    interactive=False, elem_id="downloads")
                details = gr.Markdown(elem_id="details")

        preview_in = [upload, model, ckpt_path, ratio, remove_bg, bg_model]
        preview_out = [prepared, status, clutter, prior_img, video, gif, viewer, downloads, details]
        upload.change(preview, preview_in, preview_out, api_name="preview")
        ratio.release(preview, preview_in, preview_out, api_visibility="private")
        remove_bg.change(preview, preview_in, preview_out, api_visibility="private")
        bg_model.submit(preview, preview_in, preview_out, api_visibility="private")
        model.change(defaults_for, [model, ckpt_path], [ratio, facing_auto], api_visibility="private")
        ckpt_path.submit(defaults_for, [model, ckpt_path], [ratio, facing_auto], api_visibility="private")
        for trigger in (prior.change, prior_ckpt.change):
            trigger(prior_description, [prior, prior_ckpt], [prior_info], api_visibility="private")
        run.click(reconstruct, [upload, model, ckpt_path, prior, prior_ckpt, ratio, elevation, views, remove_bg,
                                bg_model, facing, use_symmetry, mesh_level, guided, mesh_colors, facing_auto],
                  [status, prepared, prior_img, video, gif, viewer, downloads, details, clutter],
                  api_name="reconstruct", concurrency_limit=1, concurrency_id="reconstruct")
    return page


def serve(config: AppConfig) -> None:
    """Build the page and serve it until interrupted. A busy port is a one-line error before anything is loaded;
    "serving" is printed once the server is bound."""
    check_port(config.host, config.port)
    session = AppSession(config)
    previous = _stop_on_sigterm()  # SIGTERM stops the page as Ctrl+C does, loading included
    try:
        print(f"depthnerf app: loading {config.checkpoints[0]} (runs are written to {session.work_dir})", flush=True)
        page = build_page(session)
        page.queue(default_concurrency_limit=1, max_size=64)
        try:
            page.launch(server_name=config.host, server_port=config.port, share=config.share, ssr_mode=False,
                        allowed_paths=[str(Path(session.work_dir))], show_error=False, inbrowser=False, css=CSS,
                        max_file_size=MAX_UPLOAD, quiet=True, prevent_thread_lock=True)
        except OSError as err:
            raise DepthnerfError(f"cannot serve on {config.host}:{config.port} "
                                 f"({' '.join(str(err).split('.')[:1])}); pass another --port") from None
        print(f"depthnerf app: serving http://{config.host}:{config.port}/"
              + (" and a public share link" if config.share else " (this machine only)" if config.host in LOCAL
                 else "") + "; Ctrl+C stops it", flush=True)
        page.block_thread()
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if config.work_dir is None:  # our temporary folder
            shutil.rmtree(session.work_dir, ignore_errors=True)


def _stop_on_sigterm():
    """SIGTERM ends the server as Ctrl+C does (Gradio closes it, then :func:`serve` cleans up); returns the
    previous handler (None outside the main thread, where Python allows no handler)."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def stop(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    return previous if previous is not None else signal.SIG_DFL
