"""The tags' edges moved by overexposure, measured from each tag's own black border, and the corners put back.

A sensor that clips the white paper (overexposure, blooming) moves every black-to-white edge towards the black
side: the white level the edge locator sees is the clip, not the paper, so the level halfway between black and
white is reached nearer the black. The detector's quad, the outer edge of the black border, then lies inside the
printed square by that shift on every side, the tag looks smaller, and its range reads long (on a simulated world
with 30 % more exposure: ranges +0.3 % to +0.9 % at 1-4 m, the map 10 cm off instead of 3 cm). The residuals of a
tag's four corners cannot show it: it is a change of scale, which the pose absorbs.

The tag itself measures it. Its black border is exactly one cell wide, and where a white data cell lies inside it
the border has two edges with the same paper on both sides: the same shift moves both towards the black, so the
border reads ``2 δ`` px narrower than a cell. :func:`edge_shifts` samples the grey levels across each side of a tag
(through the homography of its quad, at the six data rows) and, for every profile with a white cell inside, the
border's width between the two half-level crossings; ``δ`` is half the deficit, and the offset of the outer crossing
from the detector's edge says where the detector's own edge sits. The run's shift is the median over the tags
(:func:`run_shift`); :func:`shift_corners` moves each side of a quad outwards by it.

Measured on simulated worlds that differ only in exposure (seed 52, the corridor there and back): the run's shift is
-0.010 px at the sample's exposure, 0.014 at 1.15x, 0.072 at 1.3x; at 1.3x, moving the corners out by 0.07 px takes
the full map's error from 9.5 to 4.0 cm (docs/detect.md, "Overexposed tags").
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import numpy.typing as npt
from scipy.ndimage import map_coordinates

FloatArray = npt.NDArray[np.float64]

BORDER_CELLS = {"tag36h11": 8, "tag25h9": 7, "tag16h5": 6, "tag36h10": 8}
"""Cells across the quad (the black border's outer edge) of each family detect reads; the border is one cell wide."""

_U = np.arange(-0.6, 2.0001, 0.05)
"""Sample positions across a side, in cells from the quad's edge inwards."""
_SIDES = (((0, 0), (1, 0), (0, 1)), ((1, 0), (1, 1), (-1, 0)), ((1, 1), (0, 1), (0, -1)), ((0, 1), (0, 0), (1, 0)))
"""The unit square's sides: start, end and inward normal (corner order of the quad)."""
_UNIT_SQUARE = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)
MIN_CONTRAST = 30.0
"""Grey levels between the white outside a side and its black border below which a profile is not used."""
MIN_CELL_PX = 4.0
"""Tags whose cells are smaller (px) are not measured: their border's two edges blur into each other."""


def _crossings(u: FloatArray, prof: FloatArray, level: FloatArray, falling: bool) -> FloatArray:
    """Per row of ``prof`` (sampled at ``u``), where it first crosses its ``level`` (linear interpolation); NaN where
    it does not, or already has at the first sample."""
    past = prof < level[:, None] if falling else prof > level[:, None]
    k = np.argmax(past, axis=1)
    ok = past[np.arange(len(prof)), k] & (k > 0)
    k = np.where(ok, k, 1)
    rows = np.arange(len(prof))
    p0, p1 = prof[rows, k - 1], prof[rows, k]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = u[k - 1] + (level - p0) / (p1 - p0) * (u[k] - u[k - 1])
    return np.where(ok, x, np.nan)


def edge_shifts(gray: npt.NDArray[np.uint8], quads: Sequence[npt.ArrayLike], cells: Sequence[int]) -> FloatArray:
    """For each quad of one image, how far its printed edges lie outside the detector's, px (the median over the
    quad's usable profiles); NaN for a tag too small (:data:`MIN_CELL_PX`), of a family without a known border
    (``cells`` 0) or without a profile that has a white cell inside its border."""
    out = np.full(len(quads), np.nan)
    points, owner, cell_px = [], [], []
    for i, (corners, n) in enumerate(zip(quads, cells, strict=True)):
        c = np.asarray(corners, float).reshape(4, 2)
        size = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1))) / n if n else 0.0
        if size < MIN_CELL_PX:
            continue
        H = cv2.getPerspectiveTransform(_UNIT_SQUARE, c.astype(np.float32))
        rows = (np.arange(1, n - 1) + 0.5) / n  # the data rows, away from the corners
        unit = np.concatenate(
            [
                np.asarray(a) + np.subtract(b, a) * rows[:, None, None] + np.asarray(d) * (_U[None, :, None] / n)
                for a, b, d in _SIDES
            ]
        )
        points.append(cv2.perspectiveTransform(unit.reshape(1, -1, 2), H)[0])
        owner += [i] * unit.shape[0]
        cell_px += [size] * unit.shape[0]
    if not points:
        return out
    Q = np.concatenate(points)
    sampled = map_coordinates(gray.astype(np.float32), [Q[:, 1], Q[:, 0]], order=1, mode="nearest")
    prof: FloatArray = np.asarray(sampled, dtype=np.float64).reshape(-1, len(_U))
    wo = prof[:, _U <= -0.35].mean(axis=1)
    bl = prof[:, (_U >= 0.35) & (_U <= 0.65)].mean(axis=1)
    wi = prof[:, (_U >= 1.35) & (_U <= 1.65)].mean(axis=1)
    use = (wo - bl >= MIN_CONTRAST) & (wi - bl >= 0.6 * (wo - bl))  # a white cell inside: the border has two edges
    head, mid = _U <= 0.65, (_U >= 0.35) & (_U <= 1.65)
    outer = _crossings(_U[head], prof[:, head], 0.5 * (wo + bl), falling=True)
    inner = _crossings(_U[mid], prof[:, mid], 0.5 * (wi + bl), falling=False)
    size_px = np.asarray(cell_px)
    delta = (1.0 - (inner - outer)) * size_px / 2.0  # each edge's move towards the black
    shift = delta - outer * size_px  # the printed edge, outwards of the detector's
    owners = np.asarray(owner)
    good = use & np.isfinite(shift)
    for i in np.unique(owners[good]):
        out[i] = float(np.median(shift[good & (owners == i)]))
    return out


def run_shift(shifts: FloatArray) -> tuple[float, float, int]:
    """The run's edge shift, px: the median over the measured tags, its standard error (from the tags' robust
    spread, 1.4826 MAD, times the median's 1.2533 / sqrt(n)) and how many tags were measured."""
    finite = shifts[np.isfinite(shifts)]
    if not len(finite):
        return float("nan"), float("nan"), 0
    median = float(np.median(finite))
    spread = 1.4826 * float(np.median(np.abs(finite - median)))
    return median, 1.2533 * spread / float(np.sqrt(len(finite))), len(finite)


def shift_corners(corners: npt.ArrayLike, shift_px: float) -> FloatArray:
    """The quad (4 x 2) with each side moved outwards by ``shift_px`` (its corners where the moved sides meet)."""
    c = np.asarray(corners, float).reshape(4, 2)
    if shift_px == 0.0:
        return c
    centre = c.mean(axis=0)
    lines = []
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([-d[1], d[0]])
        if n @ (centre - a) > 0:
            n = -n  # outwards
        lines.append((a + shift_px * n, d))
    out = np.empty_like(c)
    for i in range(4):  # corner i is where side i-1 and side i meet
        (p1, d1), (p2, d2) = lines[i - 1], lines[i]
        t = np.linalg.solve(np.column_stack([d1, -d2]), p2 - p1)
        out[i] = p1 + t[0] * d1
    return out
