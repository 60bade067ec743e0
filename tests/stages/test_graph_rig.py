"""Rig calibration (stages/graph/rig.py): mounts of unplaced cameras from the tags they share with placed ones."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from stages.geometry import pose3_to_vector
from stages.graph.factors import FactorRow
from stages.graph.rig import (
    MountEstimate,
    camera_poses_yaml,
    initial_mounts,
    mount_error,
    refine_mounts,
)

RNG_SEED = 7


def _pose(rng: np.random.Generator, t_scale: float = 1.0, r_scale: float = 1.0) -> gtsam.Pose3:
    return gtsam.Pose3.Expmap(np.concatenate([rng.normal(0, r_scale, 3), rng.normal(0, t_scale, 3)]))


def _rig(rng: np.random.Generator) -> tuple[dict[str, gtsam.Pose3], list[gtsam.Pose3], dict[int, gtsam.Pose3]]:
    mounts = {"a": gtsam.Pose3(), "b": _pose(rng, 0.1, 1.0), "c": _pose(rng, 0.1, 1.0), "d": _pose(rng, 0.1, 1.0)}
    rig_poses = [_pose(rng, 1.0, 0.3) for _ in range(12)]
    tags = {t: _pose(rng, 3.0, 1.0) for t in range(5)}
    return mounts, rig_poses, tags


def _sightings(
    mounts: dict[str, gtsam.Pose3], rig_poses: list[gtsam.Pose3], tags: dict[int, gtsam.Pose3], who: dict[str, set[int]]
) -> tuple[list[int], list[int], list[str], np.ndarray]:
    """Noiseless sightings: camera ``cam`` sees every tag at the keyframes listed in ``who[cam]``."""
    stamps, ids, cams, Ts = [], [], [], []
    for cam, frames in who.items():
        for k in sorted(frames):
            for t, T_tag in tags.items():
                Z = mounts[cam].inverse().compose(rig_poses[k].inverse()).compose(T_tag)
                stamps.append(k)
                ids.append(t)
                cams.append(cam)
                Ts.append(np.asarray(Z.matrix()))
    return stamps, ids, cams, np.asarray(Ts)


def test_initial_mounts_are_exact_and_reach_cameras_through_others() -> None:
    """Noiseless sightings give each mount exactly; ``c`` shares moments only with ``b``, so it is placed through
    ``b``; ``d`` never sees a tag with anyone else, so it is named as unplaced."""
    rng = np.random.default_rng(RNG_SEED)
    mounts, rig_poses, tags = _rig(rng)
    who = {"a": {0, 1, 2, 3}, "b": {2, 3, 4, 5}, "c": {5, 6, 7}, "d": {9, 10}}
    stamps, ids, cams, Ts = _sightings(mounts, rig_poses, tags, who)
    est, unplaced = initial_mounts(stamps, ids, cams, Ts, {"a": mounts["a"]}, {"b", "c", "d"})
    assert unplaced == ["d"]
    assert est["b"].via == "a" and est["c"].via == "b"
    assert est["b"].pairs == 2 * len(tags) and est["c"].pairs == len(tags)
    for cam in ("b", "c"):
        assert np.allclose(est[cam].pose.matrix(), mounts[cam].matrix(), atol=1e-9)


def test_initial_mount_ignores_a_flipped_sighting() -> None:
    """One pair whose tag pose is grossly wrong (a flipped pose estimate) does not move the robust mean."""
    rng = np.random.default_rng(RNG_SEED + 1)
    mounts, rig_poses, tags = _rig(rng)
    stamps, ids, cams, Ts = _sightings(mounts, rig_poses, tags, {"a": {0, 1, 2}, "b": {0, 1, 2}})
    bad = cams.index("b")
    Ts[bad] = Ts[bad] @ np.asarray(gtsam.Pose3(gtsam.Rot3.Rx(np.pi), np.array([0.0, 0.0, 0.0])).matrix())
    est, _ = initial_mounts(stamps, ids, cams, Ts, {"a": mounts["a"]}, {"b"})
    assert np.allclose(est["b"].pose.matrix(), mounts["b"].matrix(), atol=1e-9)


def test_mount_error_jacobians_match_numerical_derivatives() -> None:
    rng = np.random.default_rng(RNG_SEED + 2)
    Xp, Lp, C, Z = (_pose(rng, 1.0, 0.5) for _ in range(4))
    e0, J = mount_error(Xp, Lp, C, Z)
    h = 1e-6
    for which, H in enumerate(J):
        num = np.zeros((6, 6))
        for j in range(6):
            d = np.zeros(6)
            d[j] = h
            args = [Xp, Lp, C]
            args[which] = args[which].retract(d)
            num[:, j] = (mount_error(args[0], args[1], args[2], Z)[0] - e0) / h
        assert np.allclose(H, num, atol=1e-5), which


def _rows(
    mounts: dict[str, gtsam.Pose3],
    rig_poses: list[gtsam.Pose3],
    tags: dict[int, gtsam.Pose3],
    placed: dict[str, gtsam.Pose3],
    cov: np.ndarray,
    rng: np.random.Generator,
) -> tuple[list[FactorRow], list[str | None], gtsam.Values]:
    """A 3D graph: prior on the first rig pose, weak motion priors, and one noisy tag row per sighting by every
    camera at every keyframe (measurement ``T_base_tag`` at the mount in ``placed``)."""
    chol = np.linalg.cholesky(cov)
    rows = [FactorRow("prior", "PriorFactorPose3", (int(X(0)),), pose3_to_vector(rig_poses[0]), np.eye(6) * 1e-10)]
    cams: list[str | None] = [None]
    values = gtsam.Values()
    for k, P in enumerate(rig_poses):
        values.insert(int(X(k)), P)
        if k:
            rel = rig_poses[k - 1].between(P)
            rows.append(
                FactorRow(
                    "motion_prior", "BetweenFactorPose3", (int(X(k - 1)), int(X(k))), pose3_to_vector(rel), np.eye(6)
                )
            )
            cams.append(None)
        for cam, M in mounts.items():
            for t, T_tag in tags.items():
                Z = M.inverse().compose(P.inverse()).compose(T_tag).retract(chol @ rng.normal(size=6))
                meas = placed[cam].compose(Z)
                rows.append(FactorRow("tag", "BetweenFactorPose3", (int(X(k)), int(L(t))), pose3_to_vector(meas), cov))
                cams.append(cam)
    for t, T_tag in tags.items():
        values.insert(int(L(t)), T_tag)
    return rows, cams, values


def test_refined_mount_covariance_matches_monte_carlo() -> None:
    """The mount's marginal covariance against the spread of the estimate over noisy realisations: the mean NEES
    over the runs is near the 6 degrees of freedom (a covariance 2x too small gives about 12)."""
    rng = np.random.default_rng(RNG_SEED + 3)
    mounts = {"a": gtsam.Pose3(), "b": _pose(rng, 0.1, 1.0)}
    rig_poses = [_pose(rng, 0.5, 0.2) for _ in range(6)]
    ahead = np.array([0.0, 0.0, 3.0])
    tags = {t: gtsam.Pose3(gtsam.Rot3.Ypr(*rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3) + ahead) for t in range(3)}
    cov = np.diag([1e-4] * 3 + [1e-4] * 3)
    nees = []
    for _ in range(40):
        start = mounts["b"].retract(rng.normal(0, 0.01, 6))
        rows, cams, values = _rows(mounts, rig_poses, tags, {"a": mounts["a"], "b": start}, cov, rng)
        est = {"b": MountEstimate("b", start, 10, "a", 0.0)}
        refine_mounts(rows, cams, values, est)
        assert est["b"].covariance is not None
        d = mounts["b"].localCoordinates(est["b"].pose)
        nees.append(float(d @ np.linalg.solve(est["b"].covariance, d)))
    assert 6 * 0.7 < np.mean(nees) < 6 * 1.4


def test_camera_poses_yaml_round_trip(tmp_path: Path) -> None:
    """What the graph writes, ``--extrinsics`` reads back: the same mounts and information; R is written as TagSLAM
    writes it, gtsam's upper-triangular square-root information (given mounts held fixed at 1e6)."""
    import yaml

    from stages.extrinsics import load_extrinsics_file

    rng = np.random.default_rng(RNG_SEED + 5)
    T = np.asarray(_pose(rng, 0.2, 1.0).matrix())
    cov = np.diag([1e-6] * 3 + [4e-6] * 3)
    path = tmp_path / "camera_poses.yaml"
    path.write_text(camera_poses_yaml({"cam0": (np.eye(4), None), "cam1": (T, cov)}, "rig"))
    f = load_extrinsics_file(path)
    assert f.kind == "tagslam camera_poses" and np.allclose(f.mounts["cam1"], T, atol=1e-8)
    doc = yaml.safe_load(path.read_text())
    R = np.asarray(doc["cam1"]["pose"]["R"]).reshape(6, 6)
    assert np.allclose(R, np.triu(R)) and np.allclose(R.T @ R, np.linalg.inv(cov))  # TagSLAM's: gtsam's sqrt info
    assert np.allclose(f.information["cam1"], np.linalg.inv(cov))
    assert np.allclose(np.asarray(doc["cam0"]["pose"]["R"]).reshape(6, 6), np.eye(6) * 1e6)


def test_given_mount_check_names_a_wrong_given_mount() -> None:
    """Leave one out: each given mount against what the sightings shared with the other given cameras imply. Right
    mounts pass; one moved by 5 cm, or turned by 4°, fails with a line naming it."""
    from stages.graph.rig import given_mount_figures, given_mount_warning

    rng = np.random.default_rng(RNG_SEED + 6)
    mounts, rig_poses, tags = _rig(rng)
    who = {"a": set(range(12)), "b": set(range(12)), "c": set(range(6))}
    stamps, ids, cams, Ts = _sightings(mounts, rig_poses, tags, who)
    given = {c: mounts[c] for c in ("a", "b", "c")}
    figures = given_mount_figures(stamps, ids, cams, Ts, given)
    assert set(figures) == {"a", "b", "c"}
    assert all(given_mount_warning(c, f) is None for c, f in figures.items())
    for wrong in (
        mounts["c"].compose(gtsam.Pose3(gtsam.Rot3(), np.array([0.05, 0.0, 0.0]))),
        mounts["c"].compose(gtsam.Pose3(gtsam.Rot3.Rz(np.radians(4.0)), np.zeros(3))),
    ):
        figures = given_mount_figures(stamps, ids, cams, Ts, {**given, "c": wrong})
        line = given_mount_warning("c", figures["c"])
        assert line is not None and "'c'" in line


def test_hand_eye_places_a_camera_that_never_sees_the_placed_cameras_tags() -> None:
    """TagSLAM's test_14 rig: the top cameras see the ceiling's tags, the bottom ones the floor's. No tag is shared,
    at one moment or through one frame, so only the rig's motion can place a top camera (``A X = X B``): from
    noiseless sightings the mount comes back exactly; with motion about a single axis it is refused, not guessed."""
    from stages.graph.rig import hand_eye

    rng = np.random.default_rng(RNG_SEED + 7)
    mounts, rig_poses, tags = _rig(rng)
    ceiling = {t + 10: _pose(rng, 3.0, 1.0) for t in range(3)}
    stamps, ids, cams, Ts = _sightings(mounts, rig_poses, tags, {"a": set(range(12))})
    s2, i2, c2, T2 = _sightings(mounts, rig_poses, ceiling, {"c": set(range(12))})
    args = (stamps + s2, ids + i2, np.asarray(cams + c2, dtype=object), np.concatenate([Ts, T2]))
    est, unplaced = initial_mounts(args[0], args[1], args[2], args[3], {"a": mounts["a"]}, {"c"})
    assert unplaced == [] and "hand-eye" in est["c"].via
    assert np.allclose(est["c"].pose.matrix(), mounts["c"].matrix(), atol=1e-6)
    # a rig that only turns about its z axis (a robot on a floor): the mount's height is not fixed by motion
    flat = [gtsam.Pose3(gtsam.Rot3.Yaw(rng.uniform(-3, 3)), np.array([*rng.normal(0, 1, 2), 0.0])) for _ in range(12)]
    stamps, ids, cams, Ts = _sightings(mounts, flat, tags, {"a": set(range(12))})
    s2, i2, c2, T2 = _sightings(mounts, flat, ceiling, {"c": set(range(12))})
    assert (
        hand_eye(
            stamps + s2,
            ids + i2,
            np.asarray(cams + c2, dtype=object),
            np.concatenate([Ts, T2]),
            {"a": np.asarray(mounts["a"].matrix())},
            {"c"},
        )
        is None
    )
