"""Ground truth of a run, when the run has one, and the map frame it is compared in.

Where it comes from: the file named by ``--truth`` (the ``truth_file`` setting of optimize and evaluate), else
the file beside the run's source recording: ``DIR/<name>.ground_truth.json`` (the simulator's JSON; the rule of
``sample_data.simulate.ground_truth_path``), else ``DIR/<name>.truth.yaml`` (:func:`ground_truth_paths`; ``<name>``
is the bag file's stem or the ROS 2 bag folder's name). Runs without one are evaluated against the full graph
(Table I case 1) and navigate in walls rebuilt from the laser scans.

Two formats are read (:func:`read_truth`): the simulator's ``.ground_truth.json``, and a truth YAML a user can write
by hand for their own recording (``docs/evaluate.md``, "Ground truth file")::

    frame: world          # world (any fixed frame) or map (the robot's base at the first keyframe)
    tags: tags.csv        # or an inline list of [id, x, y] / [id, x, y, z], m
    poses: run.truth.tum  # TUM trajectory: stamp_s x y z qx qy qz qw (bag time), the robot's base
    walls: walls.csv      # or an inline list of [x0, y0, x1, y1], m

Paths are relative to the YAML's folder. Any part may be missing (:data:`MISSING`, what each missing part turns
off). The graph's map frame is the robot's base at the first keyframe (the graph's prior), so a truth in a world
frame is brought into it with ``T_world_map`` = the true pose at the first keyframe's stamp; without true poses,
with the best rigid planar motion of the full graph's landmarks onto the true tags.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import numpy as np
import numpy.typing as npt

from pipeline.errors import InputError

if TYPE_CHECKING:
    from pipeline.context import StageContext
    from stages.graph.load import LoadedGraph

FloatArray = npt.NDArray[np.float64]

TRUTH_PARTS: Final = ("tags", "poses", "walls")
"""The parts of a ground truth, any of which a truth file may leave out."""
MISSING: Final = {
    "tags": "no tags -> landmark errors are against case 1 (optimal) and the simulated robot measures the full "
    "map's landmarks",
    "poses": "no poses -> the map frame is placed by the tags, navigation follows the full graph's path and the "
    "consistency analysis (measurements at the truth) is off",
    "walls": "no walls -> navigation collides with the laser occupancy grid",
}
"""What each missing part of a ground truth turns off, one line each (printed as the stage's notes)."""
FRAMES: Final = ("world", "map")
YAML_KEYS: Final = ("frame", *TRUTH_PARTS)
MIN_FIT_TAGS: Final = 2
"""Tags shared with the graph needed to place a world-frame truth without poses."""


def ground_truth_path(source: Path) -> Path:
    """Where the simulator's ground-truth JSON of a recording would be (whether or not it exists)."""
    return ground_truth_paths(source)[0]


def ground_truth_paths(source: Path) -> tuple[Path, Path]:
    """The ground-truth files looked for beside a recording, in order: ``<name>.ground_truth.json``,
    ``<name>.truth.yaml``."""
    source = Path(source)
    name = source.stem if source.suffix in (".bag", ".mcap", ".db3") else source.name
    return source.parent / f"{name}.ground_truth.json", source.parent / f"{name}.truth.yaml"


def ground_truth_file(source: Path | None) -> Path | None:
    """The ground-truth file beside a run's source recording, or None when there is none."""
    if source is None:
        return None
    return next((p for p in ground_truth_paths(source) if p.is_file()), None)


def se2(x: float, y: float, yaw: float) -> FloatArray:
    """3x3 homogeneous planar transform."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def transform_points(T: npt.NDArray[np.floating], points: npt.ArrayLike) -> FloatArray:
    """Apply a 3x3 planar transform to (N, 2) points."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    return p @ T[:2, :2].T + T[:2, 2]


def _interp_poses(stamps_ns: npt.NDArray[np.int64], poses: FloatArray, query: npt.ArrayLike) -> FloatArray:
    """(x, y, yaw) interpolated at ``query`` (yaw unwrapped first)."""
    if len(stamps_ns) == 0:
        raise ValueError("the ground truth has no poses")
    t = stamps_ns.astype(float)
    q = np.asarray(query, dtype=float).reshape(-1)
    yaw = np.unwrap(poses[:, 2])
    return np.column_stack([np.interp(q, t, poses[:, 0]), np.interp(q, t, poses[:, 1]), np.interp(q, t, yaw)])


def rigid_fit(source: FloatArray, target: FloatArray) -> FloatArray:
    """The 3x3 planar rigid transform ``T`` minimising ``Σ |T source_i − target_i|²`` (≥ 2 distinct points)."""
    ca, cb = source.mean(axis=0), target.mean(axis=0)
    U, _, Vt = np.linalg.svd((source - ca).T @ (target - cb))
    D = np.diag([1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    T = np.eye(3)
    T[:2, :2], T[:2, 2] = R, cb - R @ ca
    return T


@dataclass(frozen=True)
class GroundTruth:
    """A recording's truth: walls, tag positions and the robot's true path, in one fixed frame.

    A part the file leaves out is empty (no walls, no tags, no poses).
    """

    path: Path
    walls_world: FloatArray
    """(W, 4) wall segments x0 y0 x1 y1, m."""
    tags_world: dict[int, FloatArray]
    """Tag id to its centre (x, y, z), m."""
    pose_stamps_ns: npt.NDArray[np.int64]
    poses_world: FloatArray
    """(N, 3) true x, y, yaw of the base at ``pose_stamps_ns``."""
    frame: str = "world"
    """``world``: any fixed frame, placed in the map by the poses (or tags); ``map``: already the map frame."""

    @property
    def missing(self) -> tuple[str, ...]:
        """The parts (:data:`TRUTH_PARTS`) this truth does not have."""
        have = {"tags": bool(self.tags_world), "poses": len(self.poses_world) > 0, "walls": len(self.walls_world) > 0}
        return tuple(p for p in TRUTH_PARTS if not have[p])

    @classmethod
    def load(cls, path: Path) -> GroundTruth:
        """Read ``<name>.ground_truth.json`` (as written by ``sample_data.simulate``)."""
        try:
            data = json.loads(Path(path).read_text(), object_hook=_without_frames)
            walls = np.asarray(data["world"]["walls"], dtype=float).reshape(-1, 4)
            tags = {int(t["id"]): np.asarray(t["position"], dtype=float) for t in data["tags"]}
            stamps = np.array([int(p["stamp_ns"]) for p in data["poses"]], dtype=np.int64)
            poses = np.array([[p["x"], p["y"], p["yaw"]] for p in data["poses"]], dtype=float).reshape(-1, 3)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise InputError(
                f"ground truth {str(path)!r} is unreadable ({err}); fix or remove it to evaluate against the full graph"
            ) from err
        return cls(Path(path), walls, tags, stamps, poses)

    def pose_at(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """True (x, y, yaw) interpolated at ``stamps_ns`` (yaw unwrapped, then interpolated)."""
        return _interp_poses(self.pose_stamps_ns, self.poses_world, stamps_ns)

    def T_world_map(self, first_keyframe_ns: int) -> FloatArray:
        """The map frame (the base at the first keyframe) in the world."""
        x, y, yaw = self.pose_at([first_keyframe_ns])[0]
        return se2(x, y, yaw)

    def in_map(self, first_keyframe_ns: int, landmark_estimates: Mapping[int, npt.ArrayLike] | None = None) -> MapTruth:
        """Walls, tags and the true path in the graph's map frame.

        The frame is placed by the true pose at the first keyframe; without poses, by the best rigid motion of the
        true tags onto ``landmark_estimates`` (the full graph's tag positions in the map frame, x y); a truth whose
        ``frame`` is ``map`` is already there.

        Raises:
            InputError: a world-frame truth without poses whose tags do not place it (fewer than two shared with
                ``landmark_estimates``).
        """
        T: FloatArray
        if self.frame == "map":
            T, placed_by = np.eye(3), "map"
        elif len(self.poses_world):
            T, placed_by = np.asarray(np.linalg.inv(self.T_world_map(first_keyframe_ns)), dtype=float), "poses"
        else:
            T, placed_by = self._fit_to(landmark_estimates or {}), "tags"
        walls = np.column_stack(
            [transform_points(T, self.walls_world[:, :2]), transform_points(T, self.walls_world[:, 2:])]
        )
        tags = {i: transform_points(T, p[:2])[0] for i, p in self.tags_world.items()}
        xy = transform_points(T, self.poses_world[:, :2])
        yaw = np.unwrap(self.poses_world[:, 2]) + np.arctan2(T[1, 0], T[0, 0])
        return MapTruth(
            walls, tags, self.pose_stamps_ns, np.column_stack([xy, yaw]).reshape(-1, 3), self.missing, placed_by
        )

    def _fit_to(self, estimates: Mapping[int, npt.ArrayLike]) -> FloatArray:
        """Map-from-world transform of the best rigid fit of the true tags onto the estimated ones."""
        common = sorted(set(self.tags_world) & {int(t) for t in estimates})
        if len(common) < MIN_FIT_TAGS:
            raise InputError(
                f"ground truth {str(self.path)!r} has no poses and {len(common)} tag(s) shared with the graph, so "
                f"its world frame cannot be placed in the map; add poses:, list at least {MIN_FIT_TAGS} of the "
                "graph's tags, or give the coordinates in the map frame (frame: map)"
            )
        src = np.array([self.tags_world[t][:2] for t in common], dtype=float)
        dst = np.array([np.asarray(estimates[t], dtype=float)[:2] for t in common])
        return rigid_fit(src, dst)


@dataclass(frozen=True)
class MapTruth:
    """The truth expressed in the graph's map frame (a missing part is empty, named in ``missing``)."""

    walls: FloatArray
    """(W, 4) wall segments in the map frame."""
    tags: dict[int, FloatArray]
    """Tag id to its (x, y) in the map frame."""
    pose_stamps_ns: npt.NDArray[np.int64]
    poses: FloatArray
    """(N, 3) true path in the map frame."""
    missing: tuple[str, ...] = ()
    """The parts (:data:`TRUTH_PARTS`) the truth file left out."""
    placed_by: str = "poses"
    """How the truth's frame was placed in the map: by the true ``poses``, by the ``tags``, or ``map`` (as given)."""

    @property
    def has_walls(self) -> bool:
        return "walls" not in self.missing

    @property
    def has_tags(self) -> bool:
        return "tags" not in self.missing

    @property
    def has_poses(self) -> bool:
        return "poses" not in self.missing

    def missing_notes(self) -> list[str]:
        """One line per missing part: what it turns off (:data:`MISSING`)."""
        return [f"ground truth: {MISSING[p]}" for p in self.missing]

    def pose_at(self, stamps_ns: npt.ArrayLike) -> FloatArray:
        """True (x, y, yaw) in the map frame at ``stamps_ns``."""
        if len(self.pose_stamps_ns) == 0:
            raise ValueError("the ground truth has no poses")
        t = self.pose_stamps_ns.astype(float)
        q = np.asarray(stamps_ns, dtype=float).reshape(-1)
        return np.column_stack([np.interp(q, t, self.poses[:, i]) for i in range(3)])


# ------------------------------------------------------------------------------------------- truth YAML
def _bad(path: Path, what: str) -> InputError:
    return InputError(f"ground truth {str(path)!r}: {what}; see docs/evaluate.md, 'Ground truth file'")


def _number(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text!r} is not finite")
    return value


def _rows(part: str, value: object, folder: Path, path: Path) -> list[tuple[str, list[str]]]:
    """The rows of a part given inline (a list of lists) or as a CSV file (commas or spaces, ``#`` comments,
    an optional header row), each as ``(where, fields)``."""
    if isinstance(value, list):
        rows = []
        for i, item in enumerate(value, start=1):
            if not isinstance(item, list) or any(isinstance(v, (list, dict, bool)) or v is None for v in item):
                raise _bad(path, f"{part} entry {i} is {item!r}, not a list of numbers")
            rows.append((f"{part} entry {i}", [str(v) for v in item]))
        return rows
    if not isinstance(value, str) or not value.strip():
        raise _bad(path, f"{part}: expected a file name or a list, got {value!r}")
    file = folder / Path(value).expanduser()
    try:
        text = file.read_text()
    except OSError as err:
        raise _bad(path, f"{part} file {str(file)!r} cannot be read ({err.strerror or err})") from None
    out = []
    first = True
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        if first and not _is_number(fields[0]):
            first = False
            continue  # a header row
        first = False
        out.append((f"{file.name} line {n}", fields))
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_tags(value: object, folder: Path, path: Path) -> dict[int, FloatArray]:
    tags: dict[int, FloatArray] = {}
    for where, fields in _rows("tags", value, folder, path):
        if len(fields) not in (3, 4):
            raise _bad(path, f"{where}: expected id x y [z], got {len(fields)} values")
        try:
            tag = int(fields[0])
            xyz = [_number(f) for f in fields[1:]] + ([0.0] if len(fields) == 3 else [])
        except ValueError:
            raise _bad(path, f"{where}: expected an integer id and numbers x y [z], got {' '.join(fields)!r}") from None
        if tag in tags:
            raise _bad(path, f"{where}: tag {tag} is listed twice")
        tags[tag] = np.array(xyz, dtype=float)
    return tags


def _read_walls(value: object, folder: Path, path: Path) -> FloatArray:
    walls = []
    for where, fields in _rows("walls", value, folder, path):
        if len(fields) != 4:
            raise _bad(path, f"{where}: expected x0 y0 x1 y1, got {len(fields)} values")
        try:
            walls.append([_number(f) for f in fields])
        except ValueError:
            raise _bad(path, f"{where}: expected numbers x0 y0 x1 y1, got {' '.join(fields)!r}") from None
    return np.array(walls, dtype=float).reshape(-1, 4)


def _stamp_ns(text: str) -> int:
    """A TUM stamp (seconds, decimal) as integer nanoseconds, exactly."""
    whole, _, frac = text.strip().partition(".")
    if not whole.lstrip("-").isdigit() or (frac and not frac.isdigit()) or len(frac) > 9:
        return round(_number(text) * 1e9)  # exponent notation or finer than 1 ns
    ns = int(whole) * 1_000_000_000
    return ns + (-1 if whole.startswith("-") else 1) * int(frac.ljust(9, "0") or 0)


def read_tum(file: Path, path: Path | None = None) -> tuple[npt.NDArray[np.int64], FloatArray]:
    """Stamps (ns) and planar poses (x, y, yaw) of a TUM trajectory file (``stamp x y z qx qy qz qw``)."""
    owner = path if path is not None else file
    try:
        text = file.read_text()
    except OSError as err:
        raise _bad(owner, f"poses file {str(file)!r} cannot be read ({err.strerror or err})") from None
    stamps: list[int] = []
    poses: list[list[float]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        where = f"{file.name} line {n}"
        if len(fields) != 8:
            raise _bad(owner, f"{where}: a TUM pose is 8 values (stamp_s x y z qx qy qz qw), got {len(fields)}")
        try:
            stamp = _stamp_ns(fields[0])
            x, y, _, qx, qy, qz, qw = (_number(f) for f in fields[1:])
        except ValueError:
            raise _bad(owner, f"{where}: expected 8 numbers, got {line!r}") from None
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        if not 0.5 < norm < 1.5:
            raise _bad(owner, f"{where}: the quaternion qx qy qz qw has norm {norm:.3g}, not 1")
        qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
        if stamps and stamp <= stamps[-1]:
            raise _bad(owner, f"{where}: stamps must increase (stamp {fields[0]} after {stamps[-1] / 1e9:.9f})")
        stamps.append(stamp)
        poses.append([x, y, math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))])
    return np.array(stamps, dtype=np.int64), np.array(poses, dtype=float).reshape(-1, 3)


def load_truth_yaml(path: Path) -> GroundTruth:
    """Read a truth YAML (module docstring; ``docs/evaluate.md``, "Ground truth file")."""
    import yaml

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as err:
        raise _bad(path, f"cannot be read ({err.strerror or err})") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        raise _bad(path, f"not valid YAML{f' at line {mark.line + 1}' if mark is not None else ''}") from None
    if not isinstance(data, dict):
        raise _bad(path, f"expected a mapping with keys {', '.join(YAML_KEYS)}")
    unknown = [str(k) for k in data if k not in YAML_KEYS]
    if unknown:
        raise _bad(path, f"unknown key {unknown[0]!r}; the keys are {', '.join(YAML_KEYS)}")
    frame = data.get("frame", "world")
    if frame not in FRAMES:
        raise _bad(path, f"frame {frame!r} is not one of {', '.join(FRAMES)}")
    given = {k: v for k, v in data.items() if k in TRUTH_PARTS and v is not None}
    if not given:
        raise _bad(path, f"it has none of {', '.join(TRUTH_PARTS)}")
    folder = path.parent
    tags = _read_tags(given["tags"], folder, path) if "tags" in given else {}
    walls = _read_walls(given["walls"], folder, path) if "walls" in given else np.zeros((0, 4))
    if "poses" in given:
        poses_value = given["poses"]
        if not isinstance(poses_value, str) or not poses_value.strip():
            raise _bad(path, f"poses: expected the name of a TUM file, got {poses_value!r}")
        stamps, poses = read_tum(folder / Path(poses_value).expanduser(), path)
    else:
        stamps, poses = np.zeros(0, dtype=np.int64), np.zeros((0, 3))
    return GroundTruth(path, walls, tags, stamps, poses, str(frame))


def _without_frames(obj: dict[str, Any]) -> dict[str, Any] | None:
    """``json.loads`` hook: the per-frame entries of the simulator's truth (each tag seen, its corners and pose) are
    dropped as they are parsed; ``GroundTruth`` reads the walls, tags and poses only. Kept, they cost ~550 MB of
    Python objects on an hour's recording (88 MB of JSON), in optimize and evaluate."""
    return None if "visible_tags" in obj else obj


def read_truth(path: Path) -> GroundTruth:
    """A ground-truth file: the simulator's ``.json`` or a truth YAML (any other name is read as YAML)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(
            f"ground truth {str(path)!r} not found; pass an existing truth YAML or .ground_truth.json to --truth"
        )
    return GroundTruth.load(path) if path.suffix.lower() == ".json" else load_truth_yaml(path)


def _outside_parts(ctx: StageContext, path: Path) -> None:
    """Declare the files a truth YAML names (tags, poses, walls), so a change to any of them re-runs the stage."""
    if path.suffix.lower() == ".json":
        return
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return  # read_truth says what is wrong
    if isinstance(data, dict):
        for part in TRUTH_PARTS:
            if isinstance(data.get(part), str):
                ctx.outside_file(path.parent / Path(data[part]).expanduser())


def load_truth(ctx: StageContext, loaded: LoadedGraph, truth_file: str = "") -> MapTruth | None:
    """The run's ground truth in the map frame: ``truth_file`` if given, else the file beside its source.

    Every file is declared to the runner (present or not), so the stage re-runs when one appears, changes or
    goes: the given file and the files it names, or the files looked for beside the source.
    """
    if truth_file:
        found = ctx.outside_file(truth_file)
        if found is None:
            raise InputError(
                f"ground truth {truth_file!r} not found; pass an existing truth YAML or .ground_truth.json to "
                "--truth (or clear the truth_file setting)"
            )
        path: Path | None = found
    else:
        if ctx.run.source is None:
            return None
        path = None
        for candidate in ground_truth_paths(ctx.run.source):
            path = ctx.outside_file(candidate)
            if path is not None:
                break
    if path is None:
        return None
    _outside_parts(ctx, path)
    truth = read_truth(path)
    return truth.in_map(loaded.pose_stamps_ns[0], _graph_landmarks(loaded) if not len(truth.poses_world) else None)


def _graph_landmarks(loaded: LoadedGraph) -> dict[int, FloatArray]:
    """The full graph's landmark positions (x, y) in the map frame."""
    out = {}
    for tag, key in loaded.landmark_keys.items():
        if loaded.values.exists(key):
            kind = loaded.kind(key)
            out[int(tag)] = np.asarray(kind.position(kind.read(loaded.values, key)), dtype=float)[:2]
    return out
