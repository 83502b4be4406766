"""The contact check asks for the imprint where the model looks (runtime/contact.py
``crop_fraction``): a press whose imprint lies only beside the centred square the bundle's
preprocessing crops shows the model an untouched gel, which no class was trained on and which
scores as whatever fabric lies nearest. The whole-frame check alone let it through."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from test_cell import REFERENCE, make_cell
from vs2t_edge.runtime.contact import ContactCheck
from vs2t_edge.runtime.journal import read_records
from vs2t_edge.runtime.preprocess import TactilePreprocess, centre_square, preprocess_tactile
from vs2t_edge.runtime.wiring import model_crop_fraction


def _frames(band: slice) -> tuple[np.ndarray, np.ndarray]:
    reference = np.full((480, 640, 3), 120, np.uint8)
    pressed = reference.copy()
    pressed[200:280, band] = 40
    return reference, pressed


def test_an_imprint_beside_the_models_square_is_no_contact_for_it():
    reference, side = _frames(slice(0, 70))  # left of the centred 480 px square (columns 80-560)
    whole, square = ContactCheck(), ContactCheck(crop_fraction=1.0)
    assert whole.read(side, reference).pressed  # the frame changed: 1.8 % of it
    reading = square.read(side, reference)
    assert not reading.pressed and reading.model_area_fraction == 0.0 and reading.area_fraction > 0.01
    _, centre = _frames(slice(300, 370))
    assert square.read(centre, reference).pressed and whole.read(centre, reference).pressed
    # a narrower crop is a smaller square: the same imprint at its edge falls outside it
    _, edge = _frames(slice(90, 130))  # inside the full square (80-560), left of the 0.75 one (140-500)
    assert square.read(edge, reference).pressed and not ContactCheck(crop_fraction=0.75).read(edge, reference).pressed


@pytest.mark.parametrize("hw,crop", [((480, 640), 1.0), ((240, 320), 0.75), ((400, 300), 0.9), ((61, 97), 0.5)])
def test_the_square_is_the_one_the_preprocessing_crops(hw, crop):
    """Pixels outside ``centre_square`` change nothing the model reads; one inside does."""
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, hw + (3,), dtype=np.uint8)
    spec = TactilePreprocess(size=32, crop_fraction=crop)
    rows, cols = centre_square(hw, crop)
    outside = frame.copy()
    outside[:rows.start] = outside[rows.stop:] = 0
    outside[:, :cols.start] = outside[:, cols.stop:] = 0
    reference = np.full(hw + (3,), 100, np.uint8)
    base = preprocess_tactile(frame, reference, spec)
    assert np.array_equal(preprocess_tactile(outside, reference, spec), base)
    inside = frame.copy()
    inside[rows.start:rows.stop, cols.start:cols.start + 4] ^= 255
    assert not np.array_equal(preprocess_tactile(inside, reference, spec), base)


def test_the_cell_asks_for_the_imprint_in_its_models_square(tmp_path):
    """Two presses imprinted only beside the square: retried, then a latched no-contact fault;
    never scored, the piece in the reject bin. Without the square, both were scored."""
    cell, arm, cam, gate, journal = make_cell(tmp_path, ["side", "side", 50], contact_check=ContactCheck(crop_fraction=1.0))
    results = cell.run(max_items=1)
    assert results[0].outcome == "rejected_fault" and results[0].bin == 0 and gate.sorted == []
    assert cell.model.scored == 0 and "of the square the model reads" in cell.fault
    assert [r["kind"] for r in read_records(journal.path) if r["type"] == "retry"] == ["no_contact"]
    whole = make_cell(tmp_path / "whole", ["side", "side", REFERENCE], contact_check=ContactCheck())[0]
    whole.run(max_items=1)
    assert whole.model.scored >= 2


def test_wiring_takes_the_square_from_the_bundle():
    trunk = SimpleNamespace(descriptor=None, preprocess_spec=TactilePreprocess(crop_fraction=0.85))
    assert model_crop_fraction(trunk) == 0.85
    assert model_crop_fraction(SimpleNamespace(descriptor=object(), preprocess_spec=TactilePreprocess())) is None
    assert model_crop_fraction(None) is None
