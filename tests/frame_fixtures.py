"""A rendered GelSight press for the tests that compare what a camera hands the model with what
training reads (tests/test_preprocess.py, tests/test_decode_scale.py)."""

from __future__ import annotations

import cv2
import numpy as np


def rendered_press_jpeg(quality: int = 95) -> tuple[np.ndarray, np.ndarray, list[bytes]]:
    """(press frame, no-contact frame, both as the camera's JPEG bytes at ``quality``): a dome
    pressed into a woven texture on the simulated 640 x 480 GelSight, markers and read noise in."""
    from vs2t_edge.sim.gelsight import GelSight, background, reference_frame, render_press

    rng = np.random.default_rng(3)
    sensor = GelSight()  # 640 x 480, markers, read noise
    bg = background(sensor, 3)
    ref = reference_frame(bg, sensor, rng)
    yy, xx = np.mgrid[0:sensor.height_px, 0:sensor.width_px].astype(np.float32) * np.float32(sensor.mm_per_px)
    weave = 0.04 * np.sin(2 * np.pi * xx / 0.6) * np.sin(2 * np.pi * yy / 0.6)  # a fabric's texture, mm
    dome = 0.3 * np.exp(-((xx - 7.5) ** 2 + (yy - 5.6) ** 2) / 12.0)  # the press
    frame = render_press((dome + weave * (dome > 0.05)).astype(np.float32), bg, sensor, rng)
    jpeg = [cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes() for f in (frame, ref)]
    return frame, ref, jpeg
