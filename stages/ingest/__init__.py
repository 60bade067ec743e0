"""Stage ``ingest``: read a recording into the run folder (what it writes: :mod:`stages.ingest.artifacts`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Final

from pipeline.errors import InputError
from pipeline.stage import Option, Stage, Summary, lazy, summary_figures, summary_notes
from stages.ingest.config import IngestConfig


def blueprint() -> Any:
    """The layout of ``ingest.rrd``: the map with the whole path, the camera and the summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                name="map",
                origin="/ingest/world",
                time_ranges=[
                    rrb.VisibleTimeRange(
                        "time", start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()
                    )
                ],
            ),
            rrb.Vertical(
                rrb.Spatial2DView(name="camera", origin="/ingest/camera"),
                rrb.TextDocumentView(name="summary", origin="/ingest/summary"),
            ),
        ),
        rrb.TimePanel(play_state="paused", timeline="time"),
        collapse_panels=True,
    )


def _camera_file(path: Path) -> str:
    """``--camera``: an existing file, as an absolute path (a run folder keeps working from any directory)."""
    if not path.is_file():
        raise InputError(f"camera file {str(path)!r} not found; pass an existing calibration YAML to --camera")
    return json.dumps(str(path.resolve()))


def _extrinsics_file(path: Path) -> str:
    """``--extrinsics``: an existing file, as an absolute path."""
    if not path.is_file():
        raise InputError(
            f"extrinsics file {str(path)!r} not found; pass an existing camera_poses.yaml, Kalibr camchain or "
            "frame: 4x4 YAML to --extrinsics"
        )
    return json.dumps(str(path.resolve()))


def _tags_file(path: Path) -> str:
    """``--tags``: an existing file, as an absolute path."""
    if not path.is_file():
        raise InputError(f"tags file {str(path)!r} not found; pass an existing TagSLAM tagslam.yaml to --tags")
    return json.dumps(str(path.resolve()))


def summary_line(summary: Summary) -> str:
    """The figures of an ingest (without the topic names, camera model and read time)."""
    return summary_figures(
        summary,
        hidden=("seconds", "topics", "camera", "notes", "warnings", "camera_topics", "dropped", "read_seconds"),
    )


def remarks(summary: Summary) -> list[tuple[str, str]]:
    """Warnings (an assumed identity extrinsic), notes, and how much of a damaged bag was salvaged."""
    from stages.ingest.info import salvage_text

    salvaged = summary.get("salvaged")
    dropped = summary.get("dropped")
    drops = [
        f"{topic} {sum(n for n in reasons.values() if isinstance(n, int))} ("
        + ", ".join(f"{n} with {why}" for why, n in reasons.items())
        + ")"
        for topic, reasons in (dropped.items() if isinstance(dropped, dict) else [])
        if isinstance(reasons, dict)
    ]
    warnings = summary.get("warnings")
    cameras = summary.get("camera_topics")
    return [
        *(("warning", str(w)) for w in (warnings if isinstance(warnings, list) else [])),
        *([("cameras", ", ".join(str(c) for c in cameras))] if isinstance(cameras, list) else []),
        *summary_notes(summary),
        *([("salvaged", salvage_text(salvaged) if isinstance(salvaged, dict) else str(salvaged))] if salvaged else []),
        *(
            [("warning", "dropped messages with values out of range or that do not decode: " + "; ".join(drops))]
            if drops
            else []
        ),
    ]


OPTIONS: Final = (
    Option("--start", "start_s", "Skip messages before this time (seconds from the bag start).", float),
    Option("--end", "end_s", "Skip messages after this time (seconds from the bag start).", float),
    Option("--stride", "frame_stride", "Keep every n-th camera frame.", int, min=1),
    Option(
        "--camera",
        "camera_file",
        "Camera calibration (Kalibr/TagSLAM cameras.yaml or ROS camera_info YAML).",
        Path,
        value=_camera_file,
    ),
    Option(
        "--extrinsics",
        "extrinsics_file",
        "Where the cameras sit on the rig (TagSLAM camera_poses.yaml, Kalibr camchain, or frame: 4x4 "
        "T_base_frame YAML); default: /tf_static.",
        Path,
        value=_extrinsics_file,
    ),
    Option(
        "--tags",
        "tags_file",
        "TagSLAM tagslam.yaml: tag sizes, ignore_tags, moving bodies' tags (left out), surveyed tag poses "
        "(priors) and the odometry body's T_body_odom.",
        Path,
        value=_tags_file,
    ),
    Option("--salvage", "salvage", "Read a damaged bag up to the damage and say how much was recovered.", bool),
)
"""The options of ``focusmap ingest`` (and ``focusmap run``)."""

STAGE: Final = Stage(
    name="ingest",
    config_type=IngestConfig,
    run=lazy("stages.ingest.stage:run"),
    inputs=(),
    version="1",
    needs_source=True,
    blueprint=blueprint,
    help="Read frames, odometry, laser scans, the camera model and extrinsics into OUT/<name>/ingest/.",
    options=OPTIONS,
    summary_line=summary_line,
    remarks=remarks,
)

__all__ = ["OPTIONS", "STAGE", "IngestConfig", "blueprint"]
