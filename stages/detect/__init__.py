"""Stage ``detect``: AprilTags in every ingested frame, with each tag's pose in the camera and its 6x6 covariance.

Public pieces: :class:`~stages.detect.config.DetectConfig`, :func:`~stages.detect.images.decode_frame`,
:func:`~stages.detect.backends.make_detector`, :func:`~stages.detect.pose.estimate_tag_pose`,
:func:`stages.camera.load_camera_file` and :data:`STAGE`.
"""

from __future__ import annotations

from typing import Final

from pipeline.stage import Stage
from stages.detect.config import DetectConfig
from stages.detect.stage import blueprint, run

STAGE: Final = Stage(
    name="detect",
    config_type=DetectConfig,
    run=run,
    inputs=("ingest",),
    version="1",
    blueprint=blueprint,
    help="Detect AprilTags in the ingested frames; each tag's pose in the camera with its 6x6 covariance.",
)

__all__ = ["STAGE", "DetectConfig"]
