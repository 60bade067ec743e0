"""The reduced map (or the full graph) of a run in the formats robots and other tools load.

``export_run(run_dir, "optimize", "yaml", out)`` reads the stage's artifacts (never writes in the run folder) and
writes one of:

- ``g2o``: the graph at its solution as ``graph.g2o`` writes it (:func:`stages.graph.g2o.write_g2o`: no comment
  lines, ``gtsam.readG2o`` reads every edge but the priors) and its side file ``<out>.json``.
- ``gtsam``: the same graph in GTSAM's own serialization, lossless (full bearing-range covariances, the priors):
  a JSON object whose ``graph`` and ``values`` strings ``gtsam.NonlinearFactorGraph().deserialize(...)`` and
  ``gtsam.Values().deserialize(...)`` read; ``keys`` names every key.
- ``tum``: the optimised trajectory, one ``t x y z qx qy qz qw`` line per pose (t in s).
- ``yaml``: the landmarks as tag poses in TagSLAM's layout (``bodies: - map: tags: - id: … pose: position,
  rotation (rotation vector, rad), position_noise, rotation_noise``) with the full marginal covariance.
- ``csv``: a folder with ``landmarks.csv`` and ``poses.csv``.

Graphs with the shared tag scale are written with the scale fixed at its estimate (g2o and GTSAM's
serialization hold no Python factor): every tag measurement at that scale, its prior left out.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
import yaml

from pipeline.artifacts import StageInput
from pipeline.errors import InputError
from pipeline.run_folder import RunFolder
from stages.graph.factors import FactorRow, build_graph, key_name, scaled_measurement
from stages.graph.g2o import g2o_metadata, side_file, write_g2o
from stages.graph.load import LoadedGraph, load_graph
from stages.graph.outputs import landmark_position, tum_text
from stages.select_landmarks.artifacts import FOCUSED

FORMATS = {"g2o": ".g2o", "gtsam": ".gtsam.json", "tum": ".tum", "yaml": ".yaml", "csv": "_csv"}
"""Export format to the ending of its default output path."""
STAGES = ("optimize", "graph")
"""Stages whose graph can be exported: optimize's reduced map, or the graph stage's full graph."""


def default_out(run_dir: Path, stage: str, fmt: str) -> Path:
    """``<run name>_<stage><ending>`` in the current folder."""
    return Path(f"{Path(run_dir).resolve().name}_{stage}{FORMATS[fmt]}")


def export_run(run_dir: Path, stage: str, fmt: str, out: Path | None = None) -> list[Path]:
    """Write the stage's map in ``fmt`` to ``out`` (default :func:`default_out`); return the files written.

    Raises:
        InputError: unknown stage or format, no run folder, or the stage has not run in it.
    """
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}; use one of {', '.join(FORMATS)}")
    if stage not in STAGES:
        raise InputError(f"cannot export stage {stage!r}; use {' or '.join(STAGES)}")
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"run folder {str(run_dir)!r} does not exist")
    run = RunFolder(run_dir)
    if run.stage_entry(stage) is None or not run.stage_dir(stage).is_dir():
        hint = "run 'focusmap run' or the stages up to it" if stage == "optimize" else "run 'focusmap graph'"
        raise InputError(f"{str(run_dir)!r} has no finished {stage} stage to export; {hint}")
    out = Path(out) if out is not None else default_out(run_dir, stage, fmt)
    for part in out.resolve().parents:
        if part.parent == run_dir.resolve() and (part / "summary.json").is_file():
            raise InputError(f"{str(out)!r} is inside the run's {part.name} stage folder; pass another --out")
    loaded = load_graph(StageInput(stage, run.stage_dir(stage)))
    focused = _focused(run)
    writer = _WRITERS[fmt]
    return writer(loaded, out, focused)


def _focused(run: RunFolder) -> set[int] | None:
    """The focused tag ids, when select_landmarks has run."""
    path = run.stage_dir("select_landmarks")
    if run.stage_entry("select_landmarks") is None or not (path / FOCUSED.file).is_file():
        return None
    return set(FOCUSED.read(StageInput("select_landmarks", path)).tag_ids)


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(text)
    tmp.replace(path)
    return path


# g2o and GTSAM ----------------------------------------------------------------------------------------------
def _g2o(loaded: LoadedGraph, out: Path, focused: set[int] | None) -> list[Path]:
    meta = g2o_metadata(loaded, loaded.values)
    return [_write(out, write_g2o(loaded, loaded.values)), _write(side_file(out), json.dumps(meta, indent=2) + "\n")]


def fixed_scale_rows(loaded: LoadedGraph) -> list[FactorRow]:
    """The rows with the tag scale fixed at its estimate: no scale key, tag measurements at that scale, no prior."""
    key = loaded.scale_key
    if key is None:
        return list(loaded.rows)
    s = float(loaded.values.atDouble(key))
    rows = []
    for r in loaded.rows:
        if r.kind == "scale_prior":
            continue
        keys = tuple(k for k in r.keys if k != key)
        rows.append(FactorRow(r.kind, r.type, keys, scaled_measurement(r, s), r.covariance, r.robust, r.robust_k))
    return rows


def _gtsam(loaded: LoadedGraph, out: Path, focused: set[int] | None) -> list[Path]:
    rows = fixed_scale_rows(loaded)
    graph = build_graph(rows)
    values = gtsam.Values()
    keys = sorted({k for r in rows for k in r.keys})
    for k in keys:
        loaded.kind(k).copy(values, loaded.values, k)
    doc = {
        "format": "GTSAM serialization (boost text archives) of a gtsam.NonlinearFactorGraph and gtsam.Values",
        "load": "g = gtsam.NonlinearFactorGraph(); g.deserialize(d['graph']); "
        "v = gtsam.Values(); v.deserialize(d['values'])",
        "model": loaded.model,
        "factors": graph.size(),
        "final_error": float(graph.error(values)),
        "keys": {str(k): key_name(k) for k in keys},
        "graph": graph.serialize(),
        "values": values.serialize(),
    }
    return [_write(out, json.dumps(doc) + "\n")]


# trajectory and tables -------------------------------------------------------------------------------------
def _tum(loaded: LoadedGraph, out: Path, focused: set[int] | None) -> list[Path]:
    return [_write(out, tum_text(loaded.pose_stamps_ns, loaded.pose3s(loaded.values)))]


def _landmark(loaded: LoadedGraph, tag: int) -> dict[str, Any]:
    """Position, orientation (Pose3 tags), 3x3 position covariance and tangent covariance of a landmark."""
    key = loaded.landmark_keys[tag]
    kind = loaded.kind(key)
    cov = loaded.marginals[key]
    xyz, pc = landmark_position(loaded, loaded.values, tag, cov)
    rot = np.asarray(gtsam.Rot3.Logmap(kind.read(loaded.values, key).rotation())) if kind.is_pose else None
    quat = kind.vector(loaded.values, key)[3:7] if kind.is_pose else None
    return {"xyz": xyz, "position_cov": pc, "rotvec": rot, "quat": quat, "cov": cov, "type": kind.name}


def _observations(loaded: LoadedGraph) -> dict[int, int]:
    counts: dict[int, int] = {}
    for r in loaded.rows:
        if r.kind == "tag" and r.tag_id is not None:
            counts[int(r.tag_id)] = counts.get(int(r.tag_id), 0) + 1
    return counts


def _xyz(v: Any) -> dict[str, float]:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _yaml(loaded: LoadedGraph, out: Path, focused: set[int] | None) -> list[Path]:
    obs = _observations(loaded)
    tags = []
    for tag in loaded.landmark_keys:
        lm = _landmark(loaded, tag)
        pose: dict[str, Any] = {"position": _xyz(lm["xyz"])}
        if lm["rotvec"] is not None:
            pose["rotation"] = _xyz(lm["rotvec"])
        pose["position_noise"] = _xyz(np.sqrt(np.diag(lm["position_cov"])))
        if lm["rotvec"] is not None:
            pose["rotation_noise"] = _xyz(np.sqrt(np.diag(lm["cov"])[:3]))
            pose["covariance"] = [float(v) for v in np.asarray(lm["cov"]).ravel()]
        else:
            pose["covariance"] = [float(v) for v in np.asarray(lm["position_cov"]).ravel()]
        entry: dict[str, Any] = {"id": int(tag)}
        if focused is not None:
            entry["focused"] = tag in focused
        entry["observations"] = int(obs.get(tag, 0))
        entry["pose"] = pose
        tags.append(entry)
    planar = loaded.model == "planar"
    doc = {
        "focusmap": {
            "model": loaded.model,
            "frame": "map",
            "landmarks": len(tags),
            "poses": len(loaded.pose_keys),
            "rotation": "rotation vector (axis times angle, rad) of the tag in the map frame, as TagSLAM writes it",
            "covariance": "3x3 position covariance (x, y, z) in the map frame, row-major; planar landmarks have no "
            "orientation and take their height from the mean of their sightings"
            if planar
            else "6x6 marginal covariance in GTSAM's Pose3 tangent space (rx, ry, rz, tx, ty, tz; body frame), "
            "row-major; position_noise is the map-frame position sigma",
        },
        "bodies": [{"map": {"is_static": True, "type": "simple", "tags": tags}}],
    }
    return [_write(out, yaml.dump(doc, Dumper=_Dumper, sort_keys=False, width=120))]


class _Dumper(yaml.SafeDumper):
    """Block style, but lists of numbers (the covariances) and x/y/z maps on one line."""


def _flow_numbers(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    flow = all(isinstance(v, int | float) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


def _flow_xyz(dumper: yaml.SafeDumper, data: dict[str, Any]) -> yaml.Node:
    flow = list(data) == ["x", "y", "z"]
    return dumper.represent_mapping("tag:yaml.org,2002:map", data.items(), flow_style=flow)


_Dumper.add_representer(list, _flow_numbers)
_Dumper.add_representer(dict, _flow_xyz)


_POS_COV = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
_POS_IDX = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _csv(loaded: LoadedGraph, out: Path, focused: set[int] | None) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    obs = _observations(loaded)
    lm_path, pose_path = out / "landmarks.csv", out / "poses.csv"
    with lm_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["tag_id", "type", "focused", "observations", "x", "y", "z", "qx", "qy", "qz", "qw", *_POS_COV])
        for tag in loaded.landmark_keys:
            lm = _landmark(loaded, tag)
            q = [f"{v:.9g}" for v in lm["quat"]] if lm["quat"] is not None else [""] * 4
            pc = [f"{lm['position_cov'][i, j]:.9g}" for i, j in _POS_IDX]
            flag = "" if focused is None else int(tag in focused)
            w.writerow([tag, lm["type"], flag, obs.get(tag, 0), *(f"{v:.9g}" for v in lm["xyz"]), *q, *pc])
    kind = loaded.graph_model.pose
    with pose_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["index", "stamp_ns", "x", "y", "z", "qx", "qy", "qz", "qw", *_POS_COV])
        for i, (key, stamp, p) in enumerate(
            zip(loaded.pose_keys, loaded.pose_stamps_ns, loaded.pose3s(loaded.values), strict=True)
        ):
            t = np.asarray(p.translation())
            q = p.rotation().toQuaternion()
            cov = kind.position_cov(kind.read(loaded.values, key), loaded.marginals[key])
            row = [*t, q.x(), q.y(), q.z(), q.w(), *(cov[a, b] for a, b in _POS_IDX)]
            w.writerow([i, stamp, *(f"{v:.9g}" for v in row)])
    return [lm_path, pose_path]


_WRITERS = {"g2o": _g2o, "gtsam": _gtsam, "tum": _tum, "yaml": _yaml, "csv": _csv}
