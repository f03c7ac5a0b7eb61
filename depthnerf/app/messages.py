"""What the page says: errors in one line and in the page's words, the depth-prior line, the checks of an upload
and of a request's numbers (the page's HTTP API passes whatever a client sends), and the rule for local paths on a
publicly shared page (:func:`check_local_paths`).

Messages from the package name command-line flags (``--mask``, ``--depth-checkpoint`` ...); the page shows them
with its own field names (:data:`PAGE_WORDS`).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from PIL import Image

from depthnerf.errors import DepthnerfError

PAGE_WORDS = (
    (r"; pass a mask \(--mask\)", "; upload an RGBA cut-out of the object (transparent background)"),
    (r" or pass a mask \(--mask\)", ""),
    (r"pass --depth-checkpoint ([^\s;,)]+)", r"enter \1 under 'Depth Anything V2 weights'"),
    (r"pass --background-model ([^\s;,)]+)", r"enter \1 under 'Background model'"),
    (r"background removal is off \(--background-removal off\)", "background removal is off (tick 'Remove background')"),
    (r"--background-model ([^\s;,)]+):", r"background model \1:"),
    (r"--fill", "the foreground ratio"),
    (r"--views", "orbit views"),
    (r"--elevation", "the elevation"),
    (r"--facing", "the object facing"),
)
"""(pattern, replacement): the command-line flags that messages suggest, in the page's words."""

def display_name(path: str | Path | None) -> str:
    """The file name a user recognises (Gradio uploads live in temporary folders)."""
    return Path(path).name if path else "image"


def one_line(err: BaseException, image: str | Path | None) -> str:
    """``error: ...`` for a DepthnerfError (temporary upload path -> file name), ``internal error ...`` else."""
    text = " ".join(str(err).split())
    if image:
        text = text.replace(str(image), display_name(image))
    if isinstance(err, DepthnerfError):
        return f"error: {page_words(text)}"
    return f"internal error ({type(err).__name__}): {text}"


def page_words(text: str) -> str:
    """``text`` with the command-line flags it suggests replaced by the page's fields (:data:`PAGE_WORDS`)."""
    for pattern, replacement in PAGE_WORDS:
        text = re.sub(pattern, replacement, text)
    return text


def prior_description(prior: str, depth_checkpoint: str = "") -> str:
    """Which weights a depth prior choice loads, and their licence (one line for the page)."""
    if prior == "trained":
        return ("as trained: the prior the chosen model was trained with (the shipped models: this project's bundled "
                "depth network, MIT)")
    if prior == "bundled":
        return "bundled: this project's small depth network, trained on the synthetic benchmark only (MIT)"
    from depthnerf.depth.depth_anything import DEFAULT_CHECKPOINT, licence_of

    checkpoint = depth_checkpoint.strip() or DEFAULT_CHECKPOINT
    size = next((s for s in ("Small", "Base", "Large") if s.lower() in checkpoint.lower()), None)
    what = f"Depth Anything V2 {size}" if size else "Depth Anything V2"
    paper = ", the paper's prior" if checkpoint == DEFAULT_CHECKPOINT else ""
    return f"{what} ({checkpoint}{paper}); licence {licence_of(checkpoint)}"


def check_upload(image: str | Path | None) -> Path:
    """The upload's path when it is a PNG, JPEG or WebP file; else a one-line DepthnerfError."""
    from depthnerf.reconstruct.photo import check_photo_format

    if image is None or str(image) == "":
        raise DepthnerfError("no image: upload a PNG, JPEG or WebP photo, or pick an example")
    path = Path(image)
    name = display_name(path)
    if path.is_dir():
        raise DepthnerfError(f"{name}: is a folder, not an image file")
    if not path.is_file():
        raise DepthnerfError(f"{name}: file not found")
    try:
        with Image.open(path) as im:
            fmt = im.format
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{name}: not an image ({' '.join(str(err).split())})") from None
    check_photo_format(fmt, name)  # the rule depthnerf reconstruct applies
    return path


def is_local_path(value: str) -> bool:
    """Whether a field's value names a file or folder of the server (rather than a model name or hub id): it
    exists there, starts with ``.``, ``/`` or ``~``, or is a ``.onnx`` / ``.safetensors`` file name."""
    return value.startswith((".", "/", "~")) or value.endswith((".onnx", ".safetensors")) or \
        Path(value).expanduser().exists()


def check_local_paths(checkpoint_path: str, background_model: str, depth_checkpoint: str) -> None:
    """One line when a request names a local file or folder of the server on a page that offers none (a public
    share link hides those fields; its HTTP API takes the same parameters, so the rule is applied here): a
    checkpoint path, a background model file (a name with a ``/`` is one, as rembg reads it), a Depth Anything
    folder (anything but a hub id ``owner/name``). Model names and hub ids pass."""
    if checkpoint_path.strip():
        raise DepthnerfError("local checkpoint paths are off on this shared page; pick a model from the menu")
    background, weights = background_model.strip(), depth_checkpoint.strip()
    if background and (is_local_path(background) or "/" in background):
        raise DepthnerfError(f"background model {background!r}: local files are off on this shared page; enter a "
                             "rembg model name (u2net), or leave it empty")
    if weights and (is_local_path(weights) or weights.count("/") != 1):
        raise DepthnerfError(f"Depth Anything weights {weights!r}: local folders are off on this shared page; enter "
                             "a hub id (depth-anything/Depth-Anything-V2-Small-hf), or leave it empty")


def check_ratio(ratio: float | None) -> None:
    """One line unless a request's foreground ratio is None (the training fill) or within 0.05..1: the rule of the
    preview and the run alike."""
    if ratio is not None and not 0.05 <= ratio <= 1.0:
        raise DepthnerfError(f"foreground ratio must be within 0.05..1, got {ratio}")


def check_views(views: Any, max_views: int) -> None:
    """One line unless ``views`` is a whole number within ``1..max_views``."""
    if not (isinstance(views, int | float) and math.isfinite(views) and views == int(views)
            and 1 <= views <= max_views):
        raise DepthnerfError(f"orbit views must be a whole number within 1..{max_views}, got {views}")


def as_number(value: Any, what: str) -> float:
    """``value`` as a float; one line naming ``what`` otherwise."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise DepthnerfError(f"{what} must be a number, got {value!r}") from None
