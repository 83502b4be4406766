"""The UVC camera's warm-up after each open: frames are read until their brightness holds still,
so the first grab - a piece's no-contact reference - is not a frame of auto exposure's ramp."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from test_camera import _RecordingCapture
from vs2t_edge.runtime import camera_warmup as wu
from vs2t_edge.runtime.camera import UVC_OPEN_TIMEOUT_S, UVCCamera, camera_from_config
from vs2t_edge.runtime.contact import ContactCheck


class _RampingCapture(_RecordingCapture):
    """A camera on auto exposure: the stream's frames start dark and brighten by a factor per frame
    until they reach the scene's level, from the first read after each open."""

    ramp = (0.70, 0.80, 0.88, 0.93, 0.96, 0.98, 0.99)  # exposure relative to the settled one

    def read(self):
        self.reads += 1
        h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        k = self.reads - 1
        gain = self.ramp[k] if k < len(self.ramp) else 1.0
        noise = self._rng.normal(0.0, 1.5, (h, w, 3))  # a live sensor's noise: no two frames alike
        return True, np.clip(_gel((h, w)).astype(np.float32) * gain + noise, 0, 255).astype(np.uint8)


@pytest.fixture
def ramping(monkeypatch):
    _RecordingCapture.instances = []
    monkeypatch.setattr(cv2, "VideoCapture", _RampingCapture)
    return _RecordingCapture.instances


def _gel(hw=(120, 160)):
    rng = np.random.default_rng(3)
    return cv2.GaussianBlur(rng.integers(80, 180, (*hw, 3), dtype=np.uint8), (7, 7), 0)


def test_settle_reads_until_the_level_holds_still_and_says_so():
    levels = iter([60.0, 80.0, 95.0, 104.0, 108.0, 110.0, 110.2, 110.1, 110.3, 110.2, 110.2])
    gel = _gel()
    read = lambda: (True, np.clip(gel * (next(levels) / gel.mean()), 0, 255).astype(np.uint8))  # noqa: E731
    got = wu.settle(read, limit_s=10.0)
    # settled once the last SETTLE_RUN + 1 = 4 frames span <= 0.5 levels: frames 6..9
    assert got["settled"] and got["frames"] == 9 and got["level"] == pytest.approx(110.3, abs=0.6)


def test_settle_gives_up_at_its_limit_or_at_a_failed_read_and_says_why():
    t = iter(np.arange(0.0, 100.0, 0.25))
    level = iter(np.arange(50.0, 250.0, 2.0))
    gel = _gel()
    got = wu.settle(lambda: (True, np.full_like(gel, int(next(level)))), limit_s=2.0, clock=lambda: next(t))
    assert not got["settled"] and got["why"] == "time limit" and got["frames"] == 8
    assert got["level_first"] < got["level"]
    got = wu.settle(lambda: (False, None), limit_s=2.0)
    assert got == {**got, "frames": 0, "settled": False, "why": "no frame"}


def test_frame_level_reads_every_form_a_backend_hands():
    gel = _gel((240, 320))
    level = float(gel.mean())
    assert wu.frame_level(gel) == pytest.approx(level, abs=1.0)
    jpeg = np.frombuffer(cv2.imencode(".jpg", gel, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes(), np.uint8)[None]
    grey = float(cv2.cvtColor(gel, cv2.COLOR_BGR2GRAY).mean())
    assert wu.frame_level(jpeg) == pytest.approx(grey, abs=1.5)
    from vs2t_edge.runtime.yuyv import yuyv_bytes

    yuyv = yuyv_bytes(gel)
    assert wu.frame_level(yuyv) == pytest.approx(grey, abs=3.0)
    assert wu.frame_level(yuyv.reshape(1, -1)) == pytest.approx(grey, abs=3.0)
    assert wu.frame_level(np.zeros((2, 3), np.float32)) is None and wu.frame_level(None) is None


def test_the_first_grab_after_open_is_past_auto_exposures_ramp(ramping):
    """Without a warm-up the first grab after open - the next piece's reference - is a frame of the
    ramp, 30 % darker than the presses after it, and the contact check reads the untouched gel as
    pressed; with it the reference is a settled frame, and every reopen warms up again."""
    check = ContactCheck()
    with UVCCamera(0, flush_frames=0, width=160, height=120) as cam:
        reference, later = cam.grab().image, cam.grab().image
        assert "warmup" not in cam.settings_applied
        assert check.read(later, reference).pressed  # the ramp alone reads as contact
    with UVCCamera(0, flush_frames=0, width=160, height=120, warmup_s=2.0) as cam:
        w = cam.settings_applied["warmup"]
        assert w["settled"] and w["frames"] >= len(_RampingCapture.ramp)
        reference = cam.grab().image
        assert not check.read(cam.grab().image, reference).pressed
        cam.disconnect()
        cam.connect()  # a reopen (retry, operator's clear): the new stream ramps again, and is read past
        assert cam.settings_applied["warmup"]["settled"] and ramping[-1].reads > len(_RampingCapture.ramp)
        assert not check.read(cam.grab().image, reference).pressed


def test_warmup_is_bounded_inside_the_open_and_set_from_the_config(tmp_path):
    with pytest.raises(ValueError, match="warmup_s"):
        UVCCamera(0, warmup_s=UVC_OPEN_TIMEOUT_S)
    with pytest.raises(ValueError, match="warmup_s"):
        UVCCamera(0, warmup_s=-1.0)
    from test_camera import _cell_config

    _, load = _cell_config(tmp_path, "")
    assert camera_from_config(load().camera).warmup_s == 2.0  # on by default for a live camera
    _, load = _cell_config(tmp_path, "    warmup_s: 0\n")
    assert camera_from_config(load().camera).warmup_s == 0.0
    _, load = _cell_config(tmp_path, "    warmup_s: 5\n")
    with pytest.raises(Exception, match="warmup_s"):
        load()


def test_a_failed_read_is_read_past_and_three_in_a_row_end_the_warmup():
    gel = _gel()
    script = iter([(True, gel), (False, None), (True, gel), (True, gel), (True, None), (True, gel), (True, gel),
                   (True, gel), (True, gel)])
    got = wu.settle(lambda: next(script), limit_s=10.0)
    # the unreadable frame broke the steady run: settled on the 4 frames after it
    assert got["settled"] and got["frames"] == 7
    got = wu.settle(iter([(True, gel)] * 2 + [(False, None)] * 3).__next__, limit_s=10.0)
    assert got == {**got, "settled": False, "why": "no frame", "frames": 2}


class _NeverSettling(_RecordingCapture):
    """Lighting that flickers: every frame's level differs from the last by far more than 0.5."""

    def read(self):
        self.reads += 1
        h, w = int(self.props[cv2.CAP_PROP_FRAME_HEIGHT]), int(self.props[cv2.CAP_PROP_FRAME_WIDTH])
        return True, np.full((h, w, 3), 100 + 20 * (self.reads % 2), np.uint8)


def test_a_camera_that_never_settles_still_opens_within_its_bound(monkeypatch):
    import time

    _RecordingCapture.instances = []
    monkeypatch.setattr(cv2, "VideoCapture", _NeverSettling)
    cam = UVCCamera(0, width=160, height=120, open_timeout_s=1.6, warmup_s=1.5)
    start = time.monotonic()
    cam.connect()  # the warm-up ends a margin before the open's bound: no "did not open"
    took = time.monotonic() - start
    w = cam.settings_applied["warmup"]
    assert not w["settled"] and w["why"] == "time limit" and w["frames"] > 0
    assert took < 1.6 and w["seconds"] <= 1.6 - 1.0 + 0.1
    cam.disconnect()
