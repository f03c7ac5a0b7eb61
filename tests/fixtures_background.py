"""Background-removal test material (import from ``fixtures_background``): a tiny ONNX "model" with U^2-Net's
interface that the test builds itself, and a synthetic render pasted on a bright textured background.

:func:`tiny_u2net` is one 1x1 convolution over rembg's normalised input (320x320, ImageNet mean and std) whose
output is the pixel's darkness (``sign=-1``) or brightness (``sign=+1``): on :func:`cluttered_car` (a dark car
render on a background no darker than 170 of 255) the darkness model finds the car, so its cut-out can be checked
against the render's own alpha; the brightness model finds the background instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

EXAMPLES = Path(__file__).resolve().parents[1] / "depthnerf" / "app" / "examples"
IMAGENET_STD = (0.229, 0.224, 0.225)


def tiny_u2net(path: Path, sign: float = -1.0) -> Path:
    """An ONNX graph ``input [1, 3, 320, 320] -> output [1, 1, 320, 320]``: ``sign * sum_c std_c * x_c``, i.e.
    (up to a constant) ``sign`` times the pixel's brightness before rembg's normalisation."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    weight = numpy_helper.from_array((sign * np.array(IMAGENET_STD, np.float32)).reshape(1, 3, 1, 1), "w")
    bias = numpy_helper.from_array(np.zeros(1, np.float32), "b")
    graph = helper.make_graph(
        [helper.make_node("Conv", ["input", "w", "b"], ["output"], kernel_shape=[1, 1])], "tiny_u2net",
        [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, 3, 320, 320])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 1, 320, 320])], [weight, bias])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8  # readable by every onnxruntime the [bg] extra admits
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def cluttered_car(size: tuple[int, int] = (180, 240), at: tuple[int, int] = (30, 70), seed: int = 0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(rgb uint8 [H, W, 3], truth bool [H, W])``: the bundled car render (RGBA, 128 px) pasted at ``at`` (row,
    column) on bright noise and stripes (every channel in 170..255); ``truth`` = the render's alpha > 127 there."""
    h, w = size
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:h, :w]
    stripes = np.where(((xx // 9 + yy // 6) % 2)[..., None] == 1, [250, 190, 175], [180, 235, 250])
    background = np.clip(stripes + rng.integers(-10, 11, (h, w, 3)), 170, 255).astype(np.float32)
    car = np.asarray(Image.open(EXAMPLES / "car_rgba.png"), np.float32)
    alpha = car[..., 3:] / 255.0
    r, c = at
    region = background[r:r + 128, c:c + 128]
    background[r:r + 128, c:c + 128] = car[..., :3] * alpha + region * (1 - alpha)
    truth = np.zeros((h, w), bool)
    truth[r:r + 128, c:c + 128] = car[..., 3] > 127
    return np.round(background).astype(np.uint8), truth


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))
