"""Settings of the detect stage (YAML section ``detect``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.config import SettingsModel
from stages.limits import MAX_TAG_SIZE_M

Family = Literal["tag36h11", "tag25h9", "tag16h5", "tag36h10"]
Backend = Literal["apriltag3", "opencv"]


class TagSize(SettingsModel):
    """The printed size of one tag id (edge of the black square)."""

    id: int = Field(..., ge=0, description="Tag id.")
    size_m: float = Field(..., gt=0, le=MAX_TAG_SIZE_M, description="Edge of the tag's black square, in metres.")


class DetectConfig(SettingsModel):
    """Detect AprilTags in the ingested frames and measure each tag's pose with its covariance."""

    backend: Backend = Field(
        "apriltag3",
        description="Detector: 'apriltag3' (AprilTag 3 C library via pupil-apriltags) or 'opencv' (cv2.aruco "
        "AprilTag dictionaries; the only one that reads tag36h10).",
    )
    families: tuple[Family, ...] = Field(("tag36h11",), min_length=1, description="Tag families to look for.")
    decimation: float = Field(
        1.0,
        ge=1.0,
        description="Quad detection on an image decimated by this factor (1 = full resolution; 2 is 3-4x faster "
        "but misses small tags: 9 of 12 and 7 of 10 on the real photos).",
    )
    blur_sigma: float = Field(0.0, ge=0.0, description="Gaussian blur before quad detection, pixels (0 = none).")
    min_white_black_diff: int = Field(
        15,
        ge=0,
        le=255,
        description="apriltag3: image tiles (4x4 px, with their 8 neighbours) whose grey range is below this are "
        "not segmented (the library's default is 5); the floor of the per-frame threshold (adaptive_white_black_diff)."
        " Flat noisy background then makes no candidate clusters: 3-25x faster at decimation 1 on the simulator and "
        "rendered frames, 2x on the real photos, and the same tags found on every data set (docs/detect.md).",
    )
    adaptive_white_black_diff: float = Field(
        1.2,
        ge=0.0,
        description="apriltag3: per frame, min_white_black_diff = this times the frame's median tile contrast "
        "(grey range of each 4x4 tile with its neighbours: pixel noise and fine texture), at least "
        "min_white_black_diff and at most max_white_black_diff; 0 = the fixed min_white_black_diff. 1.2 keeps "
        "noisy frames as fast as clean ones (pixel noise 4 or 5: 3x faster than the fixed 15) and finds as many "
        "tags as AprilTag 3 on every generated world; 1.5 and more lose faint tags in noise (docs/detect.md).",
    )
    edge_white_black_diff: float = Field(
        0.6,
        ge=0.0,
        description="apriltag3: the per-frame threshold (adaptive_white_black_diff > 0) is also at least this times "
        "the 95th percentile of the frame's tile contrasts (its strong edges), up to max_white_black_diff: textured "
        "frames (asphalt, clutter) then skip their texture (real photos 1.13x faster). On every frame of the "
        "generated worlds and the sample every tag the library finds survives thresholds up to 0.71 x that "
        "percentile (docs/detect.md); 0 = noise and texture only.",
    )
    max_white_black_diff: int = Field(
        64, ge=0, le=255, description="apriltag3: ceiling of the per-frame threshold (a quarter of the grey range)."
    )
    min_cluster_pixels: int = Field(
        5, ge=1, description="apriltag3: smallest edge cluster (pixels) considered for a quad (library default 5)."
    )
    refine_edges: bool = Field(True, description="Refine the tag edges on the full-resolution image.")
    decode_sharpening: float = Field(0.25, ge=0.0, description="Sharpening of the decoded image (apriltag3 only).")
    opencv_corner_refinement: Literal["none", "subpix", "contour", "apriltag"] = Field(
        "subpix", description="Corner refinement of the opencv back-end."
    )
    min_side_px: float = Field(8.0, ge=0.0, description="Detections whose shortest side is shorter are dropped, px.")
    min_decision_margin: float = Field(
        0.0,
        ge=0.0,
        description="apriltag3 detections with a lower decision margin are dropped (grey levels). 0 = none, as "
        "the library: faint tags (contrast ~20 grey levels) have margins of 5-11 and 10 lost a third of them.",
    )
    max_hamming: int = Field(
        2,
        ge=0,
        le=3,
        description="Detections with more corrected bits are dropped (2 = the AprilTag 3 library's own limit; "
        "1 lost small blurred tags the library finds).",
    )
    tag_size_m: float = Field(
        0.162, gt=0, le=MAX_TAG_SIZE_M, description="Default edge of a tag's black square, metres."
    )
    tag_sizes: tuple[TagSize, ...] = Field(
        (), description="Per-id sizes overriding tag_size_m, a list of {id, size_m} (metres)."
    )
    corner_sigma_px: float | None = Field(
        None,
        gt=0,
        description="Standard deviation of a corner coordinate, px; null = estimated from the reprojection "
        "residuals of the run's detections (2 degrees of freedom per tag), pooled per band of tag side in px.",
    )
    min_corner_sigma_px: float = Field(
        0.1, gt=0, description="Floor of the estimated corner noise, px (ignored when corner_sigma_px is set)."
    )
    corner_bias_px: float = Field(
        0.0,
        ge=0,
        description="Standard deviation of a correlated edge bias, px: all four corners moving together "
        "outwards/inwards along their diagonals (a scale error that the pose absorbs and the residuals cannot "
        "show). Corner noise = corner_sigma^2 I + corner_bias^2 s s^T. Fitted on simulator seeds 1-2: 0 "
        "(docs/detect.md); raise it for blurred or strongly compressed images.",
    )
    corner_shift_px: float | Literal["auto"] = Field(
        "auto",
        description="Move every side of each detected quad outwards by this, px, before its pose is estimated: "
        "overexposure or blooming moves the tags' edges inwards, so they look small and their ranges read long. "
        "auto: measured from the tags' own black borders (a one-cell border that reads narrower than a cell) on "
        "up to edge_frames frames, and applied when it is at least edge_shift_min_px (stages/detect/edges.py); "
        "0: never.",
    )
    edge_shift_min_px: float = Field(
        0.03,
        ge=0,
        description="corner_shift_px=auto applies the measured shift from this size on, px (measured: -0.01 at "
        "the sample's exposure, 0.015 at 1.15x, where the map is as good, 0.07 at 1.3x, where it is not).",
    )
    edge_frames: int = Field(
        300, ge=1, description="corner_shift_px=auto measures the tags of at most this many frames, spread evenly."
    )
    ambiguity_mixture: bool = Field(
        True,
        description="Report the covariance of the two-mode mixture of both planar (IPPE) solutions, weighted by "
        "their evidence, about the chosen one: a view that may be flipped says so. Off = the chosen solution's "
        "local covariance only (overconfident beyond ~2 m on the simulator: NEES/6 of 5-140).",
    )
    max_reprojection_px: float = Field(
        3.0, gt=0, description="Detections whose RMS corner reprojection error exceeds this are dropped, px."
    )
    max_ambiguity_ratio: float = Field(
        0.5,
        gt=0,
        le=1,
        description="A detection is ambiguous when the squared reprojection error of the better planar (IPPE) "
        "solution exceeds this fraction of the other's (1 = never ambiguous).",
    )
    ambiguous: Literal["flag", "drop"] = Field(
        "flag", description="What to do with ambiguous detections: keep them flagged, or drop them."
    )
    bag_corner_order: Literal["apriltag", "opencv"] = Field(
        "apriltag",
        description="Corner order of detections read from the bag: 'apriltag' (bottom-left, bottom-right, "
        "top-right, top-left, as apriltag_ros and TagSLAM publish) or 'opencv' (top-left first, clockwise).",
    )
    workers: int = Field(2, ge=1, description="Worker processes detecting in parallel.")
    batch_frames: int = Field(
        16,
        ge=1,
        description="Frames sent to a worker at a time (their tags' poses are solved as one batch: 16 frames keep "
        "pose and covariance at 25 % of the stage on the sample, 8 at 30 %).",
    )

    @model_validator(mode="after")
    def _check_backend_families(self) -> DetectConfig:
        if self.backend == "apriltag3" and "tag36h10" in self.families:
            raise ValueError("family tag36h10 is not in the AprilTag 3 library; use backend: opencv")
        return self

    def size_of(self, tag_id: int) -> float:
        """The edge length of tag ``tag_id``, metres."""
        for entry in self.tag_sizes:
            if entry.id == tag_id:
                return entry.size_m
        return self.tag_size_m
