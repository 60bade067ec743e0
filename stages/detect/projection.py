"""The pycolmap camera models the project uses, projected in numpy with their analytic Jacobian.

:func:`stages.camera.colmap_camera` makes PINHOLE, OPENCV, FULL_OPENCV or OPENCV_FISHEYE cameras. This module
evaluates the same projection as ``pycolmap.Camera.img_from_cam`` (COLMAP's formulas: normalise by depth, distort,
then ``u = fx x + cx``, ``v = fy y + cy``) for many points at once, and its derivative by the camera-frame point,
so that the tag pose solver (:mod:`stages.detect.pose`) runs batched without finite differences.

* OPENCV / FULL_OPENCV (radial-tangential, rational radial): with ``r2 = u^2 + v^2`` and
  ``a = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)``:
  ``x = a u + 2 p1 u v + p2 (r2 + 2 u^2)``, ``y = a v + 2 p2 u v + p1 (r2 + 2 v^2)``. OPENCV is the case
  ``k3 = .. = k6 = 0`` and PINHOLE the case of all coefficients zero.
* OPENCV_FISHEYE (equidistant): ``theta = atan(r)``, ``theta_d = theta (1 + k1 theta^2 + .. + k4 theta^8)``,
  ``(x, y) = theta_d / r (u, v)`` (the identity where ``r`` is below machine epsilon, as in COLMAP).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    import pycolmap

Array = npt.NDArray[np.float64]

_RADTAN = ("PINHOLE", "OPENCV", "FULL_OPENCV")
MODELS = (*_RADTAN, "OPENCV_FISHEYE")
_HESSIAN_STEP = 1e-5
"""The pycolmap camera models :class:`Projection` evaluates."""


@dataclass(frozen=True)
class Projection:
    """A pycolmap camera's projection: ``model`` (one of :data:`MODELS`), focal lengths, principal point and the
    distortion coefficients (k1 k2 p1 p2 k3 k4 k5 k6 for the radial-tangential models, k1..k4 for the fisheye)."""

    model: str
    fx: float
    fy: float
    cx: float
    cy: float
    coeffs: tuple[float, ...]

    @classmethod
    def of(cls, camera: pycolmap.Camera) -> Projection:
        """The projection of a pycolmap camera.

        Raises:
            ValueError: a camera model this module does not evaluate.
        """
        name = str(camera.model_name)
        if name not in MODELS:
            raise ValueError(f"camera model {name!r} has no numpy projection; expected one of {MODELS}")
        p = [float(v) for v in camera.params]
        if name == "PINHOLE":
            coeffs: tuple[float, ...] = (0.0,) * 8
        elif name == "OPENCV_FISHEYE":
            coeffs = tuple(p[4:8])
        else:
            coeffs = tuple((p[4:] + [0.0] * 8)[:8])
        return cls(name, p[0], p[1], p[2], p[3], coeffs)

    def project(self, points: Array, jacobian: bool = False) -> tuple[Array, Array | None]:
        """Pixels (..., 2) of camera-frame points (..., 3), and with ``jacobian`` their derivative (..., 2, 3).

        No cheirality check (like ``img_from_cam(..., check_cheirality=False)``); the caller keeps depths positive.
        """
        P = np.asarray(points, float)
        inv_z = 1.0 / P[..., 2]
        u = P[..., 0] * inv_z
        v = P[..., 1] * inv_z
        if self.model == "OPENCV_FISHEYE":
            x, y, dxu, dxv, dyu, dyv = self._fisheye(u, v)
        else:
            x, y, dxu, dxv, dyu, dyv = self._radtan(u, v)
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)
        if not jacobian:
            return uv, None
        # d(u, v)/dP = [[1/z, 0, -u/z], [0, 1/z, -v/z]]; d(pixel)/d(x, y) = diag(fx, fy) D.
        J = np.empty((*P.shape[:-1], 2, 3))
        J[..., 0, 0] = self.fx * dxu * inv_z
        J[..., 0, 1] = self.fx * dxv * inv_z
        J[..., 0, 2] = -self.fx * (dxu * u + dxv * v) * inv_z
        J[..., 1, 0] = self.fy * dyu * inv_z
        J[..., 1, 1] = self.fy * dyv * inv_z
        J[..., 1, 2] = -self.fy * (dyu * u + dyv * v) * inv_z
        return uv, J

    def weighted_hessian(self, points: Array, weights: Array) -> Array:
        """``sum_c weights_c d2 pixel_c / dP2`` (..., 3, 3): the second derivatives of the pixel coordinates by the
        camera-frame points (..., 3), weighted per point by ``weights`` (..., 2) (a residual, for Newton's method).

        Analytic through the perspective division, ``d2 u / dX dZ = -1 / Z^2`` and ``d2 u / dZ^2 = 2 u / Z^2``
        (likewise ``v``), and through the radial-tangential distortion (:meth:`_radtan_second`); the fisheye
        distortion's own curvature by central differences (step 1e-5 in the normalised image) of its analytic first
        derivatives, which leaves an error of order 1e-9 of it.
        """
        P = np.asarray(points, float)
        inv_z = 1.0 / P[..., 2]
        u, v = P[..., 0] * inv_z, P[..., 1] * inv_z
        rho = np.asarray(weights, float) * np.array([self.fx, self.fy])
        rx, ry = rho[..., 0], rho[..., 1]
        # q_a = sum_c rho_c dx_c/da; W_ab = sum_c rho_c d2 x_c / da db.
        if self.model == "OPENCV_FISHEYE":
            _, _, dxu, dxv, dyu, dyv = self._fisheye(u, v)
            h = _HESSIAN_STEP
            _, _, pxu, pxv, pyu, pyv = self._fisheye(u + h, v)
            _, _, mxu, mxv, myu, myv = self._fisheye(u - h, v)
            Wuu = (rx * (pxu - mxu) + ry * (pyu - myu)) / (2 * h)
            Wuv1 = (rx * (pxv - mxv) + ry * (pyv - myv)) / (2 * h)
            _, _, pxu, pxv, pyu, pyv = self._fisheye(u, v + h)
            _, _, mxu, mxv, myu, myv = self._fisheye(u, v - h)
            Wvv = (rx * (pxv - mxv) + ry * (pyv - myv)) / (2 * h)
            Wuv = 0.5 * (Wuv1 + (rx * (pxu - mxu) + ry * (pyu - myu)) / (2 * h))
        else:
            dxu, dxv, dyu, dyv, xuu, xuv, xvv, yuu, yuv, yvv = self._radtan_second(u, v)
            Wuu, Wuv, Wvv = rx * xuu + ry * yuu, rx * xuv + ry * yuv, rx * xvv + ry * yvv
        q = np.empty_like(rho)
        q[..., 0] = rx * dxu + ry * dyu
        q[..., 1] = rx * dxv + ry * dyv
        # d(u, v)/dP = [[1, 0, -u], [0, 1, -v]] / Z: the sandwich J^T W J, then q_u d2u/dP2 + q_v d2v/dP2.
        z2 = inv_z * inv_z
        a0 = Wuu * u + Wuv * v
        a1 = Wuv * u + Wvv * v
        out = np.empty((*u.shape, 3, 3))
        out[..., 0, 0], out[..., 0, 1], out[..., 1, 1] = Wuu * z2, Wuv * z2, Wvv * z2
        out[..., 0, 2] = (-a0 - q[..., 0]) * z2
        out[..., 1, 2] = (-a1 - q[..., 1]) * z2
        out[..., 2, 2] = (u * a0 + v * a1 + 2.0 * (q[..., 0] * u + q[..., 1] * v)) * z2
        out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = out[..., 0, 1], out[..., 0, 2], out[..., 1, 2]
        return out

    def _radtan(self, u: Array, v: Array) -> tuple[Array, ...]:
        k1, k2, p1, p2, k3, k4, k5, k6 = self.coeffs
        if self.model == "PINHOLE":
            one, zero = np.ones_like(u), np.zeros_like(u)
            return u, v, one, zero, zero, one
        uu, vv, uv = u * u, v * v, u * v
        r2 = uu + vv
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        a = num / den
        # da/dr2 = (num' den - num den') / den^2
        da = ((k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)) * den - num * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / (den * den)
        x = a * u + 2.0 * p1 * uv + p2 * (r2 + 2.0 * uu)
        y = a * v + 2.0 * p2 * uv + p1 * (r2 + 2.0 * vv)
        cross = 2.0 * uv * da + 2.0 * p1 * u + 2.0 * p2 * v
        dxu = a + 2.0 * uu * da + 2.0 * p1 * v + 6.0 * p2 * u
        dyv = a + 2.0 * vv * da + 2.0 * p2 * u + 6.0 * p1 * v
        return x, y, dxu, cross, cross, dyv

    def _radtan_second(self, u: Array, v: Array) -> tuple[Array, ...]:
        """First and second derivatives of the radial-tangential distortion ``(x, y)`` by ``(u, v)``: ``x_u, x_v,
        y_u, y_v, x_uu, x_uv, x_vv, y_uu, y_uv, y_vv``. With ``a = N / D`` of ``r2``, ``a' = (N' - a D') / D`` and
        ``a'' = (N'' - 2 a' D' - a D'') / D`` (differentiating ``a D = N`` twice); ``d r2 / du = 2 u``."""
        k1, k2, p1, p2, k3, k4, k5, k6 = self.coeffs
        uu, vv, uv = u * u, v * v, u * v
        r2 = uu + vv
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        a = num / den
        dn, dd = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2), k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        d1 = (dn - a * dd) / den
        d2 = ((2.0 * k2 + 6.0 * k3 * r2) - 2.0 * d1 * dd - a * (2.0 * k5 + 6.0 * k6 * r2)) / den
        cross = 2.0 * uv * d1 + 2.0 * p1 * u + 2.0 * p2 * v
        dxu = a + 2.0 * uu * d1 + 2.0 * p1 * v + 6.0 * p2 * u
        dyv = a + 2.0 * vv * d1 + 2.0 * p2 * u + 6.0 * p1 * v
        xuu = 6.0 * u * d1 + 4.0 * uu * u * d2 + 6.0 * p2
        xuv = 2.0 * v * d1 + 4.0 * uu * v * d2 + 2.0 * p1
        xvv = 2.0 * u * d1 + 4.0 * u * vv * d2 + 2.0 * p2
        yvv = 6.0 * v * d1 + 4.0 * vv * v * d2 + 6.0 * p1
        yuv = 2.0 * u * d1 + 4.0 * u * vv * d2 + 2.0 * p2
        yuu = 2.0 * v * d1 + 4.0 * uu * v * d2 + 2.0 * p1
        return dxu, cross, cross, dyv, xuu, xuv, xvv, yuu, yuv, yvv

    def _fisheye(self, u: Array, v: Array) -> tuple[Array, ...]:
        k1, k2, k3, k4 = self.coeffs[:4]
        r2 = u * u + v * v
        r = np.sqrt(r2)
        eps = np.finfo(float).eps
        small = r <= eps
        r_safe = np.where(small, 1.0, r)
        th = np.arctan(r_safe)
        t2 = th * th
        poly = 1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))
        dpoly = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))  # d(th poly)/dth
        s = np.where(small, 1.0, th * poly / r_safe)
        # ds/dr = (dpoly / (1 + r^2) - s) / r; with dr/du = u / r: ds/du = u g, g = ds/dr / r.
        g = np.where(small, 0.0, (dpoly / (1.0 + r_safe * r_safe) - s) / (r_safe * r_safe))
        cross = u * v * g
        return s * u, s * v, s + u * u * g, cross, cross, s + v * v * g
