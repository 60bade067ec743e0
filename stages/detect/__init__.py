"""Stage ``detect``: AprilTags in every ingested frame, with each tag's pose in the camera and its 6x6 covariance.

Public pieces: :class:`~stages.detect.config.DetectConfig`, :func:`~stages.frames.decode_frame`,
:func:`~stages.detect.backends.make_detector`, :func:`~stages.detect.pose.estimate_tag_pose`,
:func:`stages.camera.load_camera_file` and :data:`STAGE`.
"""

from __future__ import annotations

from typing import Any, Final

from pipeline.stage import Stage, lazy
from stages.detect.config import DetectConfig


def blueprint() -> Any:
    """Camera image with outlines, the tags in 3D, the series and the summary."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin="/detect/camera/image", name="camera"),
            rrb.Vertical(
                rrb.Spatial3DView(origin="/detect/camera", name="tags in the camera"),
                rrb.TimeSeriesView(origin="/detect/stats", name="detections and reprojection error"),
                rrb.TextDocumentView(origin="/detect/summary", name="summary"),
            ),
        ),
        rrb.TimePanel(play_state="paused", timeline="time"),
    )


STAGE: Final = Stage(
    name="detect",
    config_type=DetectConfig,
    run=lazy("stages.detect.stage:run"),
    inputs=("ingest",),
    version="2",
    blueprint=blueprint,
    help="Detect AprilTags in the ingested frames; each tag's pose in the camera with its 6x6 covariance.",
)

__all__ = ["STAGE", "DetectConfig", "blueprint"]
