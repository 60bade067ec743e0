"""Overexposed tags: their edges measured from their own black borders, and the corners put back (stages/detect/edges).

Frames are rendered with exact corners (tests/fixtures/tag_render.py), blurred as a lens does, then exposed: a
well-exposed frame keeps the paper below the sensor's maximum, an overexposed one clips it. The detector's quad of
a clipped tag lies inside the printed square; the border-width measurement must see that, and only that.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.config import load_settings
from pipeline.runner import run_stage
from stages import REGISTRY
from stages.camera import colmap_camera
from stages.detect.backends import make_detector
from stages.detect.config import DetectConfig
from stages.detect.edges import BORDER_CELLS, edge_shifts, run_shift, shift_corners
from tests.fixtures.detect_runs import camera_model as _camera
from tests.fixtures.detect_runs import fake_ingest as _fake_ingest
from tests.fixtures.tag_render import TagPlacement, corners_of, look_at_tag, render_frame


def _exposed(img: np.ndarray, gain: float, rng: np.random.Generator) -> np.ndarray:
    """Paper at 220 and ink at 30 grey levels, a lens blur of 1 px, then ``gain`` and the sensor's clip at 255."""
    scene = 30.0 + img.astype(float) / 255.0 * 190.0
    scene = cv2.GaussianBlur(scene, (0, 0), 1.0) * gain + rng.normal(0.0, 1.0, scene.shape)
    return np.clip(np.rint(scene), 0, 255).astype(np.uint8)


def _tags(k: int) -> list[TagPlacement]:
    """Three tags 0.6-1.1 m away, turned differently in each frame ``k``."""
    rng = np.random.default_rng(k)
    return [
        TagPlacement(
            i, "tag36h11", 0.1, look_at_tag(rng.uniform(0.6, 1.1), rng.uniform(-25, 25), rng.uniform(-15, 15), 0, off)
        )
        for i, off in ((3, (-0.17, 0.0)), (8, (0.0, 0.05)), (12, (0.17, -0.03)))
    ]


def _outward_offset(found: np.ndarray, truth: np.ndarray) -> float:
    """Mean distance of ``found``'s corners from the quad's centre minus the truth's, px (< 0: inside)."""
    centre = truth.mean(axis=0)
    return float(np.mean(np.linalg.norm(found - centre, axis=1) - np.linalg.norm(truth - centre, axis=1)))


def test_shift_corners_moves_every_side_outwards_by_the_shift() -> None:
    quad = np.array([[100.0, 100.0], [160.0, 104.0], [155.0, 170.0], [98.0, 160.0]])
    moved = shift_corners(quad, 0.4)
    for i in range(4):
        a, b = quad[i], quad[(i + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        normal = np.array([-d[1], d[0]])
        normal *= -1 if normal @ (quad.mean(axis=0) - a) > 0 else 1  # outwards
        for p in (moved[i], moved[(i + 1) % 4]):  # both ends of the moved side
            assert (p - a) @ normal == pytest.approx(0.4, abs=1e-9)
    assert np.array_equal(shift_corners(quad, 0.0), quad)


@pytest.mark.parametrize(("gain", "exposed"), [(1.0, False), (1.45, True)])
def test_edge_shift_reads_clipped_paper_and_only_that(gain: float, exposed: bool) -> None:
    """Well exposed: the measured shift is within 0.02 px of none. Clipped: the detector's corners sit inside the
    printed square, the measured shift is positive, and moving the sides out by it brings the corners nearer the
    truth."""
    cam = colmap_camera(_camera())
    detector = make_detector(DetectConfig(decimation=1.0, tag_size_m=0.1))
    rng = np.random.default_rng(1)
    shifts, inside, before, after = [], [], [], []
    frames = []
    for k in range(6):
        tags = _tags(k)
        img = _exposed(render_frame(cam, tags, background=255.0), gain, rng)
        found = {o.tag_id: o for o in detector.detect(img)}
        assert set(found) == {t.tag_id for t in tags}
        frames.append((img, tags, found))
    for img, _, found in frames:
        obs = list(found.values())
        shifts += list(edge_shifts(img, [o.corners for o in obs], [BORDER_CELLS[o.family] for o in obs]))
    shift, _, n = run_shift(np.asarray(shifts))
    assert n >= 15
    for _, tags, found in frames:
        for tag in tags:
            truth = corners_of(cam, tag)
            inside.append(_outward_offset(found[tag.tag_id].corners, truth))
            before.append(np.sqrt(np.mean(np.sum((found[tag.tag_id].corners - truth) ** 2, axis=1))))
            moved = shift_corners(found[tag.tag_id].corners, shift)
            after.append(np.sqrt(np.mean(np.sum((moved - truth) ** 2, axis=1))))
    if not exposed:
        assert abs(shift) < 0.02
        return
    assert np.mean(inside) < -0.05, "the clipped tags' corners should lie inside the printed square"
    assert shift > 0.05
    assert np.mean(after) < 0.8 * np.mean(before)


def test_the_stage_measures_overexposed_tags_and_moves_their_corners(tmp_path: Path) -> None:
    """``detect.corner_shift_px: auto`` on overexposed frames: the summary gives the measured shift, the note says
    what was done, and the tags' ranges come out nearer the truth than with the shift off (``0``)."""
    camera = _camera()
    cam = colmap_camera(camera)
    rng = np.random.default_rng(2)
    jobs, truth = [], []
    for k in range(12):
        tags = _tags(k)
        img = _exposed(render_frame(cam, tags, background=255.0), 1.45, rng)
        jobs.append(("png", cv2.imencode(".png", img)[1].tobytes()))
        truth.append({t.tag_id: float(np.linalg.norm(t.T_camera_tag[:3, 3])) for t in tags})
    errors = {}
    for label, extra in (("auto", []), ("off", ["detect.corner_shift_px=0"])):
        run = _fake_ingest(tmp_path / label, jobs, camera, 640, 480)
        settings = load_settings(REGISTRY.models(), None, ["detect.tag_size_m=0.1", "detect.workers=1", *extra])
        summary = run_stage(run, REGISTRY, "detect", settings).summary
        rows = pq.read_table(run.stage_dir("detect") / "detections.parquet").to_pylist()
        ranges = [np.linalg.norm(np.reshape(r["T_camera_tag"], (4, 4))[:3, 3]) for r in rows]
        errors[label] = np.mean([d - truth[r["frame"]][r["tag_id"]] for d, r in zip(ranges, rows, strict=True)])
        if label == "auto":
            edges = summary["edges"]
            assert edges["measured_tags"] >= 30 and edges["applied_px"] == edges["shift_px"] > 0.05
            assert "read long" in summary["notes"][0]
        else:
            assert summary["edges"] == {"setting": 0.0, "applied_px": 0.0}
    assert errors["off"] > 0.001  # the clipped tags look small: ranges read long by millimetres at ~1 m
    assert abs(errors["auto"]) < 0.5 * errors["off"]


def test_the_run_shifts_standard_error_matches_the_spread_of_its_median() -> None:
    """``auto`` applies a shift only 3 standard errors from none; the error ``run_shift`` gives is the spread of the
    median over repeated runs of 200 tags (Monte Carlo, heavy-tailed tags: Student t with 4 dof)."""
    rng = np.random.default_rng(3)
    draws = [run_shift(0.04 + 0.05 * rng.standard_t(4, size=200)) for _ in range(400)]
    medians = np.array([m for m, _, _ in draws])
    se = np.median([s for _, s, _ in draws])
    assert all(n == 200 for _, _, n in draws)
    assert se == pytest.approx(np.std(medians), rel=0.2)
    assert abs(np.mean(medians) - 0.04) < 3 * se / np.sqrt(len(draws)) + 1e-3
