"""Extrinsics files: where each camera sits on the rig, read from TagSLAM, Kalibr or a plain YAML of matrices.

Every reader returns ``T_base_frame`` per entry: the 4x4 rigid transform that maps a point given in the
entry's frame (a camera's optical frame) into the file's base frame. That is the direction of ``/tf_static``
(parent = base, child = sensor) and of ``extrinsics.json``'s ``T_base_sensor``. The conventions of the files:

- **TagSLAM** ``camera_poses.yaml``: ``camN: {pose: {position: {x, y, z}, rotation: {x, y, z}}}`` is the pose
  of camera N in the rig body (TagSLAM's ``T_rig_cam``), the rotation an angle-axis vector (angle = its norm, in
  radians). TagSLAM's own ``kalibr_to_camera_poses.py`` writes it as the inverse of Kalibr's ``T_cn_w``, so it
  maps camera points into the rig: it is ``T_base_frame`` as it stands. Base frame: ``rig``.
- **Kalibr** camchain (``camchain.yaml``, ``camchain-imucam.yaml``): ``T_cam_imu`` maps IMU points into the
  camera and ``T_cn_cnm1`` maps points of the previous camera (N-1) into camera N: both are ``T_frame_base``
  style and are inverted here. When ``cam0`` has ``T_cam_imu`` the base is the IMU (``T_imu_camN`` =
  ``T_camN_imu``⁻¹, or down the chain ``T_camN_imu = T_cn_cnm1 T_cnm1_imu`` for a camera without its own);
  otherwise the base is ``cam0`` (``T_cam0_camN`` = (``T_cn_cnm1`` ··· ``T_c1_c0``)⁻¹).
- **Plain**: ``frame: 4x4`` (4 rows of 4, or 16 numbers row-major), each ``T_base_frame``; an optional
  ``base_frame: NAME`` names the base (default ``base``).

An entry is matched to a camera by its name (``cam1``), its frame id, or its image or detections topic.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from pipeline.errors import InputError

FloatArray = npt.NDArray[np.float64]


@dataclass
class ExtrinsicsFile:
    """The transforms of one extrinsics file: ``T_base_frame`` per entry name, and what the file was."""

    path: str
    kind: str
    """``tagslam camera_poses``, ``kalibr camchain`` or ``4x4 matrices``."""
    base_frame: str
    mounts: dict[str, FloatArray] = field(default_factory=dict)
    via: str = ""
    """How the file's transforms were changed before use (appended to each mount's source), e.g. by a tags file."""
    information: dict[str, FloatArray] = field(default_factory=dict)
    """Per entry whose TagSLAM ``R`` is given: the mount's 6x6 information ``RᵀR`` (``R`` is gtsam's square-root
    information; tangent order rotation, translation, right perturbation, so moving the mount into another base
    leaves it unchanged)."""

    def find(self, *names: str | None) -> tuple[str, FloatArray] | None:
        """The first entry named by one of ``names`` (a camera name, frame id or topic), with its name."""
        for name in names:
            if name and name in self.mounts:
                return name, self.mounts[name]
        return None


def rotation_from_rotvec(v: Any) -> FloatArray:
    """The rotation matrix of an angle-axis vector (Rodrigues' formula; angle = the vector's norm)."""
    w = np.asarray(v, float).reshape(3)
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def invert(T: FloatArray) -> FloatArray:
    """The inverse of a rigid 4x4 transform."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def _rigid(value: Any, where: str) -> FloatArray:
    """A 4x4 rigid transform from 4 rows of 4 or 16 numbers; InputError naming ``where`` otherwise."""
    try:
        T = np.asarray(value, float).reshape(4, 4)
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: expected a 4x4 matrix (4 rows of 4 numbers or 16 numbers)") from err
    R = T[:3, :3]
    if not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise InputError(f"{where}: not a rigid transform (last row must be 0 0 0 1)")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise InputError(f"{where}: its rotation part is not a rotation (R R^T != I or det < 0)")
    return T


def _xyz(node: Any, where: str) -> FloatArray:
    try:
        return np.array([float(node[k]) for k in ("x", "y", "z")])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{where}: needs x, y and z numbers") from err


def _information(value: Any, where: str) -> FloatArray:
    """TagSLAM's ``R``: 36 numbers, gtsam's square-root information of the mount (upper triangular as TagSLAM writes
    it, from ``noiseModel::Gaussian::R()``): the information is ``RᵀR``, which must be positive definite."""
    try:
        R = np.asarray(value, dtype=float).reshape(6, 6)
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: expected 36 numbers (a 6x6 square-root information matrix)") from err
    if not np.all(np.isfinite(R)):
        raise InputError(f"{where}: the 6x6 square-root information matrix has a value that is not a number")
    information = R.T @ R
    if float(np.linalg.eigvalsh(information).min()) <= 1e-12 * float(np.abs(information).max() or 1.0):
        raise InputError(f"{where}: the 6x6 square-root information matrix is singular (a direction with no noise)")
    return information


def _tagslam(doc: dict[str, Any], path: str) -> ExtrinsicsFile:
    mounts = {}
    information = {}
    for name, entry in doc.items():
        pose = entry.get("pose") if isinstance(entry, dict) else None
        if not isinstance(pose, dict):
            raise InputError(f"{path!r} {name}: a TagSLAM camera_poses entry needs pose: {{position, rotation}}")
        T = np.eye(4)
        T[:3, :3] = rotation_from_rotvec(_xyz(pose.get("rotation"), f"{path!r} {name}.pose.rotation"))
        T[:3, 3] = _xyz(pose.get("position"), f"{path!r} {name}.pose.position")
        mounts[str(name)] = T
        if pose.get("R") is not None:
            information[str(name)] = _information(pose["R"], f"{path!r} {name}.pose.R")
    return ExtrinsicsFile(path, "tagslam camera_poses", "rig", mounts, information=information)


def _kalibr(doc: dict[str, Any], path: str) -> ExtrinsicsFile:
    cams = sorted((str(n), c) for n, c in doc.items() if isinstance(c, dict) and str(n).startswith("cam"))
    if not cams:
        raise InputError(f"{path!r}: a Kalibr camchain needs cam0, cam1, ... entries")
    on_imu = "T_cam_imu" in cams[0][1]
    T_cam_base: dict[str, FloatArray] = {}
    previous: FloatArray | None = None
    for i, (name, cam) in enumerate(cams):
        where = f"{path!r} {name}"
        if on_imu and "T_cam_imu" in cam:
            T = _rigid(cam["T_cam_imu"], f"{where}.T_cam_imu")
        elif i == 0:
            T = np.eye(4)
        elif "T_cn_cnm1" in cam and previous is not None:
            T = _rigid(cam["T_cn_cnm1"], f"{where}.T_cn_cnm1") @ previous
        else:
            raise InputError(f"{where}: needs T_cn_cnm1 (or T_cam_imu) to place it in the chain")
        T_cam_base[name] = previous = T
    mounts = {name: invert(T) for name, T in T_cam_base.items()}
    return ExtrinsicsFile(path, "kalibr camchain", "imu" if on_imu else cams[0][0], mounts)


def _plain(doc: dict[str, Any], path: str) -> ExtrinsicsFile:
    base = str(doc.get("base_frame", "base"))
    mounts = {str(n): _rigid(v, f"{path!r} {n}") for n, v in doc.items() if n != "base_frame"}
    if not mounts:
        raise InputError(f"{path!r}: no frame: 4x4 entries")
    return ExtrinsicsFile(path, "4x4 matrices", base, mounts)


def load_extrinsics_file(path: Path) -> ExtrinsicsFile:
    """Read a TagSLAM ``camera_poses.yaml``, a Kalibr camchain or a plain ``frame: 4x4`` YAML.

    Raises:
        InputError: unreadable file, unknown layout, or a transform that is not rigid.
    """
    name = str(path)
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        reason = "not UTF-8 text" if isinstance(err, UnicodeDecodeError) else str(err)
        raise InputError(f"extrinsics file {name!r} cannot be read as YAML ({reason})") from err
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"extrinsics file {name!r} is not a YAML mapping of frames")
    entries = [v for k, v in doc.items() if k != "base_frame"]
    if all(isinstance(v, dict) and "pose" in v for v in entries):
        return _tagslam(doc, name)
    if any(isinstance(v, dict) and ("T_cam_imu" in v or "T_cn_cnm1" in v) for v in entries):
        return _kalibr(doc, name)
    if all(isinstance(v, list) for v in entries):
        return _plain(doc, name)
    raise InputError(
        f"extrinsics file {name!r} is none of: TagSLAM camera_poses.yaml (camN: pose: position, rotation), "
        "Kalibr camchain (T_cam_imu, T_cn_cnm1), or frame: 4x4 T_base_frame"
    )
