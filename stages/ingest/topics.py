"""Which topic plays which role: found by message type, or set explicitly."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.errors import InputError
from stages.ingest.bags import Recording

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPES = ("sensor_msgs/msg/CameraInfo",)
ODOMETRY_TYPES = ("nav_msgs/msg/Odometry",)
SCAN_TYPES = ("sensor_msgs/msg/LaserScan",)
TF_TYPES = ("tf2_msgs/msg/TFMessage",)
DETECTION_TYPES = (
    "apriltag_msgs/msg/ApriltagArrayStamped",
    "apriltag_msgs/msg/AprilTagDetectionArray",
)


@dataclass(frozen=True)
class Role:
    """A kind of data ingest looks for."""

    name: str
    types: tuple[str, ...]
    setting: str
    label: str


ROLES = {
    "image": Role("image", IMAGE_TYPES, "image_topic", "camera image"),
    "camera_info": Role("camera_info", CAMERA_INFO_TYPES, "camera_info_topic", "camera info"),
    "odometry": Role("odometry", ODOMETRY_TYPES, "odometry_topic", "odometry"),
    "scan": Role("scan", SCAN_TYPES, "scan_topic", "laser scan"),
    "tf_static": Role("tf_static", TF_TYPES, "tf_static_topic", "static transform"),
    "detections": Role("detections", DETECTION_TYPES, "detections_topic", "AprilTag detection"),
}


def resolve_topic(rec: Recording, role: Role, explicit: str) -> str | None:
    """The topic for ``role``: the explicit one (checked), the only one of its type, or None.

    Raises:
        InputError: an explicit topic is absent or of the wrong type, or several topics match.
    """
    if explicit:
        info = rec.topics.get(explicit)
        if info is None:
            raise InputError(
                f"topic {explicit!r} (ingest.{role.setting}) is not in {rec.path.name}; "
                f"topics present: {sorted(rec.topics)}"
            )
        if info.type not in role.types:
            raise InputError(
                f"topic {explicit!r} (ingest.{role.setting}) is a {info.type}, not a {' or '.join(role.types)}"
            )
        return explicit
    candidates = rec.topics_of_type(*role.types)
    if role.name == "tf_static":
        candidates = [c for c in candidates if c.endswith("tf_static")]
    if len(candidates) > 1:
        raise InputError(
            f"{rec.path.name} has several {role.label} topics {candidates}; "
            f"pick one with --set ingest.{role.setting}={candidates[0]}"
        )
    return candidates[0] if candidates else None
