"""The MJPEG quality a camera streams at, read from its frames' quantisation table.

A bundle scores a UVC camera's frames best when it was trained through that camera's JPEG
(``train --camera-jpeg Q``, docs/training.md "The camera's JPEG"): trained on lossless frames, the
paper world's bundle put 62.1 % of pieces in the right bin behind a q95 camera, trained through q95
70.3 %. A UVC camera does not say its quality, but every JPEG carries the table its encoder
quantised with. Most cameras scale the IJG tables of the JPEG standard's annex K by a quality
(libjpeg's ``jpeg_quality_scaling``); the quality whose scaled luminance table is nearest the
frame's is the camera's, exactly when the tables match and approximately for an encoder with
tables of its own. The cell reads it from the first frame it takes undecoded
(``UVCCamera.settings_applied["mjpeg_quality"]``) and says when the bundle was trained for
another (``quality_note``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vs2t_edge.runtime.files import jpeg_segments

# The JPEG standard's example luminance table (ITU-T T.81 annex K.1), in natural (row-major) order
_LUMINANCE = np.array([
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55,
    14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51, 87, 80, 62,
    18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99], np.int64)
# natural index of the k-th coefficient in zigzag order: a DQT segment lists its table so
_ZIGZAG = np.array([
    0, 1, 8, 16, 9, 2, 3, 10, 17, 24, 32, 25, 18, 11, 4, 5, 12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13, 6, 7, 14,
    21, 28, 35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51, 58, 59, 52, 45, 38, 31, 39, 46, 53, 60,
    61, 54, 47, 55, 62, 63])
# every quality's scaled table, zigzag order, as libjpeg builds it for baseline JPEG (1..255)
_QUALITIES = np.arange(1, 101)
_SCALE = np.where(_QUALITIES < 50, 5000 // _QUALITIES, 200 - 2 * _QUALITIES)
_TABLES = np.clip((_LUMINANCE[_ZIGZAG][None, :] * _SCALE[:, None] + 50) // 100, 1, 255)

# a camera within this many quality steps of what the bundle trained through is taken as the same
QUALITY_SLACK = 3


@dataclass(frozen=True)
class StreamQuality:
    quality: int  # 1..100: the IJG quality whose luminance table is nearest the frame's
    exact: bool  # the frame's table is that quality's, entry for entry


def quantisation_tables(data: bytes | np.ndarray) -> dict[int, np.ndarray]:
    """The JPEG's quantisation tables (id -> 64 values in zigzag order), read from its DQT
    segments up to the scan; {} for data that is no JPEG or ends early."""
    b = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
    if b[:2] != b"\xff\xd8":
        return {}
    tables: dict[int, np.ndarray] = {}
    for marker, j, end in jpeg_segments(b):  # the header's segments, as runtime/files.py reads them
        if end < j or end > len(b):  # a length under 2, or past the data: a corrupt header
            return tables
        while marker == 0xDB and j < end:
            precision, table_id = b[j] >> 4, b[j] & 0x0F
            n = 64 * (2 if precision else 1)
            if j + 1 + n > end:
                return tables
            raw = np.frombuffer(b, np.uint8, n, j + 1)
            tables[table_id] = (raw.astype(np.int64) if not precision
                                else raw.reshape(64, 2).astype(np.int64) @ np.array([256, 1]))
            j += 1 + n
    return tables


def estimate_quality(data: bytes | np.ndarray) -> StreamQuality | None:
    """The quality a JPEG was encoded at, from its luminance table (table 0); None without one."""
    table = quantisation_tables(data).get(0)
    if table is None:
        return None
    err = np.abs(_TABLES - table[None, :]).sum(axis=1)
    best = int(np.argmin(err))
    return StreamQuality(int(_QUALITIES[best]), bool(err[best] == 0))


def quality_note(stream_quality: object, camera_jpeg: int) -> str | None:
    """What the cell says when its camera streams at another quality than its bundle trained for:
    ``stream_quality`` the camera's (``settings_applied["mjpeg_quality"]``; None: unknown, e.g. a
    camera the backend decodes), ``camera_jpeg`` the bundle's (0: trained on lossless frames).
    None when there is nothing to say."""
    if isinstance(stream_quality, bool) or not isinstance(stream_quality, int):
        return None
    if camera_jpeg and abs(camera_jpeg - stream_quality) <= QUALITY_SLACK:
        return None
    trained = (f"through JPEG q{camera_jpeg}" if camera_jpeg else "on lossless frames")
    return (f"the camera streams MJPEG at about q{stream_quality} (read from its frames' quantisation table); "
            f"this bundle was trained {trained}: a bundle trained for this camera (`vs2t-edge train DS "
            f"--camera-jpeg {stream_quality}`, exported again) scores its frames as it trained on them "
            "(README knob table, \"training through the camera's JPEG\")")


def trained_quality(model: object) -> int:
    """The camera MJPEG quality ``model``'s bundle was trained through (manifest ``camera_jpeg``), 0
    for a bundle trained on lossless frames or a model that names none (an injected one)."""
    return int(getattr(model, "camera_jpeg", 0) or 0)


def camera_format_problem(camera: dict, camera_jpeg: object) -> str:
    """Why the cell cannot score a bundle trained through the camera's MJPEG at ``camera_jpeg`` (the
    manifest's; 0 or absent: lossless frames) on the camera a config's ``devices.camera`` section
    describes, or '' when it can. A UVC camera streaming YUYV (``pixel_format: yuyv``) hands
    uncompressed frames: the bundle's trunk, scene model and operating point were fitted on JPEG
    ones, and scored on YUYV frames a tiny demo-world run trained through q90 decided 87 of its 528
    test-job pieces otherwise than training's report (right 56.1 -> 53.4 %, mis-sorts 4.36 -> 4.55 %).
    A quality the camera streams at (MJPEG) is read from its frames and only said (``quality_note``):
    close qualities score close; no JPEG at all is the frames the bundle never saw."""
    if isinstance(camera_jpeg, bool) or not isinstance(camera_jpeg, int) or camera_jpeg <= 0:
        return ""  # lossless-trained (or a value the bundle's own check refuses, naming it)
    if camera.get("kind") != "uvc" or camera.get("pixel_format", "mjpeg") != "yuyv":
        return ""
    return (f"devices.camera.pixel_format is yuyv (uncompressed frames), but the bundle was trained through the "
            f"camera's MJPEG at q{camera_jpeg} (manifest camera_jpeg): it would score frames unlike every frame "
            "its trunk, scene model and operating point were fitted on. Set pixel_format: mjpeg, or deploy a "
            "bundle trained on lossless frames (`vs2t-edge train` without --camera-jpeg)")
