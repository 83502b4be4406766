"""Issue 17, item 5: the bounds the watchdog budget leases are the waits a caller really sees.

A gate request counted as ``(retries + 1) x timeout_s`` could wait one more try behind a
heartbeat already on the wire (requests are stop-and-wait), and a failed ``to_reject`` then
waits for the heartbeat thread to stop; a UVC open had no bound at all. Each is measured here
against the one function the budget and the config validation use."""

from __future__ import annotations

import threading
import time

import cv2
import pytest

from vs2t_edge.firmware_bridge.gate_client import (GateClient, GateClientError, request_worst_case_s,
                                                  to_reject_worst_case_s)
from vs2t_edge.firmware_bridge.mcu_sim import start_simulated_gate
from vs2t_edge.runtime import camera as camera_mod
from vs2t_edge.runtime.budget import bounds_of, gate_request_bound_s
from vs2t_edge.runtime.arm import ArmConfig
from vs2t_edge.runtime.camera import UVC_OPEN_TIMEOUT_S, UVCCamera
from vs2t_edge.runtime.devices import CameraError

TIMEOUT_S, RETRIES, HEARTBEAT_S = 0.3, 1, 0.1


@pytest.fixture
def silent_gate():
    """A connected client whose gate then stops hearing anything: every request times out."""
    _, sim = start_simulated_gate(move_time_ms=20)
    client = GateClient(sim.device_path, timeout_s=TIMEOUT_S, retries=RETRIES, heartbeat_period_s=HEARTBEAT_S)
    client.connect()
    sim.faults.drop_rx = 10**9
    yield client
    client.disconnect()
    sim.stop()


def _heartbeat_on_the_wire(client: GateClient, within_s: float = 2.0) -> None:
    """Return just after the background heartbeat took the line (it holds the request lock)."""
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        if client._lock.acquire(blocking=False):
            client._lock.release()
            time.sleep(0.001)
            continue
        return
    raise AssertionError("no heartbeat went out")


def test_a_request_behind_a_heartbeat_waits_longer_than_its_own_tries_and_within_the_bound(silent_gate):
    _heartbeat_on_the_wire(silent_gate)
    start = time.monotonic()
    with pytest.raises(GateClientError) as err:
        silent_gate.sort(3)
    waited = time.monotonic() - start
    assert err.value.kind == "timeout"
    own_tries = (RETRIES + 1) * TIMEOUT_S  # what the budget counted before: the caller waits longer
    assert waited > own_tries + 0.5 * TIMEOUT_S, waited
    assert waited <= request_worst_case_s(TIMEOUT_S, RETRIES, HEARTBEAT_S), waited


def test_a_failing_to_reject_stops_the_heartbeats_within_its_bound(silent_gate):
    _heartbeat_on_the_wire(silent_gate)
    start = time.monotonic()
    silent_gate.to_reject()  # never raises: the SORT fails, then the heartbeats stop
    waited = time.monotonic() - start
    assert silent_gate._hb_thread is None
    assert request_worst_case_s(TIMEOUT_S, RETRIES, HEARTBEAT_S) < to_reject_worst_case_s(TIMEOUT_S, RETRIES,
                                                                                         HEARTBEAT_S)
    assert waited <= to_reject_worst_case_s(TIMEOUT_S, RETRIES, HEARTBEAT_S), waited


def test_the_budget_counts_the_gate_as_its_caller_waits():
    gate = {"kind": "serial", "timeout_s": 0.5, "retries": 3}
    assert gate_request_bound_s(gate) == request_worst_case_s(0.5, 3) > 4 * 0.5
    bounds = bounds_of({"kind": "uvc", "timeout_s": 2.0}, "fake", ArmConfig(), gate)
    assert bounds.to_reject_s == to_reject_worst_case_s(0.5, 3)
    assert bounds.camera_reopen_s == 2.0 + UVC_OPEN_TIMEOUT_S
    assert bounds.retry_prep_s >= bounds.camera_reopen_s and bounds.clear_s >= bounds.camera_reopen_s


class _HangingCapture:
    """A cv2.VideoCapture whose driver hangs in open until ``release_open`` is set."""

    release_open = threading.Event()
    released: list = []

    def __init__(self, *args):
        self.release_open.wait(10)

    def isOpened(self):
        return True

    def set(self, *args):
        return True

    def get(self, *args):
        return 0.0

    def release(self):
        self.released.append(self)


def test_a_hung_uvc_open_becomes_a_camera_fault_within_its_bound(monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", _HangingCapture)
    cam = UVCCamera(0, open_timeout_s=0.2)
    start = time.monotonic()
    with pytest.raises(CameraError, match="did not open within 0.2 s") as err:
        cam.connect()
    assert time.monotonic() - start < 0.2 + 0.5
    assert err.value.kind == "timeout" and cam._cap is None
    _HangingCapture.release_open.set()  # the driver comes back late: its capture is let go, never used
    deadline = time.monotonic() + 2
    while not _HangingCapture.released and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(_HangingCapture.released) == 1 and cam._cap is None


def test_a_uvc_open_that_fails_says_so_as_before(monkeypatch):
    class _Closed(_HangingCapture):
        def __init__(self, *args):
            pass

        def isOpened(self):
            return False

    monkeypatch.setattr(cv2, "VideoCapture", _Closed)
    with pytest.raises(CameraError, match="cannot open") as err:
        UVCCamera(0).connect()
    assert err.value.kind == "unplugged"
    assert camera_mod.UVC_OPEN_TIMEOUT_S == UVC_OPEN_TIMEOUT_S
