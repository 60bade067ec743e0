"""Frames drawn in the recordings (stages.frames): raw pixels as JPEG that decode to the same picture."""

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


def test_other_raw_frames_are_drawn_as_the_grey_detect_sees() -> None:
    grey = _picture()[:, :, 0]
    uyvy = np.full((48, 128), 128, np.uint8)
    uyvy[:, 1::2] = grey
    for fmt, step, data in (
        ("mono8", 0, grey.tobytes()),
        ("mono16", 128, (grey.astype("<u2") * 256).tobytes()),  # scaled by the frame's own range
        ("yuv422", 128, uyvy.tobytes()),
        ("bayer_rggb8", 64, grey.tobytes()),  # a grey scene's mosaic
    ):
        blob = frame_blob(fmt, 64, 48, step, data)
        assert blob is not None and blob[1] == "image/jpeg", fmt
        want = grey * (255 / grey.max()) if fmt == "mono16" else grey
        assert np.abs(_decoded(blob).astype(int) - want)[2:-2, 2:-2].mean() < 3.0, fmt


def test_encoded_frames_pass_through_and_damaged_ones_are_not_drawn() -> None:
    ok, jpeg = cv2.imencode(".jpg", _picture())
    assert ok
    assert frame_blob("jpeg", 0, 0, 0, jpeg.tobytes()) == (jpeg.tobytes(), "image/jpeg")
    assert frame_blob("bgr8", 64, 48, 0, bytes(64 * 48 * 3 - 1)) is None  # a message cut short
    assert frame_blob("bgr8", 64, 48, 100, bytes(64 * 48 * 3)) is None  # step below the row
    assert frame_blob("nv12", 64, 48, 0, bytes(64 * 72)) is None  # an encoding not read
