"""Read g2o files (2D and 3D, with landmarks) and GTSAM text datasets into a :class:`GraphProblem`; write g2o.

Lines read (others are counted in ``info["skipped_lines"]``):

- g2o 2D: ``VERTEX_SE2 id x y th``, ``VERTEX_XY id x y``, ``EDGE_SE2 i j x y th I(6)`` (upper-triangular
  information), ``EDGE_SE2_XY i l x y I(3)`` (landmark position in the pose frame), ``EDGE_PRIOR_SE2 i x y th I(6)``,
  ``FIX id``.
- g2o 3D: ``VERTEX_SE3:QUAT id x y z qx qy qz qw``, ``VERTEX_TRACKXYZ id x y z``, ``EDGE_SE3:QUAT i j x y z qx qy qz qw
  I(21)``, ``EDGE_SE3_TRACKXYZ i l param x y z I(6)``, ``EDGE_SE3_PRIOR i param x y z qx qy qz qw I(21)``. The 6x6
  information is permuted from g2o's (t, q) order to gtsam's (r, t) as ``gtsam.readG2o`` does.
- GTSAM ``.graph``: ``VERTEX2 id x y th``, ``EDGE2 i j x y th v(6)`` (covariance; GTSAM's layout detection),
  ``BR i l bearing range bearing_std range_std``, ``LANDMARK i l x y I(3)``, ``EQUIV i j`` (counted, not
  used, as GTSAM's ``load2D`` does).

Relative landmark positions become bearing-range factors (the same measurement to first order). Pose
vertices get keys ``X(id)`` and landmark vertices ``L(id)``; imported graphs have no clock, so the pose
stamp is the vertex id in seconds. A prior is added on the first pose when the file fixes none.
"""

from __future__ import annotations

from collections import Counter
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
from stages.graph.factors import FactorRow, scaled_measurement
from stages.graph.problem import GraphProblem, value_vector

OFFSET_TAG = "# focusmap: landmark_id_offset"
_PERM_G2O_TO_GTSAM = [3, 4, 5, 0, 1, 2]


def _upper(values: list[float], n: int) -> np.ndarray:
    M = np.zeros((n, n))
    M[np.triu_indices(n)] = values
    return M + np.triu(M, 1).T


def _upper_list(M: np.ndarray) -> list[float]:
    return [float(v) for v in M[np.triu_indices(M.shape[0])]]


def _info_to_cov(info: np.ndarray, where: str) -> np.ndarray:
    try:
        return np.linalg.inv(info)
    except np.linalg.LinAlgError:
        raise InputError(f"{where}: the information matrix is singular; fix the file") from None


def _graph_noise(v: list[float], where: str) -> np.ndarray:
    """GTSAM ``.graph`` EDGE2 noise, a covariance, with GTSAM's detection of its layout."""
    v1, v2, v3, v4, v5, v6 = v
    if v1 != 0 and v2 == 0 and v3 == 0 and v4 != 0 and v5 == 0 and v6 != 0 and not (v3 != 0 and v6 == 0):
        C = np.array([[v1, v2, v3], [v2, v4, v5], [v3, v5, v6]])  # COV layout
    else:
        C = np.array([[v1, v2, v5], [v2, v3, v6], [v5, v6, v4]])  # GRAPH/TORO layout
    if min(C[0, 0], C[1, 1], C[2, 2]) <= 0:
        raise InputError(f"{where}: the EDGE2 covariance has a zero diagonal; fix the file")
    return C


class _Reader:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.poses: dict[int, Any] = {}
        self.points: dict[int, np.ndarray] = {}
        self.pose3_landmarks: set[int] = set()
        self.rows: list[FactorRow] = []
        self.fixed: list[int] = []
        self.counts: Counter[str] = Counter()
        self.equiv = 0
        self.offset: int | None = None
        self.dim: int | None = None
        self.pending_br: list[tuple[int, int, float, float]] = []
        self.points_rel: dict[int, tuple[int, np.ndarray]] = {}

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
            if s.startswith(OFFSET_TAG):
                self.offset = int(s.split()[-1])
                continue
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            tag = parts[0]
            where = f"{self.path.name}:{n}"
            try:
                self._line(tag, parts[1:], where)
            except (ValueError, IndexError) as err:
                raise InputError(f"{where}: cannot parse {tag!r} line ({err}); fix the file") from err
            self.counts[tag] += 1

    def _line(self, tag: str, a: list[str], where: str) -> None:
        f = [float(x) for x in a]
        if tag in ("VERTEX_SE2", "VERTEX2"):
            self.set_dim(2, where)
            i = int(a[0])
            if self.is_landmark_id(i):
                self.points[i] = np.array(f[1:3])
            else:
                self.poses[i] = gtsam.Pose2(f[1], f[2], f[3])
        elif tag == "VERTEX_XY":
            self.set_dim(2, where)
            self.points[int(a[0])] = np.array(f[1:3])
        elif tag == "VERTEX_SE3:QUAT":
            self.set_dim(3, where)
            i = int(a[0])
            p = pose3_from_vector(f[1:8])
            self.poses[i] = p
            if self.is_landmark_id(i):
                self.pose3_landmarks.add(i)
        elif tag == "VERTEX_TRACKXYZ":
            self.set_dim(3, where)
            self.points[int(a[0])] = np.array(f[1:4])
        elif tag in ("EDGE_SE2", "EDGE2"):
            self.set_dim(2, where)
            i, j = int(a[0]), int(a[1])
            cov = _info_to_cov(_upper(f[5:11], 3), where) if tag == "EDGE_SE2" else _graph_noise(f[5:11], where)
            if self.is_landmark_id(j):
                raise InputError(f"{where}: EDGE_SE2 to landmark vertex {j}; use EDGE_SE2_XY")
            self.rows.append(
                FactorRow(self._pp_kind(i, j), "BetweenFactorPose2", (int(X(i)), int(X(j))), np.array(f[2:5]), cov)
            )
        elif tag in ("EDGE_SE2_XY", "LANDMARK"):
            self.set_dim(2, where)
            i, j = int(a[0]), int(a[1])
            cov = _info_to_cov(_upper(f[4:7], 2), where)
            b, r, cbr = relative_position_to_bearing_range_2d(f[2:4], cov)
            self._tag_row("BearingRangeFactor2D", i, j, np.array([b, r]), cbr)
            if j not in self.points:
                self.pending_br.append((i, j, b, r))
        elif tag == "BR":
            self.set_dim(2, where)
            i, j = int(a[0]), int(a[1])
            b, r, sb, sr = f[2], f[3], f[4], f[5]
            self._tag_row("BearingRangeFactor2D", i, j, np.array([b, r]), np.diag([sb**2, sr**2]))
            if j not in self.points:
                self.pending_br.append((i, j, b, r))
        elif tag == "EDGE_PRIOR_SE2":
            self.set_dim(2, where)
            self.rows.append(
                FactorRow(
                    "prior",
                    "PriorFactorPose2",
                    (int(X(int(a[0]))),),
                    np.array(f[1:4]),
                    _info_to_cov(_upper(f[4:10], 3), where),
                )
            )
        elif tag == "EDGE_SE3:QUAT":
            self.set_dim(3, where)
            i, j = int(a[0]), int(a[1])
            info = _upper(f[9:30], 6)[np.ix_(_PERM_G2O_TO_GTSAM, _PERM_G2O_TO_GTSAM)]
            meas = pose3_to_vector(pose3_from_vector(f[2:9]))
            if self.is_landmark_id(j):
                self._tag_row("BetweenFactorPose3", i, j, meas, _info_to_cov(info, where))
            else:
                self.rows.append(
                    FactorRow(
                        self._pp_kind(i, j),
                        "BetweenFactorPose3",
                        (int(X(i)), int(X(j))),
                        meas,
                        _info_to_cov(info, where),
                    )
                )
        elif tag == "EDGE_SE3_TRACKXYZ":
            self.set_dim(3, where)
            i, j = int(a[0]), int(a[1])
            cov = _info_to_cov(_upper(f[6:12], 3), where)
            u, r, cbr = relative_position_to_bearing_range_3d(f[3:6], cov)
            self._tag_row("BearingRangeFactor3D", i, j, np.concatenate([np.asarray(u.point3()), [r]]), cbr)
            if j not in self.points:
                self.pending_br.append((i, j, 0.0, 0.0))
                self.points_rel.setdefault(j, (i, np.array(f[3:6])))
        elif tag == "EDGE_SE3_PRIOR":
            self.set_dim(3, where)
            info = _upper(f[9:30], 6)[np.ix_(_PERM_G2O_TO_GTSAM, _PERM_G2O_TO_GTSAM)]
            self.rows.append(
                FactorRow(
                    "prior",
                    "PriorFactorPose3",
                    (int(X(int(a[0]))),),
                    pose3_to_vector(pose3_from_vector(f[2:9])),
                    _info_to_cov(info, where),
                )
            )
        elif tag == "FIX":
            self.fixed.extend(int(x) for x in a)
        elif tag == "EQUIV":
            self.equiv += 1
        elif tag == "PARAMS_SE3OFFSET":
            pass
        else:
            self.counts["skipped:" + tag] += 1

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


def _pose_prior(initial: gtsam.Values, key: int, planar: bool, sigma_m: float, sigma_rad: float) -> FactorRow:
    """A prior row holding pose ``key`` at its initial value with the given σ (m, rad)."""
    if planar:
        cov = np.diag([sigma_m**2] * 2 + [sigma_rad**2])
        return FactorRow("prior", "PriorFactorPose2", (key,), value_vector(initial, key, "Pose2")[:3], cov)
    cov = np.diag([sigma_rad**2] * 3 + [sigma_m**2] * 3)
    return FactorRow("prior", "PriorFactorPose3", (key,), value_vector(initial, key, "Pose3")[:7], cov)


def read_graph_file(path: Path, prior_sigma_m: float = 1e-3, prior_sigma_rad: float = 1e-3) -> GraphProblem:
    """Parse a g2o or GTSAM ``.graph`` file into a :class:`GraphProblem` (see the module docstring).

    Raises:
        InputError: unreadable file, unknown content, a malformed line, or an edge to a vertex that does not exist.
    """
    if not path.is_file():
        raise InputError(f"graph file {str(path)!r} not found; pass an existing .g2o or .graph file")
    r = _Reader(path)
    r.read()
    if r.dim is None or not r.poses:
        raise InputError(
            f"{path.name} holds no pose vertices (VERTEX_SE2, VERTEX_SE3:QUAT or VERTEX2); "
            "pass a g2o or GTSAM .graph file"
        )
    planar = r.dim == 2
    pose_ids = sorted(i for i in r.poses if i not in r.pose3_landmarks)
    initial = gtsam.Values()
    var_types: dict[int, str] = {}
    for i in pose_ids:
        initial.insert(int(X(i)), r.poses[i])
        var_types[int(X(i))] = "Pose2" if planar else "Pose3"
    off = r.offset or 0
    landmark_keys: dict[int, int] = {}
    for i in sorted(r.pose3_landmarks):
        key = int(L(i - off))
        initial.insert(key, r.poses[i])
        var_types[key] = "Pose3"
        landmark_keys[i - off] = key
    for j, p in sorted(r.points.items()):
        key = int(L(j - off))
        initial.insert(key, np.asarray(p, dtype=float))
        var_types[key] = "Point2" if planar else "Point3"
        landmark_keys[j - off] = key
    # landmarks without a vertex: first sighting, as GTSAM's load2D does
    rel3 = r.points_rel
    for i, j, b, rng in r.pending_br:
        key = int(L(j - off))
        if key in var_types:
            continue
        if int(X(i)) not in var_types:
            raise InputError(f"{path.name}: landmark {j} is measured from pose {i}, which has no vertex")
        if planar:
            pt = r.poses[i].transformFrom(np.array([rng * np.cos(b), rng * np.sin(b)]))
            initial.insert(key, np.asarray(pt))
            var_types[key] = "Point2"
        else:
            pi, rel = rel3[j]
            initial.insert(key, np.asarray(r.poses[pi].transformFrom(rel)))
            var_types[key] = "Point3"
        landmark_keys[j - off] = key
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
        if key in var_types and var_types[key].startswith("Pose"):
            rows.insert(0, _pose_prior(initial, key, planar, 1e-6, 1e-6))
            priors.append(rows[0])
    added_prior = False
    if not priors:
        rows.insert(0, _pose_prior(initial, int(X(pose_ids[0])), planar, prior_sigma_m, prior_sigma_rad))
        added_prior = True
    info = {
        "source_file": path.name,
        "format": "gtsam-graph" if any(t in r.counts for t in ("VERTEX2", "EDGE2", "BR")) else "g2o",
        "lines": dict(sorted(r.counts.items())),
        "equivalences_ignored": r.equiv,
        "prior_added_on_first_pose": added_prior,
    }
    return GraphProblem(
        model="planar" if planar else "3d",
        rows=rows,
        initial=initial,
        var_types=var_types,
        pose_keys=[int(X(i)) for i in pose_ids],
        pose_stamps_ns=[int(i * 1_000_000_000) for i in pose_ids],
        landmark_keys=dict(sorted(landmark_keys.items())),
        info=info,
    )


def _g2o_info_3d(cov: np.ndarray) -> list[float]:
    info = np.linalg.inv(cov)
    inv_perm = np.argsort(_PERM_G2O_TO_GTSAM)
    return _upper_list(info[np.ix_(inv_perm, inv_perm)])


def _fmt(vals: Any) -> str:
    return " ".join(f"{float(v):.9g}" for v in vals)


def write_g2o(problem: GraphProblem, values: gtsam.Values) -> str:
    """The problem at ``values`` as g2o text; landmark vertex id = offset + tag id (offset in a comment line).

    Bearing-range factors are written as relative landmark positions (``EDGE_SE2_XY`` /
    ``EDGE_SE3_TRACKXYZ``) with the covariance mapped back to first order; priors as ``EDGE_PRIOR_SE2`` /
    ``EDGE_SE3_PRIOR``. :func:`read_graph_file` reads the file back into the same graph. g2o has no
    shared scale: tag measurements that carry the tag scale ``s`` are written at its value in ``values``
    (range, translation times ``s``; a comment line gives ``s``) and its prior is left out, so the file
    is the graph with the scale fixed at that value.
    """
    n = len(problem.pose_keys)
    max_tag = max(problem.landmark_keys, default=0)
    offset = 10 ** len(str(max(n, 1)))
    vid = {k: i for i, k in enumerate(problem.pose_keys)}
    for tag, key in problem.landmark_keys.items():
        vid[key] = offset + tag
    planar = problem.model == "planar"
    out = [
        f"{OFFSET_TAG} {offset}",
        f"# focusmap graph: {n} poses, {len(problem.landmark_keys)} landmarks, max tag id {max_tag}",
    ]
    if not planar:
        out.append("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1")
    for k in problem.pose_keys:
        t = problem.var_types[k]
        v = value_vector(values, k, t)
        out.append(f"VERTEX_SE2 {vid[k]} {_fmt(v[:3])}" if t == "Pose2" else f"VERTEX_SE3:QUAT {vid[k]} {_fmt(v[:7])}")
    for _tag, k in problem.landmark_keys.items():
        t = problem.var_types[k]
        v = value_vector(values, k, t)
        if t == "Point2":
            out.append(f"VERTEX_XY {vid[k]} {_fmt(v[:2])}")
        elif t == "Point3":
            out.append(f"VERTEX_TRACKXYZ {vid[k]} {_fmt(v[:3])}")
        else:
            out.append(f"VERTEX_SE3:QUAT {vid[k]} {_fmt(v[:7])}")
    scale_key = problem.scale_key
    s = float(values.atDouble(scale_key)) if scale_key is not None and values.exists(scale_key) else 1.0
    if scale_key is not None:
        out.append(f"# focusmap: tag_scale {s:.9g} (tag measurements below are written at this scale)")
    for row in problem.rows:
        if row.kind == "scale_prior":
            continue
        C = np.asarray(row.covariance, dtype=float).reshape(row.dim, row.dim)
        m = scaled_measurement(row, s)
        ids = [vid[k] for k in row.keys if k != scale_key]
        if row.type == "BetweenFactorPose2":
            out.append(f"EDGE_SE2 {ids[0]} {ids[1]} {_fmt(m)} {_fmt(_upper_list(np.linalg.inv(C)))}")
        elif row.type == "PriorFactorPose2":
            out.append(f"EDGE_PRIOR_SE2 {ids[0]} {_fmt(m)} {_fmt(_upper_list(np.linalg.inv(C)))}")
        elif row.type == "BearingRangeFactor2D":
            p, Cp = bearing_range_to_relative_position_2d(m[0], m[1], C)
            out.append(f"EDGE_SE2_XY {ids[0]} {ids[1]} {_fmt(p)} {_fmt(_upper_list(np.linalg.inv(Cp)))}")
        elif row.type == "BetweenFactorPose3":
            out.append(f"EDGE_SE3:QUAT {ids[0]} {ids[1]} {_fmt(m)} {_fmt(_g2o_info_3d(C))}")
        elif row.type == "PriorFactorPose3":
            out.append(f"EDGE_SE3_PRIOR {ids[0]} 0 {_fmt(m)} {_fmt(_g2o_info_3d(C))}")
        elif row.type == "BearingRangeFactor3D":
            p, Cp = bearing_range_to_relative_position_3d(gtsam.Unit3(m[:3]), m[3], C)
            out.append(f"EDGE_SE3_TRACKXYZ {ids[0]} {ids[1]} 0 {_fmt(p)} {_fmt(_upper_list(np.linalg.inv(Cp)))}")
        else:
            out.append(f"# {row.type} {ids} not representable in g2o")
    return "\n".join(out) + "\n"
