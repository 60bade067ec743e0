"""What ingest writes into ``RUN/ingest/``, declared once: tables, the camera model and the extrinsics.

All stamps are nanoseconds of the bag clock (the message header stamp; the bag's log time where the
header stamp is zero). Downstream stages read these through the declarations, never by file name.
"""

from __future__ import annotations

from typing import Final

import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from pipeline.contracts import ArtifactSet, Column, JsonSpec, TableSpec
from stages.columns import CORNERS, FAMILY, FRAME, FRAME_ID, QUATERNION, STAMP_NS, TAG_ID, TOPIC, X, Y, Z

_F64 = pa.float64()


def _f64(name: str, doc: str) -> Column:
    return Column(name, _F64, doc)


# frames.parquet ----------------------------------------------------------------------------------------
FORMAT = Column(
    "format",
    pa.string(),
    "`jpeg`/`png` for compressed images (kept as their bytes), else the raw encoding (`mono8`, `bgr8`, `rgb8`, "
    "`mono16`, …)",
)
WIDTH = Column("width", pa.int32(), "image width, px (0 for compressed images)")
HEIGHT = Column("height", pa.int32(), "image height, px (0 for compressed images)")
STEP = Column("step", pa.int32(), "bytes per raw image row (0 for compressed images)")
DATA = Column("data", pa.binary(), "the image bytes")
FRAMES: Final = TableSpec(
    "frames.parquet",
    "one row per kept camera image, whatever the stride or time window",
    [FRAME, STAMP_NS, TOPIC, FORMAT, WIDTH, HEIGHT, STEP, DATA],
)

# odometry.parquet --------------------------------------------------------------------------------------
VELOCITY = tuple(
    _f64(c, f"twist {c} in the child frame ({'m/s' if c[0] == 'v' else 'rad/s'})")
    for c in ("vx", "vy", "vz", "wx", "wy", "wz")
)
POSE_COV = Column("pose_cov", pa.list_(_F64, 36), "6x6 row-major, ROS order x y z roll pitch yaw")
TWIST_COV = Column("twist_cov", pa.list_(_F64, 36), "6x6 row-major, ROS order vx vy vz wx wy wz")
ODOMETRY_FRAME_ID = Column(FRAME_ID, FRAME_ID.type, "the odometry frame (the pose's parent)")
CHILD_FRAME_ID = Column("child_frame_id", pa.string(), "the robot's base frame")
ODOMETRY: Final = TableSpec(
    "odometry.parquet",
    "one row per odometry message: the base's pose in the odometry frame, its twist and covariances",
    [STAMP_NS, X, Y, Z, *QUATERNION, *VELOCITY, POSE_COV, TWIST_COV, ODOMETRY_FRAME_ID, CHILD_FRAME_ID],
)

# scans.parquet -----------------------------------------------------------------------------------------
ANGLE_MIN = _f64("angle_min", "angle of the first range, rad")
ANGLE_MAX = _f64("angle_max", "angle of the last range, rad")
ANGLE_INCREMENT = _f64("angle_increment", "angle between ranges, rad")
TIME_INCREMENT = _f64(
    "time_increment", "time between beams, s (beam i is measured at stamp_ns + i * time_increment; 0: all at once)"
)
SCAN_TIME = _f64("scan_time", "time between scans, s (0 when the driver does not say)")
RANGE_MIN = _f64("range_min", "shortest valid range, m")
RANGE_MAX = _f64("range_max", "longest valid range, m")
RANGES = Column("ranges", pa.list_(pa.float32()), "ranges, m (inf/nan as recorded)")
SCAN_FRAME_ID = Column(FRAME_ID, FRAME_ID.type, "the laser's frame")
SCANS: Final = TableSpec(
    "scans.parquet",
    "one row per laser scan",
    [
        STAMP_NS,
        SCAN_FRAME_ID,
        ANGLE_MIN,
        ANGLE_MAX,
        ANGLE_INCREMENT,
        TIME_INCREMENT,
        SCAN_TIME,
        RANGE_MIN,
        RANGE_MAX,
        RANGES,
    ],
)

# tag_detections.parquet --------------------------------------------------------------------------------
BAG_CORNERS = Column(
    CORNERS,
    CORNERS.type,
    "x0 y0 … x3 y3, pixels, in the order the bag gives them (detect's `bag_corner_order` says which order that is)",
)
TAG_DETECTIONS: Final = TableSpec(
    "tag_detections.parquet",
    "one row per AprilTag detection the bag itself holds (apriltag_msgs), when it holds them; `frame` counts the "
    "detection messages of the topic, `topic` is the detections topic",
    [FRAME, STAMP_NS, TOPIC, TAG_ID, FAMILY, BAG_CORNERS],
    optional=True,
)


# camera.json -------------------------------------------------------------------------------------------
class CameraModel(BaseModel):
    """A calibrated pinhole camera with its lens distortion (ROS and OpenCV pixel convention)."""

    model_config = ConfigDict(extra="forbid")

    width: int = Field(gt=0, description="image width, px")
    height: int = Field(gt=0, description="image height, px")
    K: list[float] = Field(min_length=9, max_length=9, description="3x3 intrinsic matrix, row-major")
    distortion_model: str = Field(description="`plumb_bob`, `rational_polynomial`, `equidistant` or `none`")
    D: list[float] = Field(default_factory=list, description="distortion coefficients as ROS gives them")
    frame_id: str = Field("", description="the camera's optical frame")
    topic: str | None = Field(None, description="the image topic the calibration belongs to")
    tag_topic: str | None = Field(None, description="the detections topic (from a TagSLAM cameras.yaml)")
    source: str = Field("", description="`camera_info` or the calibration file it came from")


CAMERA: Final = JsonSpec(
    "camera.json", "the camera model the frames were taken with (a rig's first camera)", CameraModel
)


class Rig(BaseModel):
    """The cameras of a rig with several, each with its own calibration."""

    model_config = ConfigDict(extra="forbid")

    cameras: dict[str, CameraModel] = Field(
        description="by the topic its frames or detections come from (the `topic` of `frames.parquet` and "
        "`tag_detections.parquet`, detect's `camera`): the camera model"
    )


CAMERAS: Final = JsonSpec(
    "cameras.json",
    "every camera of a rig with several (the first is also `camera.json`); absent for one camera",
    Rig,
    optional=True,
)


# extrinsics.json ---------------------------------------------------------------------------------------
class SensorMount(BaseModel):
    """Where a sensor sits on the robot."""

    model_config = ConfigDict(extra="forbid")

    frame_id: str = Field(description="the sensor's frame")
    T_base_sensor: list[list[float]] = Field(description="4x4, maps points in the sensor frame into the base frame")
    assumed: bool = Field(False, description="true when no transform was recorded and identity was assumed")
    topic: str | None = Field(None, description="a camera's image or detections topic (detect's `camera`)")
    source: str = Field(
        "",
        description="where the transform came from: `/tf_static`, `base frame` (the sensor is the base), "
        "`FILE (kind) ENTRY` for --extrinsics, or `identity (assumed)`",
    )
    information: list[list[float]] | None = Field(
        None,
        description="the mount's 6x6 information `RᵀR` when the extrinsics file gives TagSLAM's `R` (gtsam's "
        "square-root information; tangent order rotation, translation); a mount looser than 1 mm or 1 mrad in some "
        "direction is estimated in the graph with it as its prior",
    )


class Extrinsics(BaseModel):
    """The robot's frames and its sensors' mounts, from ``/tf_static`` or an extrinsics file."""

    model_config = ConfigDict(extra="forbid")

    base_frame: str = Field(description="the odometry's child frame (the robot's base)")
    odom_frame: str | None = Field(None, description="the odometry's frame")
    sensors: dict[str, SensorMount] = Field(
        default_factory=dict,
        description="by role (`camera`: the first camera, `laser`), and each further camera of a rig by its topic: "
        "the sensor's frame and mount",
    )
    file: str | None = Field(
        None, description="the extrinsics file given (--extrinsics), absolute; null = `/tf_static` only"
    )


EXTRINSICS: Final = JsonSpec(
    "extrinsics.json",
    "the robot's frames and where its sensors sit, from the static transforms (`/tf_static`) or the file given "
    "with --extrinsics (TagSLAM camera_poses.yaml, Kalibr camchain or frame: 4x4 T_base_frame), per sensor with "
    "its source",
    Extrinsics,
)


# tags.json ---------------------------------------------------------------------------------------------
class KnownTag(BaseModel):
    """A surveyed tag of a TagSLAM static body: a prior on its landmark."""

    model_config = ConfigDict(extra="forbid")

    id: int = Field(description="tag id")
    body: str = Field(description="the TagSLAM body it belongs to")
    T_world_tag: list[list[float]] = Field(
        description="4x4, maps points in focusmap's tag frame into TagSLAM's world frame (`T_world_body T_body_tag "
        "Rz(π)`: TagSLAM's tag frame is focusmap's turned 180° about the tag's normal)"
    )
    covariance: list[list[float]] = Field(
        description="6x6 covariance of the prior, gtsam's Pose3 tangent order (rx, ry, rz, tx, ty, tz) in the tag "
        "frame, rad² and m²: the tag's sigmas squared plus the body's pose noise carried into the tag frame"
    )
    rotation_sigma_rad: list[float] = Field(description="the tag's rotation_noise (or its body's override), rad")
    position_sigma_m: list[float] = Field(description="the tag's position_noise (or its body's override), m")


class TagRemap(BaseModel):
    """A tag id that stands for another tag in a time window (TagSLAM's tag_id_remap: duplicated ids)."""

    model_config = ConfigDict(extra="forbid")

    id: int = Field(description="the id the detections carry")
    remap_id: int = Field(description="the tag they are of within the window")
    start_ns: int = Field(description="window start, ns on the bag clock (header stamps)")
    end_ns: int = Field(description="window end, ns")
    camera: str | None = Field(None, description="only this camera's (cameras.yaml name, frame id or topic)")


class TagsInfo(BaseModel):
    """What ``--tags`` (TagSLAM's ``tagslam.yaml``) says about the tags and the odometry."""

    model_config = ConfigDict(extra="forbid")

    file: str = Field(description="the tags file given (--tags), absolute")
    default_tag_size_m: float | None = Field(
        None, description="the default body's default_tag_size, m (detect's size where detect.tag_size_m is default)"
    )
    tag_sizes_m: dict[int, float] = Field(
        default_factory=dict,
        description="tag id to size, m, of every tag a body lists (its own size, else its body's default_tag_size); "
        "detect.tag_sizes entries win",
    )
    ignore_tags: list[int] = Field(default_factory=list, description="the bodies' ignore_tags: left out of the graph")
    moving_tags: dict[str, list[int]] = Field(
        default_factory=dict,
        description="per body with is_static: false (a wand, a board carried around), the ids of its tags: they move, "
        "so the graph leaves them out (no landmark)",
    )
    known_tags: list[KnownTag] = Field(
        default_factory=list, description="tags with a pose on a static body with a pose: priors on their landmarks"
    )
    tag_id_remap: list[TagRemap] = Field(
        default_factory=list, description="detections of `id` within a window are of tag `remap_id` (graph)"
    )
    odometry_body: str | None = Field(None, description="the non-static body with odom_topic or T_body_odom")
    odometry_topic: str | None = Field(None, description="that body's odom_topic")
    T_body_odom: list[list[float]] | None = Field(
        None,
        description="4x4, that body's T_body_odom: maps points of the odometry's frame into the body (rig) frame; "
        "null = not given (identity)",
    )
    T_body_odom_applied: bool = Field(
        False,
        description="whether the cameras' mounts from a TagSLAM camera_poses.yaml (in the rig) were moved into the "
        "odometry's child frame by it (`T_base_cam = T_body_odom⁻¹ T_rig_cam`)",
    )
    notes: list[str] = Field(default_factory=list, description="what was read past or not applied, and why")


TAGS: Final = JsonSpec(
    "tags.json",
    "what the TagSLAM tagslam.yaml given with --tags says: default and per-id tag sizes (detect), ignored tags and "
    "surveyed tag poses with their noise (graph: left out / priors), the odometry body's T_body_odom (applied to "
    "the camera mounts here); absent without --tags",
    TagsInfo,
    optional=True,
)


ARTIFACTS: Final = ArtifactSet(
    "ingest",
    "What the recording holds, in tables a stage can read in one go; later stages never open the bag again. "
    "All stamps are nanoseconds of the bag clock (the message header stamp; the bag's log time where the header "
    "stamp is zero). The stage's `summary.json` counts `frames`, `odometry`, `scans` and `tag_detections` and gives "
    "`duration_s`, `start_ns`, `topics` (role to topic), `reader` (`rosbags`, `mcap`, `sqlite3` or `salvage`) and "
    "`format`; `dropped` counts, per topic and reason, the messages `--salvage` dropped for values no sensor gives "
    "(a non-finite pose or twist, a non-finite or denormal covariance, a negative laser range, an image size that "
    "does not match its data) or for not decoding (without `--salvage` such a message stops the stage); "
    "`salvaged`, after a `--salvage` read, says what was read and what was lost, per topic and in time.",
    [FRAMES, ODOMETRY, SCANS, TAG_DETECTIONS, CAMERA, CAMERAS, EXTRINSICS, TAGS],
)
