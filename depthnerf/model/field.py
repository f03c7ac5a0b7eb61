"""The NeRF MLP of pixelNeRF (its ``ResnetFC``) and the positional encoding.

Per point and source view, the input is ``[gamma(x), d]`` (42 dims by default): ``gamma`` = raw coordinates
followed by ``sin(f_k x), cos(f_k x)`` for ``f_k = 1.5 * 2^k``, k = 0..5 (each a 3-vector, frequency-major:
``x, sin f0 x, cos f0 x, sin f1 x, ...``), ``d`` the unit view direction in the source camera's axes.

Network: ``lin_in`` (d_in -> d_hidden); ``n_blocks`` residual blocks ``x + fc_1(relu(fc_0(relu(x))))``; before
block ``i < combine_layer`` the features enter as ``x += lin_z[i](z)``; just before block ``combine_layer`` the
source views are averaged; ``lin_out(relu(x))`` -> 4 = (rgb logits, sigma). Colour = sigmoid, density = ReLU
(applied by the caller). Initialisation as pixelNeRF: kaiming-normal (fan_in) weights and zero biases for
lin_in, lin_z, lin_out and every fc_0; fc_1 weights and biases are zero, so each block starts as the identity
(``FieldConfig.density_bias_init`` optionally replaces the init of lin_out's density row, see there).

Mirror branch (``PixelNeRFConfig.mirror``): a second input linear ``lin_in_mirror`` takes the mirror image's
input ``[gamma(x'), d', in_frame(x), in_frame(x')]`` and a second set of feature linears ``lin_z_mirror`` the
features sampled at the mirror image's projection; both are added to the direct ones, times a per-object gate
(1 with a symmetry plane, 0 without): ``x = lin_in(u) + g lin_in_mirror(u')``, ``x += lin_z[i](z) + g
lin_z_mirror[i](z')``. The mirror linears are initialised like their direct twins.

Source pixels at the point (``PixelNeRFConfig.prior_at_point`` / ``rgb_at_point``): ``extra_inputs`` more input
columns for ``lin_in`` (the prior and/or colour at the point's projection, appended after ``d``) and for
``lin_in_mirror`` (the same at the mirror image's projection, appended after the two flags).

Global features (``PixelNeRFConfig.global_features``): ``lin_global`` maps each source view's feature maps averaged
over the image (``g``, C channels) to one more term of the first hidden layer, the same at every point of that
view: ``x = lin_in(u) + lin_global(g)`` (mirror models: plus the gated mirror term), initialised like ``lin_in``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from depthnerf.bundles import TensorBundle
from depthnerf.model.config import FieldConfig
from depthnerf.model.features import MapSamples

MIRROR_FLAGS = 2
"""Extra inputs of the mirror branch: whether the point and its mirror image project inside the source frame."""


@dataclass
class MirrorQuery(TensorBundle):
    """What the mirror branch of :meth:`ResidualField.forward` gets for every point and source view."""

    inputs: Float[Tensor, "B V N Dm"]
    """``[gamma(x'), d', in_frame(x), in_frame(x')]`` of the mirror image x' (Dm = d_in + 2), then the source
    pixels at its projection for ``prior_at_point`` / ``rgb_at_point`` models (``PixelNeRFConfig.point_columns``)."""
    latent: Float[Tensor, "B V N L"] | MapSamples
    """Features at the mirror image's projection (sampled ``latent_map(..., mirror=True)`` when projected), or
    the maps and the mirror images' grid coordinates, read by the forward (``--gather inside``)."""
    gate: Float[Tensor, " B"]
    """1.0 for objects with a symmetry plane, 0.0 without (the branch then adds nothing)."""


class PositionalEncoding(nn.Module):
    """NeRF positional encoding with pixelNeRF's frequencies ``freq_factor * 2^k``."""

    def __init__(self, num_freqs: int, freq_factor: float, include_input: bool):
        super().__init__()
        self.num_freqs, self.include_input = num_freqs, include_input
        self.register_buffer("freqs", freq_factor * 2.0 ** torch.arange(num_freqs, dtype=torch.float32),
                             persistent=False)

    def forward(self, x: Float[Tensor, "*N 3"]) -> Float[Tensor, "*N D"]:
        scaled = x[..., None, :] * self.freqs[:, None]  # [*N, F, 3]
        enc = torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2).flatten(-3)  # [*N, F*2*3]
        return torch.cat([x, enc], dim=-1) if self.include_input else enc


def _kaiming(layer: nn.Linear) -> nn.Linear:
    nn.init.kaiming_normal_(layer.weight, a=0, mode="fan_in")
    nn.init.zeros_(layer.bias)
    return layer


def linear_relu(x: Float[Tensor, "N I"], layer: nn.Linear) -> Float[Tensor, "N O"]:
    """``relu(layer(x))`` as one ``torch._addmm_activation``: on CUDA the bias and the ReLU are the epilogue of the
    cuBLASLt matrix product (elsewhere an addmm, then a ReLU), also under ``torch.compile``, which keeps the op as
    it is (an extern kernel) where it gives a plain addmm its own ReLU kernel. Under autocast the operands are cast
    to the autocast dtype first, as ``F.linear`` would be."""
    weight, bias = layer.weight, layer.bias
    device = x.device.type
    if torch.is_autocast_enabled(device):
        dtype = torch.get_autocast_dtype(device)
        x, weight, bias = x.to(dtype), weight.to(dtype), bias.to(dtype)
    return torch._addmm_activation(bias, x, weight.t())


class ResidualBlock(nn.Module):
    """``x + fc_1(relu(fc_0(relu(x))))`` with fc_1 zero-initialised (pixelNeRF's ResnetBlockFC)."""

    def __init__(self, width: int):
        super().__init__()
        self.fc_0 = _kaiming(nn.Linear(width, width))
        self.fc_1 = nn.Linear(width, width)
        nn.init.zeros_(self.fc_1.weight)
        nn.init.zeros_(self.fc_1.bias)

    def forward(self, x: Float[Tensor, "N D"]) -> Float[Tensor, "N D"]:
        h = F.relu(self.fc_0(F.relu(x)))
        return x + self.fc_1(h)  # the residual sum stays in x's dtype (fp32) under bf16 autocast

    def forward_(self, x: Float[Tensor, "N D"], relu_epilogue: bool = False) -> Float[Tensor, "N D"]:
        """Inference only (no autograd): same result, updates ``x`` in place with fewer memory passes. Under
        bf16 autocast the linears run in bf16 and the residual stream ``x`` keeps its own dtype (fp32, or bf16
        with ``residual_dtype``, :meth:`ResidualField.forward`). ``relu_epilogue``: fc_0's bias and the ReLU
        after it run in the matrix product's epilogue (:func:`linear_relu`) instead of a kernel of their own."""
        if relu_epilogue:
            h = linear_relu(x.clamp_min(0.0), self.fc_0)
        else:
            h = F.linear(x.clamp_min(0.0), self.fc_0.weight, self.fc_0.bias).relu_()
        if h.dtype == x.dtype:  # fp32 throughout, or a bf16 stream under bf16 autocast (addmm_ is not autocast)
            return x.addmm_(h, self.fc_1.weight.t().to(x.dtype)).add_(self.fc_1.bias)
        return x.add_(F.linear(h, self.fc_1.weight)).add_(self.fc_1.bias)


class ResidualField(nn.Module):
    """pixelNeRF's ResnetFC conditioned on ``d_latent`` pixel-aligned feature channels."""

    def __init__(self, cfg: FieldConfig, d_latent: int, *, mirror: bool = False, extra_inputs: int = 0,
                 global_features: bool = False):
        super().__init__()
        self.cfg = cfg
        self.encoding = PositionalEncoding(cfg.num_freqs, cfg.freq_factor, cfg.include_input)
        self.lin_in = _kaiming(nn.Linear(cfg.d_in + extra_inputs, cfg.d_hidden))
        self.blocks = nn.ModuleList([ResidualBlock(cfg.d_hidden) for _ in range(cfg.n_blocks)])
        self.n_lin_z = min(cfg.combine_layer, cfg.n_blocks)
        self.lin_z = nn.ModuleList([_kaiming(nn.Linear(d_latent, cfg.d_hidden)) for _ in range(self.n_lin_z)])
        self.mirror = mirror
        """Whether the mirror branch exists (``PixelNeRFConfig.mirror``)."""
        if mirror:
            self.lin_in_mirror = _kaiming(nn.Linear(cfg.d_in + MIRROR_FLAGS + extra_inputs, cfg.d_hidden))
            self.lin_z_mirror = nn.ModuleList([_kaiming(nn.Linear(d_latent, cfg.d_hidden))
                                               for _ in range(self.n_lin_z)])
        self.global_features = global_features
        """Whether ``lin_global`` exists (``PixelNeRFConfig.global_features``)."""
        if global_features:
            self.lin_global = _kaiming(nn.Linear(d_latent, cfg.d_hidden))
        self.lin_out = _kaiming(nn.Linear(cfg.d_hidden, 4))
        if cfg.density_bias_init is not None:
            with torch.no_grad():
                self.lin_out.weight[3].zero_()
                self.lin_out.bias[3] = cfg.density_bias_init

    def latent_map(self, maps: Float[Tensor, "N C Hf Wf"], *, mirror: bool = False) -> Float[Tensor, "N Hf Wf Z"]:
        """All ``lin_z`` (``lin_z_mirror`` with ``mirror``) applied to every feature pixel, channels-last:
        ``Z = n_lin_z * d_hidden`` channels."""
        n, c, hf, wf = maps.shape
        lins = self.lin_z_mirror if mirror else self.lin_z
        weight = torch.cat([lin.weight for lin in lins]) if self.n_lin_z else maps.new_zeros(0, c)
        bias = torch.cat([lin.bias for lin in lins]) if self.n_lin_z else maps.new_zeros(0)
        out = torch.matmul(maps.reshape(n, c, hf * wf).transpose(1, 2), weight.t()) + bias
        return out.reshape(n, hf, wf, -1)

    def global_term(self, features: Float[Tensor, "B V C Hf Wf"]) -> Float[Tensor, "B V D"]:
        """``lin_global`` of each view's feature maps averaged over the image: the global features' term of the
        first hidden layer (models built with ``global_features`` only)."""
        if not self.global_features:
            raise ValueError("global features asked of a field built without lin_global")
        return self.lin_global(features.mean(dim=(-2, -1)))

    def inputs(self, points: Float[Tensor, "*N 3"], dirs: Float[Tensor, "*N 3"] | None) -> Float[Tensor, "*N Din"]:
        """MLP input ``[gamma(points), dirs]`` (dirs dropped when ``use_viewdirs`` is off)."""
        enc = self.encoding(points)
        return torch.cat([enc, dirs], dim=-1) if self.cfg.use_viewdirs else enc

    def forward(self, inputs: Float[Tensor, "B V N Din"], latent: Float[Tensor, "B V N L"] | MapSamples, *,
                projected: bool, mirror: MirrorQuery | None = None,
                global_term: Float[Tensor, "B V D"] | None = None, residual_dtype: torch.dtype | None = None,
                relu_epilogue: bool = False) -> Float[Tensor, "B N 4"]:
        """Raw outputs (rgb logits, sigma pre-activation). ``latent`` is either the sampled features
        (``projected=False``: L = C, lin_z applied here) or the sampled :meth:`latent_map` (L = Z); ``mirror``
        (models built with ``mirror`` only; None: no object has a plane) feeds the mirror branch alike. Either
        may instead be a :class:`~depthnerf.model.features.MapSamples` of those maps (``[B*V, Hf, Wf, L]``, grid
        ``[B*V, N, 2]``): the forward gathers each block's channels itself (``--gather inside``), same values.
        ``global_term`` (models built with ``global_features``; :meth:`global_term`) is added to every point's
        first hidden layer.

        ``residual_dtype``: without autograd, the dtype the residual stream ``x`` is kept in (None: the inputs'
        dtype, fp32). ``torch.bfloat16`` under bf16 autocast halves the stream's memory traffic, at the cost of
        rounding the stream to 8 mantissa bits after every addition (docs/speed.md). With autograd it must be
        None: training keeps the fp32 stream. ``relu_epilogue``: without autograd, the blocks' first linear
        runs with its bias and ReLU in the matrix product's epilogue (:meth:`ResidualBlock.forward_`)."""
        b, v, n, _ = inputs.shape
        d = self.cfg.d_hidden
        x = self.lin_in(inputs.reshape(b * v * n, -1))
        if global_term is not None:
            if not self.global_features:
                raise ValueError("global features given to a field built without lin_global")
            x = x + global_term.to(x.dtype)[:, :, None, :].expand(b, v, n, d).reshape(b * v * n, d)
        z_part = _feature_terms(latent, self.lin_z, d, projected, b * v * n)
        inplace = not torch.is_grad_enabled()
        if residual_dtype is not None and not inplace:
            raise ValueError("residual_dtype is an inference setting: training keeps the fp32 residual stream")
        if inplace:
            x = x.to(residual_dtype or inputs.dtype)  # under autocast the stream stays fp32 unless residual_dtype
        zm_part, gate = None, None
        if mirror is not None:
            if not self.mirror:
                raise ValueError("mirror inputs given to a field built without the mirror branch")
            gate = mirror.gate.to(x.dtype)[:, None, None].expand(b, v, n).reshape(b * v * n, 1)
            x = x + self.lin_in_mirror(mirror.inputs.reshape(b * v * n, -1)).to(x.dtype) * gate
            zm_part = _feature_terms(mirror.latent, self.lin_z_mirror, d, projected, b * v * n)
        for i, block in enumerate(self.blocks):
            if i == self.cfg.combine_layer and v > 1:
                x = x.reshape(b, v, n, d).mean(dim=1).reshape(b * n, d)
            if i < self.n_lin_z:
                zi = z_part(i)
                if zm_part is not None:
                    zi = zi + zm_part(i) * gate
                x = x.add_(zi) if inplace else x + zi
            x = block.forward_(x, relu_epilogue) if inplace else block(x)
        if self.cfg.combine_layer == self.cfg.n_blocks and v > 1:
            x = x.reshape(b, v, n, d).mean(dim=1).reshape(b * n, d)
        return self.lin_out(F.relu(x)).reshape(b, n, 4)


def _feature_terms(latent: Tensor | MapSamples, lins: nn.ModuleList, d: int, projected: bool, rows: int):
    """``i -> the features' term before block i`` (``[rows, d]``): the i-th ``d`` channels of projected features,
    else ``lins[i]`` of the features; read from the maps at this point when ``latent`` is a :class:`MapSamples`."""
    if isinstance(latent, MapSamples):
        corners = latent.corners()
        if projected:
            return lambda i: latent.read(corners, i * d, (i + 1) * d)
        z = latent.read(corners)
        return lambda i: lins[i](z)
    z = latent.reshape(rows, -1)
    if projected:
        parts = z.split(d, dim=1)  # split's backward is one cat, not zero-fill + add
        return lambda i: parts[i]
    return lambda i: lins[i](z)
