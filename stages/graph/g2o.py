"""Read g2o files and GTSAM text datasets into a :class:`GraphProblem`; write g2o.

:func:`read_graph_file` reads a file with GTSAM's own readers (:mod:`stages.graph.datasets`) unless it holds
g2o lines those readers skip; only such files are read here, line by line:

- g2o 2D: ``VERTEX_SE2 id x y th``, ``VERTEX_XY id x y``, ``EDGE_SE2 i j x y th I(6)`` (upper-triangular
  information), ``EDGE_SE2_XY i l x y I(3)`` (landmark position in the pose frame), ``EDGE_PRIOR_SE2 i x y th I(6)``,
  ``FIX id``, and ``BR i l bearing range σ_b σ_r`` (GTSAM's bearing-range line; one that repeats an
  ``EDGE_SE2_XY`` of the same pose and landmark is its copy for GTSAM and is skipped).
- g2o 3D: ``VERTEX_SE3:QUAT id x y z qx qy qz qw``, ``VERTEX_TRACKXYZ id x y z``, ``EDGE_SE3:QUAT i j x y z qx qy qz qw
  I(21)``, ``EDGE_SE3_TRACKXYZ i l param x y z I(6)``, ``EDGE_SE3_PRIOR i param x y z qx qy qz qw I(21)``. The 6x6
  information is permuted from g2o's (t, q) order to gtsam's (r, t) as ``gtsam.readG2o`` does.

Relative landmark positions become bearing-range factors (the same measurement to first order). Pose
vertices get keys ``X(id)`` and landmark vertices ``L(id)``; imported graphs have no clock, so the pose
stamp is the vertex id in seconds. A prior is added on the first pose when the file fixes none.

:func:`write_g2o` writes no comment lines (GTSAM's readers stop at the first one); what a reader needs beyond
the g2o lines (the landmark vertex id offset, the tag scale the measurements were written at) is in the side
file ``<name>.g2o.json`` (:func:`g2o_metadata`), which :func:`read_graph_file` reads when it is there.
"""

from __future__ import annotations

import functools
import json
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from pipeline.errors import InputError
from stages.geometry import (
    bearing_range_to_relative_position_2d,
    bearing_range_to_relative_position_3d,
    pose3_from_vector,
    pose3_to_vector,
    relative_position_to_bearing_range_2d,
    relative_position_to_bearing_range_3d,
)
from stages.graph.datasets import TORO_TAGS, Scan, problem_from_gtsam, read_with_gtsam, scan_file
from stages.graph.factors import FactorRow, scaled_measurement
from stages.graph.models import PLANAR, SPATIAL, GraphModel
from stages.graph.problem import GraphProblem
from stages.graph.variables import POINT2, POINT3, POSE2, POSE3, VarKind, var_kind

_PERM_G2O_TO_GTSAM = [3, 4, 5, 0, 1, 2]


@functools.cache
def _triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The upper triangle's indices of an n x n matrix, row by row (made once per size: a graph writes thousands)."""
    return np.triu_indices(n)


def _upper(values: list[float], n: int) -> np.ndarray:
    M = np.zeros((n, n))
    M[_triu(n)] = values
    return M + np.triu(M, 1).T


def _upper_list(M: np.ndarray) -> list[float]:
    return [float(v) for v in M[_triu(M.shape[0])].tolist()]


def _info_to_cov(info: np.ndarray, where: str) -> np.ndarray:
    try:
        return np.linalg.inv(info)
    except np.linalg.LinAlgError:
        raise InputError(f"{where}: the information matrix is singular; fix the file") from None


class _Reader:
    def __init__(self, path: Path, offset: int | None) -> None:
        self.path = path
        self.poses: dict[int, Any] = {}
        self.points: dict[int, np.ndarray] = {}
        self.pose3_landmarks: set[int] = set()
        self.rows: list[FactorRow] = []
        self.fixed: list[int] = []
        self.counts: Counter[str] = Counter()
        self.offset = offset
        self.xy_pairs: set[tuple[int, int]] = set()
        """(pose, tag id) of every EDGE_SE2_XY line: a BR line of the same pair is its copy for GTSAM."""
        self.dim: int | None = None
        self.unplaced: dict[int, tuple[int, np.ndarray]] = {}
        """Landmark id without a vertex (yet) to the first pose that measured it and its position there."""

    def set_dim(self, d: int, where: str) -> None:
        if self.dim is None:
            self.dim = d
        elif self.dim != d:
            raise InputError(f"{where}: mixes 2D and 3D elements; a graph must be all 2D or all 3D")

    def is_landmark_id(self, i: int) -> bool:
        return self.offset is not None and i >= self.offset

    def read(self) -> None:
        try:
            lines = self.path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(
                f"cannot read {str(self.path)!r} as a text graph ({err}); pass a g2o or GTSAM .graph file"
            ) from err
        for n, line in enumerate(lines, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            tag = parts[0]
            where = f"{self.path.name}:{n}"
            try:
                self._line(tag, parts[1:], where)
            except (ValueError, IndexError) as err:
                raise InputError(f"{where}: cannot parse {tag!r} line ({err}); fix the file") from err
            if tag in _HANDLERS:
                self.counts[tag] += 1

    def _line(self, tag: str, a: list[str], where: str) -> None:
        f = [float(x) for x in a]
        handler = _HANDLERS.get(tag)
        if handler is None:
            return
        dim, method = handler
        if dim is not None:
            self.set_dim(dim, where)
        method(self, tag, a, f, where)

    # vertices
    def _vertex_se2(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        i = int(a[0])
        if self.is_landmark_id(i):
            self.points[i] = np.array(f[1:3])
        else:
            self.poses[i] = gtsam.Pose2(f[1], f[2], f[3])

    def _vertex_point(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        self.points[int(a[0])] = np.array(f[1 : 1 + (self.dim or 2)])

    def _vertex_se3(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        i = int(a[0])
        self.poses[i] = pose3_from_vector(f[1:8])
        if self.is_landmark_id(i):
            self.pose3_landmarks.add(i)

    # 2D edges
    def _edge_se2(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        i, j = int(a[0]), int(a[1])
        cov = _info_to_cov(_upper(f[5:11], 3), where)
        if self.is_landmark_id(j):
            raise InputError(f"{where}: EDGE_SE2 to landmark vertex {j}; use EDGE_SE2_XY")
        self.rows.append(
            FactorRow(self._pp_kind(i, j), "BetweenFactorPose2", (int(X(i)), int(X(j))), np.array(f[2:5]), cov)
        )

    def _edge_se2_xy(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        cov = _info_to_cov(_upper(f[4:7], 2), where)
        b, r, cbr = relative_position_to_bearing_range_2d(f[2:4], cov)
        self.xy_pairs.add((int(a[0]), int(a[1]) - (self.offset or 0)))
        self._bearing_range_2d(int(a[0]), int(a[1]), b, r, cbr)

    def _br(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        b, r, sb, sr = f[2], f[3], f[4], f[5]
        self._bearing_range_2d(int(a[0]), int(a[1]), b, r, np.diag([sb**2, sr**2]))
        self.rows[-1].extra["br"] = True

    def _bearing_range_2d(self, i: int, j: int, b: float, r: float, cov: np.ndarray) -> None:
        self._tag_row("BearingRangeFactor2D", i, j, np.array([b, r]), cov)
        if j not in self.points:
            self.unplaced.setdefault(j, (i, np.array([r * np.cos(b), r * np.sin(b)])))

    def _prior_se2(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        cov = _info_to_cov(_upper(f[4:10], 3), where)
        self.rows.append(FactorRow("prior", "PriorFactorPose2", (int(X(int(a[0]))),), np.array(f[1:4]), cov))

    # 3D edges
    def _edge_se3(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        i, j = int(a[0]), int(a[1])
        info = _upper(f[9:30], 6)[np.ix_(_PERM_G2O_TO_GTSAM, _PERM_G2O_TO_GTSAM)]
        meas = pose3_to_vector(pose3_from_vector(f[2:9]))
        if self.is_landmark_id(j):
            self._tag_row("BetweenFactorPose3", i, j, meas, _info_to_cov(info, where))
        else:
            kind = self._pp_kind(i, j)
            self.rows.append(
                FactorRow(kind, "BetweenFactorPose3", (int(X(i)), int(X(j))), meas, _info_to_cov(info, where))
            )

    def _edge_se3_trackxyz(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        i, j = int(a[0]), int(a[1])
        cov = _info_to_cov(_upper(f[6:12], 3), where)
        u, r, cbr = relative_position_to_bearing_range_3d(f[3:6], cov)
        self._tag_row("BearingRangeFactor3D", i, j, np.concatenate([np.asarray(u.point3()), [r]]), cbr)
        if j not in self.points:
            self.unplaced.setdefault(j, (i, np.array(f[3:6])))

    def _prior_se3(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        info = _upper(f[9:30], 6)[np.ix_(_PERM_G2O_TO_GTSAM, _PERM_G2O_TO_GTSAM)]
        meas = pose3_to_vector(pose3_from_vector(f[2:9]))
        self.rows.append(FactorRow("prior", "PriorFactorPose3", (int(X(int(a[0]))),), meas, _info_to_cov(info, where)))

    # others
    def _fix(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        self.fixed.extend(int(x) for x in a)

    def _ignore(self, tag: str, a: list[str], f: list[float], where: str) -> None:
        pass

    def _pp_kind(self, i: int, j: int) -> str:
        return "odometry" if abs(i - j) == 1 else "loop"

    def _tag_row(self, type_: str, i: int, j: int, meas: np.ndarray, cov: np.ndarray) -> None:
        tag_id = j - self.offset if self.offset is not None else j
        self.rows.append(
            FactorRow(
                "tag",
                type_,
                (int(X(i)), int(L(tag_id))),
                meas,
                cov,
                tag_id=tag_id,
                frame=i,
                stamp_ns=int(i * 1_000_000_000),
            )
        )


_Handler = Callable[[_Reader, str, list[str], list[float], str], None]
_HANDLERS: dict[str, tuple[int | None, _Handler]] = {
    "VERTEX_SE2": (2, _Reader._vertex_se2),
    "VERTEX_XY": (2, _Reader._vertex_point),
    "VERTEX_SE3:QUAT": (3, _Reader._vertex_se3),
    "VERTEX_TRACKXYZ": (3, _Reader._vertex_point),
    "EDGE_SE2": (2, _Reader._edge_se2),
    "EDGE_SE2_XY": (2, _Reader._edge_se2_xy),
    "BR": (2, _Reader._br),
    "EDGE_PRIOR_SE2": (2, _Reader._prior_se2),
    "EDGE_SE3:QUAT": (3, _Reader._edge_se3),
    "EDGE_SE3_TRACKXYZ": (3, _Reader._edge_se3_trackxyz),
    "EDGE_SE3_PRIOR": (3, _Reader._prior_se3),
    "FIX": (None, _Reader._fix),
    "PARAMS_SE3OFFSET": (None, _Reader._ignore),
}
"""Line tag to (the graph dimension it implies, its reader)."""


def _pose_prior(initial: gtsam.Values, key: int, model: GraphModel, sigma_m: float, sigma_rad: float) -> FactorRow:
    """A prior row holding pose ``key`` at its initial value with the given σ (m, rad)."""
    return model.prior_row(key, model.pose.vector(initial, key), sigma_m, sigma_rad)


def side_file(path: Path) -> Path:
    """The metadata file beside a g2o file focusmap wrote (``graph.g2o`` → ``graph.g2o.json``)."""
    return path.with_name(path.name + ".json")


def _side_offset(path: Path) -> int | None:
    """The landmark vertex id offset from the side file, if there is one."""
    side = side_file(path)
    if not side.is_file():
        return None
    try:
        offset = json.loads(side.read_text()).get("landmark_id_offset")
    except (OSError, ValueError, AttributeError) as err:
        raise InputError(f"cannot read {side.name} beside {path.name} ({err}); fix or remove it") from None
    return None if offset is None else int(offset)


def read_graph_file(path: Path, prior_sigma_m: float = 1e-3, prior_sigma_rad: float = 1e-3) -> GraphProblem:
    """Read a g2o file or GTSAM text dataset into a :class:`GraphProblem` (see the module docstring).

    GTSAM's readers read it unless it holds g2o lines they skip (``EDGE_SE2_XY``, priors, ``FIX``).

    Raises:
        InputError: unreadable file, no graph in it, a malformed line, a reader that rejects it, or an edge to a
            vertex that does not exist.
    """
    if not path.is_file():
        raise InputError(f"graph file {str(path)!r} not found; pass an existing .g2o or .graph file")
    scan = scan_file(path)
    side = _side_offset(path)
    if side is not None:
        scan.offset = side
    if not scan.needs_hand_parser:
        graph, values = read_with_gtsam(path, scan)
        return problem_from_gtsam(path, scan, graph, values, prior_sigma_m, prior_sigma_rad)
    return _read_by_hand(path, scan, prior_sigma_m, prior_sigma_rad)


def _read_by_hand(path: Path, scan: Scan, prior_sigma_m: float, prior_sigma_rad: float) -> GraphProblem:
    """A g2o file with lines GTSAM's readers skip, read line by line."""
    toro = sorted(TORO_TAGS & set(scan.tags))
    if toro:
        raise InputError(
            f"{path.name} mixes GTSAM dataset lines ({', '.join(toro)}) with g2o lines GTSAM's readers skip "
            f"({', '.join(sorted(set(scan.tags) & {'EDGE_SE2_XY', 'EDGE_PRIOR_SE2', 'EDGE_SE3_PRIOR', 'FIX'}))}); "
            "write the file in one of the two formats"
        )
    r = _Reader(path, scan.offset)
    r.read()
    r.rows = [row for row in r.rows if not (row.extra.get("br") and (row.frame, row.tag_id) in r.xy_pairs)]
    if r.dim is None or not r.poses:
        raise InputError(
            f"{path.name} holds no pose vertices (VERTEX_SE2 or VERTEX_SE3:QUAT); pass a g2o file with its vertices"
        )
    model = PLANAR if r.dim == 2 else SPATIAL
    pose_ids = sorted(i for i in r.poses if i not in r.pose3_landmarks)
    initial, var_types, landmark_keys = _vertices(r, model, pose_ids)
    for row in r.rows:
        for k in row.keys:
            if k not in var_types:
                sym = gtsam.Symbol(k)
                raise InputError(
                    f"{path.name}: a {row.kind} edge refers to vertex {sym.index()}, which the file does not define"
                )
    rows = list(r.rows)
    priors = [row for row in rows if row.kind == "prior"]
    for i in r.fixed:
        key = int(X(i))
        if key in var_types and var_kind(var_types[key]).is_pose:
            rows.insert(0, _pose_prior(initial, key, model, 1e-6, 1e-6))
            priors.append(rows[0])
    added_prior = not priors
    if added_prior:
        rows.insert(0, _pose_prior(initial, int(X(pose_ids[0])), model, prior_sigma_m, prior_sigma_rad))
    info = {
        "source_file": path.name,
        "format": "g2o",
        "reader": "focusmap (g2o lines GTSAM's readers skip)",
        "lines": dict(sorted(r.counts.items())),
        "skipped_lines": dict(sorted(scan.unknown.items())),
        "prior_added_on_first_pose": added_prior,
        "notes": ["read by focusmap's g2o reader (the file has lines GTSAM's readers skip)"]
        + ([f"lines no reader reads were skipped: {dict(sorted(scan.unknown.items()))}"] if scan.unknown else []),
    }
    return GraphProblem(
        model=model.name,
        rows=rows,
        initial=initial,
        var_types=var_types,
        pose_keys=[int(X(i)) for i in pose_ids],
        pose_stamps_ns=[int(i * 1_000_000_000) for i in pose_ids],
        landmark_keys=dict(sorted(landmark_keys.items())),
        info=info,
    )


def _vertices(
    r: _Reader, model: GraphModel, pose_ids: list[int]
) -> tuple[gtsam.Values, dict[int, str], dict[int, int]]:
    """Initial values, kinds and landmark keys of the vertices; landmarks without a vertex at their first sighting
    (as GTSAM's ``load2D`` does)."""
    initial = gtsam.Values()
    var_types: dict[int, str] = {}
    landmark_keys: dict[int, int] = {}

    def add(key: int, value: Any, kind: VarKind) -> None:
        initial.insert(key, value)
        var_types[key] = kind.name

    for i in pose_ids:
        add(int(X(i)), r.poses[i], model.pose)
    off = r.offset or 0
    for i in sorted(r.pose3_landmarks):
        add(int(L(i - off)), r.poses[i], POSE3)
        landmark_keys[i - off] = int(L(i - off))
    for j, p in sorted(r.points.items()):
        add(int(L(j - off)), np.asarray(p, dtype=float), model.point)
        landmark_keys[j - off] = int(L(j - off))
    for j, (i, rel) in r.unplaced.items():
        key = int(L(j - off))
        if key in var_types:
            continue
        if int(X(i)) not in var_types:
            raise InputError(f"{r.path.name}: landmark {j} is measured from pose {i}, which has no vertex")
        add(key, np.asarray(r.poses[i].transformFrom(rel)), model.point)
        landmark_keys[j - off] = key
    return initial, var_types, landmark_keys


_G2O_VERTEX = {
    POSE2.name: "VERTEX_SE2",
    POSE3.name: "VERTEX_SE3:QUAT",
    POINT2.name: "VERTEX_XY",
    POINT3.name: "VERTEX_TRACKXYZ",
}
"""The g2o vertex line of each variable kind."""
_G2O_PREAMBLE = {PLANAR.name: (), SPATIAL.name: ("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1",)}
"""Lines after the header, by graph model: the identity sensor offset the 3D landmark edges refer to."""


def _g2o_info_3d(cov: np.ndarray) -> list[float]:
    info = np.linalg.inv(cov)
    inv_perm = np.argsort(_PERM_G2O_TO_GTSAM)
    return _upper_list(info[np.ix_(inv_perm, inv_perm)])


def _fmt(vals: Any) -> str:
    return " ".join(f"{float(v):.9g}" for v in vals)


def _vertex_ids(problem: GraphProblem) -> tuple[int, dict[int, int]]:
    """The landmark vertex id offset (a power of ten above the pose count) and the vertex id of every key."""
    offset = 10 ** len(str(max(len(problem.pose_keys), 1)))
    vid = {k: i for i, k in enumerate(problem.pose_keys)}
    for tag, key in problem.landmark_keys.items():
        vid[key] = offset + tag
    return offset, vid


def _tag_scale(problem: GraphProblem, values: gtsam.Values) -> float | None:
    key = problem.scale_key
    return float(values.atDouble(key)) if key is not None and values.exists(key) else None


def g2o_metadata(problem: GraphProblem, values: gtsam.Values) -> dict[str, Any]:
    """What :func:`write_g2o` writes beside the g2o lines (the side file ``<name>.g2o.json``)."""
    offset, _ = _vertex_ids(problem)
    rows = [r for r in problem.rows if r.kind != "scale_prior"]
    written = [r for r in rows if r.type in _G2O_EDGE]
    priors = sum(r.type.startswith("Prior") for r in written)
    rho = [_correlation(np.asarray(r.covariance, dtype=float)) for r in written if r.type == "BearingRangeFactor2D"]
    return {
        "landmark_id_offset": offset,
        "poses": len(problem.pose_keys),
        "landmarks": len(problem.landmark_keys),
        "max_tag_id": max(problem.landmark_keys, default=0),
        "edges": len(written),
        "edges_gtsam_reads": len(written) - priors,
        "priors": priors,
        "tag_scale": _tag_scale(problem, values),
        "planar_landmark_br_copies": problem.model == PLANAR.name
        and any(r.type == "BearingRangeFactor2D" for r in written),
        "br_max_abs_correlation_dropped": max((abs(v) for v in rho), default=0.0),
        "not_written": sorted({r.type for r in rows if r.type not in _G2O_EDGE}),
    }


def _correlation(cov: np.ndarray) -> float:
    """The bearing-range correlation of a planar tag measurement (a ``BR`` line cannot hold it)."""
    C = cov.reshape(2, 2)
    return float(C[0, 1] / np.sqrt(C[0, 0] * C[1, 1]))


_G2O_EDGE = {
    "BetweenFactorPose2": "EDGE_SE2",
    "PriorFactorPose2": "EDGE_PRIOR_SE2",
    "BearingRangeFactor2D": "EDGE_SE2_XY",
    "BetweenFactorPose3": "EDGE_SE3:QUAT",
    "PriorFactorPose3": "EDGE_SE3_PRIOR",
    "BearingRangeFactor3D": "EDGE_SE3_TRACKXYZ",
}
"""The g2o edge of each factor type written."""


def write_g2o(problem: GraphProblem, values: gtsam.Values) -> str:
    """The problem at ``values`` as g2o text; landmark vertex id = offset + tag id (offset in :func:`g2o_metadata`).

    No comment lines: ``gtsam.readG2o`` reads every edge but the priors (it reads no prior line), and g2o every
    one. Bearing-range factors are written as relative landmark positions (``EDGE_SE2_XY`` /
    ``EDGE_SE3_TRACKXYZ``) with the covariance mapped back to first order; planar ones also as GTSAM's
    ``BR`` line right after (bearing, range and their σ; g2o skips it, GTSAM reads it and skips ``EDGE_SE2_XY``;
    ``BR`` has no bearing-range correlation). Priors as ``EDGE_PRIOR_SE2`` / ``EDGE_SE3_PRIOR``.
    :func:`read_graph_file` reads the file back into the same graph. g2o has no shared scale: tag measurements
    that carry the tag scale ``s`` are written at its value in ``values`` (range, translation times ``s``; the
    side file gives ``s``) and its prior is left out, so the file is the graph with the scale fixed at that value.
    """
    _, vid = _vertex_ids(problem)
    out = list(_G2O_PREAMBLE[problem.model])
    for k in [*problem.pose_keys, *problem.landmark_keys.values()]:
        kind = problem.kind(k)
        out.append(f"{_G2O_VERTEX[kind.name]} {vid[k]} {_fmt(kind.vector(values, k))}")
    scale_key = problem.scale_key
    s = _tag_scale(problem, values) or 1.0
    for row in problem.rows:
        if row.kind == "scale_prior" or row.type not in _G2O_EDGE:
            continue
        C = np.asarray(row.covariance, dtype=float).reshape(row.dim, row.dim)
        m = scaled_measurement(row, s)
        ids = " ".join(str(vid[k]) for k in row.keys if k != scale_key)
        tag = _G2O_EDGE[row.type]
        if row.type in ("BetweenFactorPose2", "PriorFactorPose2"):
            out.append(f"{tag} {ids} {_fmt(m)} {_fmt(_upper_list(np.linalg.inv(C)))}")
        elif row.type == "BearingRangeFactor2D":
            p, Cp = bearing_range_to_relative_position_2d(m[0], m[1], C)
            out.append(f"{tag} {ids} {_fmt(p)} {_fmt(_upper_list(np.linalg.inv(Cp)))}")
            out.append(f"BR {ids} {_fmt(m)} {_fmt(np.sqrt(np.diag(C)))}")
        elif row.type == "BetweenFactorPose3":
            out.append(f"{tag} {ids} {_fmt(m)} {_fmt(_g2o_info_3d(C))}")
        elif row.type == "PriorFactorPose3":
            out.append(f"{tag} {ids} 0 {_fmt(m)} {_fmt(_g2o_info_3d(C))}")
        else:
            p, Cp = bearing_range_to_relative_position_3d(gtsam.Unit3(m[:3]), m[3], C)
            out.append(f"{tag} {ids} 0 {_fmt(p)} {_fmt(_upper_list(np.linalg.inv(Cp)))}")
    return "\n".join(out) + "\n"
