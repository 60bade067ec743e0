"""The report's grid figures (maps.png, navigation.png) drawn from plain arrays, so a worker process can draw them.

:func:`stages.evaluate.report.figures` builds a :class:`MapsFigure` and a :class:`NavigationFigure` from the cases
and draws them in evaluate's worker process (while it draws the other figures itself) or here; either way the same
matplotlib calls make the same PNG.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg back-end."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def warm_up(plots: bool) -> None:
    """Import what evaluate's worker process will run, the navigation trials and (``plots``) matplotlib, while
    evaluate loads its inputs and solves the first case: on the sample the worker otherwise started its first
    navigation 1.5 s after it was sent, the time of these imports."""
    import stages.navigation.lqg  # noqa: F401

    if plots:
        pyplot()


def grid(n: int) -> tuple[int, int]:
    """Rows and columns of a grid of ``n`` panels, at most three across."""
    cols = min(3, n)
    return math.ceil(n / cols), cols


def draw_walls(ax: Any, walls: FloatArray | None) -> None:
    """The walls (W, 4: x0 y0 x1 y1) as grey lines."""
    if walls is not None:
        for w in walls:
            ax.plot([w[0], w[2]], [w[1], w[3]], color="0.3", lw=1)


def save(fig: Any, out_dir: Path, name: str) -> str:
    """Lay out, write ``out_dir/name`` at 110 dpi, close; returns ``name``."""
    fig.tight_layout()
    fig.savefig(out_dir / name, dpi=110)
    pyplot().close(fig)
    return name


@dataclass(frozen=True)
class MapPanel:
    """One case's landmark map: ids, positions (L, 2), covariances (L, 2, 2), and the panel's title."""

    tag_ids: npt.NDArray[np.int64]
    positions: FloatArray
    covariances: FloatArray
    title: str


@dataclass(frozen=True)
class MapsFigure:
    """maps.png: each case's landmark map with its ellipses over the walls and the path."""

    walls: FloatArray | None
    path: FloatArray
    """(K, 2+) the path drawn in every panel."""
    focus: frozenset[int]
    panels: list[MapPanel]
    n_sigma: float


@dataclass(frozen=True)
class NavigationPanel:
    """One case's sample trials (n, K, 2) and the panel's title (None: the case was not navigated)."""

    sample_paths: FloatArray | None
    title: str | None


@dataclass(frozen=True)
class NavigationFigure:
    """navigation.png: sample navigation trials of each case over the walls and the nominal path."""

    walls: FloatArray | None
    nominal: FloatArray
    panels: list[NavigationPanel]


def draw_maps(spec: MapsFigure, out_dir: Path) -> str:
    """maps.png: each case's landmark map with its ellipses, collision-focused landmarks in red."""
    from matplotlib.collections import EllipseCollection

    plt = pyplot()
    n = len(spec.panels)
    rows_, cols = grid(n)
    fig, axes = plt.subplots(rows_, cols, figsize=(5.5 * cols, 3.6 * rows_), squeeze=False)
    focus, n_sigma = spec.focus, spec.n_sigma
    for ax, panel in zip(axes.ravel(), spec.panels, strict=False):
        draw_walls(ax, spec.walls)
        ax.plot(spec.path[:, 0], spec.path[:, 1], color="tab:blue", lw=0.6)
        if len(panel.tag_ids):
            covs = 0.5 * (panel.covariances + panel.covariances.transpose(0, 2, 1))
            vals, vecs = np.linalg.eigh(covs)
            vals = np.clip(vals, 0, None)
            angles = np.degrees(np.arctan2(vecs[:, 1, 1], vecs[:, 0, 1]))
            colors = ["tab:red" if int(t) in focus else "tab:green" for t in panel.tag_ids]
            ax.add_collection(
                EllipseCollection(
                    2 * n_sigma * np.sqrt(vals[:, 1]),
                    2 * n_sigma * np.sqrt(vals[:, 0]),
                    angles,
                    units="xy",
                    offsets=panel.positions,
                    offset_transform=ax.transData,
                    facecolors="none",
                    edgecolors=colors,
                    linewidths=0.8,
                )
            )
            ax.scatter(panel.positions[:, 0], panel.positions[:, 1], s=2, c=colors)
        ax.set_title(panel.title, fontsize=9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.suptitle(f"maps ({n_sigma:g}-sigma ellipses; red: collision-focused landmarks)", fontsize=10)
    return save(fig, out_dir, "maps.png")


def draw_navigation(spec: NavigationFigure, out_dir: Path) -> str:
    """navigation.png: sample navigation trials of each case."""
    n = len(spec.panels)
    rows_, cols = grid(n)
    fig, axes = pyplot().subplots(rows_, cols, figsize=(5.5 * cols, 3.6 * rows_), squeeze=False)
    nom = spec.nominal
    for ax, panel in zip(axes.ravel(), spec.panels, strict=False):
        draw_walls(ax, spec.walls)
        ax.plot(nom[:, 0], nom[:, 1], "--", color="tab:blue", lw=0.8)
        if panel.sample_paths is not None:
            for pth in panel.sample_paths:
                ax.plot(pth[:, 0], pth[:, 1], lw=0.5, color="tab:orange")
            ax.set_title(panel.title, fontsize=9)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    return save(fig, out_dir, "navigation.png")


def draw_in_worker(spec: MapsFigure | NavigationFigure, out_dir: Path) -> str:
    """Draw ``spec`` into ``out_dir`` (what evaluate's worker process runs); returns the file name."""
    return draw_maps(spec, out_dir) if isinstance(spec, MapsFigure) else draw_navigation(spec, out_dir)
