"""What detect writes into ``RUN/detect/``: one row per tag seen in a frame, with its pose and covariance."""

from __future__ import annotations

from typing import Final

import pyarrow as pa

from pipeline.contracts import ArtifactSet, Column, TableSpec
from stages.columns import CORNERS, FAMILY, FRAME, STAMP_NS, TAG_ID

_F64 = pa.float64()

CAMERA = Column("camera", pa.string(), "the image (or detections) topic of the camera that saw the tag")
SIZE_M = Column("size_m", _F64, "the tag's side (black square), m")
T_CAMERA_TAG = Column(
    "T_camera_tag", pa.list_(_F64, 16), "4x4 row-major: maps tag-frame points into the camera optical frame"
)
ALT_T_CAMERA_TAG = Column(
    "alt_T_camera_tag", pa.list_(_F64, 16), "the second pose of the planar ambiguity (same layout)"
)
POSE_COV = Column(
    "pose_cov", pa.list_(_F64, 36), "6x6 covariance of `T_camera_tag`, GTSAM Pose3 tangent order rx ry rz tx ty tz"
)
POSITION_COV = Column("position_cov", pa.list_(_F64, 9), "3x3 covariance of the tag centre in the camera frame, m²")
REPROJECTION_PX = Column("reprojection_px", _F64, "RMS corner reprojection error of the pose, px")
AMBIGUITY_RATIO = Column(
    "ambiguity_ratio",
    _F64,
    "squared corner error of the chosen pose over the other's (0 unambiguous, 1 both fit alike)",
)
ALT_PROBABILITY = Column("alt_probability", _F64, "weight of the other pose in the mixture that `pose_cov` covers")
AMBIGUOUS = Column("ambiguous", pa.bool_(), "the two poses of the planar ambiguity are too close to call")
DECISION_MARGIN = Column("decision_margin", _F64, "the detector's decision margin")
HAMMING = Column("hamming", pa.int32(), "bits corrected when decoding the tag")

DETECTIONS: Final = TableSpec(
    "detections.parquet",
    "one row per tag seen in a frame (conventions in the README: corners, tag frame, covariance order)",
    [
        FRAME,
        STAMP_NS,
        CAMERA,
        TAG_ID,
        FAMILY,
        CORNERS,
        SIZE_M,
        T_CAMERA_TAG,
        ALT_T_CAMERA_TAG,
        POSE_COV,
        POSITION_COV,
        REPROJECTION_PX,
        AMBIGUITY_RATIO,
        ALT_PROBABILITY,
        AMBIGUOUS,
        DECISION_MARGIN,
        HAMMING,
    ],
)

ARTIFACTS: Final = ArtifactSet(
    "detect", "The AprilTags of every frame, each with its pose in the camera.", [DETECTIONS]
)
