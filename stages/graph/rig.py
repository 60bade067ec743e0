"""Rig calibration: the mount of each camera of a rig that has none, estimated from the tags it shares with the others.

TagSLAM users give the pose of one camera of a rig (``camera_poses.yaml`` with ``cam0`` only) and let the rest be
found from the data. focusmap does the same in three steps, inside the graph stage:

1. **Initial value** (:func:`initial_mounts`). When a camera ``a`` with a mount ``T_base_a`` and a camera ``c``
   without one see the same tag at the same stamp, ``T_base_c = T_base_a T_a_tag T_c_tag⁻¹``. Every such pair gives
   one estimate; their robust mean (chordal mean of the rotations after dropping those beyond three median
   deviations, median translation) is the initial mount. Cameras are reached breadth first, so a camera that
   shares tags only with another uncalibrated camera is placed through it (TagSLAM's quadruple rig: the top left
   camera never sees a tag at the moment the calibrated one does).
2. **Estimate** (:func:`refine_mounts`). The full 3D graph of the run with one ``Pose3`` variable ``C(i)`` per
   camera to calibrate, shared by all its sightings: the factor ``e = Log((C Z)⁻¹ X⁻¹ L)`` (the tag factor with
   ``T_base_tag = C Z`` for the sighting ``Z = T_camera_tag``; gtsam's ``BetweenFactorPose3`` at ``C`` fixed)
   with exact Jacobians. Levenberg-Marquardt from the initial values; the marginal covariance of each ``C`` is
   the mount's 6x6 covariance (tangent order rotation, translation; right perturbation).
3. **Use**. The graph the later stages read is built with the estimated mount, and each sighting of such a camera
   carries the mount's uncertainty in its covariance: ``Σ_Z + Ad(Z⁻¹) Σ_C Ad(Z⁻¹)ᵀ`` (``C Exp(ξ) Z = C Z
   Exp(Ad(Z⁻¹) ξ)``). That treats the mount's error as independent between sightings, which it is not; the
   inflation is small beside the detection noise when the mount rests on many pairs (it is listed per camera).

A camera that never sees a tag at the same stamp as a placed camera cannot be placed: it is named and its
detections are left out.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt

from stages.geometry import pose3_from_matrix, pose3_from_vector
from stages.graph.factors import FactorRow, make_factor, noise_model
from stages.graph.tag_motion import MOUNT_MAX_DEG

FloatArray = npt.NDArray[np.float64]

MOUNT_CHR = "c"
"""Symbol character of a camera mount variable ``C(i)`` in the calibration solve."""
MIN_PAIRS = 3
"""A camera is placed from another only through at least this many shared sightings."""
LOOSE_INFORMATION = 1e6
"""A given mount whose information (``RᵀR`` of TagSLAM's ``R``) is at least this in every direction (σ ≤ 1 mm,
1 mrad) is held fixed; a looser one is estimated with it as its prior."""
GIVEN_INFORMATION = 1e6
"""The square-root information ``R`` written for a mount held fixed (TagSLAM's own files: σ 1e-6 m, rad)."""


def is_loose(information: Any) -> bool:
    """Whether a given mount's information leaves it to be estimated (:data:`GIVEN_INFORMATION`)."""
    if information is None:
        return False
    R = np.asarray(information, dtype=float).reshape(6, 6)
    return bool(np.linalg.eigvalsh(0.5 * (R + R.T)).min() < LOOSE_INFORMATION * (1.0 - 1e-6))


def mount_key(index: int) -> int:
    """Key of the mount variable of the ``index``-th camera to calibrate."""
    return int(gtsam.symbol(MOUNT_CHR, index))


@dataclass
class MountEstimate:
    """The mount of a camera found from the data."""

    camera: str
    pose: gtsam.Pose3
    """``T_base_camera``."""
    pairs: int
    """Sightings shared with the camera it was placed from (the initial value's support)."""
    via: str
    """The camera it was placed from."""
    spread_deg: float
    """The median angle of the pair estimates from their mean (how well the pairs agree), degrees."""
    covariance: FloatArray | None = None
    """6x6 marginal covariance (rotation, translation), once estimated in the graph."""
    translation_se: float = 0.0
    """Standard error of the initial translation: the pair estimates' spread over the root of their number, m."""
    prior: FloatArray | None = None
    """The 6x6 information of a given mount estimated with it as its prior (TagSLAM's ``R``), else None."""
    initial: gtsam.Pose3 | None = None

    def summary(self, base_frame: str) -> dict[str, Any]:
        """The camera's block of the graph summary's ``rig_calibration``."""
        T = np.asarray(self.pose.matrix())
        out: dict[str, Any] = {
            "T_base_camera": T.round(6).tolist(),
            "base_frame": base_frame,
            "placed_from": self.via,
            "shared_sightings": self.pairs,
            "pair_spread_deg": round(self.spread_deg, 3),
        }
        if self.covariance is not None:
            sig = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
            out["sigma_rotation_deg"] = np.degrees(sig[:3]).round(4).tolist()
            out["sigma_translation_m"] = sig[3:].round(5).tolist()
        if self.initial is not None:
            d = self.initial.between(self.pose)
            out["moved_from_initial_m"] = round(float(np.linalg.norm(np.asarray(d.translation()))), 5)
            out["moved_from_initial_deg"] = round(float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation())))), 4)
        return out


def rotation_mean(rotations: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The chordal mean of ``rotations`` (n x 3 x 3) after dropping those beyond three median deviations from a first
    mean (and at least 2°), and which were kept."""
    keep = np.ones(len(rotations), dtype=bool)
    mean = np.eye(3)
    for _ in range(3):
        U, _, Vt = np.linalg.svd(rotations[keep].sum(axis=0))
        mean = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        angles = _angles(rotations, mean)
        cut = max(3.0 * float(np.median(angles[keep])), np.radians(2.0))
        new = angles <= cut
        if new.sum() < 1 or np.array_equal(new, keep):
            break
        keep = new
    return mean, keep


def _angles(rotations: FloatArray, mean: FloatArray) -> FloatArray:
    """The angle of each rotation from ``mean``, radians."""
    c = (np.einsum("nij,ij->n", rotations, mean) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def pair_estimate(
    T_base_a: FloatArray, T_a_tag: FloatArray, T_c_tag: FloatArray
) -> tuple[gtsam.Pose3, float, int, float]:
    """The robust mean of ``T_base_a T_a_tag T_c_tag⁻¹`` over the pairs (n x 4 x 4 each), the median angle of the
    kept pair estimates from it (degrees), how many were kept, and the standard error of its translation (m)."""
    inv_c = np.linalg.inv(T_c_tag)
    est = np.einsum("nij,njk->nik", np.einsum("ij,njk->nik", T_base_a, T_a_tag), inv_c)
    R, keep = rotation_mean(est[:, :3, :3])
    spread = float(np.degrees(np.median(_angles(est[keep, :3, :3], R))))
    pose = _mean_pose(est)
    dev = np.linalg.norm(est[keep, :3, 3] - np.asarray(pose.translation()), axis=1)
    se = 1.4826 * float(np.median(dev)) / np.sqrt(max(int(keep.sum()), 1))
    return pose, spread, int(keep.sum()), se


Views = dict[int, dict[str, dict[int, int]]]
"""The sightings indexed by moment: stamp to camera to tag id to the row (its first row when repeated)."""


def views_of(stamps: npt.ArrayLike, tags: npt.ArrayLike, cameras: Iterable[str]) -> Views:
    """Index the sightings by moment, camera and tag (:data:`Views`)."""
    views: Views = defaultdict(lambda: defaultdict(dict))
    rows = zip(np.asarray(stamps, dtype=np.int64), np.asarray(tags, dtype=np.int64), cameras, strict=True)
    for i, (st, g, c) in enumerate(rows):
        views[int(st)][str(c)].setdefault(int(g), i)
    return views


def initial_mounts(
    stamps: npt.ArrayLike,
    tags: npt.ArrayLike,
    cameras: Iterable[str],
    T_camera_tag: FloatArray,
    known: Mapping[str, gtsam.Pose3],
    unknown: Iterable[str],
) -> tuple[dict[str, MountEstimate], list[str]]:
    """Initial mounts of the ``unknown`` cameras from same-stamp sightings of one tag by a placed camera (breadth
    first: the placed camera with the most shared sightings first), and the cameras that could not be placed.

    ``stamps``, ``tags``, ``cameras``, ``T_camera_tag`` (n x 4 x 4): the usable sightings.
    """
    views = views_of(stamps, tags, cameras)
    shared: dict[tuple[str, str], list[tuple[int, int]]] = defaultdict(list)
    for by_cam in views.values():
        for a, tags_a in by_cam.items():
            for c, tags_c in by_cam.items():
                if a != c:
                    shared[(a, c)] += [(ia, tags_c[g]) for g, ia in tags_a.items() if g in tags_c]
    placed = {str(c): np.asarray(p.matrix()) for c, p in known.items()}
    todo = set(unknown)
    out: dict[str, MountEstimate] = {}
    while todo:
        best = max(
            ((len(shared.get((a, c), [])), a, c) for c in sorted(todo) for a in sorted(placed)),
            default=(0, "", ""),
        )
        n, a, c = best
        if n < MIN_PAIRS:
            linked = _through_tag_pairs(views, T_camera_tag, placed, todo)
            if linked is None:
                linked = _hand_eye(views, T_camera_tag, placed, todo)
            if linked is None:
                break
            out[linked.camera] = linked
            placed[linked.camera] = np.asarray(linked.pose.matrix())
            todo.discard(linked.camera)
            continue
        rows_a, rows_c = (np.array(x) for x in zip(*shared[(a, c)], strict=True))
        pose, spread, _, se = pair_estimate(placed[a], T_camera_tag[rows_a], T_camera_tag[rows_c])
        out[c] = MountEstimate(c, pose, n, a, spread, initial=pose, translation_se=se)
        placed[c] = np.asarray(pose.matrix())
        todo.discard(c)
    return out, sorted(todo)


def _through_tag_pairs(
    views: Views, T_camera_tag: FloatArray, placed: Mapping[str, FloatArray], todo: set[str]
) -> MountEstimate | None:
    """The unplaced camera with the most moments at which a placed camera sees tag ``t1`` and it sees another tag
    ``t2`` whose pose relative to ``t1`` some camera measured in one frame: ``T_base_c = T_base_a T_a_t1 T_t1_t2
    T_c_t2⁻¹`` (``T_t1_t2`` the robust mean of its single-frame measurements). None when no camera has
    :data:`MIN_PAIRS` such moments."""
    rel_samples: dict[tuple[int, int], list[FloatArray]] = defaultdict(list)
    for by_cam in views.values():
        for by_tag in by_cam.values():
            for t1, i1 in by_tag.items():
                for t2, i2 in by_tag.items():
                    if t1 != t2:
                        rel_samples[(t1, t2)].append(np.linalg.inv(T_camera_tag[i1]) @ T_camera_tag[i2])
    rel: dict[tuple[int, int], FloatArray] = {}
    best: tuple[int, str, str, list[FloatArray]] = (0, "", "", [])
    for c in sorted(todo):
        for a in sorted(placed):
            est: list[FloatArray] = []
            for moment in views.values():
                if a not in moment or c not in moment:
                    continue
                for t1, i1 in moment[a].items():
                    for t2, i2 in moment[c].items():
                        if (t1, t2) not in rel_samples:
                            continue
                        if (t1, t2) not in rel:
                            rel[(t1, t2)] = np.asarray(_mean_pose(np.asarray(rel_samples[(t1, t2)])).matrix())
                        est.append(placed[a] @ T_camera_tag[i1] @ rel[(t1, t2)] @ np.linalg.inv(T_camera_tag[i2]))
            if len(est) > best[0]:
                best = (len(est), a, c, est)
    n, a, c, est = best
    if n < MIN_PAIRS:
        return None
    Ts = np.asarray(est)
    pose = _mean_pose(Ts)
    spread = float(np.degrees(np.median(_angles(Ts[:, :3, :3], np.asarray(pose.rotation().matrix())))))
    return MountEstimate(c, pose, n, f"{a} (through tags seen together)", spread, initial=pose)


HAND_EYE_MIN_TURN_DEG = 10.0
"""Motions turning less than this between two moments are too short a lever for the hand-eye rotation."""
HAND_EYE_MAX_MOMENTS = 80
"""At most this many moments (evenly spread over the run) are paired for one hand-eye fit: pairs grow as their
square."""
HAND_EYE_MAX_PAIRS = 400
"""At most this many pairs of moments enter one hand-eye fit (drawn evenly from those that qualify)."""
HAND_EYE_MIN_CONDITION = 0.05
"""The hand-eye fit is refused when the smallest singular value of its rotation or translation system is below
this fraction of the largest: the motions did not turn about enough different axes to fix the mount."""


def hand_eye(
    stamps: npt.ArrayLike,
    tags: npt.ArrayLike,
    cams: npt.NDArray[np.object_],
    T_camera_tag: FloatArray,
    placed: Mapping[str, FloatArray],
    todo: set[str],
) -> MountEstimate | None:
    """The mount of a camera that never sees a tag a placed camera sees, from the rig's motion (hand-eye
    calibration, ``A X = X B``): between two moments at which a placed camera ``a`` sees one tag ``t`` both times
    and the camera ``c`` sees one tag ``u`` both times, the base moves by ``A = T_base_a Z_a1 Z_a2⁻¹ T_base_a⁻¹``
    and ``c`` by ``B = Z_c1 Z_c2⁻¹``, and ``A X = X B`` for ``X = T_base_c``. The rotation is Kabsch's fit of the
    motions' rotation axes (``log R_A = R_X log R_B``), the translation the least-squares solution of
    ``(R_A − I) t_X = R_X t_B − t_A``; pairs beyond three median deviations are dropped once. None when no camera
    has motions about enough different axes (a robot on a floor turns about one: its mount's height is not fixed
    by motion)."""
    return _hand_eye(views_of(stamps, tags, cams), T_camera_tag, placed, todo)


def _hand_eye(
    views: Views, T_camera_tag: FloatArray, placed: Mapping[str, FloatArray], todo: set[str]
) -> MountEstimate | None:
    best: MountEstimate | None = None
    for c in sorted(todo):
        for a in sorted(placed):
            est = _hand_eye_pair(views, a, c, T_camera_tag, placed[a])
            if est is not None and (best is None or est.pairs > best.pairs):
                best = est
    return best


def _hand_eye_pair(
    views: Mapping[int, Mapping[str, Mapping[int, int]]],
    a: str,
    c: str,
    T_camera_tag: FloatArray,
    T_base_a: FloatArray,
) -> MountEstimate | None:
    both = sorted(s for s, v in views.items() if a in v and c in v)
    if len(both) > HAND_EYE_MAX_MOMENTS:
        both = [both[i] for i in np.linspace(0, len(both) - 1, HAND_EYE_MAX_MOMENTS).round().astype(int)]
    pairs: list[tuple[FloatArray, FloatArray]] = []
    inv_a = np.linalg.inv(T_base_a)
    for k, s1 in enumerate(both):
        for s2 in both[k + 1 :]:
            ta = set(views[s1][a]) & set(views[s2][a])
            tc = set(views[s1][c]) & set(views[s2][c])
            if not ta or not tc:
                continue
            t, u = min(ta), min(tc)
            A = T_base_a @ T_camera_tag[views[s1][a][t]] @ np.linalg.inv(T_camera_tag[views[s2][a][t]]) @ inv_a
            B = T_camera_tag[views[s1][c][u]] @ np.linalg.inv(T_camera_tag[views[s2][c][u]])
            turn = np.degrees(_angles(A[None, :3, :3], np.eye(3))[0])
            if turn >= HAND_EYE_MIN_TURN_DEG:
                pairs.append((A, B))
    if len(pairs) < MIN_PAIRS:
        return None
    if len(pairs) > HAND_EYE_MAX_PAIRS:
        pick = np.linspace(0, len(pairs) - 1, HAND_EYE_MAX_PAIRS).round().astype(int)
        pairs = [pairs[i] for i in pick]
    keep = np.ones(len(pairs), dtype=bool)
    X = None
    for _ in range(2):
        X = _solve_hand_eye([p for p, k in zip(pairs, keep, strict=True) if k])
        if X is None:
            return None
        res = np.array([np.linalg.norm(A @ X - X @ B) for A, B in pairs])
        cut = 3.0 * float(np.median(res[keep])) + 1e-9
        if np.array_equal(res <= cut, keep) or (res <= cut).sum() < MIN_PAIRS:
            break
        keep = res <= cut
    assert X is not None
    spread = float(np.degrees(np.median([_angles((A @ X)[None, :3, :3], (X @ B)[:3, :3])[0] for A, B in pairs])))
    pose = pose3_from_matrix(X)
    return MountEstimate(c, pose, int(keep.sum()), f"{a} (hand-eye, from the rig's motion)", spread, initial=pose)


def _solve_hand_eye(pairs: list[tuple[FloatArray, FloatArray]]) -> FloatArray | None:
    """``X`` with ``A X = X B`` over the pairs (least squares), None when the motions do not fix it."""
    alpha = np.array([np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(A[:3, :3]))) for A, _ in pairs])
    beta = np.array([np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(B[:3, :3]))) for _, B in pairs])
    if np.linalg.svd(alpha, compute_uv=False)[-1] < HAND_EYE_MIN_CONDITION * np.linalg.svd(alpha, compute_uv=False)[0]:
        return None  # one turning axis: the rotation about it is free
    U, _, Vt = np.linalg.svd(beta.T @ alpha)
    R = (U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt).T
    M = np.vstack([A[:3, :3] - np.eye(3) for A, _ in pairs])
    rhs = np.concatenate([R @ B[:3, 3] - A[:3, 3] for A, B in pairs])
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[-1] < HAND_EYE_MIN_CONDITION * sv[0]:
        return None
    t = np.linalg.lstsq(M, rhs, rcond=None)[0]
    X = np.eye(4)
    X[:3, :3] = R
    X[:3, 3] = t
    return X


def _mean_pose(Ts: FloatArray) -> gtsam.Pose3:
    """The robust mean of rigid transforms (n x 4 x 4): chordal mean rotation of the inliers, median translation."""
    R, keep = rotation_mean(Ts[:, :3, :3])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.median(Ts[keep, :3, 3], axis=0)
    return pose3_from_matrix(T)


def mount_error(
    X: gtsam.Pose3, L: gtsam.Pose3, C: gtsam.Pose3, T_camera_tag: gtsam.Pose3
) -> tuple[FloatArray, list[FloatArray]]:
    """``e = Log((C Z)⁻¹ X⁻¹ L)`` and its Jacobians with respect to X, L and C (right perturbations, tangent order
    rotation, translation)."""
    Hx, Hl = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    P = X.between(L, Hx, Hl)
    Hc = np.zeros((6, 6), order="F")
    Hz = np.zeros((6, 6), order="F")
    Q = C.compose(T_camera_tag, Hc, Hz)
    Hq, Hp = np.zeros((6, 6), order="F"), np.zeros((6, 6), order="F")
    D = Q.between(P, Hq, Hp)
    Hlog = np.zeros((6, 6), order="F")
    e = gtsam.Pose3.Logmap(D, Hlog)
    return np.asarray(e, dtype=float), [Hlog @ Hp @ Hx, Hlog @ Hp @ Hl, Hlog @ Hq @ Hc]


def mount_factor(
    keys: tuple[int, int, int], T_camera_tag: gtsam.Pose3, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """The tag factor of a sighting by a camera whose mount ``C`` (key ``keys[2]``) is unknown."""
    kx, kl, kc = keys

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[FloatArray] | None) -> FloatArray:
        e, J = mount_error(v.atPose3(kx), v.atPose3(kl), v.atPose3(kc), T_camera_tag)
        if H is not None:
            H[0], H[1], H[2] = J
        return e

    return gtsam.CustomFactor(noise, list(keys), error)


def inflated(cov6: FloatArray, T_camera_tag: gtsam.Pose3, mount_cov: FloatArray | None) -> FloatArray:
    """A sighting's covariance with its camera mount's uncertainty carried in: ``Σ + Ad(Z⁻¹) Σ_C Ad(Z⁻¹)ᵀ``."""
    if mount_cov is None:
        return cov6
    Ad = np.asarray(T_camera_tag.inverse().AdjointMap())
    return np.asarray(cov6 + Ad @ mount_cov @ Ad.T)


def refine_mounts(
    rows: list[FactorRow],
    row_cameras: list[str | None],
    initial: gtsam.Values,
    estimates: dict[str, MountEstimate],
    max_iterations: int = 100,
) -> dict[str, Any]:
    """Estimate the mounts of ``estimates``' cameras in the 3D graph of ``rows`` (built with their initial mounts;
    ``row_cameras[i]`` is the camera of tag row ``i``): each becomes one ``Pose3`` variable shared by its sightings.
    Updates ``pose`` and ``covariance`` of each estimate in place; returns the solve's figures.

    The tag scale, when the graph has one, is held at 1 here (its prior row is left out, its key dropped)."""
    order = sorted(estimates)
    keys = {cam: mount_key(i) for i, cam in enumerate(order)}
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    used: set[int] = set()
    for row, cam in zip(rows, row_cameras, strict=True):
        if row.kind == "scale_prior":
            continue
        plain = replace(row, keys=row.keys[:2]) if row.kind == "tag" else row
        used.update(plain.keys)
        if row.kind == "tag" and cam in keys:
            Z = estimates[cam].pose.inverse().compose(pose3_from_vector(row.measurement))
            noise = noise_model(np.asarray(row.covariance, dtype=float).reshape(6, 6), row.robust, row.robust_k)
            graph.add(mount_factor((plain.keys[0], plain.keys[1], keys[cam]), Z, noise))
        else:
            graph.add(make_factor(plain))
    for k in sorted(used):
        values.insert(k, initial.atPose3(k))
    for cam, key in keys.items():
        values.insert(key, estimates[cam].pose)
        prior, given = estimates[cam].prior, estimates[cam].initial
        if prior is not None and given is not None:
            noise = gtsam.noiseModel.Gaussian.Information(np.asarray(prior, dtype=float))
            graph.add(gtsam.PriorFactorPose3(key, given, noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    # every mount touches every pose its camera saw from, as every landmark does: eliminated last (the usual SLAM
    # order), they leave one small dense block instead of fill-in across the whole path
    last = [k for k in sorted(used) if gtsam.Symbol(k).chr() == ord("l")] + list(keys.values())
    params.setOrdering(gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(graph, gtsam.KeyVector(last)))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    figures: dict[str, Any] = {
        "iterations": int(optimizer.iterations()),
        "error_before": float(graph.error(values)),
        "error_after": float(graph.error(result)),
    }
    from stages.graph.marginals import key_dims, tree_marginals  # the project's elimination and its fallback

    covariances: dict[int, FloatArray] = {}
    try:
        covariances = tree_marginals(graph.linearize(result), key_dims(result), list(keys.values()), last=last)
    except RuntimeError as err:
        figures["marginals"] = "not computed: " + " ".join(str(err).split()).split(". ")[0]
    for cam, key in keys.items():
        est = estimates[cam]
        est.pose = result.atPose3(key)
        if key in covariances:
            est.covariance = np.asarray(covariances[key], dtype=float)
    return figures


def sqrt_information(cov: FloatArray) -> FloatArray:
    """gtsam's square-root information of a covariance: the upper-triangular ``R`` with ``RᵀR = Σ⁻¹``."""
    information = np.linalg.inv(0.5 * (cov + cov.T))
    return np.asarray(np.linalg.cholesky(0.5 * (information + information.T)).T)


def camera_poses_yaml(mounts: Mapping[str, tuple[FloatArray, FloatArray | None]], base_frame: str) -> str:
    """TagSLAM's ``camera_poses.yaml`` for ``mounts`` (name to ``T_base_camera`` and its 6x6 covariance, None when
    given and held fixed): the pose as position and angle-axis rotation, ``R`` the square-root information
    (:func:`sqrt_information`; a fixed mount's is :data:`GIVEN_INFORMATION` times the identity)."""
    lines = [f"# camera poses in the {base_frame!r} frame, written by focusmap's rig calibration (graph stage)"]
    for name, (T, cov) in mounts.items():
        pose = pose3_from_matrix(np.asarray(T, dtype=float))
        rot = np.asarray(gtsam.Rot3.Logmap(pose.rotation()), dtype=float)
        pos = np.asarray(pose.translation(), dtype=float)
        sqrt_info = np.eye(6) * GIVEN_INFORMATION if cov is None else sqrt_information(cov)
        lines += [
            f"{name}:",
            "  pose:",
            "    position:",
            *(f"      {a}: {v:.9g}" for a, v in zip("xyz", pos, strict=True)),
            "    rotation:",
            *(f"      {a}: {v:.9g}" for a, v in zip("xyz", rot, strict=True)),
            "    R:",
            "      [ " + ",\n        ".join(", ".join(f"{v:.9g}" for v in row) for row in sqrt_info) + " ]",
        ]
    return "\n".join(lines) + "\n"


def rig_remarks(block: Any) -> list[tuple[str, str]]:
    """The graph stage's lines about the rig calibration (its summary block ``rig_calibration``)."""
    if not isinstance(block, dict):
        return []
    out: list[tuple[str, str]] = []
    for cam, c in (block.get("cameras") or {}).items():
        sig_t, sig_r = c.get("sigma_translation_m"), c.get("sigma_rotation_deg")
        sigma = f"σ {1000 * max(sig_t):.1f} mm, {max(sig_r):.2f}°" if sig_t and sig_r else "its covariance not computed"
        if c.get("placed_from") == GIVEN_PRIOR:
            out.append(
                (
                    "note",
                    f"camera {c.get('frame_id', cam)} ({cam}): its given mount is looser than 1 mm or 1 mrad (R in "
                    "--extrinsics), so the graph estimated it with that as its prior: it moved "
                    f"{100 * c.get('moved_from_initial_m', 0.0):.1f} cm, {c.get('moved_from_initial_deg', 0.0):.2f}° "
                    f"({sigma}); graph/camera_poses.yaml holds it",
                )
            )
            continue
        via = str(c.get("placed_from"))
        start = (
            f"{c.get('shared_sightings')} pairs of moments of its motion against {via.split(' (hand-eye')[0]}'s "
            "(hand-eye)"
            if "hand-eye" in via
            else f"{c.get('shared_sightings')} sightings shared with {via}"
        )
        out.append(
            (
                "note",
                f"camera {c.get('frame_id', cam)} ({cam}) had no mount: estimated from {start} and all its own "
                f"sightings ({sigma}); graph/camera_poses.yaml holds it for --extrinsics",
            )
        )
    not_refined = (block.get("solve") or {}).get("not_refined")
    if not_refined:
        out.append(
            (
                "warning",
                f"the rig's mounts could not be estimated in the graph ({not_refined}): each camera's initial mount "
                "from its shared sightings is used, without a covariance; give the mounts with --extrinsics",
            )
        )
    for cam, n in (block.get("unplaced") or {}).items():
        out.append(
            (
                "warning",
                f"camera {cam} has no mount and shares no tag with the placed cameras (the same tag at the same "
                f"moment, or a tag seen in one frame with theirs, at least {MIN_PAIRS} times): its {n} detections "
                "are left out; placing it from its motion alone (hand-eye) is not done; give its mount with "
                "--extrinsics",
            )
        )
    return out


GIVEN_PRIOR = "its given pose (prior R)"
"""``placed_from`` of a given mount estimated with its information as prior."""

CHECK_MIN_PAIRS = 20
"""A given mount is judged against the data only when the camera shares at least this many sightings with the
rig's other given cameras."""
CHECK_MAX_M = 0.03
"""A given mount whose translation differs from the data's by more than this (and 3 standard errors) fails the
``rig`` health check, m (the ``extrinsics`` check's angle, 3°, bounds the rotation)."""


def given_mount_figures(
    stamps: npt.ArrayLike,
    tags: npt.ArrayLike,
    cameras: Iterable[str],
    T_camera_tag: FloatArray,
    given: Mapping[str, gtsam.Pose3],
) -> dict[str, dict[str, Any]]:
    """Each given camera's mount against the one its same-stamp sightings with the rig's other given cameras imply
    (leave one out): the angle and distance between them, and the standard error of the data's translation (the
    spread of the pair estimates over the root of their number)."""
    cams = list(cameras)
    out: dict[str, dict[str, Any]] = {}
    if len(given) < 2:
        return out
    for cam, mount in given.items():
        others = {c: p for c, p in given.items() if c != cam}
        est, _ = initial_mounts(stamps, tags, cams, T_camera_tag, others, {cam})
        if cam not in est or est[cam].pairs < CHECK_MIN_PAIRS or "through" in est[cam].via:
            continue
        e = est[cam]
        d = mount.between(e.pose)
        out[cam] = {
            "pairs": e.pairs,
            "from": e.via,
            "angle_deg": round(float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation())))), 3),
            "distance_m": round(float(np.linalg.norm(np.asarray(e.pose.translation()) - mount.translation())), 4),
            "distance_se_m": round(e.translation_se, 5),
        }
    return out


def given_mount_warning(name: str, figures: Mapping[str, Any]) -> str | None:
    """The ``rig`` check's line for a given camera mount the data disagree with (None when they agree)."""
    angle, dist, se = figures["angle_deg"], figures["distance_m"], figures["distance_se_m"]
    if angle <= MOUNT_MAX_DEG and dist <= max(CHECK_MAX_M, 3.0 * se):
        return None
    return (
        f"the given mount of camera {name!r} is {100 * dist:.1f} cm and {angle:.1f} degrees from where its "
        f"{figures['pairs']} sightings of the tags {figures['from']!r} sees at the same moments put it: check its "
        "entry in --extrinsics, or leave it out there and let the graph estimate it (graph.rig_calibration); "
        "cameras whose frames share a stamp but are not taken at the same moment look the same on a moving rig"
    )
