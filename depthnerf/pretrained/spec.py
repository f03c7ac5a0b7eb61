"""The inference spec: everything needed to run a trained model as it was trained, stored in every checkpoint.

A checkpoint's weights metadata holds ``inference_spec`` (the JSON of :class:`InferenceSpec`). Checkpoints written
before the spec existed (older run folders) hold the model config (``config``) and the whole training config
(``train_config``) instead; :func:`spec_from_metadata` derives the same spec from those, so both load alike.
Specs written before the ``framing`` field (the shipped ``depthnerf/checkpoints/*.safetensors`` among them) have
none; :func:`depthnerf.pretrained.load.load_pretrained` derives it once, at load
(:func:`~depthnerf.data.synth.framing.checkpoint_framing`), so a loaded spec always states it.

Legacy rule for ``encoder.use_depth``: older model configs stored it beside the prior. It is accepted only when
it agrees with the prior (``use_depth == prior.estimator != "none"``) and then dropped; a disagreement is an error
naming the file. New configs never hold it: whether a model is depth-aware is :attr:`PriorConfig.enabled`.
"""

from __future__ import annotations

import copy
import json
from dataclasses import MISSING, dataclass, fields
from typing import Any

from depthnerf.config_io import NumberRules, broken_rule, from_dict, to_dict
from depthnerf.data.srn import category_defaults
from depthnerf.depth.prior import PriorConfig
from depthnerf.errors import DepthnerfError
from depthnerf.model.config import PixelNeRFConfig
from depthnerf.render.config import RENDER_NUMBER_RULES, RenderConfig

SPEC_KEY = "inference_spec"
"""Weights-metadata key of the spec's JSON."""


@dataclass
class InferenceSpec:
    """How to run a trained model: what the encoder sees, how rays are rendered, in which frame and range."""

    model: PixelNeRFConfig
    """The network (built with ``depth_aware = prior.enabled``)."""
    render: RenderConfig
    """The renderer it was trained with (samples, noise, background)."""
    prior: PriorConfig
    """The depth prior its encoder takes (``none``: the pixelNeRF baseline)."""
    category: str
    """Object category it was trained on (picks camera defaults for photos)."""
    resolution: int
    """Training image size: source views (and their priors) are encoded at this size."""
    z_near: float
    """Near bound of the ray distance."""
    z_far: float
    """Far bound of the ray distance."""
    pixel_center: float = 0.0
    """Pixel-centre convention the model read its data with (``DataConfig.pixel_center``: pixel (i, j) centred at
    ``(j + c, i + c)`` in ``intrinsics.txt``'s coordinates); 0.0 for checkpoints written before it existed (they
    all read their data so)."""
    framing: str | None = None
    """Framing of the training data (``srn`` or ``legacy``, :mod:`depthnerf.data.synth.framing`): what a photo is
    framed to and how the demo synthesises objects; a dataset without a card (real SRN) is ``srn``. None only in
    the stored JSON of checkpoints written before the field: loading derives it."""
    prior_weights_hash: str | None = None
    """SHA-256 of the prior's weights at training time (None: no prior, or not recorded by older checkpoints)."""
    preset: str = "custom"
    """Training preset name (provenance)."""

    @property
    def depth_aware(self) -> bool:
        """The model is depth-aware (derived from the prior)."""
        return self.prior.enabled

    @property
    def z_range(self) -> tuple[float, float]:
        """``(z_near, z_far)``."""
        return self.z_near, self.z_far

    def to_json(self) -> str:
        """The JSON stored under :data:`SPEC_KEY`."""
        return json.dumps(to_dict(self), sort_keys=True)


def model_config_from_dict(data: dict[str, Any], depth_aware: bool, where: str) -> PixelNeRFConfig:
    """A model config from JSON, applying the legacy ``encoder.use_depth`` rule (module docstring)."""
    if not isinstance(data, dict):
        raise DepthnerfError(f"{where}: expected a mapping for PixelNeRFConfig")
    data = copy.deepcopy(data)
    encoder = data.get("encoder")
    if isinstance(encoder, dict) and "use_depth" in encoder:
        stored = encoder.pop("use_depth")
        if bool(stored) != depth_aware:
            raise DepthnerfError(f"{where}: encoder.use_depth={stored} disagrees with the depth prior "
                                 f"({'a prior' if depth_aware else 'none'}); fix one of them")
    return from_dict(PixelNeRFConfig, data, where=where)


def spec_from_json(text: str, where: str) -> InferenceSpec:
    """Parse :meth:`InferenceSpec.to_json` output (strict)."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError:
        raise DepthnerfError(f"{where}: inference spec is not valid JSON") from None
    if not isinstance(data, dict) or not isinstance(data.get("prior"), dict):
        raise DepthnerfError(f"{where}: inference spec has no prior")
    missing = [f.name for f in fields(InferenceSpec) if f.default is MISSING and f.name not in data]
    if missing:  # every spec ever written holds them; a default model config would be another network's
        raise DepthnerfError(f"{where}: inference spec lacks {', '.join(missing)}")
    prior = from_dict(PriorConfig, data["prior"], where=f"{where} prior")
    model = model_config_from_dict(data["model"], prior.enabled, f"{where} model")
    rest = {k: v for k, v in data.items() if k not in ("model", "prior", "extra")}  # older specs: an unused "extra"
    spec = from_dict(InferenceSpec, {**rest, "model": {}, "prior": {}}, where=where)
    spec.model, spec.prior = model, prior
    return spec


def spec_from_train_config(train: dict[str, Any], model: dict[str, Any], where: str) -> InferenceSpec:
    """The spec of a checkpoint written before specs existed, from its training config and model config dicts."""
    try:
        data, prior_d = train["data"], train.get("prior", {"estimator": "none"})
        prior = from_dict(PriorConfig, prior_d, where=f"{where} train_config.prior")
        category, resolution = str(data["category"]), int(data["resolution"])
        near, far = data.get("z_near"), data.get("z_far")
        pixel_center = float(data.get("pixel_center", 0.0))
    except (KeyError, TypeError):
        raise DepthnerfError(f"{where}: training config lacks data.category/resolution or the prior") from None
    if near is None or far is None:
        defaults = category_defaults(category)
        near, far = (defaults.z_near if near is None else near), (defaults.z_far if far is None else far)
    return InferenceSpec(model=model_config_from_dict(model, prior.enabled, f"{where} model config"),
                         render=from_dict(RenderConfig, train.get("render", {}), where=f"{where} render"),
                         prior=prior, category=category, resolution=resolution, z_near=float(near), z_far=float(far),
                         pixel_center=pixel_center,
                         preset=str(train.get("preset", "custom")))


SPEC_RULES: NumberRules = {"resolution": (8, True), **RENDER_NUMBER_RULES}
"""Spec field -> (bound, inclusive), as training enforces them (``depthnerf.train.config.NUMBER_RULES``)."""


def check_spec(spec: InferenceSpec, where: str) -> InferenceSpec:
    """``spec`` if its numbers are ones training could have written, else one line naming ``where`` and the field:
    a damaged or hand-edited spec fails here, not as a traceback deep in rendering."""
    broken = broken_rule(spec, SPEC_RULES)
    if broken is not None:
        path, value, bound, inclusive = broken
        raise DepthnerfError(f"{where}: inference spec: {path} must be {'>=' if inclusive else '>'} {bound:g}, "
                             f"got {value}")
    if not 0 <= spec.z_near < spec.z_far < float("inf"):  # NaN fails too
        raise DepthnerfError(f"{where}: inference spec: z_near / z_far must satisfy 0 <= z_near < z_far (finite), "
                             f"got {spec.z_near}, {spec.z_far}")
    if not 0 <= spec.pixel_center < 1:
        raise DepthnerfError(f"{where}: inference spec: pixel_center must be in [0, 1), got {spec.pixel_center}")
    return spec


def spec_from_metadata(meta: dict[str, str], where: str) -> InferenceSpec:
    """The spec of a weights file: its own, else derived from an older checkpoint's configs (module docstring);
    checked (:func:`check_spec`)."""
    if SPEC_KEY in meta:
        return check_spec(spec_from_json(meta[SPEC_KEY], where), where)
    if "train_config" not in meta:
        raise DepthnerfError(f"{where}: checkpoint has neither an inference spec nor a training config in its "
                             "metadata (not written by depthnerf train or scripts/export_checkpoint.py)")
    try:
        train, model = json.loads(meta["train_config"]), json.loads(meta["config"])
    except (KeyError, json.JSONDecodeError):
        raise DepthnerfError(f"{where}: checkpoint's training or model config is not valid JSON") from None
    return check_spec(spec_from_train_config(train, model, where), where)
