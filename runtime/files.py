"""Bounded reads of files the cell takes from outside: configs, manifests, replay indexes, frames.

Every such file is opened once, checked on the open descriptor and read with a byte cap:

* not a regular file (a FIFO, a device, a socket, a folder) -> refused before any read: a FIFO
  opened for reading blocks until a writer comes, which may be never (the service would hang
  until systemd's watchdog kills it); the open uses O_NONBLOCK so the check can run at all;
* larger than the cap -> refused before it is read: a 5 MB YAML took 73 s and 1.6 GB to parse;
* an image: its width and height are read from the header (PNG, JPEG, BMP, TIFF; no decoder
  runs) and an image larger than the cap is refused before it is decoded - a 30000 x 30000 PNG is
  under 3 MB on disk and 2.7 GB decoded. Other formats are refused: their size cannot be known
  without decoding them.

Decoding uses ``cv2.IMREAD_UNCHANGED``: a grey, RGBA or 16-bit file comes back as what it is
(HxW, HxWx4, uint16) so that the frame check refuses it, instead of OpenCV's IMREAD_COLOR
silently turning it into the 8-bit BGR frame a GelSight sends.
"""

from __future__ import annotations

import os
import re
import stat
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

# What a real input of each kind needs, with ample room (measured sizes in the comments).
MAX_CONFIG_BYTES = 256 * 1024  # systemd/cell.yaml is 2 KB; parsing 256 KB of YAML takes ~1 s
MAX_JSON_BYTES = 16 * 1024 * 1024  # a bundle manifest is ~10 KB; a 24-item replay index ~0.2 MB
MAX_REPLAY_INDEX_BYTES = 64 * 1024 * 1024  # a long recorded session (thousands of items)
MAX_IMAGE_BYTES = 64 * 1024 * 1024  # a 640x480 PNG frame is ~0.5 MB; a 4096^2 photo < 50 MB
MAX_IMAGE_SIDE_PX = 8192  # config bounds camera frames at 4096 px a side; camera photos 8192
MAX_IMAGE_PIXELS = 4096 * 4096 * 2  # 32 Mpx (camera photos of a dataset): 96 MB as uint8 BGR
MAX_FRAME_PIXELS = 4096 * 4096  # a tactile frame: the config's largest sensor; 200 MB as float32 in preprocessing


class InputRefused(ValueError):
    """A file refused before (or instead of) reading it; ``reason`` is one short word."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.header: ImageHeader | None = None  # the image's, when its size was refused


def read_regular_file(path: Path | str, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of ``path`` if it is a regular file of at most ``max_bytes``, else InputRefused.

    OSError (missing, permission) passes through for the caller to word. Symlinks are followed
    (callers that must stay inside a folder check the resolved path first).
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise InputRefused(f"{path}: not a regular file ({_file_type(st.st_mode)}); a {what} must be one",
                           "not_regular")
    with os.fdopen(fd, "rb") as f:
        if st.st_size > max_bytes:
            raise InputRefused(f"{path}: {st.st_size} bytes, more than the {max_bytes} a {what} may have",
                               "too_large")
        data = f.read(max_bytes + 1)  # the file may grow between fstat and read
    if len(data) > max_bytes:
        raise InputRefused(f"{path}: more than the {max_bytes} bytes a {what} may have", "too_large")
    return data


def _file_type(mode: int) -> str:
    for test, name in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISDIR, "a folder")):
        if test(mode):
            return name
    return "not a plain file"


def inside(folder: Path | str, path: Path | str) -> bool:
    """Does ``path``, every symlink resolved, lie inside ``folder`` (also resolved)?"""
    real_folder = os.path.realpath(folder)
    real = os.path.realpath(path)
    return os.path.commonpath([real_folder, real]) == real_folder and real != real_folder


# --- image headers ----------------------------------------------------------------------------

@dataclass(frozen=True)
class ImageHeader:
    format: str
    width: int
    height: int


def image_header(data: bytes) -> ImageHeader | None:
    """Width and height from a PNG, JPEG, BMP or TIFF header without decoding; None if the
    format is none of those or the header is cut short."""
    try:
        if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
            w, h = struct.unpack(">II", data[16:24])
            return ImageHeader("png", w, h)
        if data[:2] == b"\xff\xd8":
            return _jpeg_header(data)
        if data[:2] == b"BM":
            dib = struct.unpack("<I", data[14:18])[0]
            if dib == 12:  # OS/2 BITMAPCOREHEADER
                w, h = struct.unpack("<HH", data[18:22])
            else:
                w, h = struct.unpack("<ii", data[18:26])
            return ImageHeader("bmp", abs(w), abs(h))  # negative height: stored top-down
        if data[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_header(data)
    except struct.error:  # cut short inside the header
        return None
    return None


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_segments(data: bytes) -> Iterator[tuple[int, int, int]]:
    """The marker segments of a JPEG's header after its SOI, in order: (marker, index of the
    payload's first byte, index just past the segment). Fill bytes and standalone markers are
    stepped over; it ends at the scan (SOS) or the image's end (EOI), at a byte that is no marker,
    and after a segment whose length is under 2. ``end`` may lie past the data: the reader checks."""
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # standalone markers carry no length
            i += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, or the scan: the header is over
            return
        length = (data[i + 2] << 8) | data[i + 3]
        yield marker, i + 4, i + 2 + length
        if length < 2:
            return
        i += 2 + length


def _jpeg_header(data: bytes) -> ImageHeader | None:
    for marker, start, _ in jpeg_segments(data):
        if marker in _JPEG_SOF:
            h, w = struct.unpack(">HH", data[start + 1:start + 5])
            return ImageHeader("jpeg", w, h)
    return None  # no frame header before the scan or the end


def _tiff_header(data: bytes) -> ImageHeader | None:
    end = "<" if data[:2] == b"II" else ">"
    ifd = struct.unpack(end + "I", data[4:8])[0]
    n = struct.unpack(end + "H", data[ifd:ifd + 2])[0]
    size: dict[int, int] = {}
    for k in range(min(n, 512)):
        tag, typ, _count = struct.unpack(end + "HHI", data[ifd + 2 + 12 * k: ifd + 10 + 12 * k])
        value = data[ifd + 10 + 12 * k: ifd + 14 + 12 * k]
        if tag in (256, 257):  # ImageWidth, ImageLength: SHORT or LONG
            size[tag] = struct.unpack(end + ("H" if typ == 3 else "I"), value[:2] if typ == 3 else value)[0]
    if 256 in size and 257 in size:
        return ImageHeader("tiff", size[256], size[257])
    return None


def check_image_size(data: bytes, name: str, expected_hw: tuple[int, int] | None = None,
                     max_side_px: int = MAX_IMAGE_SIDE_PX, max_pixels: int = MAX_IMAGE_PIXELS) -> ImageHeader:
    """The header of an encoded image, refused (InputRefused) before decoding if its format is
    unknown, or its size is over the caps or not ``expected_hw`` (height, width)."""
    head = image_header(data)
    if head is None:
        raise InputRefused(f"{name}: not a PNG, JPEG, BMP or TIFF image (or its header is damaged)", "format")
    if head.width < 1 or head.height < 1 or max(head.width, head.height) > max_side_px \
            or head.width * head.height > max_pixels:
        raise InputRefused(f"{name}: {head.format.upper()} of {head.width}x{head.height} px, over the "
                           f"{max_side_px} px a side and {max_pixels} px an image this cell decodes", "too_large")
    if expected_hw is not None and (head.height, head.width) != tuple(expected_hw):
        err = InputRefused(f"{name}: size {head.width}x{head.height}, expected {expected_hw[1]}x{expected_hw[0]}",
                           "size")
        err.header = head
        raise err
    return head


def decode_image(data: bytes, name: str, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Header check, then cv2.imdecode with IMREAD_UNCHANGED: the image as stored (channels and
    depth kept, for the frame check to judge); InputRefused if refused or undecodable."""
    import cv2

    check_image_size(data, name, expected_hw)
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None:
        raise InputRefused(f"{name}: cannot be decoded", "corrupt")
    return image


def read_image_file(path: Path | str, expected_hw: tuple[int, int] | None = None,
                    max_bytes: int = MAX_IMAGE_BYTES) -> np.ndarray:
    """A regular image file, bounded in bytes and pixels, decoded as stored (see decode_image)."""
    return decode_image(read_regular_file(path, max_bytes, "image file"), str(path), expected_hw)


def atomic_write(path: Path, text: str) -> None:
    """``text`` into the state file ``path`` (the fault file, the beta override), whole or not at
    all: written to a private .tmp, fsynced, renamed over, the folder fsynced so the rename survives
    a power cut; a failed write leaves no .tmp behind."""
    from vs2t_edge.runtime.journal import STATE_FILE_MODE, make_state_dir

    path = Path(path)
    make_state_dir(path.parent)  # STATE_DIR_MODE for folders made here
    tmp = path.with_name(path.name + ".tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, STATE_FILE_MODE)
        # deleting FAULT clears a latched fault: never writable by others, whatever the umask or the
        # mode a stale .tmp from a crash was left with
        os.fchmod(fd, STATE_FILE_MODE)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


_ABSOLUTE_PATH = re.compile(r"(?<![\w.:/])/(?:[\w.+-]+/)*?(?:([\w.+-]+)/)?([\w.+-]+)(?![\w.+-]*/)")


def _name_of(m: re.Match) -> str:
    """A folder's name; a file's with its folder's (``run/metrics.json``, not ``metrics.json``)."""
    folder, name = m.group(1), m.group(2)
    return f"{folder}/{name}" if folder and "." in name.strip(".") else name


def portable(value: Any) -> Any:
    """``value`` (text, or lists and dicts of it, as a result JSON holds) without this machine's
    folders: every absolute path keeps its last component, the name anyone gives their own dataset,
    run or bundle folder (a file's keeps its folder's too). Results that are committed and read on
    other machines are written so (bench.json, a comparison's JSON); a run's own files keep their
    paths, which its tools follow."""
    if isinstance(value, str):
        return _ABSOLUTE_PATH.sub(_name_of, value)
    if isinstance(value, dict):
        return {k: portable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [portable(v) for v in value]
    return value
