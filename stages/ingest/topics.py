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


def resolve_camera_topics(
    rec: Recording, role: Role, explicit: str | list[str], calibrated: list[set[str]] | None = None
) -> list[str]:
    """The topics of a camera role (images or detections): the explicit one(s), checked; the only one of its
    type; or, when there are several, those a multi-camera calibration file names (``calibrated``: the topic
    names of each of its cameras, in the file's order).

    Raises:
        InputError: an explicit topic is absent or of the wrong type, or several topics match and no
            calibration file tells which.
    """
    if isinstance(explicit, list):
        return [t for t in (resolve_topic(rec, role, name) for name in explicit) if t]
    if explicit:
        return [t for t in (resolve_topic(rec, role, explicit),) if t]
    candidates = rec.topics_of_type(*role.types)
    if len(candidates) <= 1:
        return candidates
    if calibrated and len(calibrated) > 1:
        named = [t for names in calibrated for t in candidates if t in names]
        if named:
            return list(dict.fromkeys(named))
    raise InputError(
        f"{rec.path.name} has several {role.label} topics {candidates}; "
        f"pick one with --set ingest.{role.setting}={candidates[0]} (or a list, "
        f"--set 'ingest.{role.setting}=[{candidates[0]}, {candidates[1]}]', or give --camera a cameras.yaml whose "
        "rostopic/tagtopic name them)"
    )
