"""TagSLAM's ``tagslam.yaml``: tag sizes, ignored tags, surveyed tag poses and the odometry body's mount.

What is read (TagSLAM's meaning, from its ``body.cpp``, ``tag.cpp`` and ``odometry_processor.cpp``):

- **Sizes.** Each body's ``default_tag_size`` is the edge of its tags' black square; an entry of its ``tags``
  list may give its own ``size``. The run's default size is the ``default_body``'s (else the first body's that
  gives one); every tag a ``tags`` list names is listed with its size (its own, else its body's default).
- **Ignored tags.** Each body's ``ignore_tags``; their union is left out of the graph.
- **Moving bodies.** The tags of a body with ``is_static: false`` (its ``tags`` list, or a ``type: board``'s
  ``board: {tag_start_id, tag_rows, tag_columns}`` grid) move with it: a wand, a cube, a board carried around,
  or tags on the camera rig itself. A landmark must stay put, so they are left out of the graph (its summary
  names the body, its tags and the detections left out).
- **Camera rig.** The body a ``cameras.yaml`` entry names as its ``rig_body`` (else a body of the old
  ``type: camera_rig``) carries the cameras. focusmap maps static tags from the motion of that rig: a rig with
  ``is_static: true`` (fixed cameras watching a moving object, TagSLAM's "aviary") is refused before anything
  runs (:func:`camera_rig_problem`). The rig body is also the base frame of a TagSLAM ``camera_poses.yaml``.
- **Known tags.** A tag entry with a ``pose`` on a *static* body that has a ``pose`` of its own is a surveyed
  landmark: ``T_world_tag = T_world_body T_body_tag``, each pose ``{position: {x, y, z}, rotation: {x, y, z}}``
  with the rotation an angle-axis vector (radians; ``rotvec`` is read as well). Its noise is TagSLAM's
  ``PriorFactor<Pose3>`` noise: ``rotation_noise`` and ``position_noise`` are sigmas (rad, m) in gtsam's local
  (tag) frame, tangent order (rotation, translation). A body with both ``override_tag_position_noise`` and
  ``override_tag_rotation_noise`` above 0 gives all its tags those isotropic sigmas instead, as TagSLAM does.
  The body's own pose noise is carried into the tag frame (``Ad(T_tag_body) Σ_body Ad^T``) and added.
- **Tag frame.** TagSLAM's tag frame (``tag.cpp``: object corners ``(-s/2, -s/2)``, ``(s/2, -s/2)``,
  ``(s/2, s/2)``, ``(-s/2, s/2)`` for a detection's corners 0 to 3, z out of the printed face) is focusmap's
  (detect's tag frame, with a bag's corners in the ``apriltag`` order, the default of ``detect.bag_corner_order``)
  turned 180° about its z axis: the same corner sits at ``(x, y)`` in one and ``(-x, -y)`` in the other. A
  surveyed pose is turned into focusmap's frame, ``T_world_tag = T_world_tag(TagSLAM) Rz(π)``, and its
  covariance with it. (Read as it stands, each surveyed tag turned the whole map 180° about the tag's normal:
  on TagSLAM's test_1, test_2 and test_21 the trajectory was 1.5 to 3.6 m from TagSLAM's in its world frame
  and matched it only after a 180° rotation; with more than one surveyed tag, test_10, the priors fought.)
- **Odometry mount.** ``T_body_odom`` of a body (``{position, rotation}``) is TagSLAM's transform from the
  frame the odometry is computed in to the body: TagSLAM turns consecutive odometry poses ``P`` (``T_world_odom``)
  into the body's motion ``T_body_odom P_prev⁻¹ P_next T_body_odom⁻¹``, i.e. ``T_world_body = P T_body_odom⁻¹``,
  so ``T_body_odom`` maps points of the odometry frame into the body (rig) frame: the pose of the odometry frame
  in the rig. focusmap's base is the odometry's child frame, so a camera placed in the rig at ``T_rig_cam``
  (``camera_poses.yaml``) sits at ``T_base_cam = T_body_odom⁻¹ T_rig_cam``.

- **Duplicate ids.** ``tag_id_remap: [{id, remaps: [{remap_id, start_time, end_time, camera}]}]``: a detection
  of tag ``id`` stamped within ``[start_time, end_time]`` (seconds of the header stamps), by ``camera`` when given
  (a cameras.yaml name such as ``cam0``, matched to the camera's frame id or topic), is tag ``remap_id``: two
  printed tags that share an id in different places.

Read and listed as not used: ``squash``, ``plane_measurements``, ``distance_measurements``,
``position_measurements``, ``coordinate_measurements`` (TagSLAM features focusmap does not have).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from pipeline.errors import InputError
from stages.extrinsics import rotation_from_rotvec

FloatArray = npt.NDArray[np.float64]

UNUSED_SECTIONS = (
    "squash",
    "plane_measurements",
    "distance_measurements",
    "position_measurements",
    "coordinate_measurements",
)
"""Top-level sections of a tagslam.yaml that focusmap reads past (named in the ingest notes when present)."""


@dataclass
class KnownTagPose:
    """A surveyed tag: its pose (focusmap's tag frame) in TagSLAM's world frame and the 6x6 covariance of its prior."""

    tag_id: int
    body: str
    T_world_tag: FloatArray
    covariance: FloatArray
    """6x6, gtsam's Pose3 tangent order (rx, ry, rz, tx, ty, tz) in the tag frame, rad² and m²."""
    rotation_sigma_rad: list[float]
    position_sigma_m: list[float]
    """The tag entry's own sigmas (or the body's override), before the body's pose noise is added."""


@dataclass
class TagRemap:
    """Detections of ``tag_id`` in a time window (by one camera, when given) are of tag ``remap_id``."""

    tag_id: int
    remap_id: int
    start_ns: int
    end_ns: int
    camera: str | None = None


@dataclass
class TagsFile:
    """What a TagSLAM ``tagslam.yaml`` says about the tags and the odometry."""

    path: str
    default_tag_size_m: float | None = None
    tag_sizes_m: dict[int, float] = field(default_factory=dict)
    ignore_tags: list[int] = field(default_factory=list)
    known_tags: list[KnownTagPose] = field(default_factory=list)
    odometry_body: str | None = None
    T_body_odom: FloatArray | None = None
    odometry_topic: str | None = None
    remaps: list[TagRemap] = field(default_factory=list)
    moving_tags: dict[str, list[int]] = field(default_factory=dict)
    """Per body with ``is_static: false``, the ids of its tags (left out of the graph: they move)."""
    static: dict[str, bool] = field(default_factory=dict)
    """Each body's ``is_static`` (absent: not given)."""
    camera_rig_bodies: list[str] = field(default_factory=list)
    """Bodies of the old ``type: camera_rig``: the rig when a cameras.yaml names none."""
    notes: list[str] = field(default_factory=list)


def _mapping(node: Any, where: str) -> dict[str, Any]:
    if not isinstance(node, dict):
        raise InputError(f"{where}: expected a mapping, got {type(node).__name__}")
    return node


def _xyz(node: Any, where: str) -> FloatArray:
    try:
        out = np.array([float(node[k]) for k in ("x", "y", "z")])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{where}: needs x, y and z numbers") from err
    if not np.all(np.isfinite(out)):
        raise InputError(f"{where}: x, y and z must be finite")
    return out


def _number(node: Any, where: str, positive: bool = True) -> float:
    try:
        value = float(node)
    except (TypeError, ValueError) as err:
        raise InputError(f"{where}: expected a number, got {node!r}") from err
    if not np.isfinite(value) or (positive and value <= 0):
        raise InputError(f"{where}: expected a positive number, got {node!r}")
    return value


def _transform(node: Any, where: str) -> FloatArray:
    """A ``{position, rotation}`` (or ``rotvec``) pose as a 4x4 transform."""
    pose = _mapping(node, where)
    rotation = pose.get("rotation", pose.get("rotvec"))
    T = np.eye(4)
    T[:3, :3] = rotation_from_rotvec(_xyz(rotation, f"{where}.rotation"))
    T[:3, 3] = _xyz(pose.get("position"), f"{where}.position")
    return T


def _sigmas(pose: dict[str, Any], where: str) -> tuple[FloatArray, FloatArray] | None:
    """(rotation, position) sigmas of a pose, None when it gives neither."""
    if "rotation_noise" not in pose and "position_noise" not in pose:
        return None
    rot = _xyz(pose.get("rotation_noise"), f"{where}.rotation_noise")
    pos = _xyz(pose.get("position_noise"), f"{where}.position_noise")
    if np.any(rot <= 0) or np.any(pos <= 0):
        raise InputError(f"{where}: rotation_noise and position_noise must be positive sigmas")
    return rot, pos


def adjoint(T: FloatArray) -> FloatArray:
    """gtsam's Pose3 adjoint of ``T`` in (rotation, translation) order: ``Exp(Ad ξ) = T Exp(ξ) T⁻¹``."""
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = tx @ R
    return A


TAGSLAM_TAG_TO_FOCUSMAP_TAG = np.diag([-1.0, -1.0, 1.0, 1.0])
"""``T_tagslamtag_tag``: focusmap's tag frame in TagSLAM's, a half turn about the tag's normal (module docstring)."""


def _bodies(doc: dict[str, Any], name: str) -> list[tuple[str, dict[str, Any]]]:
    bodies = doc.get("bodies")
    if not isinstance(bodies, list) or not bodies:
        raise InputError(f"tags file {name!r} has no bodies: list (TagSLAM tagslam.yaml)")
    out = []
    for i, entry in enumerate(bodies):
        if not isinstance(entry, dict) or len(entry) != 1:
            raise InputError(f"{name!r} bodies[{i}]: expected one 'name: {{...}}' mapping per body")
        ((body, spec),) = entry.items()
        out.append((str(body), _mapping(spec, f"{name!r} body {body}")))
    return out


def load_tags_file(path: Path) -> TagsFile:
    """Read a TagSLAM ``tagslam.yaml`` (see the module docstring for what is read and how).

    Raises:
        InputError: unreadable file, no bodies, or a malformed size, pose or noise.
    """
    name = str(path)
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        reason = "not UTF-8 text" if isinstance(err, UnicodeDecodeError) else str(err).splitlines()[0]
        raise InputError(f"tags file {name!r} cannot be read as YAML ({reason})") from err
    if not isinstance(doc, dict):
        raise InputError(f"tags file {name!r} is not a TagSLAM tagslam.yaml (a mapping with bodies:)")
    bodies = _bodies(doc, name)
    out = TagsFile(path=name)
    default_body = str(doc.get("default_body", ""))
    body_sizes = {
        b: _number(spec["default_tag_size"], f"{name!r} body {b}.default_tag_size")
        for b, spec in bodies
        if spec.get("default_tag_size") not in (None, 0, 0.0)
    }
    out.default_tag_size_m = body_sizes.get(default_body, next(iter(body_sizes.values()), None))
    ignored: set[int] = set()
    for body, spec in bodies:
        where = f"{name!r} body {body}"
        ignored |= {int(t) for t in spec.get("ignore_tags") or []}
        body_size = body_sizes.get(body, out.default_tag_size_m)
        T_world_body, body_cov = _body_pose(spec, where)
        overrides = [float(spec.get(k, -1.0)) for k in ("override_tag_rotation_noise", "override_tag_position_noise")]
        listed: list[int] = []
        for i, tag in enumerate(spec.get("tags") or []):
            tag = _mapping(tag, f"{where} tags[{i}]")
            if "id" not in tag:
                raise InputError(f"{where} tags[{i}]: needs an id")
            tag_id = int(tag["id"])
            listed.append(tag_id)
            size = _number(tag["size"], f"{where} tag {tag_id}.size") if "size" in tag else body_size
            if size is not None:
                out.tag_sizes_m[tag_id] = size
            if "pose" in tag:
                known = _known_tag(tag_id, body, tag["pose"], spec, T_world_body, body_cov, overrides, where)
                if known is not None:
                    out.known_tags.append(known)
        static = _is_static(spec)
        if static is not None:
            out.static[body] = static
        if str(spec.get("type", "")) == "camera_rig":
            out.camera_rig_bodies.append(body)
        board = _board_tags(spec, where)
        out.tag_sizes_m.update(board)
        if static is False and (ids := sorted({*listed, *board})):
            out.moving_tags[body] = ids
        if spec.get("is_static") is False and ("T_body_odom" in spec or "odom_topic" in spec):
            out.odometry_body = body
            out.odometry_topic = str(spec["odom_topic"]) if spec.get("odom_topic") else None
            if "T_body_odom" in spec:
                out.T_body_odom = _transform(spec["T_body_odom"], f"{where}.T_body_odom")
    for body, spec in bodies:
        posed_tags = any(isinstance(t, dict) and "pose" in t for t in spec.get("tags") or [])
        if spec.get("is_static") and posed_tags and _body_pose(spec, "")[0] is None:
            out.notes.append(
                f"static body {body!r} has no pose: the poses of its tags are relative to it, not used as priors"
            )
    out.ignore_tags = sorted(ignored)
    out.remaps = _remaps(doc.get("tag_id_remap") or [], name)
    unused = [s for s in UNUSED_SECTIONS if doc.get(s)]
    if unused:
        out.notes.append(f"{Path(name).name}: {', '.join(unused)} not used (focusmap has no such measurements)")
    return out


def _is_static(spec: dict[str, Any]) -> bool | None:
    """A body's ``is_static`` (YAML true/false, or 1/0), None when not given."""
    value = spec.get("is_static")
    return bool(value) if isinstance(value, (bool, int)) else None


def _board_tags(spec: dict[str, Any], where: str) -> dict[int, float]:
    """The tags of a ``type: board`` body (TagSLAM's ``board2.cpp``: ``tag_rows`` x ``tag_columns`` ids from
    ``tag_start_id``, each ``tag_size``), id to size; empty for another type."""
    if str(spec.get("type", "")) != "board":
        return {}
    board = _mapping(spec.get("board"), f"{where}.board")
    try:
        start, rows, cols = (int(board[k]) for k in ("tag_start_id", "tag_rows", "tag_columns"))
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{where}.board: needs tag_start_id, tag_rows and tag_columns (integers)") from err
    if start < 0 or rows < 0 or cols < 0:
        raise InputError(f"{where}.board: tag_start_id, tag_rows and tag_columns must not be negative")
    size = _number(board.get("tag_size"), f"{where}.board.tag_size")
    return {start + i: size for i in range(rows * cols)}


def camera_rig_problem(tags: TagsFile, rig_bodies: dict[str, str]) -> str | None:
    """Why focusmap cannot map this setup, None when it can: the cameras sit on a static body.

    Args:
        tags: the tags file.
        rig_bodies: camera name to its ``rig_body`` (a cameras.yaml's); without any, the bodies of the old
            ``type: camera_rig`` stand for the rig.
    """
    by_body: dict[str, list[str]] = {}
    for camera, body in rig_bodies.items():
        by_body.setdefault(body, []).append(camera)
    if not by_body:
        by_body = {body: [] for body in tags.camera_rig_bodies}
    fixed = [(body, cams) for body, cams in by_body.items() if tags.static.get(body) is True]
    if not fixed:
        return None
    body, cams = fixed[0]
    which = f" (carrying {', '.join(cams)})" if cams else ""
    return (
        f"{Path(tags.path).name} makes the camera rig {body!r}{which} static (is_static: true): focusmap maps static "
        "tags from a moving camera, and fixed cameras watching a moving object give it no motion to map from; "
        "map such a setup with TagSLAM, or give a recording whose camera rig moves (is_static: false)"
    )


def _body_pose(spec: dict[str, Any], where: str) -> tuple[FloatArray | None, FloatArray]:
    """A static body's pose in the world and its 6x6 covariance (zeros without noise); None without a pose."""
    pose = spec.get("pose")
    if not spec.get("is_static") or not isinstance(pose, dict):
        return None, np.zeros((6, 6))
    sig = _sigmas(pose, f"{where}.pose")
    cov = np.diag(np.concatenate(sig) ** 2) if sig is not None else np.zeros((6, 6))
    return _transform(pose, f"{where}.pose"), cov


def _known_tag(
    tag_id: int,
    body: str,
    pose: Any,
    spec: dict[str, Any],
    T_world_body: FloatArray | None,
    body_cov: FloatArray,
    overrides: list[float],
    where: str,
) -> KnownTagPose | None:
    """The world pose and prior covariance of a tag with a pose on a static body with a pose; else None."""
    if not spec.get("is_static") or T_world_body is None:
        return None
    pose = _mapping(pose, f"{where} tag {tag_id}.pose")
    T_body_tag = _transform(pose, f"{where} tag {tag_id}.pose")
    if overrides[0] > 0 and overrides[1] > 0:
        rot, pos = np.full(3, overrides[0]), np.full(3, overrides[1])
    else:
        sig = _sigmas(pose, f"{where} tag {tag_id}.pose")
        if sig is None:
            raise InputError(f"{where} tag {tag_id}.pose: needs position_noise and rotation_noise (sigmas)")
        rot, pos = sig
    # T_world_body Exp(ξ_b) T_body_tag = T_world_tag Exp(Ad(T_tag_body) ξ_b)
    A = adjoint(np.asarray(np.linalg.inv(T_body_tag), dtype=np.float64))
    cov = np.diag(np.concatenate([rot, pos]) ** 2) + A @ body_cov @ A.T
    # TagSLAM's tag frame into focusmap's: T Exp(ξ) F = T F Exp(Ad(F⁻¹) ξ)
    F = TAGSLAM_TAG_TO_FOCUSMAP_TAG
    A = adjoint(np.asarray(np.linalg.inv(F), dtype=np.float64))
    return KnownTagPose(tag_id, body, T_world_body @ T_body_tag @ F, A @ cov @ A.T, rot.tolist(), pos.tolist())


def _seconds_ns(value: Any, where: str) -> int:
    """A stamp in seconds as integer nanoseconds (a YAML float keeps about 0.1 us of a 2018 stamp; a quoted
    string keeps all nine decimals)."""
    text = str(value).strip()
    try:
        whole, _, frac = text.partition(".")
        return int(whole) * 1_000_000_000 + int((frac + "000000000")[:9] or 0)
    except ValueError as err:
        raise InputError(f"{where}: expected a time in seconds, got {value!r}") from err


def _remaps(entries: Any, name: str) -> list[TagRemap]:
    if not isinstance(entries, list):
        raise InputError(f"{name!r} tag_id_remap: expected a list of {{id, remaps}}")
    out = []
    for i, entry in enumerate(entries):
        where = f"{name!r} tag_id_remap[{i}]"
        entry = _mapping(entry, where)
        for j, r in enumerate(entry.get("remaps") or []):
            r = _mapping(r, f"{where}.remaps[{j}]")
            try:
                tag_id, remap_id = int(entry["id"]), int(r["remap_id"])
            except (KeyError, TypeError, ValueError) as err:
                raise InputError(f"{where}.remaps[{j}]: needs id and remap_id") from err
            start = _seconds_ns(r.get("start_time", 0), f"{where}.remaps[{j}].start_time")
            end = _seconds_ns(r.get("end_time", 0), f"{where}.remaps[{j}].end_time")
            camera = str(r["camera"]) if r.get("camera") else None
            out.append(TagRemap(tag_id, remap_id, start, end, camera))
    return out
