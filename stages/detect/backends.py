"""Detector back-ends behind one interface: OpenCV's aruco AprilTag dictionaries and the AprilTag 3 library.

Every back-end returns :class:`TagObservation` with corners in one convention, whatever the library:
the OpenCV aruco order (top-left, top-right, bottom-right, bottom-left of the tag as printed) and
pixel coordinates where the centre of the top-left pixel is (0, 0). The AprilTag 3 library reports
corners half a pixel larger (its pixel centres are at +0.5) and starts from another corner; both are
converted here and checked against rendered ground truth in the tests.
"""

from __future__ import annotations

import atexit
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from stages.detect.config import DetectConfig

ARUCO_DICTIONARIES = {
    "tag36h11": "DICT_APRILTAG_36h11",
    "tag25h9": "DICT_APRILTAG_25h9",
    "tag16h5": "DICT_APRILTAG_16h5",
    "tag36h10": "DICT_APRILTAG_36h10",
}

# AprilTag 3 corner i (as pupil-apriltags returns them) that is OpenCV corner k: opencv = apriltag[_AT3_TO_CV].
_AT3_TO_CV = [1, 0, 3, 2]
# Shift from AprilTag 3 pixel coordinates (pixel centres at +0.5) to OpenCV's (pixel centres at integers).
_AT3_PIXEL_OFFSET = -0.5


@dataclass(frozen=True)
class TagObservation:
    """One tag found in one image.

    Attributes:
        tag_id: decoded id.
        family: tag family.
        corners: 4 x 2 float64 distorted pixel corners, OpenCV order and pixel convention.
        decision_margin: AprilTag 3's decision margin; for OpenCV the smallest grey-level gap between a
            data cell and the black/white threshold.
        hamming: number of bits corrected when decoding.
    """

    tag_id: int
    family: str
    corners: npt.NDArray[np.float64]
    decision_margin: float
    hamming: int


class Detector(Protocol):
    """A tag detector: grayscale uint8 image in, observations out."""

    name: str

    def detect(self, gray: npt.NDArray[np.uint8]) -> list[TagObservation]:
        """Detect tags in one grayscale image."""
        ...


def shortest_side_px(corners: npt.NDArray[np.float64]) -> float:
    """Length of the shortest side of a quadrilateral (4 x 2), px."""
    # in Python floats: four sides are too few for numpy's per-call overhead (np.roll and norm took ~60 µs a tag,
    # 15 % of the pose path on the sample); sqrt(dx² + dy²) is what numpy's norm computes, to the bit
    c = np.asarray(corners, float).reshape(4, 2).tolist()
    squares = []
    for (xa, ya), (xb, yb) in zip(c, c[1:] + c[:1], strict=True):
        dx, dy = xa - xb, ya - yb
        squares.append(dx * dx + dy * dy)
    return math.sqrt(min(squares))


# pupil-apriltags 1.0.4 corrupts the heap when it destroys a detector (it frees the tag families before
# the detector that uses them; tag16h5 shows it at once). So detectors are built once per process and
# settings, kept, and never destroyed: at exit their pointer is cleared so ``__del__`` does nothing.
_AT3_DETECTORS: dict[tuple[object, ...], Any] = {}


@atexit.register
def _forget_apriltag3_detectors() -> None:
    for det in _AT3_DETECTORS.values():
        det.tag_detector_ptr = None


def _quad_thresh_params(detector: Any) -> Any:
    """The ``apriltag_quad_thresh_params`` (``qtp``) of a pupil-apriltags detector, writable.

    pupil-apriltags 1.0.4 maps only the first fields of ``apriltag_detector_t``; ``qtp`` follows them in the C
    struct (apriltag 3: nthreads, quad_decimate, quad_sigma, refine_edges, decode_sharpening, debug, qtp).
    The layout is checked against the library's defaults (5, 10, cos 10 deg, 10.0, 5) in the tests.
    """
    import ctypes

    from pupil_apriltags import bindings

    class _QuadThreshParams(ctypes.Structure):
        _fields_ = [
            ("min_cluster_pixels", ctypes.c_int),
            ("max_nmaxima", ctypes.c_int),
            ("critical_rad", ctypes.c_float),
            ("cos_critical_rad", ctypes.c_float),
            ("max_line_fit_mse", ctypes.c_float),
            ("min_white_black_diff", ctypes.c_int),
            ("deglitch", ctypes.c_int),
        ]

    class _Detector(ctypes.Structure):
        _fields_ = [*bindings._ApriltagDetector._fields_, ("qtp", _QuadThreshParams)]

    return ctypes.cast(detector.tag_detector_ptr, ctypes.POINTER(_Detector)).contents.qtp


_K4 = np.ones((4, 4), np.uint8)
# Quantile of the tile contrasts that stands for the frame's strong edges (edge_white_black_diff): 5 % of the
# tiles, so a few bright spots (lamps, specular highlights) do not set it.
EDGE_QUANTILE = 0.95
_K3 = np.ones((3, 3), np.uint8)


def tile_contrast_quantiles(gray: npt.NDArray[np.uint8], quantiles: tuple[float, ...]) -> list[int]:
    """Quantiles over the image of the grey range (max - min) of each 4x4 tile with its 8 neighbours: the quantity
    the AprilTag 3 library compares with ``min_white_black_diff`` (approximately: tiles taken on a 4-px grid).

    The median is set by pixel noise and fine texture (about 5 sigma for Gaussian noise of sigma): tags cover a
    small part of a frame, so they do not move it. The high quantiles are set by the frame's strong edges.
    """
    import cv2

    mx = np.ascontiguousarray(cv2.dilate(gray, _K4)[::4, ::4])
    mn = np.ascontiguousarray(cv2.erode(gray, _K4)[::4, ::4])
    rng = cv2.dilate(mx, _K3) - cv2.erode(mn, _K3)
    cum = np.cumsum(cv2.calcHist([rng], [0], None, [256], [0, 256]).ravel())
    return [int(np.searchsorted(cum, q * rng.size)) for q in quantiles]


def median_tile_contrast(gray: npt.NDArray[np.uint8]) -> int:
    """Median of :func:`tile_contrast_quantiles`: the frame's pixel noise or fine texture."""
    return tile_contrast_quantiles(gray, (0.5,))[0]


def frame_white_black_diff(
    gray: npt.NDArray[np.uint8], lo: int, noise_factor: float, edge_factor: float, edge_quantile: float, hi: int
) -> int:
    """The per-frame ``min_white_black_diff``: ``noise_factor`` times the median tile contrast (above the noise and
    texture), or ``edge_factor`` times its ``edge_quantile`` quantile (a fraction of the frame's strong edges)
    when that is larger, at least ``lo`` and at most ``hi``."""
    med, strong = tile_contrast_quantiles(gray, (0.5, edge_quantile))
    return int(min(max(lo, round(noise_factor * med), round(edge_factor * strong)), max(hi, lo)))


class AprilTag3Detector:
    """The AprilTag 3 C library through pupil-apriltags."""

    name = "apriltag3"

    def __init__(self, cfg: DetectConfig) -> None:
        import pupil_apriltags

        self.families = cfg.families
        key = (
            cfg.families,
            cfg.decimation,
            cfg.blur_sigma,
            cfg.refine_edges,
            cfg.decode_sharpening,
            cfg.min_white_black_diff,
            cfg.adaptive_white_black_diff,
            cfg.max_white_black_diff,
            cfg.edge_white_black_diff,
            cfg.min_cluster_pixels,
        )
        if key not in _AT3_DETECTORS:
            det = pupil_apriltags.Detector(
                families=" ".join(cfg.families),
                nthreads=1,
                quad_decimate=float(cfg.decimation),
                quad_sigma=float(cfg.blur_sigma),
                refine_edges=int(cfg.refine_edges),
                decode_sharpening=float(cfg.decode_sharpening),
            )
            qtp = _quad_thresh_params(det)
            qtp.min_white_black_diff = int(cfg.min_white_black_diff)
            qtp.min_cluster_pixels = int(cfg.min_cluster_pixels)
            _AT3_DETECTORS[key] = det
        self._detector: Any = _AT3_DETECTORS[key]
        self._qtp = _quad_thresh_params(self._detector) if cfg.adaptive_white_black_diff > 0 else None
        self._wb = (
            cfg.min_white_black_diff,
            cfg.adaptive_white_black_diff,
            cfg.edge_white_black_diff,
            EDGE_QUANTILE,
            cfg.max_white_black_diff,
        )
        self.white_black_diff = cfg.min_white_black_diff
        """The ``min_white_black_diff`` used on the last image."""

    def detect(self, gray: npt.NDArray[np.uint8]) -> list[TagObservation]:
        """Detect tags in one grayscale image."""
        out = []
        gray = np.ascontiguousarray(gray, dtype=np.uint8)
        if self._qtp is not None:
            self.white_black_diff = frame_white_black_diff(gray, *self._wb)
            self._qtp.min_white_black_diff = self.white_black_diff
        for det in self._detector.detect(gray):
            corners = np.asarray(det.corners, float)[_AT3_TO_CV] + _AT3_PIXEL_OFFSET
            family = det.tag_family.decode() if isinstance(det.tag_family, bytes) else str(det.tag_family)
            out.append(TagObservation(int(det.tag_id), family, corners, float(det.decision_margin), int(det.hamming)))
        return out


class OpenCVDetector:
    """OpenCV's aruco detector with the AprilTag dictionaries (one dictionary per family)."""

    name = "opencv"

    def __init__(self, cfg: DetectConfig) -> None:
        import cv2

        aruco = cv2.aruco
        params = aruco.DetectorParameters()
        params.cornerRefinementMethod = {
            "none": aruco.CORNER_REFINE_NONE,
            "subpix": aruco.CORNER_REFINE_SUBPIX,
            "contour": aruco.CORNER_REFINE_CONTOUR,
            "apriltag": aruco.CORNER_REFINE_APRILTAG,
        }[cfg.opencv_corner_refinement if cfg.refine_edges else "none"]
        params.aprilTagQuadDecimate = float(cfg.decimation)
        params.aprilTagQuadSigma = float(cfg.blur_sigma)
        params.errorCorrectionRate = 1.0
        self._dicts = {}
        self._detectors = {}
        self._fallback = {}
        # OpenCV 5.0's contour refinement can fail an assertion on some quads (_interpolate2Dline,
        # nContours.size() >= 2); such a frame is detected again with sub-pixel refinement.
        fallback = aruco.DetectorParameters()
        fallback.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
        fallback.aprilTagQuadDecimate = params.aprilTagQuadDecimate
        fallback.aprilTagQuadSigma = params.aprilTagQuadSigma
        fallback.errorCorrectionRate = 1.0
        for family in cfg.families:
            dictionary = aruco.getPredefinedDictionary(getattr(aruco, ARUCO_DICTIONARIES[family]))
            self._dicts[family] = dictionary
            self._detectors[family] = aruco.ArucoDetector(dictionary, params)
            self._fallback[family] = aruco.ArucoDetector(dictionary, fallback)

    def detect(self, gray: npt.NDArray[np.uint8]) -> list[TagObservation]:
        """Detect tags in one grayscale image."""
        out = []
        import cv2

        for family, detector in self._detectors.items():
            try:
                corners, ids, _ = detector.detectMarkers(gray)
            except cv2.error:
                corners, ids, _ = self._fallback[family].detectMarkers(gray)
            if ids is None:
                continue
            for c, i in zip(corners, ids.ravel(), strict=True):
                quad = np.asarray(c, float).reshape(4, 2)
                hamming, margin = _read_bits(gray, quad, self._dicts[family], int(i))
                out.append(TagObservation(int(i), family, quad, margin, hamming))
        return out


def _read_bits(
    gray: npt.NDArray[np.uint8], corners: npt.NDArray[np.float64], dictionary: object, tag_id: int
) -> tuple[int, float]:
    """Hamming distance of the sampled data bits to ``tag_id``'s code, and the grey-level decision margin."""
    import cv2

    n = int(dictionary.markerSize)  # type: ignore[attr-defined]
    cells = n + 2
    px = 6
    side = cells * px
    dst = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32) - 0.5
    H = cv2.getPerspectiveTransform(corners.astype(np.float32), dst)
    warped = cv2.warpPerspective(gray, H, (side, side), flags=cv2.INTER_LINEAR).astype(float)
    means = warped.reshape(cells, px, cells, px)[:, 1:-1, :, 1:-1].mean(axis=(1, 3))
    border = np.concatenate([means[0], means[-1], means[1:-1, 0], means[1:-1, -1]])
    data = means[1:-1, 1:-1]
    white = float(np.percentile(data, 90))
    threshold = 0.5 * (float(np.median(border)) + white)
    bits = (data > threshold).astype(np.uint8)
    try:
        hamming = int(dictionary.getDistanceToId(bits, tag_id, False))  # type: ignore[attr-defined]
    except cv2.error:
        hamming = -1
    return hamming, float(np.min(np.abs(data - threshold)))


def make_detector(cfg: DetectConfig) -> Detector:
    """The back-end named by ``cfg.backend``, configured from the settings."""
    if cfg.backend == "apriltag3":
        return AprilTag3Detector(cfg)
    return OpenCVDetector(cfg)
