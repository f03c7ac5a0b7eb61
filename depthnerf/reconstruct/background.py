"""Background removal for photos on a cluttered background: rembg's salient-object models (optional extra ``[bg]``).

Library
    `rembg <https://github.com/danielgatis/rembg>`_ (MIT), as TripoSR, Splatter Image, LGM and SF3D use in their
    demos: U^2-Net / IS-Net / BiRefNet exported to ONNX and run by ``onnxruntime``. Weights are ONNX graphs (no
    pickles, no code from the checkpoint runs), and a local file is loaded as it is. A ``transformers`` model
    was the alternative: the background-removal checkpoints there (BiRefNet, RMBG) run their own Python code
    from the hub (``trust_remote_code``), which this package never does.
Model (``--background-model NAME_OR_FILE``; :data:`DEFAULT_MODEL` when not given)
    A name from :data:`NAMED_MODELS`, read from rembg's model folder, where :func:`download_command` puts it (``~/.u2net``
    or ``~/.rembg/models/NAME``; ``U2NET_HOME`` moves it); or an ONNX file with U^2-Net's interface (rembg's
    ``u2net_custom``: one RGB input resized to 320x320 with ImageNet mean and std, the first channel of the first
    output a foreground score, min-max normalised). Nothing is downloaded here: a missing model is a one-line
    reason that says how to get it. Through the API any rembg session object also works
    (``BackgroundRemover(rembg.new_session("isnet-general-use"), "isnet-general-use")``; import rembg after
    setting ``NUMBA_THREADING_LAYER=workqueue``, see :func:`_import_rembg`).
Use (:func:`depthnerf.reconstruct.photo.photo_mask`)
    Only for photos without a given mask or an alpha channel. The model's foreground score in [0, 1], at the
    photo's size, becomes the photo's alpha; then the RGBA rules apply (object = alpha > 0.5, composited on white,
    recentred at the foreground ratio).
Modes (``--background-removal``; ``ReconstructConfig.background_removal``)
    ``auto`` (default): the model when rembg and its weights are installed, else the border-colour rule (a
    cluttered background is then one line naming what is missing); ``on``: the model or that line; ``off``: the
    border-colour rule only. A model named explicitly must load, whatever the mode. The model runs on the CPU
    (``onnxruntime``'s CPU provider; ``OMP_NUM_THREADS`` caps its threads, as in rembg).
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from jaxtyping import Float
from PIL import Image

from depthnerf.errors import DepthnerfError

MODES = ("auto", "on", "off")
"""Values of ``--background-removal``."""
DEFAULT_MODEL = "u2net"
"""The model used when none is named (TripoSR's and LGM's choice)."""
NAMED_MODELS = {
    "u2net": "Apache-2.0 (U^2-Net)",
    "u2netp": "Apache-2.0 (U^2-Net, small)",
    "isnet-general-use": "Apache-2.0 (IS-Net / DIS)",
    "birefnet-general": "MIT (BiRefNet)",
    "birefnet-general-lite": "MIT (BiRefNet lite)",
}
"""rembg model names accepted by ``--background-model`` -> licence of their weights (remote-service and
non-commercial sessions of rembg are left out)."""
INSTALL = "pip install 'depthnerf[bg]'"
"""How to install the extra."""


def download_command(name: str) -> str:
    """The shell command that fetches a named model into rembg's folder (the function ``rembg d NAME`` calls; that
    command itself needs rembg's ``[cli]`` extra, which ``depthnerf[bg]`` leaves out)."""
    return f"python -c \"from rembg.bg import download_models; download_models(['{name}'])\""


class BackgroundRemover:
    """A loaded background-removal model (a rembg session), or the reason there is none (:meth:`unavailable`)."""

    def __init__(self, session: Any, name: str, licence: str = "see the model's card", *, reason: str = "",
                 required: bool = False) -> None:
        """``session``: an object with rembg's ``predict(PIL image) -> [PIL mask, ...]``; ``name``: what the
        notes and the manifest call it."""
        self.session = session
        self.name = name
        self.licence = licence
        self.reason = reason
        """Why there is no model (None session): one clause that says how to get one."""
        self.required = required
        """With no model: a photo without alpha or mask is an error (``on``) instead of the border rule."""

    @classmethod
    def unavailable(cls, reason: str, required: bool = False) -> BackgroundRemover:
        """No model, for ``reason``."""
        return cls(None, "none", "", reason=reason, required=required)

    @property
    def available(self) -> bool:
        return self.session is not None

    def foreground(self, rgb: Float[np.ndarray, "H W 3"]) -> Float[np.ndarray, "H W"]:
        """The model's foreground score in [0, 1] at the image's size (the first mask rembg returns)."""
        if self.session is None:
            raise DepthnerfError(f"no background model: {self.reason}")
        image = Image.fromarray(np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8), "RGB")
        try:
            masks = self.session.predict(image)
        except Exception as err:  # noqa: BLE001 - onnxruntime raises its own types for a graph that does not fit
            raise DepthnerfError(f"background model {self.name}: could not segment the photo "
                                 f"({' '.join(str(err).split())[:200]})") from None
        mask = masks[0].convert("L")
        if mask.size != image.size:
            mask = mask.resize(image.size, Image.Resampling.BILINEAR)
        return np.asarray(mask, dtype=np.float32) / 255.0


def _import_rembg():
    """``(rembg.new_session, rembg's session classes)``, or a one-line error saying how to install them."""
    missing = [m for m in ("rembg", "onnxruntime") if importlib.util.find_spec(m) is None]
    if missing:
        raise DepthnerfError(f"background removal needs {' and '.join(missing)}, which "
                             f"{'is' if len(missing) == 1 else 'are'} not installed: {INSTALL}, then "
                             f"`{download_command(DEFAULT_MODEL)}` for its weights")
    # rembg imports pymatting, whose numba code starts numba's OpenMP pool beside torch's and resets torch's thread
    # count: torch's small ops then ran 15-40x slower here. numba's own thread pool and torch's count restored
    # avoid that (the user's NUMBA_THREADING_LAYER wins).
    os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
    threads = torch.get_num_threads()
    try:
        from rembg import new_session
        from rembg.sessions import sessions_class
    except ImportError as err:  # noqa: BLE001 - a broken install
        raise DepthnerfError(f"background removal: rembg does not import ({err}); reinstall it: {INSTALL}") from None
    finally:
        torch.set_num_threads(threads)
    return new_session, sessions_class


def _named_file(sessions_class: list, name: str) -> Path | None:
    """Where rembg keeps the weights of model ``name`` when they are downloaded, else None."""
    cls = next(c for c in sessions_class if c.name() == name)
    fname = f"{name}.onnx"
    if hasattr(cls, "resolve_existing"):  # rembg >= 2.0.70: per-model folders and the old flat one
        found = cls.resolve_existing(fname)
        return Path(found) if found else None
    path = Path(cls.u2net_home()) / fname
    return path if path.is_file() else None


def _file_session(path: Path):
    """A U^2-Net-style rembg session over the ONNX file ``path`` (rembg's ``u2net_custom`` without its rule that
    the file sits inside rembg's model folder)."""
    from rembg.sessions.u2net_custom import U2netCustomSession

    class FileSession(U2netCustomSession):
        @classmethod
        def download_models(cls, *args, **kwargs):
            return kwargs["model_path"]

    return FileSession("u2net_custom", _session_options(), model_path=str(path), providers=["CPUExecutionProvider"])


def _session_options():
    """onnxruntime's session options: ``OMP_NUM_THREADS`` (when set) caps the threads, as rembg does."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    threads = os.environ.get("OMP_NUM_THREADS", "")
    if threads.isdigit() and int(threads) > 0:
        options.intra_op_num_threads = options.inter_op_num_threads = int(threads)
    return options


def model_file(model: str | None) -> Path | None:
    """The ONNX file ``model`` names, or None for a name of :data:`NAMED_MODELS` (None = :data:`DEFAULT_MODEL`);
    a one-line :class:`DepthnerfError` for a word that is neither. The file need not exist (:func:`check_model`)."""
    name = model or DEFAULT_MODEL
    path = Path(name).expanduser()
    if name.lower().endswith(".onnx") or path.exists() or "/" in name:
        return path
    if name not in NAMED_MODELS:
        raise DepthnerfError(f"--background-model {name}: not a model file and not one of "
                             f"{', '.join(NAMED_MODELS)}")
    return None


def check_model(model: str | None) -> None:
    """One line, without loading anything, when ``model`` is neither a name of :data:`NAMED_MODELS` nor a file
    that exists (``depthnerf app`` checks its ``--background-model`` so before it serves)."""
    path = model_file(model)
    if path is not None and not path.is_file():
        raise DepthnerfError(f"{path}: background model file not found")


def load_remover(model: str | None = None) -> BackgroundRemover:
    """The model ``model`` names (module docstring; None = :data:`DEFAULT_MODEL`); a one-line
    :class:`DepthnerfError` saying what is missing and how to get it otherwise."""
    name = model or DEFAULT_MODEL
    path = model_file(model)
    new_session, sessions_class = _import_rembg()
    if path is not None:
        check_model(model)  # after the import: a missing rembg is the first thing to say
        try:
            session = _file_session(path)
        except Exception as err:  # noqa: BLE001 - onnxruntime's errors for a file that is not an ONNX graph
            raise DepthnerfError(f"{path}: not a loadable ONNX background model "
                                 f"({' '.join(str(err).split())[:200]})") from None
        return BackgroundRemover(session, path.name, "see the model's card")
    found = _named_file(sessions_class, name)
    if found is None:
        raise DepthnerfError(f"the background model {name} is not downloaded: run `{download_command(name)}` where there is "
                             "internet, or pass --background-model FILE.onnx")
    try:
        session = new_session(name, sess_opts=_session_options(), providers=["CPUExecutionProvider"])
    except Exception as err:  # noqa: BLE001 - a corrupt download
        raise DepthnerfError(f"{found}: not a loadable {name} model ({' '.join(str(err).split())[:200]}); "
                             f"delete it and run `{download_command(name)}` again") from None
    return BackgroundRemover(session, name, NAMED_MODELS[name])


def choose_remover(mode: str, model: str | None = None) -> BackgroundRemover:
    """The remover of a mode (module docstring): loaded, or :meth:`BackgroundRemover.unavailable` with the reason.
    ``on`` with a model that cannot be loaded, and a named model that does not exist, are errors at once."""
    if mode not in MODES:
        raise DepthnerfError(f"--background-removal {mode!r}: choose {', '.join(MODES)}")
    if mode == "off":
        return BackgroundRemover.unavailable("background removal is off (--background-removal off)")
    try:
        return load_remover(model)
    except DepthnerfError as err:
        if model is not None:  # a model the user named: its problem is the answer
            raise
        return BackgroundRemover.unavailable(str(err), required=mode == "on")
