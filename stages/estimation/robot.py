"""The one robot model shared by the risk of a path (Mu et al. Alg. 2) and the navigation simulation.

A planar unicycle, state ``x = (x, y, θ)``, control ``u = (v, ω)`` held for one control period ``dt``::

    x_{k+1} = x_k + (v cos θ, v sin θ, ω) dt,   white noise on (v, ω): Q_u = diag(σ_v², σ_ω²)

Its linearisation along a nominal path gives ``A_k`` (heading coupled to position: a heading error turns into a
cross-track error as the robot moves) and the process noise ``B_k Q_u B_kᵀ``. The risk model
(:func:`stages.estimation.collision.forward_covariances`) runs the EKF's covariance recursion with exactly these
matrices along the nominal path, and the simulation (:mod:`stages.navigation.lqg`) moves the simulated robot with
them, so stage one picks landmarks for the robot that evaluate then drives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class RobotModel:
    """Footprint, motion noise, sensor noise and control period of the robot that navigates with the map."""

    robot_radius_m: float = 0.25
    control_period_s: float = 0.2
    speed_sigma_mps: float = 0.05
    """White noise on the forward speed over one control period, m/s."""
    yaw_rate_sigma_radps: float = 0.05
    """White noise on the yaw rate over one control period, rad/s."""
    bearing_sigma_rad: float = 0.02
    range_sigma_m: float = 0.05
    initial_sigma_m: float = 0.02
    """Standard deviation of the start position (per axis), m."""
    initial_sigma_rad: float = 0.01

    @property
    def Qu(self) -> FloatArray:
        """Control noise covariance (v, ω)."""
        return np.diag([self.speed_sigma_mps**2, self.yaw_rate_sigma_radps**2])

    @property
    def R(self) -> FloatArray:
        """Range-bearing noise covariance (bearing, range)."""
        return np.diag([self.bearing_sigma_rad**2, self.range_sigma_m**2])

    @property
    def sigmas(self) -> tuple[float, float]:
        """(bearing, range) standard deviations."""
        return self.bearing_sigma_rad, self.range_sigma_m

    @property
    def P0(self) -> FloatArray:
        """Covariance of the start pose."""
        return np.diag([self.initial_sigma_m**2] * 2 + [self.initial_sigma_rad**2])


def unicycle_step(x: FloatArray, u: FloatArray, dt: float) -> FloatArray:
    """One control period of the unicycle, for any leading batch shape."""
    th = x[..., 2]
    return np.stack(
        [x[..., 0] + u[..., 0] * np.cos(th) * dt, x[..., 1] + u[..., 0] * np.sin(th) * dt, th + u[..., 1] * dt],
        axis=-1,
    )


def unicycle_jacobians(x: FloatArray, u: FloatArray, dt: float) -> tuple[FloatArray, FloatArray]:
    """Jacobians of :func:`unicycle_step` w.r.t. the state (…, 3, 3) and the control (…, 3, 2)."""
    th = x[..., 2]
    shape = th.shape
    A = np.broadcast_to(np.eye(3), (*shape, 3, 3)).copy()
    A[..., 0, 2] = -u[..., 0] * np.sin(th) * dt
    A[..., 1, 2] = u[..., 0] * np.cos(th) * dt
    B = np.zeros((*shape, 3, 2))
    B[..., 0, 0] = np.cos(th) * dt
    B[..., 1, 0] = np.sin(th) * dt
    B[..., 2, 1] = dt
    return A, B


@dataclass(frozen=True)
class PathSteps:
    """A recorded path resampled every control period, with the unicycle's controls and linearisation along it."""

    stamps_ns: IntArray
    """(K,) step stamps."""
    poses: FloatArray
    """(K, 3) x, y, θ (θ unwrapped)."""
    controls: FloatArray
    """(K-1, 2) v, ω from step k to k+1."""
    dt_s: float
    keyframe: IntArray
    """(K,) index of the recorded pose nearest in time to each step."""

    def __len__(self) -> int:
        return len(self.poses)

    def transition(self, model: RobotModel) -> tuple[FloatArray, FloatArray]:
        """``A_k`` (K-1, 3, 3) and the process noise ``B_k Q_u B_kᵀ`` (K-1, 3, 3) along the path."""
        A, B = unicycle_jacobians(self.poses[:-1], self.controls, self.dt_s)
        return A, B @ model.Qu @ np.swapaxes(B, 1, 2)

    def nearest_step(self, stamps_ns: npt.ArrayLike) -> IntArray:
        """Index of the step nearest in time to each stamp."""
        q = np.asarray(stamps_ns, dtype=np.int64)
        pos = np.clip(np.searchsorted(self.stamps_ns, q), 1, max(len(self) - 1, 1))
        left = self.stamps_ns[pos - 1]
        right = self.stamps_ns[np.minimum(pos, len(self) - 1)]
        return np.where(np.abs(q - left) <= np.abs(right - q), pos - 1, np.minimum(pos, len(self) - 1)).astype(np.int64)


def resample_path(stamps_ns: npt.ArrayLike, poses: FloatArray, dt_s: float) -> PathSteps:
    """Resample a recorded path (stamps and x, y, θ) every ``dt_s`` and derive the controls that drive along it."""
    t_all = np.asarray(stamps_ns, dtype=np.int64)
    order = np.argsort(t_all, kind="stable")
    t, p = t_all[order], np.asarray(poses, dtype=float)[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, p, kept = t[keep], p[keep], order[keep]
    if len(t) < 2:
        raise ValueError("a path needs at least two poses at distinct stamps")
    step_ns = round(dt_s * 1e9)
    q = np.arange(t[0], t[-1] + 1, step_ns, dtype=np.int64)
    yaw = np.unwrap(p[:, 2])
    tf, qf = (t - t[0]).astype(float), (q - t[0]).astype(float)
    res = np.column_stack([np.interp(qf, tf, p[:, 0]), np.interp(qf, tf, p[:, 1]), np.interp(qf, tf, yaw)])
    d = np.diff(res, axis=0)
    v = (d[:, 0] * np.cos(res[:-1, 2]) + d[:, 1] * np.sin(res[:-1, 2])) / dt_s
    w = d[:, 2] / dt_s
    pos = np.clip(np.searchsorted(t, q), 1, len(t) - 1)
    nearest = np.where(np.abs(q - t[pos - 1]) <= np.abs(t[pos] - q), pos - 1, pos)
    return PathSteps(q, res, np.column_stack([v, w]), float(dt_s), kept[nearest].astype(np.int64))
