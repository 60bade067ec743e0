"""Settings of the ingest stage (YAML section ``ingest``)."""

from __future__ import annotations

from pydantic import Field

from pipeline.config import SettingsModel
from stages.limits import MAX_BAG_SECONDS


class IngestConfig(SettingsModel):
    """What to read from the recording."""

    image_topic: str | list[str] = Field(
        "",
        description="Camera image topic (Image or CompressedImage), or a list of them for a rig with several "
        "cameras; empty = the only one, or every one a multi-camera calibration file names (rostopic).",
    )
    camera_info_topic: str = Field("", description="CameraInfo topic; empty = the only one.")
    odometry_topic: str = Field("", description="nav_msgs/Odometry topic; empty = the only one.")
    scan_topic: str = Field("", description="LaserScan topic; empty = the only one.")
    tf_static_topic: str = Field("", description="Static transforms topic; empty = the one named */tf_static.")
    detections_topic: str | list[str] = Field(
        "",
        description="AprilTag detections topic (apriltag_msgs) used instead of images, or a list of them for a rig "
        "with several cameras; empty = the only one, or every one a multi-camera calibration file names (tagtopic).",
    )
    camera_file: str = Field(
        "",
        description="Calibration file (Kalibr/TagSLAM cameras.yaml or ROS camera_info YAML) used instead of "
        "CameraInfo messages; empty = read CameraInfo from the bag.",
    )
    extrinsics_file: str = Field(
        "",
        description="Where the cameras sit on the rig: TagSLAM camera_poses.yaml, a Kalibr camchain (T_cam_imu, "
        "T_cn_cnm1) or a YAML of frame: 4x4 T_base_frame; its transforms replace /tf_static's for the cameras it "
        "names; empty = /tf_static only.",
    )
    tags_file: str = Field(
        "",
        description="TagSLAM tagslam.yaml: default and per-tag sizes (detect), ignore_tags and the tags of moving "
        "bodies (is_static: false; left out of the graph), surveyed tag poses with their noise (priors on those "
        "landmarks, 3d model) and the odometry body's T_body_odom (applied to the camera mounts of a TagSLAM "
        "camera_poses.yaml); a static camera rig is refused; empty = none.",
    )
    start_s: float = Field(
        0.0, ge=0, le=MAX_BAG_SECONDS, description="Skip messages before this time, seconds from the bag start."
    )
    end_s: float | None = Field(
        None, gt=0, le=MAX_BAG_SECONDS, description="Skip messages after this time, seconds from the bag start."
    )
    frame_stride: int = Field(1, ge=1, description="Keep every n-th camera frame (counted from the first in the bag).")
    salvage: bool = Field(False, description="Read a damaged bag up to the damage instead of failing.")
