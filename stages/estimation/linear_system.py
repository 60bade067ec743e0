"""A sparse linear(ised) information model: variables in blocks, factors as whitened Jacobians.

A factor ``f`` over the variables ``x_{v_1}, ..., x_{v_k}`` contributes ``A_fᵀ A_f`` to the
information matrix, where ``A_f`` (``m_f × Σ dim(v_i)``) is its whitened Jacobian
(``Σ^{-1/2} ∂h/∂x``). The system's information is ``Λ = Σ_f A_fᵀ A_f`` over any chosen subset of
factors; it is assembled with scipy.sparse and never densified for large problems.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal, TypeAlias

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse import csgraph

if TYPE_CHECKING:
    import gtsam

VariableKind = Literal["pose", "landmark"]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
SparseMatrix: TypeAlias = sp.csc_matrix | sp.csr_matrix | sp.coo_matrix
"""The scipy sparse matrices the estimation code passes around (information matrices, Jacobians, patterns)."""


LANDMARK_ROTATION_PRIOR_SIGMA_RAD = 1.0
"""Largest σ of the weak landmark prior on a 6-dof (Pose3) landmark's rotation: a prior of 100 "units" on a
rotation vector means nothing (rotations wrap at π) and, with centimetre tag measurements, makes the information
so ill-conditioned that the selection greedy's tracked covariance loses tens of nats (measured on TagSLAM's
test_14 in 3D: 73 nats after 90 picks)."""


def landmark_prior_sigmas(dim: int, sigma: float) -> FloatArray:
    """σ per tangent dimension of a landmark's weak prior: ``sigma`` on positions; a Pose3 landmark (6 dims, GTSAM's
    (rotation, translation) order) has at most :data:`LANDMARK_ROTATION_PRIOR_SIGMA_RAD` on its rotation."""
    out = np.full(dim, float(sigma))
    if dim == 6:
        out[:3] = min(float(sigma), LANDMARK_ROTATION_PRIOR_SIGMA_RAD)
    return out


@dataclass(frozen=True, slots=True)
class Variable:
    """One block of the state vector."""

    key: int
    """Identifier (a gtsam key when built from gtsam)."""
    dim: int
    """Tangent-space dimension of the block."""
    kind: VariableKind
    """``pose`` or ``landmark``."""


@dataclass(frozen=True, slots=True)
class Factor:
    """One whitened linear factor ``‖A x − b‖²`` (only ``A`` matters for information)."""

    variables: tuple[int, ...]
    """Indices into :attr:`LinearSystem.variables`, in the column order of :attr:`jacobian`."""
    jacobian: FloatArray
    """Whitened Jacobian, shape ``(rows, Σ dim)``."""
    kind: str = "other"
    """``prior`` (one pose), ``odometry`` (two poses), ``landmark`` (pose and landmark) or ``other``."""

    @property
    def rows(self) -> int:
        """Number of whitened residual rows."""
        return int(self.jacobian.shape[0])


def _factor_kind(kinds: Sequence[VariableKind]) -> str:
    if len(kinds) == 1 and kinds[0] == "pose":
        return "prior"
    if len(kinds) == 2 and kinds[0] == kinds[1] == "pose":
        return "odometry"
    if len(kinds) == 2 and sorted(kinds) == ["landmark", "pose"]:
        return "landmark"
    return "other"


@dataclass
class LinearSystem:
    """Variables (blocks) and whitened Jacobian factors of a linearised factor graph."""

    variables: list[Variable]
    factors: list[Factor]
    offsets: IntArray = field(init=False)
    """``offsets[i]`` is the first column of variable ``i``; ``offsets[-1]`` the total dimension."""
    _index_of_key: dict[int, int] = field(init=False, repr=False)
    _factor_cols: list[IntArray | None] = field(init=False, repr=False)
    """Per factor, its columns (:meth:`factor_columns`), computed on first use."""

    def __post_init__(self) -> None:
        dims = np.array([v.dim for v in self.variables], dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(dims)]).astype(np.int64)
        self._index_of_key = {v.key: i for i, v in enumerate(self.variables)}
        self._factor_cols: list[IntArray | None] = [None] * len(self.factors)
        for i, f in enumerate(self.factors):
            width = int(sum(self.variables[v].dim for v in f.variables))
            if f.jacobian.ndim != 2 or f.jacobian.shape[1] != width:
                raise ValueError(
                    f"factor {i}: jacobian shape {f.jacobian.shape} does not match its variables' "
                    f"total dimension {width}"
                )

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_blocks(
        cls,
        dims: Sequence[int],
        kinds: Sequence[VariableKind],
        factors: Iterable[tuple[Sequence[int], FloatArray]],
        keys: Sequence[int] | None = None,
    ) -> LinearSystem:
        """Build a system directly from block dimensions and ``(variable indices, jacobian)`` pairs."""
        keys = list(range(len(dims))) if keys is None else list(keys)
        variables = [Variable(int(k), int(d), kd) for k, d, kd in zip(keys, dims, kinds, strict=True)]
        fs = [
            Factor(
                tuple(int(v) for v in vs),
                np.asarray(A, dtype=np.float64),
                _factor_kind([variables[int(v)].kind for v in vs]),
            )
            for vs, A in factors
        ]
        return cls(variables, fs)

    @classmethod
    def from_gtsam(
        cls,
        nfg: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        is_landmark: Callable[[int], bool] | None = None,
    ) -> LinearSystem:
        """Linearise ``nfg`` at ``values`` and keep each factor's whitened Jacobian.

        ``is_landmark(key)`` tells landmark keys from pose keys; by default a key whose gtsam
        symbol character is ``l`` or ``L`` is a landmark. Factor ``i`` of the result is factor
        ``i`` of ``nfg`` (null factors are kept as empty factors so that indices line up).
        """
        import gtsam

        if is_landmark is None:

            def is_landmark(key: int) -> bool:
                return chr(gtsam.Symbol(key).chr()) in "lL"

        dims = values.dims()
        key_vector = values.keys()  # a gtsam KeyVector, not a dict
        keys = sorted(int(k) for k in key_vector)
        variables = [Variable(k, int(dims[k]), "landmark" if is_landmark(k) else "pose") for k in keys]
        index = {k: i for i, k in enumerate(keys)}
        lin = nfg.linearize(values)
        factors: list[Factor] = []
        for i in range(lin.size()):
            g = lin.at(i)
            if g is None:
                factors.append(Factor((), np.zeros((0, 0)), "other"))
                continue
            factor_keys = g.keys()  # a gtsam KeyVector
            fkeys = [int(k) for k in factor_keys]
            A, _ = g.jacobian()
            vs = tuple(index[k] for k in fkeys)
            factors.append(Factor(vs, np.asarray(A, dtype=np.float64), _factor_kind([variables[v].kind for v in vs])))
        return cls(variables, factors)

    # ------------------------------------------------------------------ queries
    @property
    def dim(self) -> int:
        """Total state dimension."""
        return int(self.offsets[-1])

    def index_of_key(self, key: int) -> int:
        """Variable index of a key."""
        return self._index_of_key[key]

    def columns(self, variable_ids: Iterable[int]) -> IntArray:
        """State-vector columns of the given variables, concatenated in the given order."""
        parts = [np.arange(self.offsets[v], self.offsets[v + 1]) for v in variable_ids]
        return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, dtype=np.int64)

    def factor_columns(self, factor_id: int) -> IntArray:
        """State-vector columns of a factor's Jacobian (cached: do not modify the array)."""
        cols = self._factor_cols[factor_id]
        if cols is None:
            cols = self.columns(self.factors[factor_id].variables)
            self._factor_cols[factor_id] = cols
        return cols

    def jacobian(self, factor_ids: Iterable[int]) -> sp.csr_matrix:
        """Stacked whitened Jacobian of the given factors, shape ``(Σ rows, dim)``.

        The factors are stacked in the given order; those of one Jacobian shape are scattered together (one numpy
        operation per shape instead of per factor: the selection stages assemble the odometry chain of an hour's
        recording, tens of thousands of factors, many times). Each row holds one factor's columns in its order, so
        the matrix is the same entry for entry as stacking the factors one by one.
        """
        ids = [int(f) for f in factor_ids]
        ids = [f for f in ids if self.factors[f].rows]
        if not ids:
            return sp.csr_matrix((0, self.dim))
        shapes = [self.factors[f].jacobian.shape for f in ids]
        starts = np.concatenate([[0], np.cumsum([m for m, _ in shapes])]).astype(np.int64)
        groups: dict[tuple[int, int], list[int]] = {}
        for k, shape in enumerate(shapes):
            groups.setdefault((int(shape[0]), int(shape[1])), []).append(k)
        rows: list[IntArray] = []
        cols: list[IntArray] = []
        vals: list[FloatArray] = []
        for (m, w), ks in groups.items():
            J = np.stack([self.factors[ids[k]].jacobian for k in ks]).astype(np.float64, copy=False)  # (g, m, w)
            C = np.stack([self.factor_columns(ids[k]) for k in ks])  # (g, w)
            R = starts[ks][:, None] + np.arange(m)[None, :]  # (g, m)
            rows.append(np.broadcast_to(R[:, :, None], (len(ks), m, w)).ravel())
            cols.append(np.broadcast_to(C[:, None, :], (len(ks), m, w)).ravel())
            vals.append(J.ravel())
        return sp.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(int(starts[-1]), self.dim)
        )

    def information(self, factor_ids: Iterable[int] | None = None) -> sp.csc_matrix:
        """``Λ = Σ_f A_fᵀ A_f`` over the given factors (all by default), as a sparse matrix."""
        ids = range(len(self.factors)) if factor_ids is None else factor_ids
        A = self.jacobian(ids)
        return sp.csc_matrix(A.T @ A)

    def factors_of_kind(self, kind: str) -> list[int]:
        """Indices of the factors of one kind."""
        return [i for i, f in enumerate(self.factors) if f.kind == kind]

    def variables_of_kind(self, kind: VariableKind) -> list[int]:
        """Indices of the variables of one kind."""
        return [i for i, v in enumerate(self.variables) if v.kind == kind]

    def diagonal_prior(self, variable_ids: Iterable[int], sigma: float) -> sp.csc_matrix:
        """Information ``σ⁻² I`` on the given variables' columns (a weak prior; see :func:`landmark_prior_sigmas` for
        the rotation of a 6-dof variable)."""
        d = np.zeros(self.dim)
        for v in variable_ids:
            d[self.offsets[v] : self.offsets[v + 1]] = 1.0 / landmark_prior_sigmas(self.variables[v].dim, sigma) ** 2
        return sp.diags(d, format="csc")


@dataclass(frozen=True)
class GraphInformation:
    """The information matrix ``Λ = AᵀA`` of a linearised graph, with its variables' keys and columns."""

    information: sp.csc_matrix
    keys: list[int]
    """The graph's keys, sorted: variable ``i`` is ``keys[i]``."""
    offsets: IntArray
    """``offsets[i]`` is the first column of variable ``i``; ``offsets[-1]`` the total dimension."""
    _index: dict[int, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_index", {k: i for i, k in enumerate(self.keys)})

    def index_of_key(self, key: int) -> int:
        """Variable index of a key."""
        return self._index[key]


def information_from_gtsam(nfg: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> GraphInformation:
    """``Λ = AᵀA`` of ``nfg`` linearised at ``values``, from GTSAM's sparse whitened Jacobian in one call.

    :meth:`LinearSystem.from_gtsam` keeps every factor's Jacobian as a Python object, which the selection greedies
    need; a covariance query needs only ``Λ``, and on an hour's graph (79,000 factors) the per-factor objects and
    their scatter indices cost about as much as the rest of evaluate's working set. ``sparseJacobian_`` returns the
    augmented Jacobian as (row, column, value) triplets, one-based, over the graph's keys in sorted order, the right-
    hand side ``b`` as its last column (dropped here).
    """
    dims = values.dims()
    lin = nfg.linearize(values)
    key_set = lin.keys()  # keep the KeySet alive while iterating it (a temporary's iterator crashes)
    keys = sorted(int(k) for k in key_set)
    ijs = lin.sparseJacobian_()
    del lin
    offsets = np.concatenate([[0], np.cumsum([int(dims[k]) for k in keys])]).astype(np.int64)
    n = int(offsets[-1])
    r = ijs[0].astype(np.int64) - 1
    c = ijs[1].astype(np.int64) - 1
    keep = c < n
    n_rows = int(r.max()) + 1 if r.size else 0
    A = sp.csr_matrix((ijs[2][keep], (r[keep], c[keep])), shape=(n_rows, n))
    del ijs, r, c, keep
    return GraphInformation(sp.csc_matrix(A.T @ A), keys, offsets)


def unanchored_poses(sub: LinearSystem, base: Sequence[int], anchors: Sequence[int]) -> list[int]:
    """The first pose of every group of variables that the ``base`` factors link but do not anchor: no unary base
    factor and no variable of ``anchors`` (landmarks whose weak prior anchors them) among them.

    Such a group has a free gauge in ``Λ₀`` (a camera-only rig whose only prior is on a surveyed tag: the poses hang
    on the tag through candidate measurements alone), so ``Λ₀`` would be singular. The weak prior put on its first
    pose fixes the gauge as loosely as the landmarks' weak prior does; a graph whose base is anchored (a prior on the
    first pose) gets none, and its numbers do not change."""
    if sub.dim == 0:
        return []
    n_var = len(sub.variables)
    rows, cols = [], []
    anchored = np.zeros(n_var, dtype=bool)
    anchored[list(anchors)] = True
    for b in base:
        vs = sub.factors[b].variables
        if len(vs) == 1:
            anchored[vs[0]] = True
        rows += [vs[0]] * len(vs)
        cols += list(vs)
    link = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_var, n_var))
    n_comp, label = csgraph.connected_components(link, directed=False)
    held = np.zeros(n_comp, dtype=bool)
    held[label[anchored]] = True
    out: list[int] = []
    for v, var in enumerate(sub.variables):
        if var.kind == "pose" and not held[label[v]]:
            out.append(v)
            held[label[v]] = True
    return out
