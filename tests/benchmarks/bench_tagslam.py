"""ATE of focusmap's trajectory against TagSLAM's own on every shared TagSLAM regression case.

    python tests/benchmarks/bench_tagslam.py [--cases test_1 test_2 ...] [--work DIR] [--timeout 1800]
                                             [--until graph] [--without-tags] [--set SECTION.KEY=VALUE ...]
                                             [--through-evaluate]

For each case in ``../shared/data/tagslam-test`` the recording (``tag_detections.bag.bz2``) and TagSLAM's
result (``reference.bag.bz2``, topic ``/tagslam/odom/body_rig``) are decompressed into a temporary folder, and
focusmap is run on the recording with the command a user types (``CASES`` below, printed in the table):
the case's ``cameras.yaml``, ``camera_poses.yaml`` and ``tagslam.yaml`` (``--tags``: tag sizes, ignored
tags, surveyed tag poses, the odometry body's ``T_body_odom``). ``--without-tags`` runs the commands of
before ``--tags`` existed instead: the tag sizes as ``--set detect.tag_size_m``/``detect.tag_sizes``.
The graph stage's ``trajectory.tum`` is then compared with TagSLAM's trajectory as evo's ``evo_ape --align``
does: poses matched by stamp (nearest within 10 ms), the positions aligned by Umeyama's method without scale
(a rigid SE(3) alignment), and the RMSE of the position differences after it (absolute trajectory error).

Printed per case: the command, its status (``solved`` or its error line), the ATE (m), the same RMSE without the
alignment (``in frame``: the trajectory in TagSLAM's world frame, which the surveyed tags of --tags define; metres
off when a tag frame convention is wrong), the path length of TagSLAM's matched trajectory (m) and the target
max(5 cm, 1 % of that path). When the ``evo`` package imports
(e.g. ``pip install --no-deps --target /tmp/evo_pkg evo`` and ``PYTHONPATH=$PYTHONPATH:/tmp/evo_pkg``), evo's
own APE is printed beside ours as an oracle; evo is not a dependency of focusmap.

``--set`` passes settings on to every case's command. ``--through-evaluate`` runs every stage up to evaluate, with
the landmark selection these camera-only recordings can run (no laser: ``select_landmarks.strategy=
mutual-information``) and navigation off (no walls: ``evaluate.trials=0``), and prints a second table: each
stage's ``seconds`` from its ``summary.json`` (stages that were up to date and skipped show the time of the run that
made them).
"""

from __future__ import annotations

import argparse
import bz2
import os
import shlex
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from stages.geometry import umeyama_alignment  # noqa: E402

SHARED = ROOT.parent / "shared" / "data" / "tagslam-test"
REFERENCE_TOPIC = "/tagslam/odom/body_rig"
MAX_DT_S = 0.01


@dataclass(frozen=True)
class Case:
    """A shared TagSLAM case: its folder, the recording (another case's for test_3) and the focusmap options."""

    name: str
    args: tuple[str, ...]
    without_tags: tuple[str, ...] = ()
    """The options without ``--tags``: the sizes its tagslam.yaml gives, as settings."""
    bag_of: str = ""
    """The case whose ``tag_detections.bag`` this one uses (test_3 replays test_2's recording)."""
    remark: str = ""


# The options a user passes: the case's cameras.yaml (every camera it names is read), camera_poses.yaml
# (test_3: TagSLAM's calibrated stereo poses for test_2's recording) and tagslam.yaml (--tags), and the 3D
# model (handheld rigs; graph.model=auto is not ours). Without --tags: the tag sizes its tagslam.yaml gives
# (default_tag_size and per-id sizes) as settings.
def _case(name: str, size: float, *extra: str, bag_of: str = "", remark: str = "") -> Case:
    files = ("--camera", f"{{shared}}/{name}/cameras.yaml", "--extrinsics", f"{{shared}}/{name}/camera_poses.yaml")
    model = ("--set", "graph.model=3d")
    with_tags = (*files, "--tags", f"{{shared}}/{name}/tagslam.yaml", *model)
    without = (*files, "--set", f"detect.tag_size_m={size:g}", *extra, *model)
    return Case(name, with_tags, without, bag_of=bag_of, remark=remark)


CASES = (
    _case("test_1", 0.225),
    _case("test_2", 0.16),
    _case("test_3", 0.16, bag_of="test_2"),
    _case("test_5", 0.15),
    _case("test_10", 0.15),
    _case("test_14", 0.125, "--set", "detect.tag_sizes=[{id: 44, size_m: 0.15}]"),
    _case("test_20", 0.16, remark="TagSLAM itself stops on this case (singular on purpose); its reference is empty"),
    _case(
        "test_21",
        0.16,
        "--set",
        "detect.tag_sizes=[" + ", ".join(f"{{id: {i}, size_m: 0.1}}" for i in range(100, 109)) + "]",
    ),
)


def decompress(src: Path, dst: Path) -> Path:
    """``src`` (``.bz2``) decompressed to ``dst`` once (kept across runs in the same work folder)."""
    if not dst.exists():
        dst.parent.mkdir(parents=True, exist_ok=True)
        part = dst.with_suffix(".part")
        with bz2.open(src, "rb") as fin, part.open("wb") as fout:
            while block := fin.read(1 << 20):
                fout.write(block)
        part.rename(dst)
    return dst


def read_reference(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (s, from the header) and positions of TagSLAM's ``/tagslam/odom/body_rig`` odometry."""
    from rosbags.highlevel import AnyReader

    stamps, xyz = [], []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == REFERENCE_TOPIC]
        for conn, _, raw in reader.messages(connections=conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            stamps.append(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
            p = msg.pose.pose.position
            xyz.append((p.x, p.y, p.z))
    return np.asarray(stamps, float), np.asarray(xyz, float).reshape(-1, 3)


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (s) and positions of a TUM trajectory (``t x y z qx qy qz qw`` rows, ``#`` comments)."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    data = np.asarray(rows, float).reshape(-1, 8)
    return data[:, 0], data[:, 1:4]


def match_stamps(t_est: np.ndarray, t_ref: np.ndarray, max_dt: float = MAX_DT_S) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (estimate, reference) of the nearest reference stamp within ``max_dt`` of each estimate."""
    order = np.argsort(t_ref)
    ts = t_ref[order]
    pos = np.clip(np.searchsorted(ts, t_est), 1, max(len(ts) - 1, 1))
    left, right = ts[pos - 1], ts[np.minimum(pos, len(ts) - 1)]
    nearest = np.where(np.abs(t_est - left) <= np.abs(right - t_est), pos - 1, pos)
    nearest = np.minimum(nearest, len(ts) - 1)
    ok = np.abs(ts[nearest] - t_est) <= max_dt
    return np.flatnonzero(ok), order[nearest[ok]]


def ate(est: np.ndarray, ref: np.ndarray) -> float:
    """RMSE of the position differences after the rigid (no scale) Umeyama alignment of ``est`` onto ``ref``."""
    R, t, _ = umeyama_alignment(est, ref, with_scale=False)
    aligned = est @ R.T + t
    return float(np.sqrt(np.mean(np.sum((aligned - ref) ** 2, axis=1))))


def path_length(xyz: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))) if len(xyz) > 1 else 0.0


def evo_ate(t_est: np.ndarray, xyz_est: np.ndarray, t_ref: np.ndarray, xyz_ref: np.ndarray) -> float | None:
    """evo's APE (translation RMSE) with ``--align`` and 10 ms association, when evo imports; else None."""
    try:
        from evo.core import metrics, sync, trajectory  # type: ignore[import-not-found]
    except ImportError:
        return None
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_est), 1))
    est = trajectory.PoseTrajectory3D(positions_xyz=xyz_est, orientations_quat_wxyz=quat, timestamps=t_est)
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_ref), 1))
    ref = trajectory.PoseTrajectory3D(positions_xyz=xyz_ref, orientations_quat_wxyz=quat, timestamps=t_ref)
    ref, est = sync.associate_trajectories(ref, est, max_diff=MAX_DT_S)
    est.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


@dataclass
class Row:
    case: str
    command: str
    status: str
    ate_m: float | None = None
    evo_m: float | None = None
    unaligned_m: float | None = None
    path_m: float | None = None
    matched: int = 0
    stage_seconds: dict[str, float | None] | None = None

    @property
    def target_m(self) -> float | None:
        return None if self.path_m is None else max(0.05, 0.01 * self.path_m)


STAGES = ("ingest", "detect", "graph", "select_landmarks", "select_measurements", "optimize", "evaluate")


def stage_seconds(run: Path) -> dict[str, float | None]:
    """Each stage's ``seconds`` from its ``summary.json`` in the run folder (None: not run)."""
    import json

    out: dict[str, float | None] = {}
    for stage in STAGES:
        path = run / stage / "summary.json"
        out[stage] = json.loads(path.read_text()).get("seconds") if path.exists() else None
    return out


def run_case(
    case: Case, work: Path, until: str, timeout: float, with_tags: bool = True, settings: tuple[str, ...] = ()
) -> Row:
    folder = SHARED / case.name
    bag_folder = SHARED / (case.bag_of or case.name)
    bag_name = case.bag_of or case.name
    bag = decompress(bag_folder / "tag_detections.bag.bz2", work / "bags" / bag_name / "tag_detections.bag")
    ref_bag = decompress(folder / "reference.bag.bz2", work / "bags" / case.name / "reference.bag")
    args = [a.replace("{shared}", str(SHARED)) for a in (case.args if with_tags else case.without_tags)]
    args += [a for kv in settings for a in ("--set", kv)]
    out = work / "runs"
    cmd = ["focusmap", "run", str(bag), "--out", str(out), "--name", case.name, "--until", until, *args]
    shown = " ".join(
        shlex.quote(a.replace(f"{SHARED}/", "").replace(str(bag), f"{bag_name}/tag_detections.bag")) for a in cmd
    )
    shown = shown.replace(f"--out {out} --name {case.name} ", "")
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=os.environ.copy())
    except subprocess.TimeoutExpired:
        return Row(case.name, shown, f"timeout after {timeout:.0f} s", stage_seconds=stage_seconds(out / case.name))
    if proc.returncode != 0:
        lines = [ln for ln in proc.stderr.splitlines() + proc.stdout.splitlines() if ln.startswith("error")]
        status = (lines or proc.stderr.strip().splitlines()[-1:] or ["failed"])[0]
        return Row(case.name, shown, status, stage_seconds=stage_seconds(out / case.name))
    warnings = [ln.strip() for ln in proc.stderr.splitlines() if ln.strip().startswith("warning:")]
    t_ref, xyz_ref = read_reference(ref_bag)
    status = "solved" + (f" ({len(warnings)} warnings)" if warnings else "")
    if len(t_ref) == 0:
        return Row(case.name, shown, status + "; reference empty", stage_seconds=stage_seconds(out / case.name))
    t_est, xyz_est = read_tum(out / case.name / "graph" / "trajectory.tum")
    i_est, i_ref = match_stamps(t_est, t_ref)
    if len(i_est) < 3:
        return Row(case.name, shown, status + f"; only {len(i_est)} poses match the reference")
    return Row(
        case.name,
        shown,
        status,
        ate(xyz_est[i_est], xyz_ref[i_ref]),
        evo_ate(t_est, xyz_est, t_ref, xyz_ref),
        unaligned_m=float(np.sqrt(np.mean(np.sum((xyz_est[i_est] - xyz_ref[i_ref]) ** 2, axis=1)))),
        path_m=path_length(xyz_ref[i_ref]),
        matched=len(i_est),
        stage_seconds=stage_seconds(out / case.name),
    )


def _m(v: float | None) -> str:
    return "—" if v is None else f"{v:.3f}"


def _s(v: float | None) -> str:
    return "—" if v is None else f"{v:.1f} s"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="*", default=[c.name for c in CASES])
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--until", default="graph")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per case")
    parser.add_argument(
        "--without-tags", action="store_true", help="the commands without --tags (tag sizes as settings)"
    )
    parser.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="passed on (repeatable)",
    )
    parser.add_argument(
        "--through-evaluate",
        action="store_true",
        help="run up to evaluate (mutual-information landmarks, evaluate.trials=0); print each stage's seconds",
    )
    args = parser.parse_args()
    settings = tuple(args.settings)
    if args.through_evaluate:
        args.until = "evaluate"
        settings = ("select_landmarks.strategy=mutual-information", "evaluate.trials=0", *settings)
    if not SHARED.exists():
        raise SystemExit(f"the shared TagSLAM cases are not present: {SHARED}")
    cases = [c for c in CASES if c.name in args.cases]
    with tempfile.TemporaryDirectory(prefix="bench_tagslam_") as tmp:
        work = args.work or Path(tmp)
        rows = []
        for case in cases:
            row = run_case(case, work, args.until, args.timeout, not args.without_tags, settings)
            rows.append(row)
            print(f"{row.case}: {row.status} ATE {_m(row.ate_m)} m", file=sys.stderr, flush=True)
    print("| case | command | status | ATE m | evo APE m | in frame m | path m | target m | within |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        within = "" if r.ate_m is None or r.target_m is None else ("yes" if r.ate_m <= r.target_m else "no")
        print(
            f"| {r.case} | `{r.command}` | {r.status} | {_m(r.ate_m)} | {_m(r.evo_m)} | {_m(r.unaligned_m)} | "
            f"{_m(r.path_m)} | "
            f"{_m(r.target_m)} | {within} |"
        )
    if args.through_evaluate or args.settings:
        print()
        print("| case | " + " | ".join(STAGES) + " |")
        print("|---|" + "---|" * len(STAGES))
        for r in rows:
            secs = r.stage_seconds or {}
            print(f"| {r.case} | " + " | ".join(_s(secs.get(st)) for st in STAGES) + " |")


if __name__ == "__main__":
    main()
