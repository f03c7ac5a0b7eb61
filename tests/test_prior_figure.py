"""``scripts/prior_figure.py`` on a tiny SRN fixture with depth: one row per view, one panel per net; bad flags and
missing views are one-line errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from fixtures_scripts import load_script
from fixtures_srn import make_srn_fixture
from PIL import Image

from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled

prior_figure = load_script("prior_figure")


def test_figure_has_a_row_per_view_and_a_panel_per_net(tmp_path: Path, capsys) -> None:
    data = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 2}, views=3, size=16, with_depth=True)
    torch.manual_seed(0)
    tiny = tmp_path / "tiny.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(4, 6, 8), input_size=64)), tiny)
    out = tmp_path / "fig.png"
    assert prior_figure.main(["--data", str(tmp_path / "none"), str(data), "--categories", "cars", "--objects", "2",
                              "--view", "1", "--weights", "shipped=default", f"tiny={tiny}", "--out", str(out)]) == 0
    assert "2 views x 4 panels" in capsys.readouterr().out
    with Image.open(out) as im:
        assert im.width > im.height > 100


def test_bad_weights_view_and_category_are_errors(tmp_path: Path) -> None:
    data = make_srn_fixture(tmp_path / "data", "cars", splits={"test": 1}, views=2, size=16, with_depth=True)
    out = str(tmp_path / "fig.png")
    with pytest.raises(SystemExit, match="expected LABEL=WEIGHTS"):
        prior_figure.main(["--data", str(data), "--categories", "cars", "--weights", "nolabel", "--out", out])
    with pytest.raises(SystemExit, match="no view 5"):
        prior_figure.main(["--data", str(data), "--categories", "cars", "--view", "5", "--out", out])
    with pytest.raises(SystemExit, match="no chairs_test/"):
        prior_figure.main(["--data", str(data), "--categories", "chairs", "--out", out])
