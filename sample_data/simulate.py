"""Deterministic simulator of a recorded robot run, written as ROS 1 / ROS 2 bags.

The world is the office of Mu et al. (RSS 2015, Fig. 1/6): an open room of 8 m x 6 m,
a 0.9 m door in its east wall and a 1.2 m wide, 10 m long corridor behind it. Walls are
vertical 2D segments extruded from the floor (z = 0) to ``wall_height_m``. Real
tag36h11 bitmaps (OpenCV's ``DICT_APRILTAG_36h11``, white quiet border of one cell) hang
on the walls at camera height. A planar robot drives a smooth path through the room,
the door and the corridor (and back); a camera, wheel odometry and a laser scanner are
simulated along it, and every random draw comes from ``numpy.random.default_rng``
streams spawned from ``SimConfig.seed``, so a configuration gives the same messages
every time.

Frames (all right-handed; quaternions are ``xyzw`` everywhere, as ROS stores them):

- ``world``: z up, origin on the floor at the south-west corner of the room, x east
  (along the room's 8 m side, towards the door and the corridor), y north. The robot
  does *not* start at the origin: its first true pose is ``ground_truth["poses"][0]``
  (also ``T_world_odom``).
- ``odom``: the odometry frame; it coincides with the true ``base_link`` pose at the
  first odometry stamp (odometry starts at the identity) and then drifts from the truth.
- ``base_link``: on the floor under the robot's centre, x forward, y left, z up.
- ``camera``: the optical frame, z forward (optical axis), x right, y down (image
  rows). Its optical axis is horizontal (no pitch, no roll).
- ``laser``: x forward, y left, z up; scan angles are counter-clockwise about z from x.
- tag frame: origin at the centre of the tag's black square, z out of the tag face
  towards the viewer, x to the viewer's right and y *up* as seen by a viewer facing the
  tag. This is OpenCV's marker frame (the object points of ``SOLVEPNP_IPPE_SQUARE``);
  "x right, y down" with "z towards the viewer" would be left-handed. Corners are in
  OpenCV aruco order: top-left, top-right, bottom-right, bottom-left of the marker as
  printed, i.e. ``(-s/2, s/2, 0), (s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0)`` in
  the tag frame, with ``s = size_m`` the side of the black square (the white quiet
  border is outside it). ``T_a_b`` maps points from frame b to frame a.

Pixels: the centre of the top-left pixel is (0, 0) (OpenCV and ROS convention); the
camera model is pinhole with plumb_bob (k1, k2, p1, p2, k3) distortion, as
``cv2.projectPoints`` applies it.

Ground truth goes beside the bag as ``<name>.ground_truth.json`` where ``<name>`` is the
bag file's stem (``office.bag`` -> ``office.ground_truth.json``, ``run.mcap`` ->
``run.ground_truth.json``) or the ROS 2 folder's name (``run/`` ->
``run.ground_truth.json`` in the folder's parent); see :func:`ground_truth_path`. The walls, tags and
true poses also go beside it as ``<name>.truth.yaml`` and ``<name>.truth.tum``, focusmap's hand-writable
ground-truth format (:func:`write_truth_yaml`, ``docs/evaluate.md``).

Usage::

    python -m sample_data.simulate --out sample_data/office --name office --format ros1
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import shutil
import sys
import tempfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Final, Literal

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

ImageFormat = Literal["jpeg", "png", "mono8", "bgr8", "bayer_rggb8", "yuv422"]
BagFormat = Literal["ros1", "ros2-sqlite", "ros2-mcap", "mcap"]
Compression = Literal["bz2", "lz4"]
PathName = Literal["office", "corridor", "corridor_return"]

BAG_FORMATS: Final[tuple[str, ...]] = ("ros1", "ros2-sqlite", "ros2-mcap", "mcap")
IMAGE_FORMATS: Final[tuple[str, ...]] = ("jpeg", "png", "mono8", "bgr8", "bayer_rggb8", "yuv422")
RAW_BYTES_PER_PIXEL: Final = {"mono8": 1, "bgr8": 3, "bayer_rggb8": 1, "yuv422": 2}
"""Bytes per pixel of the raw formats (sensor_msgs/Image); ``yuv422`` is ROS's UYVY byte order."""
TAG_FAMILY: Final = "tag36h11"
DEFAULT_START_NS: Final = 1_700_000_000 * 1_000_000_000

# Grey levels of the printed tag (paper is not perfectly white, ink not perfectly black).
_TAG_BLACK: Final = 25.0
_TAG_WHITE: Final = 230.0
# Tags stand this far proud of their wall, so the wall never hides its own tags.
_TAG_OFFSET_M: Final = 0.002
# World layout jitter is fixed (not the seed): every seed sees the same office.
_WORLD_SEED: Final = 20150713


@dataclass(frozen=True)
class SimConfig:
    """Settings of one simulated run. Every field has a default; units are in the names."""

    seed: int = 0
    """Seed of every random draw (odometry, laser and pixel noise). The world is fixed."""
    path: PathName = "office"
    """'office': wander the room, through the door, down the corridor, turn, come back.
    'corridor': start just before the door and drive down the corridor (short tests).
    'corridor_return': start just before the door, drive to the corridor's end, turn in place and come back."""
    duration_s: float | None = None
    """Length of the recording; None = until the path ends. Past its end the robot rests."""
    start_time_ns: int = DEFAULT_START_NS
    """Stamp of the first message (ns since the Unix epoch)."""

    camera_rate_hz: float = 5.0
    odom_rate_hz: float = 20.0
    scan_rate_hz: float = 10.0

    image_width: int = 640
    image_height: int = 480
    image_format: ImageFormat = "jpeg"
    """jpeg / png -> sensor_msgs/CompressedImage; mono8 / bgr8 / bayer_rggb8 / yuv422 -> sensor_msgs/Image (the
    grey scene as a colour camera would give it: a Bayer mosaic of it, or UYVY with neutral chroma)."""
    jpeg_quality: int = 85
    fx: float | None = None
    """Focal length in px; None = 0.65 * image_width (416 px at 640, about 75 deg wide)."""
    fy: float | None = None
    """None = 1.003 * fx."""
    cx: float | None = None
    """Principal point in px (top-left pixel centre = 0); None = slightly off centre."""
    cy: float | None = None
    distortion: tuple[float, float, float, float, float] = (-0.06, 0.012, 0.0006, -0.0004, 0.0)
    """plumb_bob coefficients (k1, k2, p1, p2, k3)."""
    pixel_noise_sigma: float = 1.5
    """Standard deviation of the Gaussian pixel noise, in grey levels (0-255)."""
    supersample: int = 3
    """Tags are rendered at this many sub-pixels per pixel and box-filtered down."""
    exposure_gain: float = 1.0
    """Scene brightness times this before the pixel noise (< 1: an under-exposed, darker image; the noise stays)."""
    contrast: float = 1.0
    """After the exposure, grey levels are pulled towards mid grey 128 by this factor (< 1: a flat, hazy image)."""
    vignetting: float = 0.0
    """Brightness times 1 - vignetting * (r / r_corner)^2, r the distance to the principal point in the image
    (the image corners get 1 - vignetting of the light)."""
    motion_blur_px: float = 0.0
    """Length of a linear blur kernel, px, centred (corners do not move), along the image motion of each frame's
    principal ray (from the true camera motion; horizontal when the camera is at rest)."""

    camera_xyz_m: tuple[float, float, float] = (0.12, 0.0, 0.40)
    """Camera optical centre in base_link."""
    camera_yaw_deg: float = 30.0
    """Camera yaw left of the robot's forward axis (forward-left sees the walls)."""
    laser_xyz_m: tuple[float, float, float] = (0.10, 0.0, 0.20)
    """Laser centre in base_link (yaw 0)."""
    laser_beams: int = 360
    laser_range_min_m: float = 0.05
    laser_range_max_m: float = 8.0
    laser_range_sigma_m: float = 0.01
    laser_sweep: bool = False
    """Sweep the beams over the scan period as a spinning scanner does: beam i is cast from the true pose at
    stamp + i * time_increment (time_increment = 1 / (scan_rate_hz * laser_beams)); False: every beam from the
    stamp's pose, time_increment 0."""

    odom_v_sigma_mps: float = 0.04
    """Noise on the forward speed, per odometry sample (white)."""
    odom_yaw_rate_sigma_radps: float = 0.03
    """Noise on the yaw rate, per odometry sample (white)."""
    odom_distance_scale_error: float = 0.0
    """Systematic wheel error: the odometry reports (1 + this) times the distance driven (a wrong wheel radius)."""
    odom_yaw_scale_error: float = 0.0
    """Systematic wheel error: the odometry reports (1 + this) times the angle turned (a wrong track width)."""
    odom_yaw_bias_rad_per_m: float = 0.0
    """Systematic wheel error: the odometry adds this much yaw per metre driven forwards (unequal wheel radii)."""
    odom_cov_scale: float = 1.0
    """The pose covariances the odometry messages report: this times the first-order propagation of the white
    noise above (it grows over the run, as real drivers report; it never contains the systematic errors).
    < 1: too small; 0: all zero, as drivers that fill in no covariance."""
    odom_cov_model: str = "propagated"
    """How the reported pose covariance grows: ``propagated`` (through the motion's Jacobian, with the
    position-heading cross terms a heading error makes) or ``diagonal`` (each step's white noise added to a diagonal
    in the odometry frame, no lever arm and no cross terms, as some drivers and other simulators report it)."""

    max_speed_mps: float = 0.45
    max_accel_mps2: float = 0.3
    max_lateral_accel_mps2: float = 0.25
    max_yaw_rate_radps: float = 0.6

    wall_height_m: float = 2.5
    tag_size_m: float = 0.16
    """Side of the black square of every tag ..."""
    tag_size_overrides: tuple[tuple[int, float], ...] = ()
    """... except these (tag id, size in m) pairs."""
    tag_spacing_m: float = 0.6
    corridor_length_m: float = 10.0
    """Length of the corridor behind the door (x from 8 m to 8 m + this)."""
    laps: int = 1
    """``corridor_return`` only: drive the there-and-back this many times (a turn in place between laps), for
    recordings of any length (the scaling benchmark)."""
    first_tag_id: int = 0
    """Tags get ids first_tag_id, first_tag_id + 1, ... in wall order."""

    camera_frame: str = "camera"
    laser_frame: str = "laser"
    base_frame: str = "base_link"
    odom_frame: str = "odom"


# --------------------------------------------------------------------------- maths


def yaw_to_quat_xyzw(yaw: float) -> list[float]:
    """Quaternion (x, y, z, w) of a rotation by ``yaw`` about z."""
    return [0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)]


def rot_to_quat_xyzw(rot: FloatArray) -> list[float]:
    """Quaternion (x, y, z, w), w >= 0, of a rotation matrix."""
    m = rot
    tr = float(m[0, 0] + m[1, 1] + m[2, 2])
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    qa = np.asarray(q, dtype=np.float64)
    qa /= np.linalg.norm(qa)
    if qa[3] < 0.0:
        qa = -qa
    return [float(v) for v in qa]


def planar_T(x: float, y: float, yaw: float, z: float = 0.0) -> FloatArray:
    """4x4 homogeneous transform of a planar pose (rotation about z by yaw)."""
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [x, y, z]
    return T


def inv_T(T: FloatArray) -> FloatArray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


# Optical frame axes (x right, y down, z forward) expressed in a body frame (x fwd, y left, z up).
_R_BODY_OPTICAL: Final = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def ray_segment_hits(
    origin: FloatArray, dirs: FloatArray, walls: FloatArray
) -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray]:
    """Cast 2D rays ``origin + t * dirs`` against wall segments.

    Args:
        origin: (2,) ray origin shared by all rays, or (N, 2) one per ray.
        dirs: (N, 2) ray directions (need not be unit; t is in units of the direction).
        walls: (M, 4) segments x0, y0, x1, y1.

    Returns:
        t of the first hit (inf if none), index of the wall hit (-1 if none), and the
        distance along that wall from its first end point (m).
    """
    a = walls[:, :2]
    e = walls[:, 2:] - a
    ao = a - np.asarray(origin)[..., None, :]  # (M, 2), or (N, M, 2) with one origin per ray
    dx, dy = dirs[:, 0:1], dirs[:, 1:2]
    denom = dx * e[:, 1] - dy * e[:, 0]  # (N, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[..., 0] * e[:, 1] - ao[..., 1] * e[:, 0]) / denom
        s = (ao[..., 0] * dy - ao[..., 1] * dx) / denom
    ok = (np.abs(denom) > 1e-12) & (t > 1e-9) & (s >= 0.0) & (s <= 1.0)
    t = np.where(ok, t, np.inf)
    idx = np.argmin(t, axis=1)
    rows = np.arange(len(dirs))
    t_min = t[rows, idx]
    s_min = s[rows, idx] * np.linalg.norm(e, axis=1)[idx]
    idx = np.where(np.isfinite(t_min), idx, -1)
    return t_min, idx, np.where(np.isfinite(t_min), s_min, 0.0)


def distance_to_walls(points: FloatArray, walls: FloatArray) -> FloatArray:
    """Euclidean distance from each 2D point (N, 2) to the nearest wall segment."""
    a = walls[:, :2]
    e = walls[:, 2:] - a
    rel = points[:, None, :] - a[None, :, :]
    u = np.clip((rel * e).sum(-1) / (e * e).sum(-1), 0.0, 1.0)
    closest = a[None] + u[..., None] * e[None]
    return np.linalg.norm(points[:, None, :] - closest, axis=-1).min(axis=1)


# --------------------------------------------------------------------------- world


@dataclass(frozen=True)
class Tag:
    """One tag on a wall. ``T_world_tag`` maps tag-frame points to the world."""

    id: int
    size_m: float
    wall: int
    T_world_tag: FloatArray


@dataclass(frozen=True)
class World:
    """Walls (x0, y0, x1, y1 in m; free space on the left of x0,y0 -> x1,y1) and tags."""

    walls: FloatArray
    height_m: float
    tags: tuple[Tag, ...]

    def wall_normals(self) -> FloatArray:
        """Unit normals pointing into free space (the left of each segment)."""
        e = self.walls[:, 2:] - self.walls[:, :2]
        n = np.stack([-e[:, 1], e[:, 0]], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


# Room 8 x 6 m (x 0..8, y 0..6), door 0.9 m at x = 8, y 2.55..3.45, corridor x 8..18, y 2.4..3.6
# (the default corridor_length_m of 10 m; office_walls gives other lengths).
OFFICE_WALLS: Final = np.array(
    [
        [0.0, 0.0, 8.0, 0.0],  # 0 room south
        [8.0, 0.0, 8.0, 2.55],  # 1 room east, south of the door
        [8.0, 2.4, 18.0, 2.4],  # 2 corridor south
        [18.0, 2.4, 18.0, 3.6],  # 3 corridor end
        [18.0, 3.6, 8.0, 3.6],  # 4 corridor north
        [8.0, 3.45, 8.0, 6.0],  # 5 room east, north of the door
        [8.0, 6.0, 0.0, 6.0],  # 6 room north
        [0.0, 6.0, 0.0, 0.0],  # 7 room west
    ]
)


def office_walls(corridor_length_m: float = 10.0) -> FloatArray:
    """The office's walls with a corridor of that length (x from 8 m to 8 m + the length)."""
    walls = OFFICE_WALLS.copy()
    end = 8.0 + corridor_length_m
    walls[2, 2] = walls[3, 0] = walls[3, 2] = walls[4, 0] = end
    return walls


def build_world(cfg: SimConfig) -> World:
    """The office: walls and tags (ids contiguous from ``cfg.first_tag_id``, wall order)."""
    walls = office_walls(cfg.corridor_length_m)
    rng = np.random.default_rng(_WORLD_SEED)
    overrides = dict(cfg.tag_size_overrides)
    tags: list[Tag] = []
    margin = 0.35
    tag_id = cfg.first_tag_id
    e_all = walls[:, 2:] - walls[:, :2]
    for w, (seg, e) in enumerate(zip(walls, e_all, strict=True)):
        length = float(np.linalg.norm(e))
        if length < 2 * margin:
            continue
        d = e / length
        n2 = np.array([-d[1], d[0]])
        count = int((length - 2 * margin) // cfg.tag_spacing_m) + 1
        for i in range(count):
            s = length / 2 + (i - (count - 1) / 2) * cfg.tag_spacing_m
            s += float(rng.uniform(-0.08, 0.08))
            z = cfg.camera_xyz_m[2] + float(rng.uniform(-0.06, 0.06))
            xy = seg[:2] + s * d + _TAG_OFFSET_M * n2
            n3 = np.array([n2[0], n2[1], 0.0])
            up = np.array([0.0, 0.0, 1.0])
            T = np.eye(4)
            T[:3, 0] = np.cross(up, n3)  # x: the viewer's right
            T[:3, 1] = up  # y: up
            T[:3, 2] = n3  # z: out of the wall, towards the viewer
            T[:3, 3] = [xy[0], xy[1], z]
            size = overrides.get(tag_id, cfg.tag_size_m)
            tags.append(Tag(id=tag_id, size_m=size, wall=w, T_world_tag=T))
            tag_id += 1
    return World(walls=walls, height_m=cfg.wall_height_m, tags=tuple(tags))


# --------------------------------------------------------------------------- path


_OFFICE_LEG1: Final = [
    (1.2, 1.4), (1.0, 2.6), (1.0, 3.8), (1.3, 4.7), (2.3, 5.05), (4.0, 5.1), (5.6, 5.05),
    (6.7, 4.7), (7.05, 3.8), (7.05, 2.2), (6.7, 1.3), (5.6, 0.95), (4.0, 0.9), (2.7, 1.0),
    (2.0, 1.6), (2.3, 2.6), (3.5, 3.0), (5.2, 3.0), (6.6, 3.0), (8.0, 3.0), (10.0, 3.0),
    (13.0, 3.0), (16.3, 3.0), (17.0, 3.0),
]  # fmt: skip
_OFFICE_LEG2: Final = [
    (17.0, 3.0), (16.3, 3.0), (13.0, 3.0), (10.0, 3.0), (8.0, 3.0), (6.8, 3.0),
    (5.8, 3.3), (5.0, 3.9), (3.8, 4.1), (2.4, 4.0),
]  # fmt: skip
_CORRIDOR_LEG: Final = [(6.0, 3.0), (6.6, 3.0), (8.0, 3.0), (10.0, 3.0), (13.0, 3.0), (16.3, 3.0), (17.0, 3.0)]


def _corridor_leg(cfg: SimConfig) -> list[tuple[float, float]]:
    """Just before the door to 1 m before the corridor's end (the default corridor: :data:`_CORRIDOR_LEG`)."""
    if cfg.corridor_length_m == 10.0:
        return list(_CORRIDOR_LEG)
    end = 8.0 + cfg.corridor_length_m - 1.0
    xs = [6.0, 6.6, 8.0, *np.arange(10.0, end - 0.7, 3.0).tolist(), end - 0.7, end]
    return [(float(x), 3.0) for x in xs]


@dataclass(frozen=True)
class Trajectory:
    """True planar motion of base_link in the world, densely sampled in time.

    ``t`` (s from the start) increases strictly; ``yaw`` is unwrapped (continuous);
    ``v`` is the forward speed (m/s) and ``w`` the yaw rate (rad/s).
    """

    t: FloatArray
    x: FloatArray
    y: FloatArray
    yaw: FloatArray
    v: FloatArray
    w: FloatArray

    @property
    def duration_s(self) -> float:
        """Time at which the path ends (the robot rests afterwards)."""
        return float(self.t[-1])

    def sample(self, t: float | FloatArray) -> tuple[FloatArray, ...]:
        """(x, y, yaw, v, w) at time(s) t; held constant past the end."""
        tt = np.asarray(t, dtype=np.float64)
        return tuple(np.interp(tt, self.t, arr) for arr in (self.x, self.y, self.yaw, self.v, self.w))


def _bspline(points: list[tuple[float, float]], per_segment: int = 1500) -> tuple[FloatArray, ...]:
    """Uniform cubic B-spline (C2) with clamped ends: position, first and second derivative."""
    P = np.asarray(points, dtype=np.float64)
    P = np.vstack([P[:1], P[:1], P, P[-1:], P[-1:]])
    u = np.linspace(0.0, 1.0, per_segment, endpoint=False)
    B = np.stack([(1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4, -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3], 1) / 6
    dB = np.stack([-3 * (1 - u) ** 2, 9 * u**2 - 12 * u, -9 * u**2 + 6 * u + 3, 3 * u**2], 1) / 6
    ddB = np.stack([6 * (1 - u), 18 * u - 12, -18 * u + 6, 6 * u], 1) / 6
    pos, d1, d2 = [], [], []
    for i in range(len(P) - 3):
        C = P[i : i + 4]
        pos.append(B @ C)
        d1.append(dB @ C)
        d2.append(ddB @ C)
    # Clamped ends: the speed vanishes at u = 0 of the first segment and tends to 0 at the end;
    # the (near-)zero-speed samples are dropped by the caller.
    return np.vstack(pos), np.vstack(d1), np.vstack(d2)


def _drive_leg(points: list[tuple[float, float]], cfg: SimConfig) -> tuple[FloatArray, ...]:
    """Drive along a B-spline from rest to rest: arrays t, x, y, yaw, v, w."""
    pos, d1, d2 = _bspline(points)
    speed_u = np.linalg.norm(d1, axis=1)
    keep = speed_u > 1e-9  # drop degenerate samples at the clamped ends
    pos, d1, d2, speed_u = pos[keep], d1[keep], d2[keep], speed_u[keep]
    ds = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    keep = np.concatenate([[True], ds > 1e-7])
    pos, d1, d2, speed_u = pos[keep], d1[keep], d2[keep], speed_u[keep]
    ds = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    yaw = np.unwrap(np.arctan2(d1[:, 1], d1[:, 0]))
    kappa = (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / speed_u**3
    ak = np.maximum(np.abs(kappa), 1e-9)
    v_lim = np.minimum.reduce(
        [
            np.full_like(ak, cfg.max_speed_mps),
            np.sqrt(cfg.max_lateral_accel_mps2 / ak),
            cfg.max_yaw_rate_radps / ak,
        ]
    )
    v = v_lim.copy()
    v[0] = v[-1] = 0.0
    a = cfg.max_accel_mps2
    for i in range(1, len(v)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * a * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * a * ds[i]))
    dt = 2 * ds / (v[:-1] + v[1:])
    t = np.concatenate([[0.0], np.cumsum(dt)])
    return t, pos[:, 0], pos[:, 1], yaw, v, kappa * v


def _spin_leg(x: float, y: float, yaw0: float, angle: float, cfg: SimConfig) -> tuple[FloatArray, ...]:
    """Turn in place by ``angle`` (rad) with a trapezoidal yaw-rate profile, rest to rest."""
    w_max, alpha = cfg.max_yaw_rate_radps, 1.0
    t_acc = w_max / alpha
    if abs(angle) < w_max * t_acc:
        t_acc = math.sqrt(abs(angle) / alpha)
        w_max = alpha * t_acc
    t_cruise = abs(angle) / w_max - t_acc
    total = 2 * t_acc + t_cruise
    t = np.linspace(0.0, total, max(int(total / 0.002), 10) + 1)
    w = np.minimum.reduce([alpha * t, np.full_like(t, w_max), alpha * (total - t)])
    turned = np.concatenate([[0.0], np.cumsum((w[1:] + w[:-1]) / 2 * np.diff(t))])
    turned *= abs(angle) / turned[-1]
    sign = math.copysign(1.0, angle)
    return t, np.full_like(t, x), np.full_like(t, y), yaw0 + sign * turned, np.zeros_like(t), sign * w


def build_trajectory(cfg: SimConfig) -> Trajectory:
    """The robot's true path for ``cfg.path``, from rest to rest."""
    if cfg.path == "office":
        legs = [_drive_leg(_OFFICE_LEG1, cfg)]
        _, x, y, yaw, _, _ = legs[0]
        legs.append(_spin_leg(float(x[-1]), float(y[-1]), float(yaw[-1]), math.pi, cfg))
        legs.append(_drive_leg(_OFFICE_LEG2, cfg))
    elif cfg.path == "corridor":
        legs = [_drive_leg(_corridor_leg(cfg), cfg)]
    elif cfg.path == "corridor_return":
        out = _corridor_leg(cfg)
        legs = []
        for lap in range(max(cfg.laps, 1)):
            if lap:  # back at the start facing the room: turn to face the corridor again
                _, x, y, yaw, _, _ = legs[-1]
                legs.append(_spin_leg(float(x[-1]), float(y[-1]), float(yaw[-1]), math.pi, cfg))
            legs.append(_drive_leg(out, cfg))
            _, x, y, yaw, _, _ = legs[-1]
            legs.append(_spin_leg(float(x[-1]), float(y[-1]), float(yaw[-1]), math.pi, cfg))
            legs.append(_drive_leg(out[::-1], cfg))
    else:
        msg = f"unknown path {cfg.path!r}; expected 'office', 'corridor' or 'corridor_return'"
        raise ValueError(msg)
    cols: list[list[FloatArray]] = [[] for _ in range(6)]
    t_off = 0.0
    yaw_prev: float | None = None
    for k, leg in enumerate(legs):
        t, x, y, yaw, v, w = leg
        if yaw_prev is not None:  # keep yaw continuous across legs
            yaw = yaw + 2 * math.pi * round((yaw_prev - float(yaw[0])) / (2 * math.pi))
        sl = slice(None) if k == 0 else slice(1, None)
        for c, arr in zip(cols, (t + t_off, x, y, yaw, v, w), strict=True):
            c.append(arr[sl])
        t_off += float(t[-1])
        yaw_prev = float(yaw[-1])
    t_all, x_all, y_all, yaw_all, v_all, w_all = (np.concatenate(c) for c in cols)
    return Trajectory(t=t_all, x=x_all, y=y_all, yaw=yaw_all, v=v_all, w=w_all)


# --------------------------------------------------------------------------- camera


@dataclass(frozen=True)
class CameraModel:
    """Pinhole + plumb_bob camera; ``K`` is 3x3, ``D`` is (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    K: FloatArray
    D: FloatArray

    @staticmethod
    def from_config(cfg: SimConfig) -> CameraModel:
        """Intrinsics of the configured camera (defaults scale with the image size)."""
        w, h = cfg.image_width, cfg.image_height
        fx = cfg.fx if cfg.fx is not None else 0.65 * w
        fy = cfg.fy if cfg.fy is not None else 1.003 * fx
        cx = cfg.cx if cfg.cx is not None else (w - 1) / 2 + 0.004 * w
        cy = cfg.cy if cfg.cy is not None else (h - 1) / 2 - 0.003 * h
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return CameraModel(width=w, height=h, K=K, D=np.asarray(cfg.distortion, dtype=np.float64))

    def distort_normalized(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Apply plumb_bob distortion to normalized image coordinates (as OpenCV does)."""
        k1, k2, p1, p2, k3 = self.D
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def undistort_normalized(self, xd: FloatArray, yd: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Invert :meth:`distort_normalized` by Newton iterations (to ~1e-12)."""
        x, y = xd.copy(), yd.copy()
        eps = 1e-6
        for _ in range(12):
            fx_, fy_ = self.distort_normalized(x, y)
            rx, ry = fx_ - xd, fy_ - yd
            ax, ay = self.distort_normalized(x + eps, y)
            bx, by = self.distort_normalized(x, y + eps)
            j11, j21 = (ax - fx_) / eps, (ay - fy_) / eps
            j12, j22 = (bx - fx_) / eps, (by - fy_) / eps
            det = j11 * j22 - j12 * j21
            x = x - (j22 * rx - j12 * ry) / det
            y = y - (-j21 * rx + j11 * ry) / det
        return x, y


class _Renderer:
    """Renders the camera image of the office from a camera pose.

    The scene is drawn as an ideal pinhole image on a canvas larger than the image (so
    that every distorted pixel has a source), with walls, floor and ceiling ray cast per
    pixel and tags warped in by homography at ``supersample`` x resolution with a depth
    test against the walls; the canvas is then resampled through the lens distortion.
    """

    def __init__(self, cfg: SimConfig, world: World, cam: CameraModel) -> None:
        self.cfg, self.world, self.cam = cfg, world, cam
        self.S = max(int(cfg.supersample), 1)
        fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
        self.fx, self.fy = fx, fy
        ud, vd = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
        xu, yu = cam.undistort_normalized((ud - cx) / fx, (vd - cy) / fy)
        xr, yr = cam.distort_normalized(xu, yu)
        assert max(np.abs(xr * fx + cx - ud).max(), np.abs(yr * fy + cy - vd).max()) < 1e-6
        # Largest normalized radius the image sees; projections beyond it are not trusted.
        self.r_valid = float(np.sqrt(xu**2 + yu**2).max()) * 1.05
        u_src, v_src = xu * fx + cx, yu * fy + cy
        ox = math.ceil(max(0.0, -float(u_src.min()))) + 3
        oy = math.ceil(max(0.0, -float(v_src.min()))) + 3
        self.W = math.ceil(float(u_src.max())) + ox + 4
        self.H = math.ceil(float(v_src.max())) + oy + 4
        self.cxc, self.cyc = cx + ox, cy + oy
        self.map_x = (u_src + ox).astype(np.float32)
        self.map_y = (v_src + oy).astype(np.float32)
        walls = world.walls
        self.wall_len = np.linalg.norm(walls[:, 2:] - walls[:, :2], axis=1)
        self.wall_grey = 150.0 + 12.0 * np.cos(np.arange(len(walls)) * 2.3)
        self.yn_rows = (np.arange(self.H, dtype=np.float64) - self.cyc) / fy

    # Columns of the canvas map to fixed horizontal directions (optical axis horizontal).
    def _column_dirs(self, T_world_cam: FloatArray, u: FloatArray) -> FloatArray:
        R = T_world_cam[:3, :3]
        xn = (u - self.cxc) / self.fx
        return (R[:2, 0][None, :] * xn[:, None]) + R[:2, 2][None, :]

    def wall_depth(self, T_world_cam: FloatArray, u: FloatArray) -> tuple[FloatArray, ...]:
        """Depth (along the optical axis) of the first wall seen in canvas columns u."""
        dirs = self._column_dirs(T_world_cam, u)
        return ray_segment_hits(T_world_cam[:2, 3], dirs, self.world.walls)

    def render(
        self, T_world_cam: FloatArray, rng: np.random.Generator, blur_dir: tuple[float, float] = (1.0, 0.0)
    ) -> npt.NDArray[np.uint8]:
        """Distorted, noisy uint8 grey image seen from ``T_world_cam`` (motion blur along ``blur_dir``, px)."""
        R = T_world_cam[:3, :3]
        if abs(R[2, 1] + 1.0) > 1e-9:
            msg = "the renderer needs a horizontal optical axis (camera y pointing down)"
            raise ValueError(msg)
        canvas = self._background(T_world_cam)
        for tag in self.world.tags:
            self._draw_tag(canvas, T_world_cam, tag)
        img = cv2.remap(canvas, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        img = self._expose(img, blur_dir)
        img = img.astype(np.float64) + rng.normal(0.0, self.cfg.pixel_noise_sigma, img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def _expose(self, img: npt.NDArray[np.float32], blur_dir: tuple[float, float]) -> npt.NDArray[np.float32]:
        """Exposure gain, contrast, vignetting and motion blur (each skipped at its neutral value)."""
        cfg = self.cfg
        if cfg.exposure_gain != 1.0:
            img = img * np.float32(cfg.exposure_gain)
        if cfg.contrast != 1.0:
            img = np.float32(128.0) + np.float32(cfg.contrast) * (img - np.float32(128.0))
        if cfg.vignetting > 0.0:
            img = img * self._vignette_map
        if cfg.motion_blur_px > 0.0:
            img = cv2.filter2D(img, -1, line_kernel(cfg.motion_blur_px, blur_dir), borderType=cv2.BORDER_REPLICATE)
        return img

    @functools.cached_property
    def _vignette_map(self) -> npt.NDArray[np.float32]:
        cam = self.cam
        cx, cy = cam.K[0, 2], cam.K[1, 2]
        u, v = np.meshgrid(np.arange(cam.width) - cx, np.arange(cam.height) - cy)
        r_corner = max(np.hypot(x, y) for x in (-cx, cam.width - 1 - cx) for y in (-cy, cam.height - 1 - cy))
        return (1.0 - self.cfg.vignetting * (u**2 + v**2) / r_corner**2).astype(np.float32)

    def _background(self, T_world_cam: FloatArray) -> npt.NDArray[np.float32]:
        c = T_world_cam[:3, 3]
        u = np.arange(self.W, dtype=np.float64)
        dirs = self._column_dirs(T_world_cam, u)
        t_wall, wall_idx, s_wall = ray_segment_hits(c[:2], dirs, self.world.walls)
        yn = self.yn_rows[:, None]  # world z of the ray direction is -yn
        z_hit = c[2] - yn * t_wall[None, :]
        on_wall = (z_hit >= 0.0) & (z_hit <= self.world.height_m) & np.isfinite(t_wall)[None, :]
        # Walls: a per-wall grey with a gentle texture along the wall and with height.
        grey = self.wall_grey[np.maximum(wall_idx, 0)]
        wall_val = (
            grey[None, :]
            + 8.0 * np.sin(1.7 * s_wall + 0.9 * wall_idx)[None, :]
            + 5.0 * np.sin(2.3 * z_hit + 0.4 * s_wall[None, :])
        )
        # Floor and ceiling: where the ray leaves the wall band.
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(yn > 0, c[2] / yn, np.inf)
        floor_t = np.broadcast_to(t_floor, on_wall.shape)
        fx_ = c[0] + dirs[None, :, 0] * floor_t
        fy_ = c[1] + dirs[None, :, 1] * floor_t
        with np.errstate(invalid="ignore"):
            floor_val = 95.0 + 10.0 * np.sin(0.9 * fx_) * np.cos(1.1 * fy_) - 12.0 * np.tanh(floor_t / 6.0)
        ceil_val = np.full(on_wall.shape, 210.0)
        out = np.where(on_wall, wall_val, np.where(yn > 0, floor_val, ceil_val))
        return np.nan_to_num(out, nan=128.0).astype(np.float32)

    def _draw_tag(self, canvas: npt.NDArray[np.float32], T_world_cam: FloatArray, tag: Tag) -> None:
        T_ct = inv_T(T_world_cam) @ tag.T_world_tag
        R, t = T_ct[:3, :3], T_ct[:3, 3]
        n_c = R[:, 2]
        if float(n_c @ -t) <= 1e-6:  # seen from behind or edge-on
            return
        half = tag.size_m * 10.0 / 16.0  # half side of the outer square, quiet border included
        outer = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
        pc = outer @ R.T + t
        if (pc[:, 2] < 0.05).any():
            return
        uc = self.fx * pc[:, 0] / pc[:, 2] + self.cxc
        vc = self.fy * pc[:, 1] / pc[:, 2] + self.cyc
        S = self.S
        i0 = max(math.floor(uc.min()) - 1, 0)
        i1 = min(math.ceil(uc.max()) + 2, self.W)
        j0 = max(math.floor(vc.min()) - 1, 0)
        j1 = min(math.ceil(vc.max()) + 2, self.H)
        if i1 <= i0 or j1 <= j0:
            return
        side_hi = S * max(np.hypot(np.diff(uc, append=uc[0]), np.diff(vc, append=vc[0])))
        k = int(min(max(math.ceil(side_hi / 10.0), 1), 48))
        bitmap = _tag_bitmap(tag.id, k)
        N = bitmap.shape[0]
        L = 2 * half
        # bitmap pixel (p, q) centre -> tag (x, y): x = (p + .5) L / N - L / 2, y = L / 2 - (q + .5) L / N
        B = np.array([[L / N, 0.0, L / (2 * N) - L / 2], [0.0, -L / N, L / 2 - L / (2 * N)], [0.0, 0.0, 1.0]])
        Kc = np.array([[self.fx, 0.0, self.cxc], [0.0, self.fy, self.cyc], [0.0, 0.0, 1.0]])
        H_lo = Kc @ np.column_stack([R[:, 0], R[:, 1], t]) @ B
        # canvas pixel x -> sub-pixel S x + (S - 1) / 2 (pixel centres stay centres), ROI shift
        A = np.array([[S, 0.0, (S - 1) / 2 - S * i0], [0.0, S, (S - 1) / 2 - S * j0], [0.0, 0.0, 1.0]])
        M = A @ H_lo
        size = (S * (i1 - i0), S * (j1 - j0))
        flags = cv2.INTER_LINEAR
        col = cv2.warpPerspective(bitmap, M, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        alpha = cv2.warpPerspective(
            np.ones_like(bitmap), M, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )
        # Depth test against the walls (walls are vertical: their depth depends on the column only).
        a_hi = np.arange(size[0], dtype=np.float64)
        b_hi = np.arange(size[1], dtype=np.float64)
        u_lo = (a_hi + 0.5) / S - 0.5 + i0
        v_lo = (b_hi + 0.5) / S - 0.5 + j0
        t_wall = self.wall_depth(T_world_cam, u_lo)[0]
        rx = (u_lo - self.cxc) / self.fx
        ry = (v_lo - self.cyc) / self.fy
        denom = n_c[0] * rx[None, :] + n_c[1] * ry[:, None] + n_c[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            z_tag = float(n_c @ t) / denom
        hidden = ~(z_tag <= t_wall[None, :]) | (denom >= 0)  # denom < 0: ray meets the front face
        if hidden.any():
            col[hidden] = 0.0
            alpha[hidden] = 0.0
        h_lo, w_lo = j1 - j0, i1 - i0
        col_lo = col.reshape(h_lo, S, w_lo, S).mean(axis=(1, 3))
        alpha_lo = alpha.reshape(h_lo, S, w_lo, S).mean(axis=(1, 3))
        roi = canvas[j0:j1, i0:i1]
        roi[...] = roi * (1.0 - alpha_lo) + col_lo


def line_kernel(length_px: float, direction: tuple[float, float]) -> npt.NDArray[np.float32]:
    """Normalised kernel of a centred line segment ``length_px`` long along ``direction`` (anti-aliased)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d) if np.linalg.norm(d) > 0 else np.array([1.0, 0.0])
    half = math.ceil(length_px / 2) + 1
    size = 2 * half + 1
    kernel = np.zeros((size, size), np.float64)
    n = max(int(8 * length_px), 2)
    for s in np.linspace(-length_px / 2, length_px / 2, n):
        x, y = half + s * d[0], half + s * d[1]
        x0, y0 = math.floor(x), math.floor(y)
        fx_, fy_ = x - x0, y - y0
        kernel[y0, x0] += (1 - fx_) * (1 - fy_)
        kernel[y0, x0 + 1] += fx_ * (1 - fy_)
        kernel[y0 + 1, x0] += (1 - fx_) * fy_
        kernel[y0 + 1, x0 + 1] += fx_ * fy_
    return (kernel / kernel.sum()).astype(np.float32)


def image_motion_direction(cam: CameraModel, T_wc_before: FloatArray, T_wc_after: FloatArray) -> tuple[float, float]:
    """Direction (du, dv) in which the point 2 m along the optical axis moves in the image between two poses."""
    p_world = T_wc_before @ np.array([0.0, 0.0, 2.0, 1.0])
    p_after = inv_T(T_wc_after) @ p_world
    if p_after[2] <= 0.1:
        return (1.0, 0.0)
    du = cam.K[0, 0] * p_after[0] / p_after[2]
    dv = cam.K[1, 1] * p_after[1] / p_after[2]
    return (float(du), float(dv)) if math.hypot(du, dv) > 1e-6 else (1.0, 0.0)


@functools.lru_cache(maxsize=4096)
def _tag_bitmap(tag_id: int, px_per_cell: int) -> npt.NDArray[np.float32]:
    """Grey float32 image of a tag36h11 marker, one white cell of quiet border around it."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, 8 * px_per_cell, borderBits=1)
    marker = cv2.copyMakeBorder(marker, *([px_per_cell] * 4), cv2.BORDER_CONSTANT, value=255)
    grey = _TAG_BLACK + (_TAG_WHITE - _TAG_BLACK) * (marker.astype(np.float32) / 255.0)
    grey.setflags(write=False)
    return grey


def tag_corners_tag_frame(size_m: float) -> FloatArray:
    """The 4 corners (TL, TR, BR, BL as printed) of a tag's black square in the tag frame."""
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def project_points(cam: CameraModel, T_camera_tag: FloatArray, pts_tag: FloatArray) -> FloatArray:
    """Distorted pixel coordinates (N, 2) of tag-frame points, with ``cv2.projectPoints``."""
    rvec, _ = cv2.Rodrigues(T_camera_tag[:3, :3])
    px, _ = cv2.projectPoints(pts_tag.reshape(-1, 1, 3), rvec, T_camera_tag[:3, 3].copy(), cam.K, cam.D)
    return px.reshape(-1, 2).astype(np.float64)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Header:
    """stamp (ns since the epoch) and frame id, shared by every stamped message."""

    stamp_ns: int
    frame_id: str


@dataclass(frozen=True)
class ImageMsg:
    """A camera frame: encoded bytes (``format`` jpeg/png) or raw pixels (mono8/bgr8)."""

    header: Header
    encoding: ImageFormat
    width: int
    height: int
    data: bytes


@dataclass(frozen=True)
class CameraInfoMsg:
    """Calibration published with each frame (plumb_bob)."""

    header: Header
    width: int
    height: int
    D: tuple[float, ...]
    K: tuple[float, ...]
    R: tuple[float, ...]
    P: tuple[float, ...]


@dataclass(frozen=True)
class OdometryMsg:
    """Wheel odometry: pose of base_link in odom, twist in base_link, 6x6 covariances.

    Covariance order is ROS's (x, y, z, rot x, rot y, rot z), row-major, 36 values.
    """

    header: Header
    child_frame_id: str
    x: float
    y: float
    yaw: float
    pose_covariance: tuple[float, ...]
    vx: float
    vy: float
    wz: float
    twist_covariance: tuple[float, ...]


@dataclass(frozen=True)
class ScanMsg:
    """A planar laser scan; ranges in m, +inf where nothing is within range_max."""

    header: Header
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: npt.NDArray[np.float32]


@dataclass(frozen=True)
class TransformMsg:
    """One static transform parent -> child: translation (m) and quaternion (x, y, z, w)."""

    header: Header
    child_frame_id: str
    translation: tuple[float, float, float]
    rotation_xyzw: tuple[float, float, float, float]


@dataclass(frozen=True)
class TFMsg:
    """A tf2_msgs/TFMessage."""

    transforms: tuple[TransformMsg, ...]


Payload = ImageMsg | CameraInfoMsg | OdometryMsg | ScanMsg | TFMsg


@dataclass(frozen=True)
class SimMessage:
    """One message of the recording; ``stamp_ns`` is both the header and the bag time."""

    topic: str
    stamp_ns: int
    payload: Payload


@dataclass(frozen=True)
class Recording:
    """Everything a run produced: time-ordered messages and the ground truth (JSON-ready)."""

    config: SimConfig
    messages: tuple[SimMessage, ...]
    ground_truth: dict[str, Any] = field(repr=False)

    def counts(self) -> dict[str, int]:
        """Number of messages per topic."""
        return dict(sorted(Counter(m.topic for m in self.messages).items()))


def image_topic(cfg: SimConfig) -> str:
    """The image topic for the configured image format."""
    return "/camera/image_raw/compressed" if cfg.image_format in ("jpeg", "png") else "/camera/image_raw"


CAMERA_INFO_TOPIC: Final = "/camera/camera_info"
ODOM_TOPIC: Final = "/odom"
SCAN_TOPIC: Final = "/scan"
TF_STATIC_TOPIC: Final = "/tf_static"


# --------------------------------------------------------------------------- simulation


def _stamps(start_ns: int, phase_s: float, rate_hz: float, duration_s: float) -> list[int]:
    period_ns = round(1e9 / rate_hz)
    phase_ns = round(phase_s * 1e9)
    n = math.floor((duration_s * 1e9 - phase_ns) / period_ns) + 1
    return [start_ns + phase_ns + k * period_ns for k in range(max(n, 0))]


def mount_transforms(cfg: SimConfig) -> tuple[FloatArray, FloatArray]:
    """T_base_camera (optical frame) and T_base_laser."""
    T_bc = np.eye(4)
    T_bc[:3, :3] = planar_T(0, 0, math.radians(cfg.camera_yaw_deg))[:3, :3] @ _R_BODY_OPTICAL
    T_bc[:3, 3] = cfg.camera_xyz_m
    T_bl = np.eye(4)
    T_bl[:3, 3] = cfg.laser_xyz_m
    return T_bc, T_bl


def _validate(cfg: SimConfig) -> None:
    if cfg.image_format not in IMAGE_FORMATS:
        msg = f"image_format {cfg.image_format!r} is not one of {IMAGE_FORMATS}"
        raise ValueError(msg)
    for name in ("camera_rate_hz", "odom_rate_hz", "scan_rate_hz"):
        if getattr(cfg, name) <= 0:
            msg = f"{name} must be > 0, got {getattr(cfg, name)}"
            raise ValueError(msg)
    if cfg.pixel_noise_sigma < 0 or cfg.odom_v_sigma_mps < 0 or cfg.odom_yaw_rate_sigma_radps < 0:
        msg = "pixel and odometry noise must be >= 0"
        raise ValueError(msg)
    if cfg.exposure_gain <= 0 or cfg.contrast <= 0 or not 0 <= cfg.vignetting < 1 or cfg.motion_blur_px < 0:
        msg = "exposure_gain and contrast must be > 0, vignetting in [0, 1) and motion_blur_px >= 0"
        raise ValueError(msg)
    if not 1 <= cfg.jpeg_quality <= 100 or cfg.tag_size_m <= 0:
        msg = f"jpeg_quality must be in 1..100 and tag_size_m > 0 (got {cfg.jpeg_quality}, {cfg.tag_size_m})"
        raise ValueError(msg)
    if cfg.duration_s is not None and cfg.duration_s <= 0:
        msg = f"duration_s must be > 0 (or None for the whole path), got {cfg.duration_s}"
        raise ValueError(msg)
    if not 0.1 <= cfg.camera_xyz_m[2] <= cfg.wall_height_m - 0.2:
        msg = (
            f"the camera's height must be 0.1 to {cfg.wall_height_m - 0.2:g} m (the tags hang at it on walls "
            f"{cfg.wall_height_m:g} m high), got {cfg.camera_xyz_m[2]:g}"
        )
        raise ValueError(msg)
    if cfg.laps < 1 or (cfg.laps > 1 and cfg.path != "corridor_return"):
        msg = f"laps must be >= 1, and above 1 only with path corridor_return (got {cfg.laps}, path {cfg.path})"
        raise ValueError(msg)


def _r(x: float, nd: int = 9) -> float:
    return round(float(x), nd)


def _T_list(T: FloatArray) -> list[list[float]]:
    return [[_r(v, 12) for v in row] for row in T]


def _odometry(
    cfg: SimConfig,
    true_pose: Callable[[int], tuple[float, float, float]],
    traj: Trajectory,
    odom_ns: list[int],
    rng: np.random.Generator,
) -> list[OdometryMsg]:
    """Wheel odometry: true body-frame increments with the systematic wheel errors, plus white noise on the
    forward increment and the yaw increment; the pose covariance is the first-order propagation of that white
    noise times ``cfg.odom_cov_scale`` (the systematic errors are not in it, as in real drivers)."""
    sv, sw = cfg.odom_v_sigma_mps, cfg.odom_yaw_rate_sigma_radps
    k_d, k_w, bias = 1.0 + cfg.odom_distance_scale_error, 1.0 + cfg.odom_yaw_scale_error, cfg.odom_yaw_bias_rad_per_m
    small = 1e-9  # variance of the unmodelled planar dofs (z, roll, pitch / vy, vz, wx, wy)
    ox = oy = oyaw = 0.0
    P = np.zeros((3, 3))
    out: list[OdometryMsg] = []
    prev = true_pose(odom_ns[0])
    for k, stamp in enumerate(odom_ns):
        cur = true_pose(stamp)
        if k == 0:
            _, _, _, v_true, w_true = traj.sample(0.0)
            dx_b, dy_b, dyaw = 0.0, 0.0, 0.0
            vx = float(v_true) + sv * float(rng.standard_normal())
            wz = float(w_true) + sw * float(rng.standard_normal())
            vy = 0.0
        else:
            dt = (stamp - odom_ns[k - 1]) * 1e-9
            c, s = math.cos(prev[2]), math.sin(prev[2])
            ddx, ddy = cur[0] - prev[0], cur[1] - prev[1]
            n_v, n_w = rng.standard_normal(2)
            fwd = c * ddx + s * ddy
            dx_b = k_d * fwd + sv * dt * float(n_v)
            dy_b = k_d * (-s * ddx + c * ddy)
            dyaw = k_w * (cur[2] - prev[2]) + bias * fwd + sw * dt * float(n_w)
            co, so = math.cos(oyaw), math.sin(oyaw)
            F = np.array([[1, 0, -so * dx_b - co * dy_b], [0, 1, co * dx_b - so * dy_b], [0, 0, 1]])
            G = np.array([[co, 0], [so, 0], [0, 1]])
            Q = np.diag([(sv * dt) ** 2, (sw * dt) ** 2])
            step = G @ Q @ G.T
            P = P + np.diag(np.diag(step)) if cfg.odom_cov_model == "diagonal" else F @ P @ F.T + step
            ox += co * dx_b - so * dy_b
            oy += so * dx_b + co * dy_b
            oyaw += dyaw
            vx, vy, wz = dx_b / dt, dy_b / dt, dyaw / dt
        prev = cur
        pose_cov = np.diag([0.0, 0.0, small, small, small, 0.0])
        idx = [0, 1, 5]
        pose_cov[np.ix_(idx, idx)] = P
        twist_cov = np.diag([sv**2, small, small, small, small, sw**2])
        if cfg.odom_cov_scale != 1.0:
            pose_cov[np.ix_(idx, idx)] *= cfg.odom_cov_scale
            if cfg.odom_cov_scale == 0.0:
                pose_cov[:] = 0.0
                twist_cov[:] = 0.0
        out.append(
            OdometryMsg(
                header=Header(stamp, cfg.odom_frame),
                child_frame_id=cfg.base_frame,
                x=ox,
                y=oy,
                yaw=oyaw,
                pose_covariance=tuple(float(v) for v in pose_cov.ravel()),
                vx=vx,
                vy=vy,
                wz=wz,
                twist_covariance=tuple(float(v) for v in twist_cov.ravel()),
            )
        )
    return out


def simulate_odometry(cfg: SimConfig) -> list[OdometryMsg]:
    """The odometry messages :func:`simulate` makes for ``cfg`` (the same draws), without rendering anything."""
    _validate(cfg)
    traj = build_trajectory(cfg)
    duration = traj.duration_s + 1.0 if cfg.duration_s is None else cfg.duration_s
    rng_odom = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(3)[0])
    t0 = cfg.start_time_ns
    odom_ns = _stamps(t0, 0.0, cfg.odom_rate_hz, duration)

    def true_pose(stamp_ns: int) -> tuple[float, float, float]:
        x, y, yaw, _, _ = traj.sample((stamp_ns - t0) * 1e-9)
        return float(x), float(y), float(yaw)

    return _odometry(cfg, true_pose, traj, odom_ns, rng_odom)


def laser_scan(cfg: SimConfig, walls: FloatArray, traj: Trajectory, stamp: int, rng: np.random.Generator) -> ScanMsg:
    """One scan at ``stamp``: the beams ray-cast against ``walls`` from the true pose, plus range noise.

    With ``cfg.laser_sweep`` beam ``i`` is cast from the pose at ``stamp + i * time_increment`` (a spinning
    scanner's sweep over one scan period; the header stamp is the first beam's time, as in ROS); else every
    beam from the stamp's pose and ``time_increment`` is 0. Draws ``laser_beams`` standard normals from ``rng``.
    """
    _, T_bl = mount_transforms(cfg)
    n_beams = cfg.laser_beams
    inc = 2 * math.pi / n_beams
    angles = -math.pi + inc * np.arange(n_beams)
    beam_dt = 1.0 / (cfg.scan_rate_hz * n_beams) if cfg.laser_sweep else 0.0
    t_s = (stamp - cfg.start_time_ns) * 1e-9
    if cfg.laser_sweep:  # each beam from the pose at its own time
        bx, by, byaw, _, _ = traj.sample(t_s + beam_dt * np.arange(n_beams, dtype=np.float64))
        c, s = np.cos(byaw), np.sin(byaw)
        origin: FloatArray = np.column_stack(
            [bx + c * T_bl[0, 3] - s * T_bl[1, 3], by + s * T_bl[0, 3] + c * T_bl[1, 3]]
        )
        a = byaw + angles
    else:
        x, y, yaw, _, _ = traj.sample(t_s)
        origin = (planar_T(float(x), float(y), float(yaw)) @ T_bl)[:2, 3]
        a = float(yaw) + angles
    dirs = np.stack([np.cos(a), np.sin(a)], axis=1)
    rng_true, _, _ = ray_segment_hits(origin, dirs, walls)
    ranges = rng_true + cfg.laser_range_sigma_m * rng.standard_normal(n_beams)
    ranges = np.where(rng_true > cfg.laser_range_max_m, np.inf, ranges)
    return ScanMsg(
        header=Header(stamp, cfg.laser_frame),
        angle_min=float(angles[0]),
        angle_max=float(angles[-1]),
        angle_increment=inc,
        time_increment=beam_dt,
        scan_time=1.0 / cfg.scan_rate_hz,
        range_min=cfg.laser_range_min_m,
        range_max=cfg.laser_range_max_m,
        ranges=ranges.astype(np.float32),
    )


def simulate(cfg: SimConfig) -> Recording:
    """Simulate a run: every message in time order, plus the ground truth, in memory."""
    _validate(cfg)
    world = build_world(cfg)
    traj = build_trajectory(cfg)
    cam = CameraModel.from_config(cfg)
    renderer = _Renderer(cfg, world, cam)
    duration = traj.duration_s + 1.0 if cfg.duration_s is None else cfg.duration_s
    rng_odom, rng_scan, rng_pix = (np.random.default_rng(s) for s in np.random.SeedSequence(cfg.seed).spawn(3))
    T_bc, T_bl = mount_transforms(cfg)
    t0 = cfg.start_time_ns
    odom_ns = _stamps(t0, 0.0, cfg.odom_rate_hz, duration)
    cam_ns = _stamps(t0, 0.021, cfg.camera_rate_hz, duration)
    scan_ns = _stamps(t0, 0.013, cfg.scan_rate_hz, duration)

    def true_pose(stamp_ns: int) -> tuple[float, float, float]:
        x, y, yaw, _, _ = traj.sample((stamp_ns - t0) * 1e-9)
        return float(x), float(y), float(yaw)

    messages: list[tuple[int, int, SimMessage]] = []  # (stamp, topic order, message)

    def add(order: int, topic: str, stamp: int, payload: Payload) -> None:
        messages.append((stamp, order, SimMessage(topic=topic, stamp_ns=stamp, payload=payload)))

    # Static transforms, once at the start (latched / transient local).
    tfs = []
    for child, T in ((cfg.camera_frame, T_bc), (cfg.laser_frame, T_bl)):
        q = rot_to_quat_xyzw(T[:3, :3])
        tfs.append(
            TransformMsg(
                header=Header(t0, cfg.base_frame),
                child_frame_id=child,
                translation=(float(T[0, 3]), float(T[1, 3]), float(T[2, 3])),
                rotation_xyzw=(q[0], q[1], q[2], q[3]),
            )
        )
    add(0, TF_STATIC_TOPIC, t0, TFMsg(transforms=tuple(tfs)))

    for stamp, msg in zip(odom_ns, _odometry(cfg, true_pose, traj, odom_ns, rng_odom), strict=True):
        add(3, ODOM_TOPIC, stamp, msg)

    # Laser: exact ray cast against the walls plus Gaussian range noise.
    for stamp in scan_ns:
        add(4, SCAN_TOPIC, stamp, laser_scan(cfg, world.walls, traj, stamp, rng_scan))

    # Camera.
    K, D = cam.K, cam.D
    P_mat = np.hstack([K, np.zeros((3, 1))])
    frames_gt: list[dict[str, Any]] = []
    topic_img = image_topic(cfg)
    for index, stamp in enumerate(cam_ns):
        x, y, yaw = true_pose(stamp)
        T_wc = planar_T(x, y, yaw) @ T_bc
        blur_dir = (1.0, 0.0)
        if cfg.motion_blur_px > 0:
            before, after = (true_pose(stamp + d) for d in (-10_000_000, 10_000_000))
            blur_dir = image_motion_direction(cam, planar_T(*before) @ T_bc, planar_T(*after) @ T_bc)
        grey = renderer.render(T_wc, rng_pix, blur_dir)
        add(1, topic_img, stamp, _encode_image(grey, cfg, Header(stamp, cfg.camera_frame)))
        add(
            2,
            CAMERA_INFO_TOPIC,
            stamp,
            CameraInfoMsg(
                header=Header(stamp, cfg.camera_frame),
                width=cam.width,
                height=cam.height,
                D=tuple(float(v) for v in D),
                K=tuple(float(v) for v in K.ravel()),
                R=tuple(float(v) for v in np.eye(3).ravel()),
                P=tuple(float(v) for v in P_mat.ravel()),
            ),
        )
        frames_gt.append({"stamp_ns": stamp, "index": index, "visible_tags": _visible_tags(renderer, T_wc)})

    messages.sort(key=lambda m: (m[0], m[1]))
    pose_stamps = sorted(set(odom_ns) | set(cam_ns) | set(scan_ns))
    poses = []
    for stamp in pose_stamps:
        x, y, yaw = true_pose(stamp)
        poses.append({"stamp_ns": stamp, "x": _r(x), "y": _r(y), "yaw": _r(yaw)})
    x0, y0, yaw0 = true_pose(odom_ns[0])
    gt: dict[str, Any] = {
        "seed": cfg.seed,
        "config": _config_json(cfg),
        "world": {"walls": [[_r(v) for v in w] for w in world.walls], "height_m": world.height_m, "frame": "world"},
        "tags": [
            {
                "id": tag.id,
                "family": TAG_FAMILY,
                "size_m": tag.size_m,
                "position": [_r(v) for v in tag.T_world_tag[:3, 3]],
                "quat_xyzw": [_r(v, 12) for v in rot_to_quat_xyzw(tag.T_world_tag[:3, :3])],
                "wall": tag.wall,
            }
            for tag in world.tags
        ],
        "poses": poses,
        "T_world_odom": _T_list(planar_T(x0, y0, yaw0)),
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "K": [float(v) for v in K.ravel()],
            "D": [float(v) for v in D],
            "distortion_model": "plumb_bob",
            "frame_id": cfg.camera_frame,
        },
        "T_base_camera": _T_list(T_bc),
        "T_base_laser": _T_list(T_bl),
        "noise": {
            "odom_v_sigma_mps": cfg.odom_v_sigma_mps,
            "odom_yaw_rate_sigma_radps": cfg.odom_yaw_rate_sigma_radps,
            "odom_model": "per odometry sample, white: forward increment += N(0, (odom_v_sigma_mps*dt)^2), "
            "yaw increment += N(0, (odom_yaw_rate_sigma_radps*dt)^2); lateral increment exact",
            "laser_range_sigma_m": cfg.laser_range_sigma_m,
            "pixel_noise_sigma": cfg.pixel_noise_sigma,
            "jpeg_quality": cfg.jpeg_quality if cfg.image_format == "jpeg" else None,
        },
        "topics": {
            "image": topic_img,
            "camera_info": CAMERA_INFO_TOPIC,
            "odom": ODOM_TOPIC,
            "scan": SCAN_TOPIC,
            "tf_static": TF_STATIC_TOPIC,
        },
        "conventions": CONVENTIONS,
        "frames": frames_gt,
    }
    if errors := wheel_errors(cfg):
        gt["odometry_errors"] = errors
    return Recording(config=cfg, messages=tuple(m[2] for m in messages), ground_truth=gt)


CONVENTIONS: Final = {
    "world": "z up, origin on the floor at the room's south-west corner; the robot starts at poses[0]",
    "odom": "coincides with base_link at the first odometry stamp (T_world_odom)",
    "camera": "optical frame: z forward, x right, y down",
    "tag": "origin at the black square's centre, z out of the face towards the viewer, "
    "x right and y up as seen by the viewer (OpenCV marker / IPPE_SQUARE frame)",
    "corners": "top-left, top-right, bottom-right, bottom-left of the printed marker (OpenCV aruco order) "
    "= tag-frame (-s/2,s/2),(s/2,s/2),(s/2,-s/2),(-s/2,-s/2); distorted pixels, top-left pixel centre = (0, 0)",
    "T_a_b": "4x4, maps points from frame b to frame a",
    "quaternions": "x, y, z, w",
    "poses": "true base_link in world at every odometry, camera and scan stamp",
}


_NEW_FIELDS: Final = {
    "odom_distance_scale_error": 0.0,
    "odom_yaw_scale_error": 0.0,
    "odom_yaw_bias_rad_per_m": 0.0,
    "odom_cov_scale": 1.0,
    "odom_cov_model": "propagated",
    "corridor_length_m": 10.0,
    "laser_sweep": False,
    "exposure_gain": 1.0,
    "contrast": 1.0,
    "vignetting": 0.0,
    "motion_blur_px": 0.0,
}
"""Fields added after the sample was made: left out of the ground truth's ``config`` at their defaults, so the
ground truth of a run that does not use them stays byte-identical."""


def wheel_errors(cfg: SimConfig) -> dict[str, Any]:
    """The systematic odometry errors and covariance scale applied (empty when there are none)."""
    if (
        cfg.odom_distance_scale_error == 0.0
        and cfg.odom_yaw_scale_error == 0.0
        and cfg.odom_yaw_bias_rad_per_m == 0.0
        and cfg.odom_cov_scale == 1.0
        and cfg.odom_cov_model == "propagated"
    ):
        return {}
    return {
        "distance_scale": 1.0 + cfg.odom_distance_scale_error,
        "yaw_rate_scale": 1.0 + cfg.odom_yaw_scale_error,
        "yaw_bias_rad_per_m": cfg.odom_yaw_bias_rad_per_m,
        "covariance_scale": cfg.odom_cov_scale,
        "covariance_model": cfg.odom_cov_model,
        "model": "per odometry sample, with the true body-frame increments (dx, dy, dyaw): reported forward and "
        "lateral increments = distance_scale * (dx, dy) + white noise on the forward one; reported yaw increment = "
        "yaw_rate_scale * dyaw + yaw_bias_rad_per_m * dx + white noise; the pose covariance is covariance_scale "
        "times the white noise propagated through the motion (covariance_model propagated) or summed on a diagonal "
        "(diagonal: no position-heading terms) (0: all zero), without the systematic part",
    }


def _config_json(cfg: SimConfig) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        if f.name in _NEW_FIELDS and v == _NEW_FIELDS[f.name]:
            continue
        out[f.name] = [list(x) if isinstance(x, tuple) else x for x in v] if isinstance(v, tuple) else v
    return out


def _visible_tags(renderer: _Renderer, T_world_cam: FloatArray) -> list[dict[str, Any]]:
    """Tags whose whole marker is in the image, facing the camera and not hidden by a wall."""
    cam, world = renderer.cam, renderer.world
    T_cw = inv_T(T_world_cam)
    out = []
    for tag in world.tags:
        T_ct = T_cw @ tag.T_world_tag
        R, t = T_ct[:3, :3], T_ct[:3, 3]
        if float(R[:, 2] @ -t) <= 1e-6:
            continue
        half = tag.size_m * 10.0 / 16.0
        outer = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]]) @ R.T + t
        if (outer[:, 2] < 0.1).any():
            continue
        corners_tag = tag_corners_tag_frame(tag.size_m)
        pc = corners_tag @ R.T + t
        if np.hypot(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]).max() > renderer.r_valid:
            continue
        px = project_points(cam, T_ct, corners_tag)
        if (px < 0).any() or (px[:, 0] > cam.width - 1).any() or (px[:, 1] > cam.height - 1).any():
            continue
        # Walls are vertical and full height: occlusion is a 2D question along the tag's width.
        xs = np.linspace(-half, half, 9)
        pts = (tag.T_world_tag @ np.stack([xs, np.zeros(9), np.zeros(9), np.ones(9)]))[:2].T
        origin = T_world_cam[:2, 3]
        t_hit, _, _ = ray_segment_hits(origin, pts - origin, world.walls)
        if (t_hit < 1.0 - 1e-6).any():
            continue
        out.append({"id": tag.id, "corners_px": [_r(v) for v in px.ravel()], "T_camera_tag": _T_list(T_ct)})
    return out


def _encode_image(grey: npt.NDArray[np.uint8], cfg: SimConfig, header: Header) -> ImageMsg:
    h, w = grey.shape
    if cfg.image_format == "jpeg":
        ok, buf = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        data = buf.tobytes()
    elif cfg.image_format == "png":
        ok, buf = cv2.imencode(".png", grey, [cv2.IMWRITE_PNG_COMPRESSION, 6])
        data = buf.tobytes()
    elif cfg.image_format in ("mono8", "bayer_rggb8"):  # a grey scene's mosaic holds its grey at every site
        ok, data = True, grey.tobytes()
    elif cfg.image_format == "yuv422":  # UYVY: U Y0 V Y1, chroma neutral
        uyvy = np.full((h, 2 * w), 128, np.uint8)
        uyvy[:, 1::2] = grey
        ok, data = True, uyvy.tobytes()
    else:
        ok, data = True, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR).tobytes()
    if not ok:
        msg = f"OpenCV could not encode a {cfg.image_format} image"
        raise RuntimeError(msg)
    return ImageMsg(header=header, encoding=cfg.image_format, width=w, height=h, data=data)


def decode_image(msg: ImageMsg) -> npt.NDArray[np.uint8]:
    """Grey uint8 pixels of a simulated image message (any of its formats)."""
    if msg.encoding in ("jpeg", "png"):
        img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_GRAYSCALE)
        return np.asarray(img, dtype=np.uint8)
    arr = np.frombuffer(msg.data, np.uint8)
    if msg.encoding in ("mono8", "bayer_rggb8"):
        return arr.reshape(msg.height, msg.width)
    if msg.encoding == "yuv422":
        return np.ascontiguousarray(arr.reshape(msg.height, 2 * msg.width)[:, 1::2])
    return cv2.cvtColor(arr.reshape(msg.height, msg.width, 3), cv2.COLOR_BGR2GRAY)


# --------------------------------------------------------------------------- writers


def ground_truth_path(bag: Path) -> Path:
    """Where the ground truth of ``bag`` goes: ``<name>.ground_truth.json`` beside it.

    ``<name>`` is the file's stem for a bag file (``.bag``, ``.mcap``, ``.db3``) and the
    folder's name for a ROS 2 bag folder.
    """
    bag = Path(bag)
    name = bag.stem if bag.suffix in (".bag", ".mcap", ".db3") else bag.name
    return bag.parent / f"{name}.ground_truth.json"


_MSGTYPES: Final = {
    ImageMsg: "sensor_msgs/msg/Image",
    CameraInfoMsg: "sensor_msgs/msg/CameraInfo",
    OdometryMsg: "nav_msgs/msg/Odometry",
    ScanMsg: "sensor_msgs/msg/LaserScan",
    TFMsg: "tf2_msgs/msg/TFMessage",
}


def _msgtype(payload: Payload) -> str:
    if isinstance(payload, ImageMsg) and payload.encoding in ("jpeg", "png"):
        return "sensor_msgs/msg/CompressedImage"
    return _MSGTYPES[type(payload)]


class _RosBuilder:
    """Turns simulator messages into rosbags message objects of one typestore."""

    def __init__(self, ros1: bool) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros1
        self.store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.store.types:  # the Noetic store lacks tf2_msgs
            from rosbags.typesys import get_types_from_msg

            msgdef = "geometry_msgs/TransformStamped[] transforms"
            self.store.register(get_types_from_msg(msgdef, "tf2_msgs/msg/TFMessage"))
        self.T = self.store.types
        self.seq: Counter[str] = Counter()

    def header(self, h: Header, topic: str) -> Any:
        stamp = self.T["builtin_interfaces/msg/Time"](
            sec=h.stamp_ns // 1_000_000_000, nanosec=h.stamp_ns % 1_000_000_000
        )
        if self.ros1:
            seq = self.seq[topic]
            self.seq[topic] += 1
            return self.T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=h.frame_id)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=h.frame_id)

    def build(self, topic: str, p: Payload) -> Any:
        T, f64 = self.T, np.float64
        if isinstance(p, ImageMsg):
            hdr = self.header(p.header, topic)
            data = np.frombuffer(p.data, dtype=np.uint8).copy()
            if p.encoding in ("jpeg", "png"):
                return T["sensor_msgs/msg/CompressedImage"](header=hdr, format=p.encoding, data=data)
            return T["sensor_msgs/msg/Image"](
                header=hdr,
                height=p.height,
                width=p.width,
                encoding=p.encoding,
                is_bigendian=0,
                step=p.width * RAW_BYTES_PER_PIXEL[p.encoding],
                data=data,
            )
        if isinstance(p, CameraInfoMsg):
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            arrays = {"D": p.D, "K": p.K, "R": p.R, "P": p.P}
            kw = {(k if self.ros1 else k.lower()): np.asarray(v, dtype=f64) for k, v in arrays.items()}
            return T["sensor_msgs/msg/CameraInfo"](
                header=self.header(p.header, topic),
                height=p.height,
                width=p.width,
                distortion_model="plumb_bob",
                binning_x=0,
                binning_y=0,
                roi=roi,
                **kw,
            )
        if isinstance(p, OdometryMsg):
            q = yaw_to_quat_xyzw(p.yaw)
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=p.x, y=p.y, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            twist = T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=p.vx, y=p.vy, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=p.wz),
            )
            return T["nav_msgs/msg/Odometry"](
                header=self.header(p.header, topic),
                child_frame_id=p.child_frame_id,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=pose, covariance=np.asarray(p.pose_covariance, f64)
                ),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=twist, covariance=np.asarray(p.twist_covariance, f64)
                ),
            )
        if isinstance(p, ScanMsg):
            return T["sensor_msgs/msg/LaserScan"](
                header=self.header(p.header, topic),
                angle_min=p.angle_min,
                angle_max=p.angle_max,
                angle_increment=p.angle_increment,
                time_increment=p.time_increment,
                scan_time=p.scan_time,
                range_min=p.range_min,
                range_max=p.range_max,
                ranges=p.ranges.astype(np.float32),
                intensities=np.zeros(0, dtype=np.float32),
            )
        transforms = [
            T["geometry_msgs/msg/TransformStamped"](
                header=self.header(tf.header, topic),
                child_frame_id=tf.child_frame_id,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](
                        x=tf.translation[0], y=tf.translation[1], z=tf.translation[2]
                    ),
                    rotation=T["geometry_msgs/msg/Quaternion"](
                        x=tf.rotation_xyzw[0], y=tf.rotation_xyzw[1], z=tf.rotation_xyzw[2], w=tf.rotation_xyzw[3]
                    ),
                ),
            )
            for tf in p.transforms
        ]
        return T["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        if self.ros1:
            return bytes(self.store.serialize_ros1(msg, msgtype))
        return bytes(self.store.serialize_cdr(msg, msgtype))


def _topic_types(rec: Recording) -> dict[str, str]:
    types: dict[str, str] = {}
    for m in rec.messages:
        types.setdefault(m.topic, _msgtype(m.payload))
    return types


def _write_ros1(rec: Recording, path: Path, compression: Compression | None) -> None:
    from rosbags.rosbag1 import Writer

    b = _RosBuilder(ros1=True)
    writer = Writer(path)
    if compression is not None:
        writer.set_compression({"bz2": Writer.CompressionFormat.BZ2, "lz4": Writer.CompressionFormat.LZ4}[compression])
    with writer:
        conns = {
            topic: writer.add_connection(
                topic,
                msgtype,
                typestore=b.store,
                callerid="/focusmap_sim",
                latching=1 if topic == TF_STATIC_TOPIC else None,
            )
            for topic, msgtype in _topic_types(rec).items()
        }
        for m in rec.messages:
            msgtype = _msgtype(m.payload)
            writer.write(conns[m.topic], m.stamp_ns, b.serialize(b.build(m.topic, m.payload), msgtype))


def _write_ros2(rec: Recording, path: Path, storage: Literal["sqlite3", "mcap"]) -> None:
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    from rosbags.rosbag2 import StoragePlugin, Writer

    zero = QosTime(sec=0, nsec=0)
    latched = Qos(
        history=QosHistory.KEEP_LAST,
        depth=1,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    b = _RosBuilder(ros1=False)
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {
            topic: writer.add_connection(
                topic, msgtype, typestore=b.store, offered_qos_profiles=[latched] if topic == TF_STATIC_TOPIC else []
            )
            for topic, msgtype in _topic_types(rec).items()
        }
        for m in rec.messages:
            msgtype = _msgtype(m.payload)
            writer.write(conns[m.topic], m.stamp_ns, b.serialize(b.build(m.topic, m.payload), msgtype))


def write_ground_truth(rec: Recording, path: Path) -> Path:
    """Write ``rec.ground_truth`` as compact JSON to ``path``; returns ``path``."""
    path.write_text(json.dumps(rec.ground_truth, separators=(",", ":")) + "\n", encoding="utf-8")
    return path


def truth_yaml_paths(bag: Path) -> tuple[Path, Path]:
    """Where the ground truth of ``bag`` goes in focusmap's hand-writable format: ``<name>.truth.yaml`` and the
    ``<name>.truth.tum`` it names (``<name>`` as in :func:`ground_truth_path`)."""
    json_path = ground_truth_path(bag)
    name = json_path.name.removesuffix(".ground_truth.json")
    return json_path.with_name(f"{name}.truth.yaml"), json_path.with_name(f"{name}.truth.tum")


def write_truth_yaml(rec: Recording, yaml_path: Path, tum_path: Path) -> Path:
    """Write the walls, tags and true poses of ``rec`` as a truth YAML (tags and walls inline) and a TUM file.

    The format is focusmap's ground-truth file (``docs/evaluate.md``, "Ground truth file"): what a user writes by
    hand for their own recording. The numbers are those of the JSON, so both read as the same truth.
    """
    gt = rec.ground_truth
    lines = [
        f"# Ground truth of a simulated recording (seed {gt.get('seed')}); docs/evaluate.md, 'Ground truth file'.",
        "frame: world  # z up, origin on the floor at the room's south-west corner",
        f"poses: {tum_path.name}  # TUM: stamp_s x y z qx qy qz qw, the base_link in world",
        "tags:  # id x y z, m (tag centres)",
        *(f"  - {json.dumps([int(t['id']), *[float(v) for v in t['position']]])}" for t in gt["tags"]),
        "walls:  # x0 y0 x1 y1, m",
        *(f"  - {json.dumps([float(v) for v in w])}" for w in gt["world"]["walls"]),
    ]
    yaml_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    tum = ["# stamp_s x y z qx qy qz qw"]
    for p in gt["poses"]:
        ns, half = int(p["stamp_ns"]), float(p["yaw"]) / 2
        tum.append(
            f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} {float(p['x'])!r} {float(p['y'])!r} 0.0 "
            f"0.0 0.0 {math.sin(half)!r} {math.cos(half)!r}"
        )
    tum_path.write_text("\n".join(tum) + "\n", encoding="utf-8")
    return yaml_path


def write_bag(
    rec: Recording,
    path: Path,
    fmt: BagFormat,
    compression: Compression | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a recording as a bag and its ground truth beside it: the JSON (:func:`ground_truth_path`) and the
    same truth as focusmap's truth YAML with its TUM poses (:func:`truth_yaml_paths`).

    Args:
        rec: the simulated recording.
        path: the bag to create: a ``.bag`` file (ros1), a folder (ros2-sqlite,
            ros2-mcap) or a ``.mcap`` file (mcap: the MCAP storage file alone).
        fmt: ``ros1``, ``ros2-sqlite``, ``ros2-mcap`` or ``mcap``.
        compression: ROS 1 chunk compression, ``bz2`` or ``lz4`` (ros1 only).
        overwrite: replace an existing bag (and ground truth) instead of refusing.

    Returns:
        The path of the bag.
    """
    path = Path(path)
    if fmt not in BAG_FORMATS:
        msg = f"unknown bag format {fmt!r}; expected one of {BAG_FORMATS}"
        raise ValueError(msg)
    if compression is not None and (fmt != "ros1" or compression not in ("bz2", "lz4")):
        msg = f"compression {compression!r} is only available for ros1 (bz2 or lz4), not for {fmt}"
        raise ValueError(msg)
    suffix = {"ros1": ".bag", "mcap": ".mcap"}.get(fmt)
    if suffix is not None and path.suffix != suffix:
        msg = f"a {fmt} bag must be named *{suffix}, got {path.name!r}"
        raise ValueError(msg)
    if path.exists():
        if not overwrite:
            msg = f"{path} exists already; pass overwrite=True (--force) to replace it"
            raise FileExistsError(msg)
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "ros1":
        _write_ros1(rec, path, compression)
    elif fmt == "ros2-sqlite":
        _write_ros2(rec, path, "sqlite3")
    elif fmt == "ros2-mcap":
        _write_ros2(rec, path, "mcap")
    else:
        with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
            folder = Path(tmp) / path.stem
            _write_ros2(rec, folder, "mcap")
            (mcap_file,) = folder.glob("*.mcap")
            shutil.move(mcap_file, path)
    write_ground_truth(rec, ground_truth_path(path))
    write_truth_yaml(rec, *truth_yaml_paths(path))
    return path


# --------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    """Command line: simulate a run and write it as a bag plus ground truth."""
    parser = argparse.ArgumentParser(prog="python -m sample_data.simulate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--name", default="office", help="bag name (file stem or ROS 2 folder name)")
    parser.add_argument("--format", choices=BAG_FORMATS, default="ros1", dest="fmt")
    parser.add_argument("--compression", choices=("bz2", "lz4"), default=None, help="ROS 1 chunk compression")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=None, help="seconds (default: the whole path)")
    parser.add_argument("--path", choices=("office", "corridor", "corridor_return"), default="office")
    parser.add_argument("--image-format", choices=IMAGE_FORMATS, default="jpeg")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--camera-rate", type=float, default=5.0, help="Hz")
    parser.add_argument("--corridor-length", type=float, default=10.0, help="corridor length behind the door, m")
    parser.add_argument(
        "--laps", type=int, default=1, help="corridor_return: drive there and back this many times (longer recordings)"
    )
    wheel = parser.add_argument_group("systematic wheel odometry errors (default: none)")
    wheel.add_argument(
        "--odom-distance-scale-error", type=float, default=0.0, help="reported distance = (1 + this) x driven"
    )
    wheel.add_argument("--odom-yaw-scale-error", type=float, default=0.0, help="reported turn = (1 + this) x turned")
    wheel.add_argument("--odom-yaw-bias", type=float, default=0.0, help="yaw added per metre driven forwards, rad/m")
    wheel.add_argument(
        "--odom-cov-scale",
        type=float,
        default=1.0,
        help="reported pose covariance = this x the propagated white noise (< 1: too small; 0: all zero)",
    )
    wheel.add_argument(
        "--odom-cov-model",
        choices=("propagated", "diagonal"),
        default="propagated",
        help="how the reported pose covariance grows: through the motion (propagated) or summed on a diagonal "
        "without position-heading terms (diagonal, as some drivers report it)",
    )
    noise = parser.add_argument_group("sensor noise (default: the sample's)")
    noise.add_argument(
        "--pixel-noise",
        type=float,
        default=SimConfig.pixel_noise_sigma,
        help="Gaussian pixel noise, grey levels (the tags' corner noise, so their measurement noise, grows with it)",
    )
    noise.add_argument(
        "--odom-noise-scale",
        type=float,
        default=1.0,
        help="multiply the odometry's white speed and yaw-rate noise (and so its reported covariance) by this",
    )
    look = parser.add_argument_group("rendering (default: the sample's)")
    look.add_argument("--jpeg-quality", type=int, default=SimConfig.jpeg_quality, help="JPEG quality, 1-100")
    look.add_argument(
        "--distortion",
        type=float,
        nargs=5,
        metavar=("K1", "K2", "P1", "P2", "K3"),
        default=SimConfig.distortion,
        help="plumb_bob lens distortion (e.g. -0.28 0.07 0 0 0: strong barrel)",
    )
    look.add_argument(
        "--exposure", type=float, default=1.0, help="scene brightness gain before the pixel noise (< 1: darker)"
    )
    look.add_argument(
        "--contrast", type=float, default=1.0, help="grey levels pulled towards 128 by this factor (< 1: flatter)"
    )
    look.add_argument(
        "--vignetting", type=float, default=0.0, help="light lost in the image corners, 0-1 (quadratic in radius)"
    )
    look.add_argument(
        "--motion-blur",
        type=float,
        default=0.0,
        help="length of a linear blur per frame along the image motion, px (0: none)",
    )
    look.add_argument(
        "--tag-size", type=float, default=SimConfig.tag_size_m, help="edge of every tag's black square, m"
    )
    rig = parser.add_argument_group("rig (default: the sample's)")
    rig.add_argument(
        "--camera-xyz",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        default=SimConfig.camera_xyz_m,
        help="camera optical centre in base_link, m (the tags hang at its height)",
    )
    rig.add_argument(
        "--camera-yaw",
        type=float,
        default=SimConfig.camera_yaw_deg,
        help="camera yaw left of the robot's forward axis, degrees (90: looking left, 180: backwards)",
    )
    rig.add_argument(
        "--laser-xyz",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        default=SimConfig.laser_xyz_m,
        help="laser centre in base_link, m",
    )
    parser.add_argument(
        "--laser-sweep",
        action="store_true",
        help="cast each laser beam at its own time over the scan period (time_increment > 0; default: all at once)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing bag")
    args = parser.parse_args(argv)
    cfg = SimConfig(
        seed=args.seed,
        path=args.path,
        duration_s=args.duration,
        image_format=args.image_format,
        image_width=args.width,
        image_height=args.height,
        camera_rate_hz=args.camera_rate,
        corridor_length_m=args.corridor_length,
        laps=args.laps,
        odom_distance_scale_error=args.odom_distance_scale_error,
        odom_yaw_scale_error=args.odom_yaw_scale_error,
        odom_yaw_bias_rad_per_m=args.odom_yaw_bias,
        odom_cov_scale=args.odom_cov_scale,
        odom_cov_model=args.odom_cov_model,
        laser_sweep=args.laser_sweep,
        pixel_noise_sigma=args.pixel_noise,
        jpeg_quality=args.jpeg_quality,
        distortion=tuple(args.distortion),
        exposure_gain=args.exposure,
        contrast=args.contrast,
        vignetting=args.vignetting,
        motion_blur_px=args.motion_blur,
        tag_size_m=args.tag_size,
        camera_xyz_m=tuple(args.camera_xyz),
        camera_yaw_deg=args.camera_yaw,
        laser_xyz_m=tuple(args.laser_xyz),
        odom_v_sigma_mps=SimConfig.odom_v_sigma_mps * args.odom_noise_scale,
        odom_yaw_rate_sigma_radps=SimConfig.odom_yaw_rate_sigma_radps * args.odom_noise_scale,
    )
    suffix = {"ros1": ".bag", "mcap": ".mcap"}.get(args.fmt, "")
    out = args.out / f"{args.name}{suffix}"
    try:
        rec = simulate(cfg)
        write_bag(rec, out, args.fmt, args.compression, overwrite=args.force)
    except (ValueError, FileExistsError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {out}, {ground_truth_path(out)} and {truth_yaml_paths(out)[0]} (+ .tum)")
    for topic, n in rec.counts().items():
        print(f"  {topic}: {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
