"""Camera frames as ingest stores them (compressed bytes or raw ROS pixel buffers): decoded to grey for detection
(:func:`decode_frame`), and encoded for drawing in the recordings (:func:`frame_blob`).

A raw 640x480 ``bgr8`` frame is 0.9 MB; drawn as it is (every ``rerun.image_stride``-th frame, in ingest.rrd
and again in detect.rrd) an hour at 5 Hz put gigabytes into each recording and held hundreds of megabytes in the
logging process. The recordings are for a person to look at, so raw frames go in as JPEG at
:data:`RAW_JPEG_QUALITY` (about 15 times smaller): colour ones in colour, the others (grey, 16-bit, YUV, Bayer)
as the grey detect sees. The frames the stages compute on are the tables' bytes, untouched.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

RAW_JPEG_QUALITY = 90
"""JPEG quality of raw frames drawn in the recordings."""

MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}
"""Media types of the frame formats stored encoded."""

_COLOUR = {
    "bgr8": (3, None),
    "8uc3": (3, None),
    "rgb8": (3, "RGB2BGR"),
    "bgra8": (4, "BGRA2BGR"),
    "rgba8": (4, "RGBA2BGR"),
}
"""Colour encodings drawn in colour: channels, and OpenCV's conversion to BGR (None: it is BGR)."""


def frame_blob(fmt: str, width: int, height: int, step: int, data: bytes) -> tuple[bytes, str] | None:
    """A frame as encoded image bytes and their media type, or None where its bytes do not decode (a damaged
    message or an encoding not read: the caller skips the drawing, not the frame)."""
    if fmt in MEDIA_TYPES:
        return data, MEDIA_TYPES[fmt]
    import cv2  # only here: ingest does not load OpenCV for compressed frames

    colour = _COLOUR.get(fmt.lower())
    pix: npt.NDArray[np.uint8]
    if colour is not None:
        channels, convert = colour
        try:
            pix = _pixel_rows(fmt.lower(), width, height, step, data).reshape(height, width, channels)
        except CorruptFrameError:
            return None
        if convert is not None:
            pix = np.asarray(cv2.cvtColor(pix, getattr(cv2, f"COLOR_{convert}")), dtype=np.uint8)
    else:
        try:
            pix = decode_frame(fmt, width, height, step, data)
        except CorruptFrameError:
            return None
    ok, buf = cv2.imencode(".jpg", pix, [cv2.IMWRITE_JPEG_QUALITY, RAW_JPEG_QUALITY])
    return (buf.tobytes(), "image/jpeg") if ok else None


class CorruptFrameError(ValueError):
    """A frame's bytes cannot be decoded into an image of the stated size."""


_BAYER = {"rggb": "BG", "bggr": "RG", "gbrg": "GR", "grbg": "GB"}
"""ROS's Bayer pattern (the first row's first two sites) -> OpenCV's name for it (which names the second row's
second and third sites), as cv_bridge maps them."""
_RAW_LAYOUT: dict[str, tuple[int, int]] = {  # encoding (lower case): (bytes per sample, samples per pixel)
    "mono8": (1, 1),
    "8uc1": (1, 1),
    "mono16": (2, 1),
    "16uc1": (2, 1),
    "bgr8": (1, 3),
    "8uc3": (1, 3),
    "rgb8": (1, 3),
    "bgra8": (1, 4),
    "rgba8": (1, 4),
    "yuv422": (1, 2),  # UYVY
    "uyvy": (1, 2),
    "yuv422_yuy2": (1, 2),  # YUYV
    "yuyv": (1, 2),
    **{f"bayer_{p}8": (1, 1) for p in _BAYER},
    **{f"bayer_{p}16": (2, 1) for p in _BAYER},
}
RAW_ENCODINGS = tuple(_RAW_LAYOUT)
"""The sensor_msgs/Image encodings :func:`decode_frame` reads (any case)."""
_COMPRESSED = ("jpeg", "jpg", "png", "compressed")


def readable_encoding(fmt: str) -> bool:
    """Whether :func:`decode_frame` reads frames stored in this format (compressed, or a raw encoding)."""
    return fmt.lower() in _COMPRESSED or fmt.lower() in _RAW_LAYOUT


def _pixel_rows(fmt: str, width: int, height: int, step: int, data: bytes) -> npt.NDArray[np.uint8]:
    """A raw frame's pixel bytes, height x (width x bytes per pixel), without the rows' padding (the last row's
    padding may be missing: it is zeros here).

    Raises:
        CorruptFrameError: the bytes cannot hold the stated image.
    """
    bytes_per, samples = _RAW_LAYOUT[fmt]
    row = width * samples * bytes_per
    step = step or row
    buf = np.frombuffer(data, dtype=np.uint8)
    if width <= 0 or height <= 0 or step < row or buf.size < step * (height - 1) + row:
        raise CorruptFrameError(f"{buf.size} B cannot hold a {width}x{height} {fmt} image with step {step}")
    padded = np.zeros(step * height, dtype=np.uint8)
    padded[: min(buf.size, padded.size)] = buf[: padded.size]
    return np.ascontiguousarray(padded.reshape(height, step)[:, :row])


def decode_frame(fmt: str, width: int, height: int, step: int, data: bytes) -> npt.NDArray[np.uint8]:
    """Decode one frame of ``frames.parquet`` into a grayscale uint8 image (height x width).

    Args:
        fmt: ``jpeg`` / ``png`` (compressed bytes) or a raw ROS encoding (:data:`RAW_ENCODINGS`: grey, colour,
            YUV 4:2:2 and Bayer mosaics, 8 or 16 bits).
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
    if fmt in _COMPRESSED:
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if buf.size else None
        if img is None:
            raise CorruptFrameError(f"{fmt} bytes ({buf.size} B) do not decode")
        if width and height and img.shape != (height, width):
            raise CorruptFrameError(f"decoded {img.shape[1]}x{img.shape[0]}, expected {width}x{height}")
        return np.asarray(img, dtype=np.uint8)
    if fmt not in _RAW_LAYOUT:
        raise CorruptFrameError(
            f"unsupported encoding {fmt!r}; expected jpeg, png or one of {', '.join(RAW_ENCODINGS)}"
        )
    bytes_per, samples = _RAW_LAYOUT[fmt]
    rows = _pixel_rows(fmt, width, height, step, data)
    if bytes_per == 2:
        # ROS 16-bit images are little-endian on every platform we read; scale to 8 bits by the image's own range.
        img16 = rows.view("<u2").reshape(height, width).astype(np.float32)
        hi = float(img16.max()) or 1.0
        pix = np.clip(img16 * (255.0 / hi), 0, 255).astype(np.uint8)
    elif fmt in ("yuv422", "uyvy", "yuv422_yuy2", "yuyv"):  # the luma is every other byte
        return rows[:, 1::2].copy() if fmt in ("yuv422", "uyvy") else rows[:, 0::2].copy()
    else:
        pix = rows.reshape(height, width, samples)
    if fmt.startswith("bayer_"):  # edge-aware demosaicking: on a simulated 30 s run it keeps 706 tag sightings of
        # the 758 the scene's own grey gives, against 696 for OpenCV's bilinear Bayer-to-grey, at 0.15 ms a frame
        code = getattr(cv2, f"COLOR_Bayer{_BAYER[fmt[6:10]]}2BGR_EA")
        return np.asarray(
            cv2.cvtColor(cv2.cvtColor(pix.reshape(height, width), code), cv2.COLOR_BGR2GRAY), dtype=np.uint8
        )
    if samples == 1:
        return pix.reshape(height, width).copy()
    code = {
        "bgr8": cv2.COLOR_BGR2GRAY,
        "8uc3": cv2.COLOR_BGR2GRAY,
        "rgb8": cv2.COLOR_RGB2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
        "rgba8": cv2.COLOR_RGBA2GRAY,
    }[fmt]
    return np.asarray(cv2.cvtColor(pix, code), dtype=np.uint8)
