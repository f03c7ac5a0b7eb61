"""The one reader of dataset cards (``<root>/<category>_card.json``, :mod:`depthnerf.data.card`): every user
(training's ``data_card.json``, eval's summary and pixel centre, a checkpoint's framing) reads it the same way."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from depthnerf.data.card import card_pixel_center, dataset_pixel_center, read_dataset_card
from depthnerf.data.synth.framing import checkpoint_framing, dataset_framing
from depthnerf.errors import DepthnerfError


def test_missing_card_is_none_and_states_integer_centres(tmp_path: Path) -> None:
    assert read_dataset_card(tmp_path, "cars") is None
    assert dataset_pixel_center(tmp_path, "cars") == 0.0 and card_pixel_center(None) == 0.0
    assert dataset_framing(None) == "srn"  # no card: a real SRN download, SRN's own framing


def test_card_fields(tmp_path: Path) -> None:
    (tmp_path / "cars_card.json").write_text(json.dumps({"framing": "srn", "camera": {"pixel_center": 0.5}}))
    (tmp_path / "chairs_card.json").write_text(json.dumps({"generator": "depthnerf-synth-1/chairs"}))
    assert read_dataset_card(tmp_path, "cars")["framing"] == "srn"
    assert dataset_pixel_center(tmp_path, "cars") == 0.5 and dataset_pixel_center(tmp_path, "chairs") == 0.0
    assert dataset_framing(read_dataset_card(tmp_path, "chairs")) == "legacy"  # a card before framings


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", "\"srn\""])
def test_a_bad_card_is_one_error_naming_it_for_every_reader(tmp_path: Path, text: str) -> None:
    card = tmp_path / "cars_card.json"
    card.write_text(text)
    for read in (lambda: read_dataset_card(tmp_path, "cars"), lambda: dataset_pixel_center(tmp_path, "cars"),
                 lambda: checkpoint_framing(tmp_path / "w.safetensors", tmp_path, "cars")):
        with pytest.raises(DepthnerfError, match=f"{card}: unreadable dataset card"):
            read()



@pytest.mark.parametrize("stated", [0.0, 0.25, 0.5, 1])
def test_a_stated_pixel_centre_is_returned_as_stated(tmp_path: Path, stated: float) -> None:
    """Ground truth: the number written into the card's ``camera.pixel_center`` (an explicit 0.0 included)."""
    (tmp_path / "cars_card.json").write_text(json.dumps({"camera": {"pixel_center": stated}}))
    assert dataset_pixel_center(tmp_path, "cars") == stated
    assert card_pixel_center({"camera": {"pixel_center": stated}}) == stated


@pytest.mark.parametrize("card", [{}, {"camera": None}, {"camera": "blender"}, {"camera": [0.5]},
                                  {"camera": {}}, {"camera": {"pixel_center": None}}])
def test_a_card_that_states_no_pixel_centre_is_integer_centred(card: dict) -> None:
    """A card whose ``camera`` is not an object, or has no ``pixel_center``, states none: 0.0 (integer centres)."""
    assert card_pixel_center(card) == 0.0


def test_a_folder_in_place_of_the_card_is_no_card(tmp_path: Path) -> None:
    """Ground truth: the documented rule that no card *file* reads as None."""
    (tmp_path / "cars_card.json").mkdir()
    assert read_dataset_card(tmp_path, "cars") is None and dataset_pixel_center(tmp_path, "cars") == 0.0


def test_a_card_that_is_not_utf8_is_one_error_naming_it(tmp_path: Path) -> None:
    """Bytes that are no text (a Latin-1 file) are an unreadable card naming the file, not a decoding traceback."""
    card = tmp_path / "cars_card.json"
    card.write_bytes(b'{"framing": "\xe9t\xe9"}')
    with pytest.raises(DepthnerfError, match=f"{card}: unreadable dataset card"):
        read_dataset_card(tmp_path, "cars")

def test_load_object_says_which_pixel_centre_it_used(tmp_path: Path) -> None:
    import warnings

    from fixtures_srn import make_srn_fixture

    from depthnerf.data.srn import index_split, load_object

    record = index_split(make_srn_fixture(tmp_path, "cars", {"test": 1}, views=2, size=8), "cars", "test").objects[0]
    with pytest.warns(UserWarning, match=r"no pixel centre stated; intrinsics.txt read integer-centred"):
        unstated = load_object(record, [0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_object(record, [0], pixel_center=0.0).intrinsics == unstated.intrinsics
        assert load_object(record, [0], pixel_center=0.5).intrinsics.cx == unstated.intrinsics.cx - 0.5


@pytest.mark.parametrize("stated", ["0.5", float("nan"), -0.5, 37, True, [0.5]])
def test_a_stated_pixel_centre_that_is_not_a_number_in_0_1_is_named(tmp_path: Path, stated) -> None:
    """Eval back-projects depth maps with the card's pixel centre: a string was a ValueError traceback, NaN a
    crash in the geometry metrics, 37 a silent shift of 37 pixels."""
    card = tmp_path / "cars_card.json"
    card.write_text(json.dumps({"camera": {"pixel_center": stated}}))
    for read in (lambda: read_dataset_card(tmp_path, "cars"), lambda: dataset_pixel_center(tmp_path, "cars")):
        with pytest.raises(DepthnerfError, match=f"^{card}: camera.pixel_center must be a number in"):
            read()


@pytest.mark.parametrize("framing", ["blender", ["srn"]])
def test_an_unknown_framing_in_a_card_names_the_card(tmp_path: Path, framing) -> None:
    card = tmp_path / "cars_card.json"
    card.write_text(json.dumps({"framing": framing}))
    with pytest.raises(DepthnerfError, match=f"^{card} framing: unknown framing"):
        dataset_framing(read_dataset_card(tmp_path, "cars"), str(card))
    with pytest.raises(DepthnerfError, match=f"^{card} framing: unknown framing"):
        checkpoint_framing(tmp_path / "w.safetensors", tmp_path, "cars")
