"""Frames drawn in the recordings (stages.frames): raw pixels as JPEG or PNG that decode to the same picture."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from stages.frames import frame_blob


def _picture(h: int = 48, w: int = 64) -> np.ndarray:
    """A smooth BGR picture with distinct channels (JPEG keeps it within a few grey levels)."""
    y, x = np.mgrid[0:h, 0:w]
    return np.dstack([x * 255 // w, y * 255 // h, (x + y) * 255 // (w + h)]).astype(np.uint8)


def _decoded(blob: tuple[bytes, str] | None, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    assert blob is not None
    return cv2.imdecode(np.frombuffer(blob[0], np.uint8), flags)


@pytest.mark.parametrize("fmt", ["bgr8", "rgb8", "bgra8", "rgba8"])
def test_colour_frames_keep_their_channel_order(fmt: str) -> None:
    bgr = _picture()
    pix = {
        "bgr8": bgr,
        "rgb8": bgr[:, :, ::-1],
        "bgra8": np.dstack([bgr, np.full(bgr.shape[:2], 255, np.uint8)]),
        "rgba8": np.dstack([bgr[:, :, ::-1], np.full(bgr.shape[:2], 255, np.uint8)]),
    }[fmt]
    h, w, c = pix.shape
    padded = np.zeros((h, w * c + 7), np.uint8)  # rows padded beyond the pixels (step > width x channels)
    padded[:, : w * c] = pix.reshape(h, w * c)
    blob = frame_blob(fmt, w, h, w * c + 7, padded.tobytes())
    assert blob is not None and blob[1] == "image/jpeg"
    assert np.abs(_decoded(blob, cv2.IMREAD_COLOR).astype(int) - bgr).mean() < 3.0


def test_grey_frames_jpeg_and_16_bit_png_lossless() -> None:
    grey = _picture()[:, :, 0]
    blob = frame_blob("mono8", 64, 48, 0, grey.tobytes())
    assert blob is not None and blob[1] == "image/jpeg"
    assert np.abs(_decoded(blob).astype(int) - grey).mean() < 3.0
    deep = (grey.astype(np.uint16) * 257 + 3).astype(np.uint16)
    blob = frame_blob("mono16", 64, 48, 128, deep.tobytes())
    assert blob is not None and blob[1] == "image/png"
    assert np.array_equal(_decoded(blob), deep)


def test_encoded_frames_pass_through_and_damaged_ones_are_not_drawn() -> None:
    ok, jpeg = cv2.imencode(".jpg", _picture())
    assert ok
    assert frame_blob("jpeg", 0, 0, 0, jpeg.tobytes()) == (jpeg.tobytes(), "image/jpeg")
    assert frame_blob("bgr8", 64, 48, 0, bytes(64 * 48 * 3 - 1)) is None  # a message cut short
    assert frame_blob("bgr8", 64, 48, 100, bytes(64 * 48 * 3)) is None  # step below the row
    assert frame_blob("yuv422", 64, 48, 0, bytes(64 * 48 * 2)) is None  # not drawable
