"""An MJPEG frame cut short in transit: what libjpeg decodes without saying so, found by its marks.

A UVC frame whose last USB payloads were lost (or a chunk of it, so the scan runs out of bytes
before the image's end) still decodes: libjpeg only warns ("premature end of data segment"), and
OpenCV does not pass the warning on. What it hands back has its own marks:

* the entropy-coded data runs out before the last block: libjpeg decodes every block it has no
  data for with all coefficients zero - exactly (128, 128, 128) - to the image's end, so the
  frame's last pixel row ends in that flat grey (from edge to edge once the data ran out before
  the last row of blocks). A real sensor's frame never does (read noise, vignetting: on
  the 200 real GelSight Mini frames of ``../shared/real`` and the ViTac cloth frames, at q50, q75 and
  q95, decoded at 1/1 to 1/8, at most 0.4 % of a bottom row's pixels lie at exactly 128);
* the bytes end without the JPEG's end marker (EOI, ``FF D9``; zero bytes of padding after it
  allowed): OpenCV 5 refuses such a buffer, but OpenCV 4 (``opencv>=4.8`` is allowed) decodes
  it with its missing part filled, black or grey.

Either is a frame whose lower part the sensor never sent; scored, it moves a press's posterior to
another fabric (docs/cell.md, "An MJPEG frame damaged in transit"), and against the no-contact
reference the fill reads as an imprint, so an unpressed gel passes the contact check. The camera
refuses it (runtime/camera.py, ``CameraError`` kind ``corrupt``, reason ``jpeg``). A chunk lost
mid-stream whose garbled remainder still fills the frame carries neither mark and is not caught.

Numpy only: the cell runtime never imports torch.
"""

from __future__ import annotations

import numpy as np

JPEG_FILL = 128  # what libjpeg decodes a block with no data to, in every channel (DC 0 = mid-grey)
EOI = (0xFF, 0xD9)
TAIL_BYTES = 256  # where the end marker is looked for first (a frame's zero padding is shorter)
FILLED_TAIL = 0.125  # of the last pixel row: real frames have at most 0.4 % of it at exactly 128, anywhere


def ends_with_eoi(data: np.ndarray | bytes) -> bool:
    """Do the frame's bytes end with the JPEG's end marker (after trailing zero padding)?"""
    flat = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray)) else np.asarray(data, np.uint8).ravel()
    if flat.size >= 2 and flat[-1] == EOI[1] and flat[-2] == EOI[0]:
        return True  # no padding (a frame's usual end): the search below would find the same two bytes
    nonzero = np.flatnonzero(flat[-TAIL_BYTES:])  # the padding is short: the tail, not the frame
    offset = max(0, flat.size - TAIL_BYTES)
    if nonzero.size == 0:  # padding longer than the tail (or nothing): the whole buffer
        nonzero, offset = np.flatnonzero(flat), 0
        if nonzero.size == 0:
            return False
    end = offset + int(nonzero[-1]) + 1
    return end >= 2 and (int(flat[end - 2]), int(flat[end - 1])) == EOI


def filled_bottom_row(image: np.ndarray) -> bool:
    """Does libjpeg's fill for blocks it had no data for end the decoded frame's last pixel row?
    The fill runs in block order from where the data ran out to the image's end, so it is the
    row's tail: refused when it spans at least ``FILLED_TAIL`` of the row (data that ran out inside
    the last row of blocks fills only part of it)."""
    if image.ndim < 2 or image.shape[0] == 0 or image.shape[1] == 0:
        return False
    row = image[-1].reshape(image.shape[1], -1)
    if row[-1].tobytes() != bytes((JPEG_FILL,)) * row.shape[1]:
        return False  # the row does not end in the fill (every real frame): its grey tail is empty
    grey = np.all(row == JPEG_FILL, axis=1)
    tail = grey.size - int(np.flatnonzero(~grey)[-1]) - 1 if not grey.all() else grey.size
    return tail >= max(1, int(np.ceil(FILLED_TAIL * grey.size)))


def damaged_jpeg(data: np.ndarray | None, image: np.ndarray) -> str:
    """Why the decoded MJPEG frame ``image`` is one cut short in transit ('' when it shows neither
    mark). ``data``: its bytes, when the camera took them undecoded (None: the backend decoded it,
    and only the fill can tell)."""
    if data is not None and not ends_with_eoi(data):
        return "that end without the JPEG's end marker (FF D9): a frame cut short in transit"
    if filled_bottom_row(image):
        return ("whose last pixel row is libjpeg's flat grey fill (128, 128, 128): the frame's data ran out "
                "before its end, its lower part lost in transit")
    return ""


__all__ = ["JPEG_FILL", "ends_with_eoi", "filled_bottom_row", "damaged_jpeg"]
