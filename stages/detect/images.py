"""Decode the frames that ingest stored (compressed bytes or raw pixel buffers) into grayscale images."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


class CorruptFrameError(ValueError):
    """A frame's bytes cannot be decoded into an image of the stated size."""


_RAW_CHANNELS = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "bgra8": 4, "rgba8": 4, "mono16": 1, "16uc1": 1}


def decode_frame(fmt: str, width: int, height: int, step: int, data: bytes) -> npt.NDArray[np.uint8]:
    """Decode one frame of ``frames.parquet`` into a grayscale uint8 image (height x width).

    Args:
        fmt: ``jpeg`` / ``png`` (compressed bytes) or a raw ROS encoding (``mono8``, ``bgr8``, ``rgb8``,
            ``bgra8``, ``rgba8``, ``mono16``).
        width: image width in pixels (checked for compressed frames when non-zero).
        height: image height in pixels.
        step: bytes per row of a raw image (0 for compressed frames).
        data: the frame's bytes.

    Raises:
        CorruptFrameError: the bytes do not decode, or do not match the stated size.
    """
    import cv2

    fmt = fmt.lower()
    buf = np.frombuffer(data, dtype=np.uint8)
    if fmt in ("jpeg", "jpg", "png", "compressed"):
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if buf.size else None
        if img is None:
            raise CorruptFrameError(f"{fmt} bytes ({buf.size} B) do not decode")
        if width and height and img.shape != (height, width):
            raise CorruptFrameError(f"decoded {img.shape[1]}x{img.shape[0]}, expected {width}x{height}")
        return np.asarray(img, dtype=np.uint8)
    if fmt not in _RAW_CHANNELS:
        raise CorruptFrameError(f"unsupported encoding {fmt!r}; expected jpeg, png, {', '.join(_RAW_CHANNELS)}")
    channels = _RAW_CHANNELS[fmt]
    bytes_per = 2 if fmt in ("mono16", "16uc1") else 1
    row = width * channels * bytes_per
    step = step or row
    if width <= 0 or height <= 0 or step < row or buf.size < step * (height - 1) + row:
        raise CorruptFrameError(f"{buf.size} B cannot hold a {width}x{height} {fmt} image with step {step}")
    padded = np.zeros(step * height, dtype=np.uint8)
    padded[: min(buf.size, padded.size)] = buf[: padded.size]
    rows = padded.reshape(height, step)[:, :row]
    if bytes_per == 2:
        # ROS mono16 is little-endian on every platform we read; scale to 8 bits by the image's own range.
        img16 = np.ascontiguousarray(rows).view("<u2").reshape(height, width).astype(np.float32)
        hi = float(img16.max()) or 1.0
        return np.clip(img16 * (255.0 / hi), 0, 255).astype(np.uint8)
    pix = np.ascontiguousarray(rows).reshape(height, width, channels)
    if channels == 1:
        return pix[:, :, 0].copy()
    code = {
        "bgr8": cv2.COLOR_BGR2GRAY,
        "rgb8": cv2.COLOR_RGB2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY,
    }[fmt]
    return np.asarray(cv2.cvtColor(pix, code), dtype=np.uint8)
