"""The kinds of graph variables (Pose2, Pose3, Point2, Point3 and the shared tag scale) as one table.

Every variable of a graph has a kind, named in ``values.npz`` and ``GraphProblem.var_types`` by its gtsam
type name. A :class:`VarKind` holds everything code switches on by kind: the tangent dimension, the stored
vector and its round trip through ``gtsam.Values``, and where the variable sits in the map frame::

    kind = var_kind(problem.var_types[key])
    kind.dim                                      # tangent dimension (its marginal is dim x dim)
    vec = kind.vector(values, key)                # stored numbers (Pose3: x y z qx qy qz qw)
    kind.insert(other_values, key, kind.from_vector(vec))
    kind.position(kind.read(values, key))         # x, y, z in the map frame (2D kinds: z = 0)
    kind.position_cov(value, marginal)            # 3x3 position covariance in the map frame
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt

from stages.geometry import pose2_to_vector, pose3_from_pose2, pose3_from_vector, pose3_to_vector

FloatArray = npt.NDArray[np.float64]

VALUE_WIDTH = 7
"""Width of stored value vectors: Pose2 x y theta, Pose3 x y z qx qy qz qw, Point2 x y, Point3 x y z,
Scale s (a gtsam ``Double``: the shared tag scale) (NaN-padded)."""


class VarKind:
    """One kind of variable: its name, dimensions, stored vector, and position in the map frame.

    Attributes:
        name: the gtsam type name stored in ``values.npz`` (``Scale`` for the tag scale, a ``Double``).
        dim: tangent dimension.
        width: length of the stored vector (at most :data:`VALUE_WIDTH`).
        is_pose: whether the variable has an orientation (a robot pose or a Pose3 tag).
    """

    name: str = ""
    dim: int = 0
    width: int = 0
    is_pose: bool = False

    def read(self, values: gtsam.Values, key: int) -> Any:
        """The gtsam value of ``key``."""
        raise NotImplementedError

    def to_vector(self, value: Any) -> FloatArray:
        """The stored numbers of a value (length :attr:`width`)."""
        raise NotImplementedError

    def from_vector(self, vec: npt.ArrayLike) -> Any:
        """The gtsam value of stored numbers (inverse of :meth:`to_vector`)."""
        raise NotImplementedError

    def position(self, value: Any) -> FloatArray:
        """x, y, z of the value in the map frame (z = 0 for the 2D kinds)."""
        raise ValueError(f"a {self.name} variable has no position")

    def position_cov(self, value: Any, cov: FloatArray) -> FloatArray:
        """3x3 position covariance in the map frame from the variable's tangent-space marginal ``cov``."""
        raise ValueError(f"a {self.name} variable has no position")

    def position_jacobian(self, value: Any) -> FloatArray:
        """(3, dim): the map-frame position's derivative w.r.t. the tangent (``position_cov`` is ``J cov Jᵀ``)."""
        raise ValueError(f"a {self.name} variable has no position")

    def pose3(self, value: Any) -> gtsam.Pose3:
        """The value as a Pose3 (poses only)."""
        raise ValueError(f"a {self.name} variable is not a pose")

    def planar_pose(self, value: Any) -> FloatArray:
        """x, y and yaw of the value in the map frame (poses only)."""
        raise ValueError(f"a {self.name} variable is not a pose")

    def vector(self, values: gtsam.Values, key: int) -> FloatArray:
        """The stored numbers of ``key``."""
        return self.to_vector(self.read(values, key))

    def insert(self, values: gtsam.Values, key: int, value: Any) -> None:
        """Insert ``value`` under ``key``."""
        values.insert(key, value)

    def copy(self, dst: gtsam.Values, src: gtsam.Values, key: int) -> None:
        """Insert the value of ``key`` in ``src`` into ``dst``."""
        self.insert(dst, key, self.read(src, key))

    def __repr__(self) -> str:
        return f"VarKind({self.name})"


def _symmetric(c: FloatArray) -> FloatArray:
    return 0.5 * (c + c.T)


class _Pose2(VarKind):
    name, dim, width, is_pose = "Pose2", 3, 3, True

    def read(self, values: gtsam.Values, key: int) -> gtsam.Pose2:
        return values.atPose2(key)

    def to_vector(self, value: gtsam.Pose2) -> FloatArray:
        return pose2_to_vector(value)

    def from_vector(self, vec: npt.ArrayLike) -> gtsam.Pose2:
        v = np.asarray(vec, dtype=float)
        return gtsam.Pose2(v[0], v[1], v[2])

    def position(self, value: gtsam.Pose2) -> FloatArray:
        return np.array([value.x(), value.y(), 0.0])

    def position_cov(self, value: gtsam.Pose2, cov: FloatArray) -> FloatArray:
        out = np.zeros((3, 3))
        c, s = np.cos(value.theta()), np.sin(value.theta())
        R2 = np.array([[c, -s], [s, c]])
        out[:2, :2] = R2 @ cov[:2, :2] @ R2.T
        return _symmetric(out)

    def position_jacobian(self, value: gtsam.Pose2) -> FloatArray:
        c, s = np.cos(value.theta()), np.sin(value.theta())
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 0.0]])

    def pose3(self, value: gtsam.Pose2) -> gtsam.Pose3:
        return pose3_from_pose2(value)

    def planar_pose(self, value: gtsam.Pose2) -> FloatArray:
        return np.array([value.x(), value.y(), value.theta()])


class _Pose3(VarKind):
    name, dim, width, is_pose = "Pose3", 6, 7, True

    def read(self, values: gtsam.Values, key: int) -> gtsam.Pose3:
        return values.atPose3(key)

    def to_vector(self, value: gtsam.Pose3) -> FloatArray:
        return pose3_to_vector(value)

    def from_vector(self, vec: npt.ArrayLike) -> gtsam.Pose3:
        return pose3_from_vector(np.asarray(vec, dtype=float)[:7])

    def position(self, value: gtsam.Pose3) -> FloatArray:
        return np.asarray(value.translation(), dtype=float)

    def position_cov(self, value: gtsam.Pose3, cov: FloatArray) -> FloatArray:
        R = np.asarray(value.rotation().matrix())
        return _symmetric(R @ cov[3:, 3:] @ R.T)

    def position_jacobian(self, value: gtsam.Pose3) -> FloatArray:
        return np.hstack([np.zeros((3, 3)), np.asarray(value.rotation().matrix())])

    def pose3(self, value: gtsam.Pose3) -> gtsam.Pose3:
        return value

    def planar_pose(self, value: gtsam.Pose3) -> FloatArray:
        t = np.asarray(value.translation())
        return np.array([t[0], t[1], value.rotation().yaw()])


class _Point2(VarKind):
    name, dim, width = "Point2", 2, 2

    def read(self, values: gtsam.Values, key: int) -> FloatArray:
        return values.atPoint2(key)

    def to_vector(self, value: FloatArray) -> FloatArray:
        return np.asarray(value, dtype=float)

    def from_vector(self, vec: npt.ArrayLike) -> FloatArray:
        return np.asarray(vec, dtype=float)[:2].copy()

    def position(self, value: FloatArray) -> FloatArray:
        p = np.asarray(value, dtype=float)
        return np.array([p[0], p[1], 0.0])

    def position_cov(self, value: Any, cov: FloatArray) -> FloatArray:
        out = np.zeros((3, 3))
        out[:2, :2] = cov
        return _symmetric(out)

    def position_jacobian(self, value: Any) -> FloatArray:
        return np.vstack([np.eye(2), np.zeros((1, 2))])


class _Point3(VarKind):
    name, dim, width = "Point3", 3, 3

    def read(self, values: gtsam.Values, key: int) -> FloatArray:
        return values.atPoint3(key)

    def to_vector(self, value: FloatArray) -> FloatArray:
        return np.asarray(value, dtype=float)

    def from_vector(self, vec: npt.ArrayLike) -> FloatArray:
        return np.asarray(vec, dtype=float)[:3].copy()

    def position(self, value: FloatArray) -> FloatArray:
        return np.asarray(value, dtype=float)

    def position_cov(self, value: Any, cov: FloatArray) -> FloatArray:
        return _symmetric(np.asarray(cov, dtype=float).copy())

    def position_jacobian(self, value: Any) -> FloatArray:
        return np.eye(3)


class _Scale(VarKind):
    name, dim, width = "Scale", 1, 1

    def read(self, values: gtsam.Values, key: int) -> float:
        return values.atDouble(key)

    def to_vector(self, value: float) -> FloatArray:
        return np.array([value], dtype=float)

    def from_vector(self, vec: npt.ArrayLike) -> float:
        return float(np.asarray(vec, dtype=float)[0])


POSE2: VarKind = _Pose2()
POSE3: VarKind = _Pose3()
POINT2: VarKind = _Point2()
POINT3: VarKind = _Point3()
SCALE: VarKind = _Scale()
VAR_KINDS: dict[str, VarKind] = {k.name: k for k in (POSE2, POSE3, POINT2, POINT3, SCALE)}
"""Every kind by its stored name."""
VAR_DIMS: dict[str, int] = {name: k.dim for name, k in VAR_KINDS.items()}
"""Tangent dimension of each variable type."""


def var_kind(name: str) -> VarKind:
    """The kind stored under ``name`` (``Pose2``, ``Pose3``, ``Point2``, ``Point3``, ``Scale``)."""
    try:
        return VAR_KINDS[str(name)]
    except KeyError:
        raise ValueError(f"unknown variable type {name!r}") from None


def value_vector(values: gtsam.Values, key: int, var_type: str) -> FloatArray:
    """The stored vector of one variable (NaN-padded to :data:`VALUE_WIDTH`)."""
    kind = var_kind(var_type)
    out = np.full(VALUE_WIDTH, np.nan)
    out[: kind.width] = kind.vector(values, key)
    return out


def insert_value(values: gtsam.Values, key: int, var_type: str, vec: npt.ArrayLike) -> None:
    """Insert one variable from its stored vector."""
    kind = var_kind(var_type)
    kind.insert(values, key, kind.from_vector(vec))
