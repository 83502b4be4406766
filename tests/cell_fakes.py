"""In-test fakes for the cell loop: a scripted model, a simple evidence rule and a frame camera.

They satisfy the same protocols the real runtime/inference.py and runtime/evidence.py do, so
the loop's tests do not wait for (or depend on the numbers of) a trained bundle. The score and the
evidence rule are the fault matrix's own (sim/fakes.py), under the names the tests use.
"""

from __future__ import annotations

import numpy as np

from vs2t_edge.runtime.devices import CameraError, Frame
from vs2t_edge.runtime.preprocess import FrameError, check_frame
from vs2t_edge.sim.fakes import GreyEvidence as FakeEvidence  # noqa: F401 - one copy, shared with sim/
from vs2t_edge.sim.fakes import GreyScore as FakeScore
from vs2t_edge.sim.scene import fake_cell_yaml

# the loop tests' cell config: fake devices, denim / silk touched, wool untouched, bins 1-3
LOOP_CONFIG = fake_cell_yaml(camera={"kind": "replay", "path": "x"},
                             evidence={"confidence": 0.95, "max_presses": 4}, journal="j.jsonl")


class FakeModel:
    """Scores frames by their mean grey level: a frame of value v votes for ``votes[v]``."""

    def __init__(self, votes: dict[int, str], classes, strength=3.0):
        self.votes, self.classes, self.strength = votes, list(classes), strength
        self.reference = None
        self.scored = 0

    def set_reference(self, frame):
        self.reference = check_frame(frame, name="reference frame")

    def score_press(self, frame):
        check_frame(frame)
        v = int(round(float(frame[..., 0].mean())))
        target = self.votes.get(v)
        self.scored += 1
        lp = {c: (0.0 if c == target else -self.strength) for c in self.classes}
        return FakeScore(lp, novelty=float(v), untouched=False)

    def press_novelty(self, frame, reduced_by=1):  # TactileModel's, for calibrate
        return float(self.score_press(frame).novelty)


class ScriptedCamera:
    """Returns a reference frame when the gel is up and the scripted frames when pressed.

    ``script`` entries: an int grey level, "black" (a bad frame), "side" (pressed only beside the
    centred square a model reads), "error" (CameraError), or
    "unplugged" (the cable comes out: that grab and every grab after it fail with an unplugged
    CameraError until connect(); connect() fails while ``cable_out`` - set it back to False, as
    the operator plugging it in, or leave ``back_on_reconnect`` True for a cable that is back at
    once).
    """

    def __init__(self, arm, script, size=(48, 64)):
        self.arm, self.script, self.size = arm, list(script), size
        self.index = 0
        self.connected = False
        self.connects = 0
        self.cable_out = False
        self.lost = False  # unplugged since the last successful connect()
        self.back_on_reconnect = True

    def connect(self):
        self.connects += 1
        if self.cable_out and not self.back_on_reconnect:
            raise CameraError("cannot open (unplugged)", device="camera", kind="unplugged")
        self.cable_out = self.lost = False
        self.connected = True

    def disconnect(self):
        self.connected = False

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc):
        self.disconnect()

    def grab(self):
        if self.lost:
            raise CameraError("not connected (unplugged)", device="camera", kind="unplugged")
        self.index += 1
        pressed = bool(self.arm.calls) and self.arm.calls[-1] == "press"
        if not pressed:
            return Frame(np.full(self.size + (3,), 100, np.uint8), float(self.index), self.index)
        what = self.script.pop(0) if self.script else 100
        if what == "error":
            raise CameraError("no frame (injected)", device="camera", kind="timeout")
        if what == "unplugged":
            self.cable_out = self.lost = True
            self.connected = False
            raise CameraError("no frame (unplugged)", device="camera", kind="unplugged")
        if what == "black":
            return Frame(np.zeros(self.size + (3,), np.uint8), float(self.index), self.index)
        if what == "side":  # an imprint in the band left of the centred square, the rest the gel at rest
            image = np.full(self.size + (3,), 100, np.uint8)
            image[:, :self.size[1] // 16] = 60  # its box-averaged change stays outside the square
            return Frame(image, float(self.index), self.index)
        return Frame(np.full(self.size + (3,), int(what), np.uint8), float(self.index), self.index)


def strict_model_frame_check(frame):
    check_frame(frame)
    if frame.mean() < 3:
        raise FrameError("black", "black")


def latch_skipping(monkeypatch, device: str, call: str) -> None:
    """Patch Cell.latch_fault so that, while it runs, ``cell.<device>.<call>()`` does nothing:
    the regression of a latch that no longer sends that safety step (arm.stop, gate.to_reject)."""
    from vs2t_edge.runtime import cell as cell_mod

    real_latch = cell_mod.Cell.latch_fault

    def latch(self, *args, **kwargs):
        dev = getattr(self, device)
        sent = getattr(dev, call)
        setattr(dev, call, lambda: None)
        try:
            real_latch(self, *args, **kwargs)
        finally:
            setattr(dev, call, sent)

    monkeypatch.setattr(cell_mod.Cell, "latch_fault", latch)
