"""The UVC camera trusts the driver's capture time over its queue length: a frame the driver took
before the grab was asked (a queue deeper than the flush allows for) is read past, never scored as
this press; a driver that keeps handing such frames is a camera fault naming it; a backend whose
times are not the monotonic clock falls back to the blind flush alone."""

from __future__ import annotations

import time

import cv2
import pytest

from test_camera import _RecordingCapture
from vs2t_edge.runtime.camera import MAX_STALE_DROPS, UVCCamera
from vs2t_edge.runtime.devices import CameraError


class _TimedCapture(_RecordingCapture):
    """A V4L2 capture whose frames carry capture times (CAP_PROP_POS_MSEC, monotonic ms): the first
    ``held`` frames read after each grab request are old ones the driver kept (taken ``age_ms``
    before now; ``rearm(..., untimed=True)``: handed with no time), the rest are taken now.
    ``clock`` = "monotonic" or "file" (a file's position)."""

    held, age_ms, clock = 0, 500.0, "monotonic"

    def __init__(self, device, api=None):
        super().__init__(device, api)
        self._pending = type(self).held
        self._last_ms = 0.0

    def grab(self):
        self.grabs += 1
        self._stamp()
        return True

    def read(self):
        self._stamp()
        return super().read()

    def _stamp(self):
        now = 1e3 * time.monotonic()
        self._last_untimed = False
        if self._pending > 0:
            self._pending -= 1
            self._last_ms = now - type(self).age_ms
            self._last_untimed = getattr(self, "_untimed", False)
        else:
            self._last_ms = now + 1.0
        if type(self).clock == "file":
            self._last_ms = 33.3 * self.reads

    def rearm(self, n, age_ms=None, untimed=False):
        self._pending = n
        if age_ms is not None:
            type(self).age_ms = age_ms
        self._untimed = untimed

    def get(self, prop):
        if prop == cv2.CAP_PROP_POS_MSEC:
            return 0.0 if getattr(self, "_last_untimed", False) else self._last_ms  # 0: a buffer without a time
        return super().get(prop)


@pytest.fixture
def timed(monkeypatch):
    _RecordingCapture.instances = []
    _TimedCapture.held, _TimedCapture.age_ms, _TimedCapture.clock = 0, 500.0, "monotonic"
    monkeypatch.setattr(cv2, "VideoCapture", _TimedCapture)
    return _RecordingCapture.instances


def test_frames_taken_before_the_grab_are_read_past(timed):
    with UVCCamera(0, flush_frames=2, buffer_size=1) as cam:  # the driver takes 1 buffer: flush 2
        cap = timed[0]
        cap.rearm(5)  # the driver held 5 frames from before the press: the flush of 2 leaves 3
        before = 1e3 * time.monotonic()
        frame = cam.grab()
        assert cam.stale_dropped == 3 and cap.reads == 4  # 3 stale reads past, the 4th is fresh
        assert 1e3 * frame.timestamp_s >= before  # stamped with the driver's capture time
        frame2 = cam.grab()  # a well-behaved queue: nothing more to drop
        assert cam.stale_dropped == 3 and frame2.timestamp_s >= frame.timestamp_s


def test_a_driver_that_only_hands_stale_frames_is_a_fault_naming_it(timed):
    with UVCCamera(0, flush_frames=0, buffer_size=1, read_timeout_s=2.0) as cam:
        timed[0].rearm(MAX_STALE_DROPS + 5)
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.reason == "stale" and exc.value.kind == "timeout" and "before the grab was asked" in str(exc.value)


def test_times_that_are_not_the_monotonic_clock_leave_the_blind_flush(timed):
    _TimedCapture.clock = "file"  # e.g. a backend reading a file: positions, not capture times
    with UVCCamera(0, flush_frames=2, buffer_size=1) as cam:
        timed[0].rearm(5)
        before = time.monotonic()
        frame = cam.grab()
        assert cam.stale_dropped == 0 and timed[0].reads == 1  # the flush only
        assert frame.timestamp_s >= before  # stamped when admitted


def test_a_queue_kept_from_minutes_ago_is_read_past_too(timed):
    """The case the check is for: the cell stood, and the driver's queue kept the frames taken just
    after the last grab. However old, once the driver has shown it stamps with the monotonic clock,
    a frame taken before the grab is never this press."""
    with UVCCamera(0, flush_frames=2, buffer_size=1) as cam:
        cam.grab()  # a fresh frame: the driver's times are the monotonic clock
        timed[0].rearm(5, age_ms=15_000.0)  # held since 15 s ago
        asked = time.monotonic()
        frame = cam.grab()
    assert cam.stale_dropped == 3 and frame.timestamp_s >= asked


def test_a_stale_buffer_without_a_time_is_read_past_once_the_driver_stamps(timed):
    with UVCCamera(0, flush_frames=2, buffer_size=1) as cam:
        cam.grab()
        timed[0].rearm(5, untimed=True)  # five old buffers, handed with POS_MSEC 0: the flush takes 2
        asked = time.monotonic()
        frame = cam.grab()
        assert cam.stale_dropped == 3 and frame.timestamp_s >= asked
        timed[0].rearm(MAX_STALE_DROPS + 5, untimed=True)
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.reason == "stale" and "without a capture time" in str(exc.value)


def test_an_error_inside_the_drivers_read_is_named(timed, monkeypatch):
    """A backend raising inside read() (cv2.error on a bad buffer) used to end the read thread with
    a traceback on stderr and a grab that said "no frame (unplugged or stream ended)"."""
    def broken(self):
        raise cv2.error("VIDIOC_DQBUF: No such device")

    with UVCCamera(0, flush_frames=0, buffer_size=None) as cam:
        monkeypatch.setattr(_TimedCapture, "read", broken)
        with pytest.raises(CameraError) as exc:
            cam.grab()
    assert exc.value.kind == "unplugged" and "VIDIOC_DQBUF" in str(exc.value)
