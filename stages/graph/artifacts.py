"""What the graph stage writes into ``RUN/graph/``, declared once (optimize writes the same files for its
reduced graph, through the same writer): the factors, the solution, the marginals, the path and the map.

Readers go through :func:`stages.graph.load.load_graph` or these declarations, never by file name.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Final

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field

from pipeline.artifacts import StageInput, StageOutput
from pipeline.contracts import ArtifactSet, Column, FileSpec, JsonSpec, TableSpec
from pipeline.errors import InputError
from stages.columns import FRAME, KEY, QUATERNION, STAMP_NS, TAG_ID, YAW, X, Y, Z

_F64_LIST = pa.list_(pa.float64())

INDEX = Column("index", pa.int64(), "position of the row (factor or keyframe) in the graph, from 0")
TANGENT_COVARIANCE = Column(
    "covariance",
    _F64_LIST,
    "marginal covariance in the variable's tangent space, row-major (Pose2 x y θ: 9; Pose3 rx ry rz tx ty tz: 36)",
)
POSITION_COV = Column(
    "position_cov", _F64_LIST, "3x3 position covariance in the map frame, row-major, m² (planar: zz is the height's)"
)

# factors.parquet ---------------------------------------------------------------------------------------
KIND = Column(
    "kind",
    pa.string(),
    "`prior`, `odometry`, `loop` (imported edge between non-consecutive poses), `motion_prior`, `tag`, "
    "`scale_prior`, `tag_prior` (a surveyed tag's pose from --tags); `tag` rows are the candidates of the "
    "selection stages",
)
TYPE = Column(
    "type",
    pa.string(),
    "gtsam class: `PriorFactorPose2/3`, `BetweenFactorPose2/3`, `BearingRangeFactor2D/3D`, `PriorFactorPoint2/3`, "
    "`PriorFactorDouble`; a tag row with the third key `s0` is the scaled form of its type",
)
KEYS = Column("keys", pa.list_(pa.uint64()), "gtsam keys of the factor's variables")
KEY_NAMES = Column("key_names", pa.list_(pa.string()), "the keys as `x12`, `l17`, `s0`")
MEASUREMENT = Column(
    "measurement",
    _F64_LIST,
    "Pose2 `x y θ`; Pose3 `x y z qx qy qz qw`; BearingRange2D `bearing range`; BearingRange3D `ux uy uz range`; "
    "Point `x y (z)`; Double `s`",
)
FACTOR_COVARIANCE = Column(
    "covariance", _F64_LIST, "`dim`×`dim` row-major, in the factor's tangent order (Pose3 rx ry rz tx ty tz)"
)
DIM = Column("dim", pa.int32(), "dimension of the residual")
ROBUST = Column("robust", pa.string(), "robust kernel: `none`, `huber` or `cauchy`")
ROBUST_K = Column("robust_k", pa.float64(), "the kernel's threshold (0 without a kernel)")
FACTOR_TAG_ID = Column(TAG_ID, TAG_ID.type, "tag rows: the AprilTag id (null on other rows)")
FACTOR_FRAME = Column(FRAME, FRAME.type, "tag rows: detect's `frame` of the detection (null on other rows)")
FACTOR_STAMP_NS = Column(STAMP_NS, STAMP_NS.type, "tag rows: the detection's stamp, ns (null on other rows)")
FACTORS: Final = TableSpec(
    "factors.parquet",
    "one row per factor, in graph order: factor `i` of the optimised graph is the row with `index` = i",
    [
        INDEX,
        KIND,
        TYPE,
        KEYS,
        KEY_NAMES,
        MEASUREMENT,
        FACTOR_COVARIANCE,
        DIM,
        ROBUST,
        ROBUST_K,
        FACTOR_TAG_ID,
        FACTOR_FRAME,
        FACTOR_STAMP_NS,
    ],
)

# poses.parquet -----------------------------------------------------------------------------------------
POSE_KEY = Column(KEY, KEY.type, "gtsam key of the keyframe's pose")
POSE_STAMP_NS = Column(STAMP_NS, STAMP_NS.type, "the keyframe's stamp, ns (imported graphs: vertex id × 1 s)")
POSES: Final = TableSpec(
    "poses.parquet",
    "one row per keyframe, in time order: the optimised pose of the base in the map frame",
    [INDEX, POSE_KEY, POSE_STAMP_NS, X, Y, Z, *QUATERNION, YAW, TANGENT_COVARIANCE, POSITION_COV],
)

# landmarks.parquet -------------------------------------------------------------------------------------
LANDMARK_KEY = Column(KEY, KEY.type, "gtsam key of the landmark")
VARIABLE_TYPE = Column("type", pa.string(), "the landmark's variable: `Point2`, `Point3` or `Pose3`")
N_OBSERVATIONS = Column("n_observations", pa.int64(), "tag factors that measure the landmark")
LANDMARK_QUATERNION = tuple(Column(c, c.type, f"{c.doc} (null for point landmarks)") for c in QUATERNION)
LANDMARKS: Final = TableSpec(
    "landmarks.parquet",
    "one row per landmark (tag), by tag id: its optimised position in the map frame and its marginal",
    [
        TAG_ID,
        LANDMARK_KEY,
        X,
        Y,
        Z,
        *LANDMARK_QUATERNION,
        POSITION_COV,
        TANGENT_COVARIANCE,
        VARIABLE_TYPE,
        N_OBSERVATIONS,
    ],
)

# values.npz and marginals.npz --------------------------------------------------------------------------
VALUES: Final = FileSpec(
    "values.npz",
    "every variable: `keys` (uint64), `types` (`Pose2`/`Pose3`/`Point2`/`Point3`/`Scale`), `initial` (dead "
    "reckoning and first sightings) and `optimised` (N×7, NaN-padded: Pose2 `x y θ`, Pose3 `x y z qx qy qz qw`, "
    "Point2 `x y`, Point3 `x y z`, Scale `s`)",
)
MARGINALS: Final = FileSpec(
    "marginals.npz",
    "every variable's marginal: `keys`, `types`, `dims` (3/6/2/3/1) and `covariance` (N×6×6; the top-left "
    "`dims`×`dims` block is the marginal in the variable's tangent space, Pose3 `rx ry rz tx ty tz` body frame)",
)


def _write_npz(out: StageOutput, spec: FileSpec, arrays: ValueArrays | MarginalArrays) -> None:
    out.write_npz(spec.file, **{f.name: getattr(arrays, f.name) for f in fields(arrays)})


def _read_npz(inp: StageInput, spec: FileSpec, names: Sequence[str]) -> dict[str, np.ndarray]:
    """The named arrays of an ``.npz`` artifact of a finished stage.

    Raises:
        InputError: the file is missing or lacks one of ``names`` (an old run; the message names the stage).
    """
    arrays = inp.read_npz(spec.file)
    if missing := [n for n in names if n not in arrays]:
        raise InputError(
            f"{inp.stage}/{spec.file} lacks arrays {missing}; re-run 'focusmap {inp.stage.replace('_', '-')} RUN "
            "--force'"
        )
    return {n: arrays[n] for n in names}


@dataclass(frozen=True)
class ValueArrays:
    """``values.npz``: one entry per variable, in the same order in every array."""

    keys: np.ndarray
    """uint64 gtsam keys."""
    types: np.ndarray
    """Variable type names (``Pose2``, ``Pose3``, ``Point2``, ``Point3``, ``Scale``)."""
    initial: np.ndarray
    """N×7 initial vectors, NaN-padded."""
    optimised: np.ndarray
    """N×7 optimised vectors, NaN-padded."""

    def write(self, out: StageOutput) -> None:
        """Write ``values.npz``."""
        _write_npz(out, VALUES, self)

    @classmethod
    def read(cls, inp: StageInput) -> ValueArrays:
        """Read ``values.npz`` of a finished stage (InputError naming the stage when an array is missing)."""
        return cls(**_read_npz(inp, VALUES, [f.name for f in fields(cls)]))


@dataclass(frozen=True)
class MarginalArrays:
    """``marginals.npz``: one entry per variable, in the same order in every array."""

    keys: np.ndarray
    """uint64 gtsam keys."""
    types: np.ndarray
    """Variable type names."""
    dims: np.ndarray
    """int32 tangent dimension of each variable."""
    covariance: np.ndarray
    """N×6×6; the top-left ``dims × dims`` block is the marginal in the variable's tangent space."""

    def write(self, out: StageOutput) -> None:
        """Write ``marginals.npz``."""
        _write_npz(out, MARGINALS, self)

    @classmethod
    def read(cls, inp: StageInput) -> MarginalArrays:
        """Read ``marginals.npz`` of a finished stage (InputError naming the stage when an array is missing)."""
        return cls(**_read_npz(inp, MARGINALS, [f.name for f in fields(cls)]))


# text files --------------------------------------------------------------------------------------------
TRAJECTORY: Final = FileSpec(
    "trajectory.tum", "the optimised keyframe poses, one `t x y z qx qy qz qw` line each (TUM; t in s)"
)
DEAD_RECKONING: Final = FileSpec("dead_reckoning.tum", "the initial (dead-reckoning) keyframe poses, as TUM")
G2O: Final = FileSpec(
    "graph.g2o",
    "the graph at the solution as g2o (`VERTEX_SE2/SE3:QUAT/XY/TRACKXYZ`, `EDGE_SE2`, `EDGE_SE2_XY` each followed "
    "by its copy as GTSAM's `BR` line, `EDGE_PRIOR_SE2`, `EDGE_SE3:QUAT`, `EDGE_SE3_TRACKXYZ`, `EDGE_SE3_PRIOR`); "
    "no comment lines, so `gtsam.readG2o` reads every edge but the priors; landmark vertex id = offset + tag id "
    "(the offset in `graph.g2o.json`); no shared tag scale; `import-graph` reads it",
)


class G2oMetadata(BaseModel):
    """What a reader of ``graph.g2o`` needs beyond its lines."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    landmark_id_offset: int = Field(description="landmark vertex id = this offset + tag id; pose vertex id = index")
    poses: int = Field(description="pose vertices")
    landmarks: int = Field(description="landmark vertices")
    max_tag_id: int = Field(description="the largest tag id (0 without landmarks)")
    edges: int = Field(description="factors written (a planar tag measurement and its `BR` copy count once)")
    edges_gtsam_reads: int = Field(description="factors `gtsam.readG2o` returns: every edge but the priors")
    priors: int = Field(description="`EDGE_PRIOR_SE2` / `EDGE_SE3_PRIOR` lines (GTSAM's reader skips them)")
    tag_scale: float | None = Field(
        description="the tag scale the tag measurements are written at (null: the graph has none)"
    )
    planar_landmark_br_copies: bool = Field(
        description="each `EDGE_SE2_XY` line (g2o's) is followed by the same measurement as GTSAM's `BR` line"
    )
    br_max_abs_correlation_dropped: float = Field(
        description="the largest bearing-range correlation of a planar tag measurement (`BR` holds only the two σ)"
    )
    not_written: list[str] = Field(description="factor types g2o cannot hold, left out")


G2O_META: Final = JsonSpec(
    "graph.g2o.json", "what a reader of `graph.g2o` needs beyond its lines (it has no comment lines)", G2oMetadata
)

CALIBRATION: Final = FileSpec(
    "calibration.npz",
    "when the odometry calibration was applied: `value` (k_d, k_w, b), `covariance` (3x3, from the joint system), "
    "`factor_index` (the corrected odometry rows' indices in `factors.parquet`) and `jacobian` (N x dim x 3: the "
    "derivative of each of those factors' error, in its tangent, by each component of the calibration); readers "
    "add the calibration's uncertainty to graphs built from the corrected rows (stages/graph/consider.py)",
    optional=True,
)

CAMERA_POSES: Final = FileSpec(
    "camera_poses.yaml",
    "when the rig calibration estimated a camera's mount: every camera's pose in the base frame, in TagSLAM's "
    "`camera_poses.yaml` layout (`camN: pose: {position: {x, y, z}, rotation: {x, y, z} (angle-axis, rad), R}`, R "
    "gtsam's upper-triangular square-root information, tangent order rotation, translation, as TagSLAM writes it); "
    "given mounts held fixed are written with R = 1e6 I; `--extrinsics` reads it back",
    optional=True,
)

ARTIFACTS: Final = ArtifactSet(
    "graph",
    "The full factor graph of the run, optimised, with the marginal covariance of every variable.",
    [
        FACTORS,
        VALUES,
        MARGINALS,
        POSES,
        LANDMARKS,
        TRAJECTORY,
        DEAD_RECKONING,
        G2O,
        G2O_META,
        CALIBRATION,
        CAMERA_POSES,
    ],
)
