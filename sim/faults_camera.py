"""Fault-matrix rows at the camera: unplugged, frozen, corrupt or black frames, bad recorded files.

Loop rows (sim/fault_rig.py): the simulated camera (sim/devices.py) or a ReplayCamera under the
real loop, the arm and gate fakes; registered in sim/faults.py SCENARIOS.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from vs2t_edge.sim.fault_rig import Rig, _at, _check, _loop_row


def _unplug_camera(rig: Rig, item: int, press: int, *, for_good: bool) -> dict:
    """Pull the simulated camera's cable just before that press: a real disconnect, every grab
    fails until the camera is reopened. It is back for the first reopen, or (``for_good``) only
    once the operator has plugged it back in (``rig.camera.replug``). Returns a dict the row
    reads afterwards: ``connects`` = the camera's connect() calls when the cable came out."""
    seen: dict = {}

    def pull() -> None:
        seen["connects"] = rig.camera.connects
        rig.camera.unplug(failed_connects=None if for_good else 0)

    _at(rig, item, press, pull)
    return seen


def camera_unplugged_and_back(w: Path):
    # cable out mid-press, back at once: the loop reopens the camera before its one retry
    # (without the reopen the retry's grab finds it still disconnected and latches a fault)
    held: dict = {}

    def inject(r: Rig) -> None:
        held["rig"], held["seen"] = r, _unplug_camera(r, 1, 2, for_good=False)

    words, problems = _loop_row(w, inject=inject, expect_outcomes={"sorted": 4}, fault_words=None, retries=1,
                                holder_out=held)
    cam, seen = held["rig"].camera, held["seen"]
    _check(problems, "connects" in seen, "the cable was never pulled")
    _check(problems, cam.connects == seen.get("connects", 0) + 1 and not cam.cable_out,
           f"expected one reopen after the unplug, the camera saw {cam.connects - seen.get('connects', 0)}")
    pre = {r["item_id"]: r for r in held["audit"]["records"] if r.get("type") == "pre_sort"}
    _check(problems, [(r["bin"], r["stopped_by"]) for r in pre.values() if r["stopped_by"] == "camera_reopened"]
           == [(0, "camera_reopened")], "the piece whose camera was reopened mid-press did not go to the reject bin "
                                        "(its no-contact reference predates the reopen)")
    return words + f"; camera reopened {cam.connected_count - 1}x, that piece to reject", problems



def camera_unplugged_for_good(w: Path):
    # cable out mid-press and the retry's reopen fails: latched fault naming it, piece rejected;
    # the operator plugs it back in and clears, the clear reopens the camera, the rest are sorted
    # (without that reopen the next piece needs a retry of its own)
    held: dict = {}

    def inject(r: Rig) -> None:
        held["rig"], held["seen"] = r, _unplug_camera(r, 1, 2, for_good=True)

    def operator_fix(r: Rig):
        def fix() -> None:
            held["connects_at_fix"] = r.camera.connects
            r.camera.replug()
            grab = r.camera.grab

            def first_grab_after_the_clear():  # was the camera open again before the loop used it?
                held.setdefault("open_at_next_grab", r.camera.is_connected)
                return grab()
            r.camera.grab = first_grab_after_the_clear
        return fix

    words, problems = _loop_row(w, inject=inject, operator_fix_for=operator_fix,
                                expect_outcomes={"sorted": 3, "rejected_fault": 1},
                                fault_words="reopening the camera for the retry failed", retries=1)
    cam, seen = held["rig"].camera, held["seen"]
    _check(problems, "connects" in seen, "the cable was never pulled")
    _check(problems, cam.connects == seen.get("connects", 0) + 2,
           f"expected a failed reopen on the retry and one at the clear, got "
           f"{cam.connects - seen.get('connects', 0)} connect() calls")
    _check(problems, held.get("open_at_next_grab") is True and cam.connects == held.get("connects_at_fix", -9) + 1,
           "the operator's clear did not reopen the camera")
    return words + ("; camera reopened by the clear" if held.get("open_at_next_grab") else ""), problems


def _record_scores(rig: Rig, note: Callable[[np.ndarray], Any]) -> list:
    """Wrap the rig's model: ``note(frame)`` of every frame it scores, in order, in the list returned."""
    scored: list = []
    score = rig.cell.model.score_press

    def recording(frame):
        scored.append(note(frame))
        return score(frame)
    rig.cell.model.score_press = recording
    return scored


def camera_frozen(w: Path):
    # From press 1 of piece-0001 on, the driver hands out its last buffer (the piece's no-contact
    # frame) again, until the operator power-cycles the sensor. The first repeat is CameraFrozen
    # (frozen_after 2), the press is retried after a reopen, still frozen: the fault latches on
    # piece-0001 itself, which is rejected with no decision; the rest are sorted after the clear.
    # (With frozen_after 5 piece-0001 was decided on 3 frozen frames and the fault hit piece-0002.)
    held: dict = {}

    def inject(r: Rig) -> None:
        # (piece id, frame bytes) of every frame the model scored
        held["scored"] = _record_scores(r, lambda frame: (r.pieces.current.id, np.asarray(frame).tobytes()))
        _at(r, 1, 1, lambda: r.camera.inject("frozen", 1000))

    words, problems = _loop_row(w, inject=inject, operator_fix_for=lambda r: r.camera.clear_faults,
                                expect_outcomes={"rejected_fault": 1, "sorted": 3}, fault_words="same frame",
                                retries=1, holder_out=held)
    recs, faults = held["audit"]["records"], held["audit"]["faults"]
    _check(problems, len(faults) == 1 and "(piece-0001)" in faults[0],
           f"expected the fault on piece-0001, the first frozen piece, got {faults}")
    final = next((r for r in recs if r.get("type") == "final" and r.get("item_id") == "piece-0001"), {})
    _check(problems, final.get("outcome") == "rejected_fault" and final.get("presses") == 0,
           f"piece-0001: expected rejected_fault after 0 scored presses, got {final}")
    _check(problems, not any(r.get("type") == "pre_sort" and r.get("item_id") == "piece-0001" for r in recs),
           "piece-0001 was decided (a pre_sort record) from frozen frames")
    scored = held["scored"]
    _check(problems, not any(piece == "piece-0001" for piece, _ in scored),
           f"the model scored {sum(p == 'piece-0001' for p, _ in scored)} frame(s) of the frozen piece-0001")
    repeats = [p for (p, a), (_, b) in zip(scored, scored[1:]) if a == b]
    _check(problems, not repeats, f"a frame identical to the one before it was scored ({repeats})")
    return words + f"; {len(scored)} frames scored", problems


def corrupt_frames(w: Path):
    """A black and a truncated frame: the camera's frame guard refuses them (a retryable camera
    error), so the press is retried once each. Checked directly, not from the retry count: the
    guard refused exactly those two frames by reason, every frame the model scored has the
    camera's size and is not black, and the journal's scores are exactly the frames scored."""
    held: dict = {"refused": []}

    def inject(r: Rig):
        _at(r, 1, 1, lambda: r.camera.inject("black", 1))
        _at(r, 2, 1, lambda: r.camera.inject("truncated", 1))
        grab = r.camera.grab

        def watched_grab():
            try:
                return grab()
            except Exception as exc:  # noqa: BLE001 - recorded, then raised as the loop sees it
                held["refused"].append((r.pieces.index, getattr(exc, "kind", ""), getattr(exc, "reason", "")))
                raise
        r.camera.grab = watched_grab
        held["scored"] = _record_scores(r, lambda frame: (r.pieces.index, tuple(np.shape(frame)),
                                                          float(np.max(frame))))

    words, problems = _loop_row(w, inject=inject, expect_outcomes={"sorted": 4}, fault_words=None, retries=2,
                                holder_out=held)
    refused, scored = held["refused"], held["scored"]
    _check(problems, refused == [(1, "corrupt", "black"), (2, "corrupt", "size")],
           f"the frame guard refused {refused}, expected piece 1's black and piece 2's truncated frame")
    bad = [s for s in scored if s[1] != (48, 64, 3) or s[2] == 0.0]
    _check(problems, scored and not bad, f"frames scored that should not have been: {bad}")
    journal_scores = [sc for r in held["audit"]["records"] if r.get("type") == "pre_sort"
                      for sc in r.get("scores", [])]
    _check(problems, len(journal_scores) == len(scored),
           f"the journal holds {len(journal_scores)} scores for {len(scored)} frames scored")
    dark = [sc for sc in journal_scores if sc.get("novelty", 0.0) < 10.0]  # the grey model's novelty = mean level
    _check(problems, not dark, f"a black frame's score reached the evidence: {dark}")
    return words + (f"; guard refused {len(refused)} frames ({', '.join(f'piece {i} {why}' for i, _, why in refused)}),"
                    f" {len(scored)} frames scored, {len(bad)} of them corrupt"), problems


def all_frames_black(w: Path):
    # the gel is covered (black) for the press and its retry: a camera fault naming the cause
    return _loop_row(w, inject=lambda r: _at(r, 1, 1, lambda: r.camera.inject("black", 2)),
                     expect_outcomes={"sorted": 3, "rejected_fault": 1}, fault_words="all black", retries=1)


def replay_camera_bad_frames(w: Path):
    """The camera is a ReplayCamera (runtime/camera.py) on a folder of recorded frames, not the
    simulated one: frame 000004.png is corrupt (not a PNG) and 000007.png vanished from the disk
    after the camera listed the folder. Each must be refused naming the file, the press retried
    on the next recorded frame, and every other frame served once, in order: no frame of an
    earlier piece served again, nothing lost. The retry reopened the camera after the piece's
    no-contact reference was taken, so that piece goes to the reject bin, its retried frame
    unscored (docs/cell.md, retry policy); the piece without a bad file is sorted into its bin.
    Every frame has its own grey level, so the journal's scores (the grey model's novelty is the
    frame's mean level) and the frames served show which recorded frame each grab took."""
    import cv2

    from vs2t_edge.runtime.camera import ReplayCamera

    frames_dir = w / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    truths = ["denim", "silk", "wool"]
    # per piece: its no-contact reference, then two presses (the grey evidence decides on two); a
    # bad file sits where piece 1's and piece 2's first press would be, the retry takes the next
    levels: list[int | str] = [118, 48, 52, 119, "corrupt", 58, 120, "missing", 68]
    for i, v in enumerate(levels):
        path = frames_dir / f"{i:06d}.png"
        if v == "corrupt":
            path.write_bytes(b"\x89PNG\r\n\x1a\n not a picture")
        else:
            cv2.imwrite(str(path), np.full((48, 64, 3), 100 if v == "missing" else v, np.uint8))
    cam = ReplayCamera(frames_dir, expected_hw=(48, 64))
    served = _serving(cam)
    held: dict = {}

    def inject(r: Rig) -> None:
        (frames_dir / f"{levels.index('missing'):06d}.png").unlink()  # gone after the camera listed the folder

    words, problems = _loop_row(w, inject=inject, truths=truths, camera=cam, expect_outcomes={"sorted": 3},
                                fault_words=None, retries=2, holder_out=held)
    retries = held["audit"]["retries"]
    for name, rec in zip(("000004.png", "000007.png"), retries):
        _check(problems, name in rec.get("error", ""), f"the refusal does not name {name}: {rec.get('error')!r}")
    pre = [r for r in held["audit"]["records"] if r.get("type") == "pre_sort"]
    scored = [round(sc["novelty"]) for r in pre for sc in r["scores"]]
    _check(problems, scored == [48, 52], f"press frames scored {scored}, expected [48, 52]: the first piece's "
                                         "presses only (the others' retried frames decide nothing)")
    _check(problems, [(r["bin"], r["stopped_by"]) for r in pre[1:]] == [(0, "camera_reopened")] * 2,
           f"the pieces whose camera was reopened: {[(r['bin'], r['stopped_by']) for r in pre[1:]]}, "
           "expected the reject bin 0, camera_reopened")
    want = [v for v in levels if isinstance(v, int)]
    _check(problems, served == want, f"frames served {served}, the recording's good frames in order are {want} "
                                     "(a frame served twice or skipped: the camera lost its place)")
    return words + f"; both bad files refused by name, frames served in recorded order: {served}", problems


def _serving(cam) -> list[int]:
    """Wrap ``cam.grab``: the grey level of every frame it serves, in order, in the list returned."""
    served: list[int] = []
    grab = cam.grab

    def noting():
        frame = grab()
        served.append(int(round(float(frame.image.mean()))))
        return frame
    cam.grab = noting
    return served
