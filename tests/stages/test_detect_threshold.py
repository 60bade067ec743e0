"""detect: the AprilTag 3 quad-threshold parameters set through pupil-apriltags (``min_white_black_diff``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.camera import colmap_camera
from stages.detect.backends import _quad_thresh_params, make_detector
from stages.detect.config import DetectConfig
from tests.fixtures.tag_render import TagPlacement, look_at_tag, plumb_bob_camera, render_frame

CAMERA = plumb_bob_camera()


def test_quad_thresh_params_layout_reads_the_library_defaults() -> None:
    import pupil_apriltags

    det = pupil_apriltags.Detector(families="tag36h11")
    try:
        qtp = _quad_thresh_params(det)
        assert qtp.min_cluster_pixels == 5
        assert qtp.max_nmaxima == 10
        assert math.isclose(qtp.cos_critical_rad, math.cos(math.radians(10)), rel_tol=1e-6)
        assert qtp.max_line_fit_mse == 10.0
        assert qtp.min_white_black_diff == 5
        assert qtp.deglitch == 0
    finally:
        det.tag_detector_ptr = None  # never destroy (pupil-apriltags 1.0.4 heap corruption, see backends)


def test_settings_reach_the_library() -> None:
    detector = make_detector(DetectConfig(min_white_black_diff=23, min_cluster_pixels=7))
    qtp = _quad_thresh_params(detector._detector)  # type: ignore[attr-defined]
    assert (qtp.min_white_black_diff, qtp.min_cluster_pixels) == (23, 7)


@pytest.mark.parametrize("contrast", [60.0, 30.0])
def test_default_threshold_keeps_small_and_faint_tags(contrast: float) -> None:
    """The default (15) finds what the library's default (5) finds, on small tags of modest contrast in noise."""
    cam = colmap_camera(CAMERA)
    rng = np.random.default_rng(4)
    tags = [
        TagPlacement(10 + k, "tag36h11", 0.16, look_at_tag(d, a, 5, 0, ((k % 3 - 1) * 0.9, (k // 3 - 0.5) * 0.5)))
        for k, (d, a) in enumerate([(3.0, 10), (4.0, 30), (5.0, 0), (3.5, 45), (4.5, 20), (2.5, 50)])
    ]
    frame = render_frame(cam, tags, background=140.0, noise_sigma=2.0, rng=rng).astype(float)
    # squeeze the grey levels around the background: tag contrast ~ ``contrast`` grey levels
    frame = np.clip(140.0 + (frame - 140.0) * contrast / 200.0, 0, 255).astype(np.uint8)
    ids_lib = {o.tag_id for o in make_detector(DetectConfig(min_white_black_diff=5)).detect(frame)}
    ids_default = {o.tag_id for o in make_detector(DetectConfig()).detect(frame)}
    assert len(ids_lib) >= 4
    assert ids_default == ids_lib
