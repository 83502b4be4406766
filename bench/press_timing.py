"""The press as the cell pays for it, for the bench (bench/measure.py): the camera's MJPEG frame
decoded at the bundle's scale, the camera's frame checks, the cell's own scoring and evidence,
stage by stage; and a fused press graph cut into its trunk and its tail so each can be timed."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

JPEG_QUALITY = 95  # what the press frames are re-encoded at to stand for a UVC camera's MJPEG stream
STAGES = ("decode_mjpeg", "camera_checks", "preprocess", "trunk", "heads", "router", "decision", "evidence")
OUTSIDE_STAGES = tuple(k for k in STAGES if k != "trunk")
# what the camera streams (devices.camera.pixel_format) and the stage its frame's decode is timed as
DECODE_STAGE = {"mjpeg": "decode_mjpeg", "yuyv": "decode_yuyv"}
CAMERA_FORMATS = tuple(DECODE_STAGE)  # runtime/camera.py PIXEL_FORMATS (tests/test_bench.py holds them equal)
# the cell's devices.camera.decode_scale settings: runtime/wiring.py DECODE_SCALES (tests/test_decode_scale.py holds them equal)
DECODE_SCALES = ("auto", "full")
DECODE_LABEL = {"decode_mjpeg": "MJPEG decode", "decode_yuyv": "YUYV to BGR"}


def stages_of(camera_format: str) -> tuple[str, ...]:
    """``STAGES`` with the decode of ``camera_format``'s frames first."""
    return (DECODE_STAGE[camera_format], *STAGES[1:])


def decode_key(overhead: dict) -> str | None:
    """The decode stage a result's stage medians hold (None: a bench.json from before decode was timed)."""
    return next((k for k in DECODE_LABEL if k in overhead), None)


def camera_payload(frame: np.ndarray, camera_format: str, jpeg_quality: int = JPEG_QUALITY):
    """A lossless frame as the camera sends it: JPEG bytes at ``jpeg_quality``, or YUYV (HxWx2)."""
    import cv2

    if camera_format == "yuyv":
        from vs2t_edge.runtime.yuyv import yuyv_bytes

        return yuyv_bytes(frame)
    ok, enc = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    if not ok:
        raise RuntimeError("could not JPEG-encode a frame")
    return enc.tobytes()


def _is_yuyv(payload) -> bool:
    """``camera_payload``'s YUYV frame (HxWx2), not JPEG bytes."""
    return isinstance(payload, np.ndarray) and payload.ndim == 3


def decode_payload(payload, scale: int) -> np.ndarray | None:
    """The cell camera's decode of ``camera_payload``'s output at 1/``scale``."""
    if _is_yuyv(payload):
        from vs2t_edge.runtime.yuyv import decode_yuyv

        return decode_yuyv(payload, payload.shape[:2], scale)
    from vs2t_edge.runtime.preprocess import decode_jpeg

    return decode_jpeg(payload, scale)


def decode_scale(model, frame_hw: tuple[int, int] | None = None, setting: str = "auto",
                 camera_format: str = "mjpeg") -> int:
    """The scale the cell's UVC camera decodes ``frame_hw`` frames at for this bundle with
    ``devices.camera.decode_scale`` = ``setting`` (runtime/wiring.py ``model_decode_scale``: 1/reduce
    on the reduced path; auto: a float-path bundle's too, 1/2 of 640x480 at 128 or 224 px). Imported
    on call: runtime.wiring loads the cell (the arm, the gate, cv2), which the bench's CLI need not."""
    from vs2t_edge.runtime.wiring import model_decode_scale

    return model_decode_scale(model, frame_hw, setting, camera_format)


class CameraChecks:
    """What the cell does to each grabbed frame before scoring it: the camera's frame guard
    (check_frame, frozen frame), an MJPEG frame's marks of a cut in transit (its end marker, its
    last row; runtime/jpeg_integrity.py) and the press-frame contact check against the item's
    no-contact frame (on by default for a UVC camera, docs/cell.md)."""

    def __init__(self, reference_image: np.ndarray, model=None) -> None:
        from vs2t_edge.runtime.frame_guard import FrameGuard
        from vs2t_edge.runtime.contact import ContactCheck
        from vs2t_edge.runtime.jpeg_integrity import damaged_jpeg
        from vs2t_edge.runtime.wiring import model_crop_fraction

        self.damaged_jpeg = damaged_jpeg
        self.contact = ContactCheck(crop_fraction=model_crop_fraction(model))  # the model's square too, as the cell
        self.guard, self.reference = FrameGuard("bench", None, 2), reference_image

    def __call__(self, image: np.ndarray, jpeg: np.ndarray | None = None) -> None:
        if jpeg is not None and self.damaged_jpeg(jpeg, image):
            raise ValueError("the bench's own JPEG reads as cut short in transit")
        self.guard.admit(image)
        self.contact.read(image, self.reference)


def press_stages(model, jpeg, evidence, checks: CameraChecks | None = None,
                 scale: int | None = None) -> dict[str, float]:
    """One press as the cell pays for it, in ms per stage: decode the camera's frame (a UVC
    GelSight streams MJPEG by default; the camera decodes it with libjpeg, at 1/reduce scale for a
    bundle on the reduced path, and for a float-path one with decode_scale auto: ``scale``, from
    ``decode_scale``; None: the bundle's own, without a frame size); a YUYV frame - ``camera_payload`` - is made BGR
    and reduced instead), the camera's frame checks (``checks``), preprocess, trunk,
    heads, router, decision (TactileModel.score_press) and the evidence update. For a fused bundle
    (format 2) "trunk" is the one onnxruntime call, heads and projections included, and "heads" is
    0 (``speed_worker`` measures what the graph's tail costs apart)."""
    scale = decode_scale(model) if scale is None else scale
    stage = DECODE_STAGE["yuyv" if _is_yuyv(jpeg) else "mjpeg"]
    t0 = time.perf_counter()
    frame = decode_payload(jpeg, scale)
    t1 = time.perf_counter()
    if checks is not None:
        checks(frame, None if stage != DECODE_STAGE["mjpeg"] else jpeg)
    t1c = time.perf_counter()
    s = model.score_press(frame, scale)
    tm = dict(model.last_timing)
    t2 = time.perf_counter()
    evidence.add(s)
    t3 = time.perf_counter()
    return {stage: 1e3 * (t1 - t0), "camera_checks": 1e3 * (t1c - t1), "preprocess": tm["preprocess_ms"],
            "trunk": tm["trunk_ms"], "heads": tm["heads_ms"], "router": tm["router_ms"], "decision": tm["decision_ms"],
            "evidence": 1e3 * (t3 - t2), "press": 1e3 * (t3 - t0)}


def _time_runs(sess, name: str, xs: list, n: int) -> list[float]:
    for x in xs[:3]:
        sess.run(None, {name: x})
    times = []
    for k in range(n):
        x = xs[k % len(xs)]
        t0 = time.perf_counter()
        sess.run(None, {name: x})
        times.append(1e3 * (time.perf_counter() - t0))
    return times


def _time_split(trunk, tail, name: str, xs: list, n: int) -> tuple[list[float], list[float]]:
    """The trunk part, then the tail part on its feature, press after press (the tail finds the
    caches as the trunk left them, as inside the one call): (trunk times, tail times)."""
    for x in xs[:3]:
        tail.run(None, {"feature": trunk.run(None, {name: x})[0]})
    tt, tl = [], []
    for k in range(n):
        t0 = time.perf_counter()
        (f,) = trunk.run(None, {name: xs[k % len(xs)]})
        t1 = time.perf_counter()
        tail.run(None, {"feature": f})
        t2 = time.perf_counter()
        tt.append(1e3 * (t1 - t0))
        tl.append(1e3 * (t2 - t1))
    return tt, tl


def split_press_graph(model, threads: int):
    """(trunk part, tail part) of a fused press graph as two sessions opened like the bundle's:
    image -> feature, and feature -> the other outputs; cut with ``onnx`` (train extra), None
    without it. Timing the tail apart slightly overstates it (one more session call)."""
    try:
        import onnx
        from onnx.utils import Extractor
    except ImportError:
        return None
    import tempfile

    from vs2t_edge.runtime.bundle import open_session

    ex = Extractor(onnx.load(str(model.bundle.path("trunk"))))
    with tempfile.TemporaryDirectory() as tmp:
        out = []
        for part, ins, outs in (("trunk", [model._trunk_in], ["feature"]), ("tail", ["feature"], model._press_outputs[1:])):
            path = Path(tmp) / f"{part}.onnx"
            onnx.save(ex.extract_model(ins, outs), str(path))
            out.append(open_session(path, threads))
        return tuple(out)
