"""Read pose graphs and landmark graphs with GTSAM's own readers (``load2D``, ``load3D``, ``readG2o``).

:func:`scan_file` looks at every line once: which element tags the file holds, whether each known line has
the numbers its tag needs (GTSAM's readers read a short line silently as something else), and whether it is
2D or 3D. :func:`read_with_gtsam` then hands the file to the GTSAM reader for its format and turns the result
into a :class:`GraphProblem`:

- 2D, GTSAM text datasets (``VERTEX2``, ``EDGE2``, ``ODOMETRY``, ``LANDMARK``, ``BR``, ``EQUIV``):
  ``gtsam.load2D`` with its noise-layout detection; ``LANDMARK`` lines become bearing-range factors with
  GTSAM's own noise heuristic.
- 2D g2o (``VERTEX_SE2``, ``VERTEX_XY``, ``EDGE_SE2``, and ``BR``): ``gtsam.readG2o(path, False)``.
- 3D (``VERTEX3``, ``EDGE3``, ``VERTEX_SE3:QUAT``, ``EDGE_SE3:QUAT``, ``VERTEX_TRACKXYZ``,
  ``EDGE_SE3_TRACKXYZ`` with an identity ``PARAMS_SE3OFFSET``): ``gtsam.load3D`` / ``gtsam.readG2o(path, True)``.

Poses without a vertex (edge-only files such as ``w20000.txt``, ``sphere2500.txt`` or ``manhattan.g2o``) start
where the odometry chain puts them: edges in file order, each placing the pose it reaches from one already
placed, the first one at the origin (what ``load2D`` does in 2D; ``load3D`` leaves them out). Landmarks
without a vertex start at their first bearing-range sighting. Comment lines are left out of the copy
GTSAM reads (its readers stop reading edges at the first ``#`` line).
"""

from __future__ import annotations

import math
import tempfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from pipeline.errors import InputError
from stages.geometry import pose2_to_vector, pose3_to_vector
from stages.graph.factors import FactorRow
from stages.graph.models import PLANAR, SPATIAL, GraphModel
from stages.graph.problem import GraphProblem
from stages.graph.variables import POSE3, VarKind

NUMBERS = {
    "VERTEX_SE2": 4,
    "VERTEX2": 4,
    "VERTEX": 4,
    "VERTEX_XY": 3,
    "EDGE_SE2": 11,
    "EDGE2": 11,
    "EDGE": 11,
    "ODOMETRY": 11,
    "BR": 6,
    "LANDMARK": 7,
    "EQUIV": 2,
    "VERTEX_SE3:QUAT": 8,
    "VERTEX3": 7,
    "EDGE_SE3:QUAT": 30,
    "EDGE3": 29,
    "VERTEX_TRACKXYZ": 4,
    "EDGE_SE3_TRACKXYZ": 12,
    "PARAMS_SE3OFFSET": 8,
    "EDGE_SE2_XY": 7,
    "EDGE_PRIOR_SE2": 10,
    "EDGE_SE3_PRIOR": 30,
}
"""The numbers each known line tag needs after the tag (``FIX`` takes any number of ids)."""
WHAT = {
    "EDGE_SE2": "i j x y theta and the 6 values of the upper-triangular information",
    "EDGE2": "i j x y theta and the 6 values of its noise",
    "EDGE3": "i j x y z roll pitch yaw and the 21 values of the upper-triangular information",
    "EDGE_SE3:QUAT": "i j x y z qx qy qz qw and the 21 values of the upper-triangular information",
}
DIM_2D = {"VERTEX_SE2", "VERTEX2", "VERTEX", "VERTEX_XY", "EDGE_SE2", "EDGE2", "EDGE", "ODOMETRY", "BR", "LANDMARK"}
DIM_2D |= {"EDGE_SE2_XY", "EDGE_PRIOR_SE2"}
DIM_3D = {"VERTEX_SE3:QUAT", "VERTEX3", "EDGE_SE3:QUAT", "EDGE3", "VERTEX_TRACKXYZ", "EDGE_SE3_TRACKXYZ"}
DIM_3D |= {"EDGE_SE3_PRIOR"}
TORO_TAGS = {"VERTEX2", "VERTEX", "EDGE2", "EDGE", "ODOMETRY", "LANDMARK", "EQUIV", "VERTEX3", "EDGE3"}
"""GTSAM's text-dataset lines (``load2D``/``load3D``); g2o's own tags are read by ``readG2o``."""
HAND_TAGS = {"EDGE_SE2_XY", "EDGE_PRIOR_SE2", "EDGE_SE3_PRIOR", "FIX"}
"""g2o lines GTSAM's readers skip: a file with any of them is read by focusmap's own g2o reader."""
EDGE_TAGS = {"EDGE_SE2", "EDGE2", "EDGE", "ODOMETRY", "BR", "LANDMARK", "EDGE_SE3:QUAT", "EDGE3"}
EDGE_TAGS |= {"EDGE_SE3_TRACKXYZ"} | HAND_TAGS - {"FIX"}
NOT_GRAPHS = {
    ".xml": "a GTSAM XML (boost serialization) archive",
    ".pyfg": "a PyFG (factor graph for range-aided SLAM) file",
    ".csv": "a CSV table",
    ".qps": "a QPS quadratic program",
    ".out": "a Bundler / BAL structure-from-motion file",
    ".mat": "a MATLAB file",
    ".bag": "a ROS bag (use focusmap run)",
    ".mcap": "an MCAP recording (use focusmap run)",
    ".db3": "a ROS 2 bag (use focusmap run)",
}
"""Files by extension that are no factor graph import-graph reads."""


@dataclass
class Scan:
    """What :func:`scan_file` found in a graph file.

    Attributes:
        tags: lines per element tag (comment and blank lines not counted).
        unknown: lines per tag no reader reads (skipped).
        dim: 2 or 3.
        comments: number of ``#`` lines.
        offset: the landmark vertex id offset of a file focusmap wrote (its ``graph.g2o.json``, or the
            ``# focusmap: landmark_id_offset N`` line of older files), else None.
    """

    tags: Counter[str] = field(default_factory=Counter)
    unknown: Counter[str] = field(default_factory=Counter)
    dim: int = 0
    comments: int = 0
    offset: int | None = None

    @property
    def needs_hand_parser(self) -> bool:
        """Whether the file holds lines that GTSAM's readers skip but focusmap reads."""
        return bool(HAND_TAGS & set(self.tags))

    @property
    def reader(self) -> str:
        """The GTSAM reader for the file."""
        if self.dim == 3:
            return "gtsam.load3D" if TORO_TAGS & set(self.tags) else "gtsam.readG2o"
        return "gtsam.load2D" if TORO_TAGS & set(self.tags) else "gtsam.readG2o"


OFFSET_COMMENT = "# focusmap: landmark_id_offset"


def not_a_graph(path: Path) -> None:
    """Raise :class:`InputError` for files whose extension names a format that holds no graph import-graph reads."""
    what = NOT_GRAPHS.get(path.suffix.lower())
    if what is not None:
        raise InputError(
            f"{path.name} is {what}, not a pose graph; import-graph reads g2o files and GTSAM text datasets "
            "(.g2o, .graph, .txt with VERTEX/EDGE/ODOMETRY/LANDMARK/BR lines)"
        )


def scan_file(path: Path) -> Scan:
    """Tags, dimension and comment lines of a graph file; checks that every known line has its numbers.

    Raises:
        InputError: unreadable, no graph lines, a short or non-numeric line (``file:line``), or 2D and 3D mixed.
    """
    not_a_graph(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(
            f"cannot read {str(path)!r} as a text graph ({err}); pass a g2o file or a GTSAM text dataset"
        ) from err
    scan = Scan()
    dims: dict[int, tuple[str, int]] = {}
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            scan.comments += 1
            if s.startswith(OFFSET_COMMENT):
                scan.offset = int(s.split()[-1])
            continue
        parts = s.split()
        tag = parts[0]
        need = NUMBERS.get(tag)
        if need is None and tag != "FIX":
            scan.unknown[tag] += 1
            continue
        where = f"{path.name}:{n}"
        if need is not None and len(parts) - 1 < need:
            what = WHAT.get(tag, f"{need} numbers")
            raise InputError(f"{where}: {tag} needs {what} ({need} numbers); the line has {len(parts) - 1}")
        try:
            [float(x) for x in parts[1 : 1 + (need or len(parts))]]
        except ValueError as err:
            raise InputError(f"{where}: cannot parse {tag!r} line ({err}); fix the file") from None
        scan.tags[tag] += 1
        d = 2 if tag in DIM_2D else 3 if tag in DIM_3D else 0
        if d:
            dims.setdefault(d, (tag, n))
    if len(dims) > 1:
        (t2, n2), (t3, n3) = dims[2], dims[3]
        raise InputError(
            f"{path.name} mixes 2D ({t2}, line {n2}) and 3D ({t3}, line {n3}) elements; a graph is all 2D or all 3D"
        )
    if not dims or not EDGE_TAGS & set(scan.tags):
        first = next(iter(scan.unknown), None)
        found = f"; its lines start with {first!r}" if first and not dims else ""
        vertices = "vertices but " if dims else ""
        raise InputError(
            f"{path.name} holds {vertices}no edges GTSAM's readers read{found}; pass a g2o file or a GTSAM text "
            "dataset (VERTEX/EDGE/ODOMETRY/LANDMARK/BR lines)"
        )
    scan.dim = next(iter(dims))
    return scan


def read_with_gtsam(path: Path, scan: Scan) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph and values GTSAM's reader for the file returns (comment lines left out of what it reads).

    Raises:
        InputError: GTSAM's reader rejects the file (its message).
    """
    if scan.comments:
        with tempfile.TemporaryDirectory(prefix="focusmap-graph-") as tmp:
            copy = Path(tmp) / path.name
            lines = path.read_text().splitlines()
            copy.write_text("\n".join(s for s in lines if not s.lstrip().startswith("#")) + "\n")
            return _gtsam_read(copy, scan, path.name)
    return _gtsam_read(path, scan, path.name)


def _gtsam_read(path: Path, scan: Scan, name: str) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    try:
        if scan.reader == "gtsam.load2D":
            return gtsam.load2D(str(path))
        if scan.reader == "gtsam.load3D":
            return gtsam.load3D(str(path))
        return gtsam.readG2o(str(path), scan.dim == 3)
    except (RuntimeError, ValueError, IndexError) as err:
        raise InputError(f"{name}: {scan.reader} rejects the file ({err}); fix the file") from None


@dataclass
class _Converted:
    rows: list[FactorRow] = field(default_factory=list)
    poses: dict[int, Any] = field(default_factory=dict)
    landmarks: dict[int, Any] = field(default_factory=dict)
    pose_landmarks: set[int] = field(default_factory=set)
    first_sighting: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)
    composed: int = 0


def problem_from_gtsam(
    path: Path,
    scan: Scan,
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    prior_sigma_m: float,
    prior_sigma_rad: float,
) -> GraphProblem:
    """The :class:`GraphProblem` of what a GTSAM reader returned.

    Pose keys (plain vertex ids) become ``X(id)``; landmark keys ``L(id)`` keep their id less the landmark offset
    of a file focusmap wrote, whose pose vertices at or above the offset are Pose3 tags. A prior is added on the
    first pose (the readers add none).
    """
    model = PLANAR if scan.dim == 2 else SPATIAL
    offset = scan.offset
    c = _Converted()
    keys = values.keys()
    for k in keys:
        sym = gtsam.Symbol(k)
        if sym.chr() == 0 and offset is not None and k >= offset:
            c.landmarks[k - offset] = values.atPose3(k)
            c.pose_landmarks.add(k - offset)
        elif sym.chr() == 0:
            c.poses[k] = model.pose.read(values, k)
        elif sym.chr() == ord("l"):
            c.landmarks[sym.index() - (offset or 0)] = model.point.read(values, k)
    for i in range(graph.size()):
        _convert_factor(graph.at(i), c, model, offset, path.name)
    _compose_chain(c, model, path.name)
    _odometry_or_loop(c.rows, sorted(c.poses))
    initial = gtsam.Values()
    var_types: dict[int, str] = {}

    def add(key: int, kind: VarKind, value: Any) -> None:
        kind.insert(initial, key, value)
        var_types[key] = kind.name

    pose_ids = sorted(c.poses)
    for i in pose_ids:
        add(int(X(i)), model.pose, c.poses[i])
    for j in sorted(c.landmarks):
        add(int(L(j)), POSE3 if j in c.pose_landmarks else model.point, c.landmarks[j])
    for j, (i, rel) in sorted(c.first_sighting.items()):
        if j not in c.landmarks:
            add(int(L(j)), model.point, np.asarray(c.poses[i].transformFrom(rel), dtype=float))
    landmark_keys = {j: int(L(j)) for j in sorted(set(c.landmarks) | set(c.first_sighting))}
    first = int(X(pose_ids[0]))
    rows = [model.prior_row(first, model.pose.vector(initial, first), prior_sigma_m, prior_sigma_rad), *c.rows]
    return GraphProblem(
        model=model.name,
        rows=rows,
        initial=initial,
        var_types=var_types,
        pose_keys=[int(X(i)) for i in pose_ids],
        pose_stamps_ns=[int(i * 1_000_000_000) for i in pose_ids],
        landmark_keys=landmark_keys,
        info={
            "source_file": path.name,
            "format": "gtsam-graph" if TORO_TAGS & set(scan.tags) else "g2o",
            "reader": scan.reader,
            "lines": dict(sorted(scan.tags.items())),
            "skipped_lines": dict(sorted(scan.unknown.items())),
            "equivalences_ignored": int(scan.tags.get("EQUIV", 0)),
            "poses_placed_by_odometry": c.composed,
            "prior_added_on_first_pose": True,
            "notes": _notes(scan, c.composed),
        },
    )


def _notes(scan: Scan, composed: int) -> list[str]:
    """What the import-graph command prints under the graph stage's line."""
    notes = [f"read with {scan.reader}"]
    if composed:
        notes.append(f"{composed} poses without a vertex start where the odometry chain puts them")
    if scan.unknown:
        lines = ", ".join(f"{n} {tag}" for tag, n in sorted(scan.unknown.items()))
        notes.append(f"lines no reader reads were skipped: {lines}")
    return notes


def _pose_id(key: int, offset: int | None, name: str) -> int:
    if gtsam.Symbol(key).chr() != 0:
        raise InputError(f"{name}: an edge joins {gtsam.Symbol(key)!s}, which is no pose")
    return int(key)


def _convert_factor(f: Any, c: _Converted, model: GraphModel, offset: int | None, name: str) -> None:
    """One GTSAM factor as a row: pose-pose edges are odometry (consecutive ids) or loops; the rest are tags."""
    keys = list(f.keys())
    cov = np.asarray(f.noiseModel().covariance(), dtype=float)
    if isinstance(f, gtsam.BetweenFactorPose2 | gtsam.BetweenFactorPose3):
        i, j = (_pose_id(k, offset, name) for k in keys)
        vec = (
            pose2_to_vector(f.measured()) if isinstance(f, gtsam.BetweenFactorPose2) else pose3_to_vector(f.measured())
        )
        if offset is not None and j >= offset:
            c.rows.append(_tag_row("BetweenFactorPose3", i, j - offset, vec, cov))
        else:
            kind = "odometry" if abs(i - j) == 1 else "loop"
            c.rows.append(FactorRow(kind, type(f).__name__, (int(X(i)), int(X(j))), vec, cov))
    elif isinstance(f, gtsam.BearingRangeFactor2D | gtsam.BearingRangeFactor3D):
        i = _pose_id(keys[0], offset, name)
        j = gtsam.Symbol(keys[1]).index() - (offset or 0)
        br: Any = f.measured()  # BearingRange2D / BearingRange3D
        r = float(br.range())
        if isinstance(f, gtsam.BearingRangeFactor2D):
            b = float(br.bearing().theta())
            vec, rel = np.array([b, r]), np.array([r * math.cos(b), r * math.sin(b)])
        else:
            u = np.asarray(br.bearing().point3(), dtype=float)
            vec, rel = np.concatenate([u, [r]]), u * r
        c.rows.append(_tag_row(type(f).__name__, i, j, vec, cov))
        c.first_sighting.setdefault(j, (i, rel))
    else:
        raise InputError(f"{name}: GTSAM's reader returned a {type(f).__name__}, which focusmap does not import")
    for k in keys:
        if gtsam.Symbol(k).chr() == 0 and not (offset is not None and k >= offset):
            c.poses.setdefault(int(k), None)


def _tag_row(type_: str, i: int, tag_id: int, vec: np.ndarray, cov: np.ndarray) -> FactorRow:
    keys = (int(X(i)), int(L(tag_id)))
    return FactorRow("tag", type_, keys, vec, cov, tag_id=tag_id, frame=i, stamp_ns=int(i * 1_000_000_000))


def _odometry_or_loop(rows: list[FactorRow], pose_ids: list[int]) -> None:
    """Pose-pose edges between poses next to each other in id order are odometry, the others loops."""
    index = {int(X(i)): n for n, i in enumerate(pose_ids)}
    for row in rows:
        if row.kind in ("odometry", "loop"):
            row.kind = "odometry" if abs(index[row.keys[0]] - index[row.keys[1]]) == 1 else "loop"


def _compose_chain(c: _Converted, model: GraphModel, name: str) -> None:
    """Place the poses without a value by composing the pose-pose edges in file order (GTSAM's load2D rule)."""
    missing = {i for i, p in c.poses.items() if p is None}
    if not missing:
        return
    between = [r for r in c.rows if r.kind in ("odometry", "loop")]
    for row in between:
        i, j = (gtsam.Symbol(k).index() for k in row.keys)
        a, b = c.poses.get(i), c.poses.get(j)
        if a is not None and b is not None:
            continue
        m = model.pose.from_vector(row.measurement)
        if a is None and b is None:
            a = c.poses[i] = model.pose.from_vector(model.identity)
            c.composed += 1
        if b is None:
            c.poses[j] = a.compose(m)  # type: ignore[union-attr]  # a is placed here
        else:
            c.poses[i] = b.compose(m.inverse())
        c.composed += 1
    left = sorted(i for i, p in c.poses.items() if p is None)
    if left:
        raise InputError(f"{name}: pose {left[0]} has no vertex and no edge to a placed pose; fix the file")
