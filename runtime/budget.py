"""The watchdog budget: every wait of the loop against systemd's WatchdogSec, from one place.

systemd kills the service when no ``WATCHDOG=1`` arrives for ``WatchdogSec`` (30 s in
systemd/vs2t-edge.service). A fault the cell can name (a hung grab, a lost arm, a silent gate)
must become a latched fault - the piece in the reject bin, the reason journalled - before that,
never a kill and a restart. So:

* the loop pings when a tenth of the watchdog has passed (``PING_FRACTION``; it was a half:
  scaled to a 3 s watchdog, a 1.5 s wait plus a 2 s step left a 3.45 s gap), at every step
  boundary: each try of a press step, each frame, the sort, the wait for a piece;
* a device wait that may last longer than that - one press step's try (arm moves, press, grab,
  retract), the retry's preparation (lift, camera reopen), lifting the gel before a fault, the
  operator's clear, the abort on SIGTERM - is *leased* (``Notifier.bounded_wait``): the watchdog is fed
  while the wait is within the bound the device enforces itself (the arm worker is ended past
  ``isolated_call_bound_s``, a grab past the camera's ``timeout_s``, an open past
  ``UVC_OPEN_TIMEOUT_S``, a gate request past ``gate_client.request_worst_case_s`` - behind a
  heartbeat on the wire, then ``retries + 1`` tries), and no longer: a call hung past its own bound is a hung loop,
  and systemd is right to kill it. An IsolatedURArm whose worker died (the very fault it exists
  for) starts a new one and connects it inside the next call, whatever that call is: each lease
  that calls the arm counts one such start (``arm_start_s``);
* every wait that is not leased (a sort and its one retry, the wait for the next piece, the
  fault latch's arm stop and gate-to-reject) must fit in the watchdog with the ping interval and
  a margin: ``watchdog_problems`` says which does not, and config validation refuses it.
"""

from __future__ import annotations

from dataclasses import dataclass

from vs2t_edge.firmware_bridge.gate_client import request_worst_case_s, to_reject_worst_case_s
from vs2t_edge.runtime.arm import ArmConfig
from vs2t_edge.runtime.arm_isolated import WORKER_START_TIMEOUT_S, isolated_call_bound_s
from vs2t_edge.runtime.camera import UVC_OPEN_TIMEOUT_S
from vs2t_edge.runtime.notify import PING_FRACTION

SYSTEMD_WATCHDOG_S = 30.0  # systemd/vs2t-edge.service WatchdogSec (tests/test_systemd.py ties the two)
MARGIN_S = 1.0  # scheduling, the journal's fsync, the model's few ms per press
ARM_STOP_BOUND_S = 5.0  # IsolatedURArm.stop(): the worker answers or is ended
ARM_WORKER_START_S = WORKER_START_TIMEOUT_S  # IsolatedURArm(start_timeout_s): a new worker starting
SIM_GATE = (0.5, 3)  # the simulated serial gate's timeout_s and retries (runtime/gate.py)


@dataclass(frozen=True)
class StepBounds:
    """The longest each kind of device wait may take, in seconds, from the config."""

    arm_call_s: float  # one move_above / press / retract
    grab_s: float  # one frame (the grab's own timeout)
    gate_request_s: float  # one gate request as its caller waits (gate_client.request_worst_case_s)
    # a dead arm worker replaced inside the next arm call: the start and its connect
    # (IsolatedURArm only; an in-process arm has no worker, 0)
    arm_start_s: float = 0.0
    # gate.to_reject() beyond its request: a failed one stops the heartbeats (gate_client.to_reject_worst_case_s)
    gate_fail_safe_s: float = 0.0
    camera_open_s: float = 0.0  # one camera open (UVCCamera ends a hung open past open_timeout_s)

    @property
    def to_reject_s(self) -> float:
        """The gate to reject: the SORT, and when it fails, the heartbeats stopped."""
        return self.gate_request_s + self.gate_fail_safe_s

    @property
    def camera_reopen_s(self) -> float:
        """Close (a read stuck in the driver is waited for up to the grab timeout before its
        handle is left), then open."""
        return self.grab_s + self.camera_open_s

    @property
    def press_try_s(self) -> float:
        """One try of a press step: move above, press, grab, retract."""
        return self.arm_start_s + 3 * self.arm_call_s + self.grab_s

    @property
    def lift_s(self) -> float:
        """Lifting the gel off the piece (one retract) before a fault is latched."""
        return self.arm_start_s + self.arm_call_s

    @property
    def abort_s(self) -> float:
        """SIGTERM mid-item: lift the gel, then the gate to reject."""
        return self.lift_s + self.to_reject_s

    @property
    def clear_s(self) -> float:
        """The operator's clear: gate clear, the arm's stop cleared and reconnected (after a worker
        fault the clear call is the one that starts the new worker), the camera reopened."""
        return self.gate_request_s + self.arm_start_s + 2 * self.arm_call_s + self.camera_reopen_s

    @property
    def retry_prep_s(self) -> float:
        """Between two tries: lift the gel (after a worker that died, the retract starts the new
        one), reopen the camera."""
        return self.arm_start_s + self.arm_call_s + self.camera_reopen_s


def arm_call_bound_s(kind: str, arm: ArmConfig) -> float:
    if kind == "ur_rtde":
        return isolated_call_bound_s(arm)  # the bound IsolatedURArm enforces by ending its worker
    return max(arm.move_timeout_s, arm.press_timeout_s + arm.settle_s)  # in-process: its own timeouts


def _gate_timing(gate: dict) -> tuple[float, int] | None:
    if gate["kind"] == "serial":
        return gate["timeout_s"], gate["retries"]
    return SIM_GATE if gate["kind"] == "sim" else None  # fake: no waits


def gate_request_bound_s(gate: dict) -> float:
    timing = _gate_timing(gate)
    return request_worst_case_s(*timing) if timing else 0.0


def gate_fail_safe_bound_s(gate: dict) -> float:
    timing = _gate_timing(gate)
    return to_reject_worst_case_s(*timing) - request_worst_case_s(*timing) if timing else 0.0


def camera_open_bound_s(camera: dict) -> float:
    if camera.get("kind") == "uvc":
        return UVC_OPEN_TIMEOUT_S  # UVCCamera ends a hung open past it
    return camera["timeout_s"]  # replay: a local folder or file, counted as one grab


def arm_start_bound_s(kind: str, arm: ArmConfig) -> float:
    """A new IsolatedURArm worker: its start, then its connect (one call's bound)."""
    return ARM_WORKER_START_S + isolated_call_bound_s(arm) if kind == "ur_rtde" else 0.0


def bounds_of(camera: dict, arm_kind: str, arm: ArmConfig, gate: dict) -> StepBounds:
    return StepBounds(arm_call_s=arm_call_bound_s(arm_kind, arm), grab_s=camera["timeout_s"],
                      gate_request_s=gate_request_bound_s(gate), arm_start_s=arm_start_bound_s(arm_kind, arm),
                      gate_fail_safe_s=gate_fail_safe_bound_s(gate), camera_open_s=camera_open_bound_s(camera))


def unleased_waits(bounds: StepBounds, wait_item_timeout_s: float) -> list[tuple[str, float, str]]:
    """(what, longest seconds, the config keys that set it) of every wait between two pings that
    is not leased."""
    return [
        ("a sort and its one retry (each behind a heartbeat, then (retries + 1) tries)", 2 * bounds.gate_request_s,
         "devices.gate.timeout_s"),
        ("the wait for the next piece", wait_item_timeout_s, "watchdog.wait_item_timeout_s"),
        ("a fault latch: arm stop, then gate to reject", ARM_STOP_BOUND_S + bounds.to_reject_s,
         "devices.gate.timeout_s"),
    ]


def allowed_wait_s(watchdog_s: float = SYSTEMD_WATCHDOG_S) -> float:
    """The longest un-leased wait the watchdog tolerates: a ping may be up to one ping interval
    late at its start, and the margin covers the rest."""
    return watchdog_s * (1.0 - PING_FRACTION) - MARGIN_S


def watchdog_problems(bounds: StepBounds, wait_item_timeout_s: float,
                      watchdog_s: float = SYSTEMD_WATCHDOG_S) -> list[tuple[str, str]]:
    """(config key, problem) for each un-leased wait the watchdog would not survive."""
    limit = allowed_wait_s(watchdog_s)
    return [(key, f"{what} may take {seconds:.3g} s, more than the {limit:.3g} s the service's "
                  f"WatchdogSec={watchdog_s:g} leaves (less the ping interval and a {MARGIN_S:g} s margin): "
                  "systemd would kill the cell before it can latch the fault")
            for what, seconds, key in unleased_waits(bounds, wait_item_timeout_s) if seconds > limit]
