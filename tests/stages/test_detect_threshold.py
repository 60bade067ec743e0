"""detect: the AprilTag 3 quad-threshold parameters set through pupil-apriltags (``min_white_black_diff``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stages.camera import colmap_camera
from stages.detect.backends import _quad_thresh_params, make_detector, median_tile_contrast
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


def test_median_tile_contrast_follows_the_noise() -> None:
    rng = np.random.default_rng(2)
    assert median_tile_contrast(np.full((240, 320), 128, np.uint8)) == 0
    for sigma in (1.5, 4.0, 8.0):
        img = np.clip(np.rint(128 + rng.normal(0, sigma, (240, 320))), 0, 255).astype(np.uint8)
        # range of 144 Gaussian samples (a 4x4 tile with its 8 neighbours): about 5.3 sigma
        assert 4.5 * sigma <= median_tile_contrast(img) <= 6.2 * sigma


def _six_tags(first_id: int) -> list[TagPlacement]:
    """Six 0.16 m tags 1.8-3 m in front of the camera, seen at 0-50 degrees."""
    return [
        TagPlacement(first_id + k, "tag36h11", 0.16, look_at_tag(d, a, 5, 0, ((k % 3 - 1) * 0.9, (k // 3 - 0.5) * 0.5)))
        for k, (d, a) in enumerate([(2.0, 10), (2.5, 30), (3.0, 0), (2.2, 45), (2.8, 20), (1.8, 50)])
    ]


def _faint_tags(noise_sigma: float, contrast: float, seed: int) -> np.ndarray:
    cam = colmap_camera(CAMERA)
    rng = np.random.default_rng(seed)
    tags = _six_tags(20)
    frame = render_frame(cam, tags, background=140.0, noise_sigma=0.0, rng=rng).astype(float)
    frame = 140.0 + (frame - 140.0) * contrast / 200.0 + rng.normal(0, noise_sigma, frame.shape)
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


def test_adaptive_threshold_rises_with_noise_and_keeps_the_tags() -> None:
    """Clean frames keep the floor (15); noisy ones get 1.2 x their median tile contrast, and the faint tags in
    them are still all found (what the library finds at its own threshold of 5)."""
    det = make_detector(DetectConfig())
    clean = _faint_tags(1.0, 120.0, 5)
    det.detect(clean)
    assert det.white_black_diff == 15  # type: ignore[attr-defined]
    noisy = _faint_tags(4.0, 40.0, 6)
    found = {o.tag_id for o in det.detect(noisy)}
    assert det.white_black_diff == round(1.2 * median_tile_contrast(noisy)) > 15  # type: ignore[attr-defined]
    library = {
        o.tag_id for o in make_detector(DetectConfig(min_white_black_diff=5, adaptive_white_black_diff=0)).detect(noisy)
    }
    assert len(library) >= 4 and found >= library
    capped = make_detector(DetectConfig(max_white_black_diff=18))
    capped.detect(noisy)
    assert capped.white_black_diff == 18  # type: ignore[attr-defined]
    fixed = make_detector(DetectConfig(adaptive_white_black_diff=0))
    fixed.detect(noisy)
    assert fixed.white_black_diff == 15  # type: ignore[attr-defined]


def _textured_frame(seed: int) -> np.ndarray:
    """Strong tags (contrast ~120) on a background whose left 40 % carry a real-photo-like texture: grey
    blotches of 2-8 px and +-40 grey levels (asphalt, clutter), as on the apriltag-photos / apriltag-multi images."""
    import cv2

    cam = colmap_camera(CAMERA)
    rng = np.random.default_rng(seed)
    tags = _six_tags(30)
    frame = render_frame(cam, tags, background=140.0, noise_sigma=1.5, rng=rng).astype(float)
    h, w = frame.shape
    blotches = cv2.resize(rng.uniform(-40, 40, (h // 3, w // 3)), (w, h), interpolation=cv2.INTER_NEAREST)
    blotches = cv2.GaussianBlur(blotches, (0, 0), 0.8)
    background = np.abs(frame - 140.0) < 8  # leave the tags (and their white quiet zone) as rendered
    texture = np.zeros_like(frame, bool)
    texture[:, : 2 * w // 5] = True
    frame[background & texture] += blotches[background & texture]
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


def test_edge_term_raises_the_threshold_on_textured_frames_and_keeps_the_tags() -> None:
    """A textured frame gets 0.6 x the 95th percentile of its tile contrasts (its strong edges: the tags, the
    texture), capped at max_white_black_diff, where the noise term alone gives less; every tag the library finds at
    its own threshold of 5 is still found."""
    from stages.detect.backends import frame_white_black_diff, tile_contrast_quantiles

    frame = _textured_frame(7)
    med, q95 = tile_contrast_quantiles(frame, (0.5, 0.95))
    assert med == median_tile_contrast(frame)
    det = make_detector(DetectConfig())
    found = {o.tag_id for o in det.detect(frame)}
    assert det.white_black_diff == min(64, round(0.6 * q95)) > max(15, round(1.2 * med))  # type: ignore[attr-defined]
    library = {
        o.tag_id for o in make_detector(DetectConfig(min_white_black_diff=5, adaptive_white_black_diff=0)).detect(frame)
    }
    assert len(library) >= 5 and found >= library
    # without the edge term, the noise / texture term (the median) alone
    noise_only = make_detector(DetectConfig(edge_white_black_diff=0))
    noise_only.detect(frame)
    assert noise_only.white_black_diff == max(15, min(64, round(1.2 * med)))  # type: ignore[attr-defined]
    assert frame_white_black_diff(frame, 15, 1.2, 0.6, 0.95, 40) == 40  # the ceiling


def test_edge_term_leaves_faint_noisy_frames_to_the_noise_term() -> None:
    """On faint tags in noise (contrast 40, noise 4) the strong edges are the tags themselves: 0.6 x their 95th
    percentile stays below 1.2 x the noise, so the threshold is the noise term's, as before."""
    from stages.detect.backends import tile_contrast_quantiles

    noisy = _faint_tags(4.0, 40.0, 6)
    med, q95 = tile_contrast_quantiles(noisy, (0.5, 0.95))
    assert round(0.6 * q95) <= round(1.2 * med)
    det = make_detector(DetectConfig())
    det.detect(noisy)
    assert det.white_black_diff == round(1.2 * med)  # type: ignore[attr-defined]
