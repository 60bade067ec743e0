"""Camera frames as images in the recordings: JPEG and PNG frames as they are, raw pixels compressed.

A raw 640x480 ``bgr8`` frame is 0.9 MB; drawn as it is (every ``rerun.image_stride``-th frame, in ingest.rrd
and again in detect.rrd) an hour at 5 Hz put gigabytes into each recording and held hundreds of megabytes in the
logging process. The recordings are for a person to look at, so raw 8-bit frames go in as JPEG at
:data:`RAW_JPEG_QUALITY` (about 15 times smaller) and 16-bit ones as PNG (lossless). The frames the stages
compute on are the tables' bytes, untouched.
"""

from __future__ import annotations

from typing import Any

import numpy as np

RAW_JPEG_QUALITY = 90
"""JPEG quality of raw 8-bit frames drawn in the recordings."""

MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}
"""Media types of the frame formats stored encoded."""

_RAW_LAYOUT = {  # encoding: (bytes per channel, channels, OpenCV conversion to BGR or grey, or None)
    "mono8": (1, 1, None),
    "8UC1": (1, 1, None),
    "mono16": (2, 1, None),
    "16UC1": (2, 1, None),
    "bgr8": (1, 3, None),
    "rgb8": (1, 3, "RGB2BGR"),
    "bgra8": (1, 4, "BGRA2BGR"),
    "rgba8": (1, 4, "RGBA2BGR"),
}


def frame_blob(fmt: str, width: int, height: int, step: int, data: bytes) -> tuple[bytes, str] | None:
    """A frame as encoded image bytes and their media type, or None where its encoding is not drawable or its
    bytes are short of its layout (a damaged message: the caller skips the drawing, not the frame)."""
    if fmt in MEDIA_TYPES:
        return data, MEDIA_TYPES[fmt]
    layout = _RAW_LAYOUT.get(fmt)
    if layout is None or width <= 0 or height <= 0:
        return None
    size, channels, convert = layout
    row = width * channels * size
    step = step or row
    if step < row or len(data) < step * height:
        return None
    import cv2  # only here: ingest does not load OpenCV for compressed frames

    dtype = np.uint16 if size == 2 else np.uint8
    rows = np.frombuffer(data, np.uint8, count=step * height).reshape(height, step)[:, :row]
    pix: Any = np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)
    if channels == 1:
        pix = pix[:, :, 0]
    if convert is not None:
        pix = cv2.cvtColor(pix, getattr(cv2, f"COLOR_{convert}"))
    if size == 2:
        ok, buf = cv2.imencode(".png", pix)
        return (buf.tobytes(), "image/png") if ok else None
    ok, buf = cv2.imencode(".jpg", pix, [cv2.IMWRITE_JPEG_QUALITY, RAW_JPEG_QUALITY])
    return (buf.tobytes(), "image/jpeg") if ok else None
