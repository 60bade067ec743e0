"""``graph.model: auto``: the planar model when the run's motion is planar, the 3D model otherwise, and why.

The planar model (Pose2 poses, Point2 tags) is right for a wheeled robot on a flat floor: it has fewer unknowns
and its odometry and tag factors hold exactly there. It is wrong when the camera moves in 3D: a handheld
camera-only recording (TagSLAM's ``test_1``) is 0.66 m off with it and 0.032 m with the 3D model. The motion
is taken as planar when every one of these holds:

- the run has odometry (a camera-only run has no wheels that keep it on a floor);
- the odometry's height stays within :data:`MAX_HEIGHT_RANGE_M` and its roll and pitch within
  :data:`MAX_TILT_RAD` of the first message's;
- seen from the base, each tag's height and tilt stay the same over its sightings (the median over the tags
  of their spread is within :data:`MAX_TAG_HEIGHT_SPREAD_M` and :data:`MAX_TAG_TILT_SPREAD_RAD`): a fixed tag
  keeps its height above a base that moves in a plane, even when the odometry reports a flat world it is not in.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np

from stages.detect.artifacts import CAMERA, T_CAMERA_TAG
from stages.geometry import pose3_from_matrix
from stages.graph.odometry import Odometry

MAX_HEIGHT_RANGE_M = 0.10
"""Odometry heights spanning more than this (max - min over the run) make the motion 3D, m."""
MAX_TILT_RAD = float(np.radians(5.0))
"""Odometry roll or pitch leaving the first message's by more than this makes the motion 3D, rad."""
MAX_TAG_HEIGHT_SPREAD_M = 0.08
"""Median over the tags of the standard deviation of a tag's height in the base frame over its sightings, m."""
MAX_TAG_TILT_SPREAD_RAD = float(np.radians(8.0))
"""Median over the tags of the RMS angle between a tag's sightings of the base's up axis (in the tag frame), rad."""
MIN_SIGHTINGS = 3
"""Tags seen fewer times do not enter the tag statistics."""


@dataclass(frozen=True)
class ModelChoice:
    """The graph model to build and why (``graph.model`` and the figures ``auto`` decided on)."""

    model: str
    setting: str
    reason: str
    figures: dict[str, Any]

    def summary(self) -> dict[str, Any]:
        """The ``model_choice`` block of the graph summary."""
        return {"setting": self.setting, "model": self.model, "reason": self.reason, **self.figures}

    @property
    def note(self) -> str:
        """One line naming the model and why (printed as a ``note:`` when ``auto`` chose it)."""
        return f"graph model {self.model} (graph.model={self.setting}): {self.reason}"


def choose_model(
    setting: str,
    odom: Odometry | None,
    det: dict[str, list[Any]],
    usable: np.ndarray,
    extrinsic_of: Callable[[str], gtsam.Pose3],
    tag_ids: list[Any],
) -> ModelChoice:
    """The model of ``setting`` (``planar``, ``3d`` or ``auto``); ``auto`` decides from the odometry and the usable
    detections (``det`` columns, ``usable`` row indices, ``tag_ids`` the tag id column, ``extrinsic_of`` a
    camera's ``T_base_camera``)."""
    if setting != "auto":
        return ModelChoice(setting, setting, "set in the settings", {})
    if odom is None:
        return ModelChoice("3d", setting, "the run has no odometry, so nothing keeps the camera on a plane", {})
    figures = {**_odometry_figures(odom), **_tag_figures(det, usable, extrinsic_of, tag_ids)}
    why = []
    if figures["odometry_height_range_m"] > MAX_HEIGHT_RANGE_M:
        why.append(f"the odometry's height spans {figures['odometry_height_range_m']:.2f} m")
    if figures["odometry_tilt_deg"] > np.degrees(MAX_TILT_RAD):
        why.append(f"the odometry tilts by {figures['odometry_tilt_deg']:.1f} deg")
    h, tilt = figures.get("tag_height_spread_m"), figures.get("tag_tilt_spread_deg")
    if h is not None and h > MAX_TAG_HEIGHT_SPREAD_M:
        why.append(f"tags seen from the base change height by {h:.3f} m (median std)")
    if tilt is not None and tilt > np.degrees(MAX_TAG_TILT_SPREAD_RAD):
        why.append(f"tags seen from the base change tilt by {tilt:.1f} deg (median)")
    if why:
        return ModelChoice("3d", setting, "the motion is not planar: " + "; ".join(why), figures)
    spread = "" if h is None else f", tags keep their height ({h:.3f} m median std) and tilt ({tilt:.1f} deg)"
    reason = (
        f"planar motion: odometry height within {figures['odometry_height_range_m']:.3f} m and tilt within "
        f"{figures['odometry_tilt_deg']:.1f} deg{spread}"
    )
    return ModelChoice("planar", setting, reason, figures)


def _odometry_figures(odom: Odometry) -> dict[str, float]:
    """Height range and largest roll/pitch change (relative to the first message) of the odometry."""
    z = np.array([float(p.translation()[2]) for p in odom.poses])
    R0 = odom.poses[0].rotation()
    tilt = 0.0
    for p in odom.poses:
        up = np.asarray(R0.between(p.rotation()).matrix())[:, 2]  # the body's up axis in the first body's frame
        tilt = max(tilt, float(np.arccos(np.clip(up[2], -1.0, 1.0))))
    return {"odometry_height_range_m": round(float(np.ptp(z)), 4), "odometry_tilt_deg": round(np.degrees(tilt), 3)}


def _tag_figures(
    det: dict[str, list[Any]], usable: np.ndarray, extrinsic_of: Callable[[str], gtsam.Pose3], tag_ids: list[Any]
) -> dict[str, Any]:
    """Median over the tags of the spread of their height and of the base's up axis in their frame."""
    cache: dict[str, gtsam.Pose3] = {}
    heights: dict[int, list[float]] = {}
    ups: dict[int, list[np.ndarray]] = {}
    for r in usable:
        cam = str(det[CAMERA][r])
        if cam not in cache:
            cache[cam] = extrinsic_of(cam)
        T = np.asarray(cache[cam].compose(pose3_from_matrix(det[T_CAMERA_TAG][r])).matrix())
        tag = int(tag_ids[r])
        heights.setdefault(tag, []).append(float(T[2, 3]))
        ups.setdefault(tag, []).append(T[2, :3])  # the base's up axis in the tag frame
    h_spread, tilt_spread = [], []
    for tag, hs in heights.items():
        if len(hs) < MIN_SIGHTINGS:
            continue
        h_spread.append(float(np.std(hs)))
        u = np.array(ups[tag])
        mean = u.mean(axis=0)
        mean /= max(float(np.linalg.norm(mean)), 1e-12)
        ang = np.arccos(np.clip(u @ mean, -1.0, 1.0))
        tilt_spread.append(float(np.sqrt(np.mean(ang**2))))
    if not h_spread:
        return {"tags_compared": 0}
    return {
        "tags_compared": len(h_spread),
        "tag_height_spread_m": round(float(np.median(h_spread)), 4),
        "tag_tilt_spread_deg": round(float(np.degrees(np.median(tilt_spread))), 3),
    }
