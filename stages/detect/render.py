"""Render synthetic camera frames of AprilTags at known poses, with exact ground-truth corners.

For tests and benchmarks: every pixel's ray is cast through the (distorted) camera model onto the tag
planes, so lens distortion, perspective and partial visibility are exact; pixels are supersampled for
anti-aliasing, then optional Gaussian blur and noise are added. Pixel centres are at integer
coordinates (the centre of the top-left pixel is (0, 0)), the convention of the detections.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import numpy.typing as npt

from stages.detect.pose import tag_object_points

_ARUCO_DICTS = {
    "tag36h11": "DICT_APRILTAG_36h11",
    "tag25h9": "DICT_APRILTAG_25h9",
    "tag16h5": "DICT_APRILTAG_16h5",
    "tag36h10": "DICT_APRILTAG_36h10",
}


@dataclass(frozen=True)
class TagPlacement:
    """A tag in the camera frame: ``T_camera_tag`` maps tag-frame points (x right, y up, z out of the face)."""

    tag_id: int
    family: str
    size_m: float
    T_camera_tag: npt.NDArray[np.float64]


@lru_cache(maxsize=512)
def tag_bitmap(family: str, tag_id: int) -> npt.NDArray[np.uint8]:
    """The tag as cells (one pixel per cell): black square with its data bits, plus a one-cell white border."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, _ARUCO_DICTS[family]))
    cells = dictionary.markerSize + 2
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, cells, borderBits=1)
    return np.pad(marker, 1, constant_values=255)


def project(camera: object, points_camera: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Pixel coordinates of camera-frame points through a pycolmap camera (no cheirality check)."""
    return np.asarray(camera.img_from_cam(np.asarray(points_camera, float), check_cheirality=False))  # type: ignore[attr-defined]


def corners_of(camera: object, tag: TagPlacement) -> npt.NDArray[np.float64]:
    """Ground-truth distorted pixel corners (4 x 2) of a placed tag, in the OpenCV aruco order."""
    obj = tag_object_points(tag.size_m)
    T = np.asarray(tag.T_camera_tag)
    return project(camera, obj @ T[:3, :3].T + T[:3, 3])


def render_frame(
    camera: object,
    tags: Sequence[TagPlacement],
    background: float = 140.0,
    blur_sigma: float = 0.0,
    noise_sigma: float = 0.0,
    supersample: int = 3,
    rng: np.random.Generator | None = None,
) -> npt.NDArray[np.uint8]:
    """A grayscale frame of ``tags`` seen by a pycolmap ``camera``.

    Args:
        camera: pycolmap camera (any model with ``cam_from_img``).
        tags: tags to draw, nearest last (later tags are painted over earlier ones).
        background: grey level around the tags.
        blur_sigma: Gaussian blur applied after rendering, px (0 = none).
        noise_sigma: standard deviation of additive Gaussian noise, grey levels.
        supersample: sub-samples per pixel and axis.
        rng: random generator for the noise.
    """
    import cv2

    w, h = int(camera.width), int(camera.height)  # type: ignore[attr-defined]
    img = np.full((h, w), float(background))
    s = supersample
    offsets = (np.arange(s) + 0.5) / s - 0.5
    for tag in tags:
        bitmap = tag_bitmap(tag.family, tag.tag_id).astype(float)
        n_tex = bitmap.shape[0]
        cell = tag.size_m / (n_tex - 2)
        half = tag.size_m / 2 + cell
        T = np.asarray(tag.T_camera_tag, float)
        R, t = T[:3, :3], T[:3, 3]
        # Bounding box of the tag (with its white border) from points along its outline.
        edge = np.linspace(-half, half, 25)
        zero = np.zeros_like(edge)
        sides = [np.stack([edge, np.full_like(edge, v), zero], 1) for v in (-half, half)]
        sides += [np.stack([np.full_like(edge, v), edge, zero], 1) for v in (-half, half)]
        outline = np.concatenate(sides)
        pc = outline @ R.T + t
        if np.any(pc[:, 2] <= 1e-6):
            continue
        uv = project(camera, pc)
        u0, v0 = np.floor(uv.min(0)).astype(int) - 2
        u1, v1 = np.ceil(uv.max(0)).astype(int) + 2
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w - 1), min(v1, h - 1)
        if u1 < u0 or v1 < v0:
            continue
        us = (np.arange(u0, u1 + 1)[:, None] + offsets[None, :]).ravel()
        vs = (np.arange(v0, v1 + 1)[:, None] + offsets[None, :]).ravel()
        U, V = np.meshgrid(us, vs)
        rays = np.asarray(camera.cam_from_img(np.stack([U.ravel(), V.ravel()], 1)))  # type: ignore[attr-defined]
        rays = np.column_stack([rays, np.ones(len(rays))])
        # Intersect each ray with the tag plane z_tag = 0: R^T (lam * r - t) has zero z.
        n = R[:, 2]
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (t @ n) / denom
        pts = (lam[:, None] * rays - t) @ R
        col = np.floor((pts[:, 0] + half) / cell).astype(int)
        row = np.floor((half - pts[:, 1]) / cell).astype(int)
        inside = (lam > 0) & (col >= 0) & (col < n_tex) & (row >= 0) & (row < n_tex)
        sub = np.full(len(rays), np.nan)
        sub[inside] = bitmap[row[inside], col[inside]]
        sub = sub.reshape(v1 - v0 + 1, s, u1 - u0 + 1, s)
        covered = np.isfinite(sub)
        frac = covered.mean(axis=(1, 3))
        val = np.where(covered, sub, 0.0).sum(axis=(1, 3)) / np.maximum(covered.sum(axis=(1, 3)), 1)
        patch = img[v0 : v1 + 1, u0 : u1 + 1]
        img[v0 : v1 + 1, u0 : u1 + 1] = frac * val + (1 - frac) * patch
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    if noise_sigma > 0:
        rng = rng or np.random.default_rng(0)
        img = img + rng.normal(0.0, noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def look_at_tag(
    distance_m: float,
    yaw_deg: float = 0.0,
    pitch_deg: float = 0.0,
    roll_deg: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
) -> npt.NDArray[np.float64]:
    """``T_camera_tag`` of a tag ``distance_m`` ahead, facing the camera, turned by yaw/pitch/roll (degrees).

    ``offset`` shifts the tag sideways and down in the camera frame (metres).
    """
    from scipy.spatial.transform import Rotation

    # Facing the camera: tag x = camera x, tag y = -camera y, tag z = -camera z.
    facing = np.diag([1.0, -1.0, -1.0])
    turn = Rotation.from_euler("yxz", [yaw_deg, pitch_deg, roll_deg], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = turn @ facing
    T[:3, 3] = [offset[0], offset[1], distance_m]
    return T
