"""Factors as table rows, and back: the one representation that the graph stage writes and later stages rebuild.

A :class:`FactorRow` names a gtsam factor type, its keys, its measurement as plain numbers, its
covariance, and an optional robust kernel. :func:`make_factor` turns it into the gtsam factor, so
``factors.parquet`` rebuilds exactly the graph that was optimised.

Measurement layouts per ``type``:

| type | measurement | covariance (tangent order) |
| --- | --- | --- |
| ``PriorFactorPose2`` / ``BetweenFactorPose2`` | x, y, theta | 3x3 (x, y, theta) |
| ``PriorFactorPose3`` / ``BetweenFactorPose3`` | x, y, z, qx, qy, qz, qw | 6x6 (rx, ry, rz, tx, ty, tz) |
| ``BearingRangeFactor2D`` (Pose2 -> Point2) | bearing (rad), range (m) | 2x2 (bearing, range) |
| ``BearingRangeFactor3D`` (Pose3 -> Point3) | ux, uy, uz (unit bearing), range (m) | 3x3 (Unit3 basis 2, range) |
| ``PriorFactorPoint2`` / ``PriorFactorPoint3`` | x, y (, z) | 2x2 / 3x3 |
| ``PriorFactorDouble`` (the tag scale ``s0``) | 1.0 | 1x1 (relative variance) |

The tag scale: a ``BearingRangeFactor2D`` or ``BetweenFactorPose3`` row with a third key (the scale variable
``S = symbol('s', 0)``, a ``Double``) measures ``s · measured``: the range (planar) or the translation (3d)
of every tag measurement is multiplied by one shared unknown ``s`` (the error of the printed tag size; a
tag printed 0.3 % large makes every range 0.3 % short). It becomes a ``gtsam.CustomFactor`` with exact
Jacobians (:func:`scaled_bearing_range_error`, :func:`scaled_between_error`); the measurement and
covariance columns keep their meaning, so a reader that ignores the third key gets the old factor at
``s = 1``. ``s`` has a ``PriorFactorDouble`` N(1, sigma²) (kind ``scale_prior``, always kept).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import gtsam
import numpy as np
import pyarrow as pa

from stages.geometry import pose3_from_vector
from stages.graph.artifacts import (
    DIM,
    FACTOR_COVARIANCE,
    FACTOR_FRAME,
    FACTOR_STAMP_NS,
    FACTOR_TAG_ID,
    FACTORS,
    INDEX,
    KEY_NAMES,
    KEYS,
    KIND,
    MEASUREMENT,
    ROBUST,
    ROBUST_K,
    TYPE,
)

KINDS = ("prior", "odometry", "loop", "motion_prior", "tag", "scale_prior", "tag_prior")
"""Factor kinds: ``tag`` rows are the landmark measurements (the candidates of the selection stages);
``loop`` is a pose-to-pose edge between non-consecutive poses of an imported graph; ``scale_prior`` is
the prior N(1, sigma²) of the shared tag scale; ``tag_prior`` the prior on a surveyed tag's pose (``--tags``)."""

SCALE_KEY = int(gtsam.symbol("s", 0))
"""Key of the shared tag scale ``s`` (a ``Double``; type name ``Scale`` in ``values.npz``)."""

FACTOR_DIMS = {
    "PriorFactorPose2": 3,
    "BetweenFactorPose2": 3,
    "PriorFactorPose3": 6,
    "BetweenFactorPose3": 6,
    "BearingRangeFactor2D": 2,
    "BearingRangeFactor3D": 3,
    "PriorFactorPoint2": 2,
    "PriorFactorPoint3": 3,
    "PriorFactorDouble": 1,
}


@dataclass(slots=True)
class FactorRow:
    """One factor of the graph as plain data (one row of ``factors.parquet``).

    Slotted: an hour's graph holds about 80,000 of them in every stage that loads it (without slots each carried
    its own attribute dict)."""

    kind: str
    type: str
    keys: tuple[int, ...]
    measurement: np.ndarray
    covariance: np.ndarray
    robust: str = "none"
    robust_k: float = 0.0
    tag_id: int | None = None
    frame: int | None = None
    stamp_ns: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def dim(self) -> int:
        """Dimension of the residual."""
        return FACTOR_DIMS[self.type]


def noise_model(cov: np.ndarray, robust: str = "none", robust_k: float = 0.0) -> gtsam.noiseModel.Base:
    """A Gaussian noise model from a full covariance, wrapped in a Huber or Cauchy kernel if asked."""
    C = np.asarray(cov, dtype=float)
    C = 0.5 * (C + C.T)
    base = gtsam.noiseModel.Gaussian.Covariance(C)
    if robust == "none":
        return base
    if robust == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k), base)
    if robust == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_k), base)
    raise ValueError(f"unknown robust kernel {robust!r}; use none, huber or cauchy")


def scaled_bearing_range_error(
    pose: gtsam.Pose2, point: np.ndarray, s: float, bearing: float, rng: float
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Error of a bearing-range measurement of a tag whose true size is ``s`` times the assumed one, and its Jacobians.

    ``e = (wrap(bearing(pose, point) − bearing), range(pose, point) / s − rng)``: the measured range is the true
    range divided by ``s`` plus the noise the factor's covariance describes (gtsam's ``BearingRangeFactor2D`` error
    at ``s = 1``). Dividing the prediction, not multiplying the measurement, keeps that noise independent of ``s``;
    ``range − s · rng`` would scale the noise by ``s`` and the least-squares ``s`` would shrink towards 0 by about the
    range noise over the spread of each tag's ranges (measured: −1.2 σ_s on image-free runs). Jacobians in the
    tangent spaces of the Pose2 (x, y, θ), the Point2 and the scale: 2x3, 2x2, 2x1.
    """
    # Written out in floats (a third of the time of gtsam's bearing/range with Jacobian arrays; this runs once per
    # tag factor per linearisation). Body-frame point d = Rᵀ(p − t); right perturbation of the pose:
    # ∂d/∂(v, ω) = [−I | (d_y, −d_x)], ∂d/∂p = Rᵀ; bearing atan2(d_y, d_x), range |d|.
    c, sn = math.cos(pose.theta()), math.sin(pose.theta())
    wx, wy = float(point[0]) - pose.x(), float(point[1]) - pose.y()
    dx, dy = c * wx + sn * wy, -sn * wx + c * wy
    r2 = dx * dx + dy * dy
    r = math.sqrt(r2)
    eb = (math.atan2(dy, dx) - bearing + math.pi) % (2 * math.pi) - math.pi
    gbx, gby, grx, gry = -dy / r2, dx / r2, dx / (r * s), dy / (r * s)
    H_pose = np.array([[-gbx, -gby, -1.0], [-grx, -gry, 0.0]])
    H_point = np.array([[gbx * c - gby * sn, gbx * sn + gby * c], [grx * c - gry * sn, grx * sn + gry * c]])
    return np.array([eb, r / s - rng]), [H_pose, H_point, np.array([[0.0], [-r / (s * s)]])]


def scaled_between_error(
    a: gtsam.Pose3, b: gtsam.Pose3, s: float, measured: gtsam.Pose3
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Error of a relative-pose measurement of a tag whose true size is ``s`` times the assumed one, and its Jacobians.

    ``e = Log(M⁻¹ P(s))`` with ``P = a⁻¹ b = (R, t)`` and ``P(s) = (R, t / s)``: the measured translation is the true
    one divided by ``s`` (gtsam's ``BetweenFactorPose3`` error at ``s = 1``; why the prediction is divided: see
    :func:`scaled_bearing_range_error`). Jacobians 6x6, 6x6 (right perturbations, tangent order (r, t)) and 6x1:
    ``∂P(s)/∂P = diag(I, I / s)``, ``P(s + ds) = P(s) Exp((0, −Rᵀ t ds / s²))``.
    """
    Ha, Hb = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    pred = a.between(b, Ha, Hb)
    t = np.asarray(pred.translation())
    R = pred.rotation()
    Hm, Hp = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    E = measured.between(gtsam.Pose3(R, t / s), Hm, Hp)
    Hlog = np.zeros((6, 6), order="F")
    e = gtsam.Pose3.Logmap(E, Hlog)
    Hlp = Hlog @ Hp
    Hlp_scaled = Hlp.copy()
    Hlp_scaled[:, 3:] /= s  # ∂P(s)/∂P = diag(I, I / s)
    dP = np.zeros((6, 1))
    dP[3:, 0] = -(np.asarray(R.matrix()).T @ t) / (s * s)
    return np.asarray(e, dtype=float), [Hlp_scaled @ Ha, Hlp_scaled @ Hb, Hlp @ dP]


def _scaled_bearing_range_factor(
    keys: tuple[int, ...], m: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    bearing, rng = float(m[0]), float(m[1])
    kx, kl, ks = keys

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        e, J = scaled_bearing_range_error(v.atPose2(kx), v.atPoint2(kl), v.atDouble(ks), bearing, rng)
        if H is not None:
            H[0], H[1], H[2] = J
        return e

    return gtsam.CustomFactor(noise, list(keys), error)


def _scaled_between_factor(keys: tuple[int, ...], m: np.ndarray, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    measured = pose3_from_vector(m)
    ka, kb, ks = keys

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        e, J = scaled_between_error(v.atPose3(ka), v.atPose3(kb), v.atDouble(ks), measured)
        if H is not None:
            H[0], H[1], H[2] = J
        return e

    return gtsam.CustomFactor(noise, list(keys), error)


def scaled_measurement(row: FactorRow, s: float) -> np.ndarray:
    """The measurement of a row at tag scale ``s`` (unchanged for rows without the scale key)."""
    m = np.asarray(row.measurement, dtype=float).copy()
    if len(row.keys) == 3 and row.type == "BearingRangeFactor2D":
        m[1] *= s
    elif len(row.keys) == 3 and row.type == "BetweenFactorPose3":
        m[:3] *= s
    return m


def make_factor(row: FactorRow) -> gtsam.NonlinearFactor:
    """The gtsam factor of a row (a ``CustomFactor`` for the tag rows that carry the scale key)."""
    d = row.dim
    cov = np.asarray(row.covariance, dtype=float).reshape(d, d)
    noise = noise_model(cov, row.robust, row.robust_k)
    m = np.asarray(row.measurement, dtype=float)
    k = row.keys
    t = row.type
    if len(k) == 3 and t == "BearingRangeFactor2D":
        return _scaled_bearing_range_factor(k, m, noise)
    if len(k) == 3 and t == "BetweenFactorPose3":
        return _scaled_between_factor(k, m, noise)
    if t == "PriorFactorDouble":
        return gtsam.PriorFactorDouble(k[0], float(m[0]), noise)
    if t == "PriorFactorPose2":
        return gtsam.PriorFactorPose2(k[0], gtsam.Pose2(m[0], m[1], m[2]), noise)
    if t == "BetweenFactorPose2":
        return gtsam.BetweenFactorPose2(k[0], k[1], gtsam.Pose2(m[0], m[1], m[2]), noise)
    if t == "PriorFactorPose3":
        return gtsam.PriorFactorPose3(k[0], pose3_from_vector(m), noise)
    if t == "BetweenFactorPose3":
        return gtsam.BetweenFactorPose3(k[0], k[1], pose3_from_vector(m), noise)
    if t == "BearingRangeFactor2D":
        return gtsam.BearingRangeFactor2D(k[0], k[1], gtsam.Rot2(m[0]), float(m[1]), noise)
    if t == "BearingRangeFactor3D":
        return gtsam.BearingRangeFactor3D(k[0], k[1], gtsam.Unit3(m[:3]), float(m[3]), noise)
    if t == "PriorFactorPoint2":
        return gtsam.PriorFactorPoint2(k[0], m[:2], noise)
    if t == "PriorFactorPoint3":
        return gtsam.PriorFactorPoint3(k[0], m[:3], noise)
    raise ValueError(f"unknown factor type {t!r}")


def has_python_factors(rows: Iterable[FactorRow]) -> bool:
    """Whether any row becomes a ``gtsam.CustomFactor`` (the tag rows that carry the shared scale)."""
    return any(len(r.keys) == 3 and r.type in ("BearingRangeFactor2D", "BetweenFactorPose3") for r in rows)


def build_graph(rows: Iterable[FactorRow]) -> gtsam.NonlinearFactorGraph:
    """A ``NonlinearFactorGraph`` with one factor per row, in row order (factor i is row i)."""
    graph = gtsam.NonlinearFactorGraph()
    for row in rows:
        graph.add(make_factor(row))
    return graph


def key_name(key: int) -> str:
    """``x12`` / ``l17`` / ``s0`` for symbol keys, the number otherwise."""
    sym = gtsam.Symbol(int(key))
    ch = sym.chr()
    if ch in (ord("x"), ord("l"), ord("s")):
        return f"{chr(ch)}{sym.index()}"
    return str(int(key))


def rows_to_table(rows: Sequence[FactorRow]) -> pa.Table:
    """``factors.parquet`` (:data:`stages.graph.artifacts.FACTORS`): one row per factor, ``index`` = position in the
    graph."""
    return FACTORS.table(
        {
            INDEX: np.arange(len(rows), dtype=np.int64),
            KIND: [r.kind for r in rows],
            TYPE: [r.type for r in rows],
            KEYS: [[int(k) for k in r.keys] for r in rows],
            KEY_NAMES: [[key_name(k) for k in r.keys] for r in rows],
            MEASUREMENT: [np.asarray(r.measurement, dtype=float).tolist() for r in rows],
            FACTOR_COVARIANCE: [np.asarray(r.covariance, dtype=float).ravel().tolist() for r in rows],
            DIM: np.array([r.dim for r in rows], dtype=np.int32),
            ROBUST: [r.robust for r in rows],
            ROBUST_K: np.array([r.robust_k for r in rows], dtype=float),
            FACTOR_TAG_ID: [r.tag_id for r in rows],
            FACTOR_FRAME: [r.frame for r in rows],
            FACTOR_STAMP_NS: [r.stamp_ns for r in rows],
        }
    )


def table_to_rows(table: pa.Table) -> list[FactorRow]:
    """Inverse of :func:`rows_to_table` (rows in ``index`` order).

    Every row's measurement and covariance are read-only views into one array per column (an hour's graph has
    about 80,000 rows: one small array each, with its own buffer, cost twice the memory); the kind, type and robust
    loss are interned, one string object per distinct value."""
    table = table.sort_by(INDEX)
    meas, meas_at = _flat_lists(table.column(MEASUREMENT))
    cov, cov_at = _flat_lists(table.column(FACTOR_COVARIANCE))
    scalar = [KIND, TYPE, KEYS, DIM, ROBUST, ROBUST_K, FACTOR_TAG_ID, FACTOR_FRAME, FACTOR_STAMP_NS]
    cols = table.select(scalar).to_pydict()
    rows = []
    for i in range(table.num_rows):
        d = int(cols[DIM][i])
        rows.append(
            FactorRow(
                kind=sys.intern(cols[KIND][i]),
                type=sys.intern(cols[TYPE][i]),
                keys=tuple(int(k) for k in cols[KEYS][i]),
                measurement=meas[meas_at[i] : meas_at[i + 1]],
                covariance=cov[cov_at[i] : cov_at[i + 1]].reshape(d, d),
                robust=sys.intern(cols[ROBUST][i]),
                robust_k=float(cols[ROBUST_K][i]),
                tag_id=cols[FACTOR_TAG_ID][i],
                frame=cols[FACTOR_FRAME][i],
                stamp_ns=cols[FACTOR_STAMP_NS][i],
            )
        )
    return rows


def _flat_lists(column: pa.ChunkedArray) -> tuple[np.ndarray, np.ndarray]:
    """A list<double> column as (all values in one read-only float array, each row's start and end offsets)."""
    lists = cast("pa.ListArray[Any]", column.combine_chunks())
    offsets = np.asarray(lists.offsets, dtype=np.int64)
    values = np.array(lists.values.to_numpy(zero_copy_only=False)[offsets[0] : offsets[-1]], dtype=np.float64)
    values.setflags(write=False)
    return values, offsets - offsets[0]
