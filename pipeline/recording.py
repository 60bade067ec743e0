"""Rerun helpers: one recording per stage, all sharing the run's recording id, and covariance drawing.

Timelines: ``time`` (the bag's clock, a timestamp) for anything tied to a moment of the run;
``selection_step`` (a sequence) for the greedy steps of the selection stages.
Entity paths start with the stage name (``/ingest/odometry``, ``/graph/landmarks``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
import rerun as rr

if TYPE_CHECKING:
    import rerun.blueprint as rrb
    from rerun.encodings import Rgba32ArrayLike

    from pipeline.stage import Summary

APPLICATION_ID = "focusmap"


class _FileWriter:
    """Writes a recording's encoded bytes into its file when it is closed.

    Rerun's own file sink cannot be used: once one of its writes fails (a full disk), every later
    flush, disconnect or drop of the recording waits forever, even the interpreter's exit. Here the
    encoding stays in memory (a stage's recording is a few MB) and Python writes the file, so a failed
    write is an ``OSError``. The bytes are read once: Rerun 0.41 ends every read of its in-memory
    stream with its own index, and pieces read at several times do not join into one valid file.
    """

    def __init__(self, stream: rr.BinaryStream, path: Path) -> None:
        self.path = path
        self._stream = stream

    def close(self) -> None:
        """Write the recording's file; a failed write raises ``OSError`` and leaves no file."""
        data = self._stream.read(flush=True) or b""
        try:
            with open(self.path, "wb") as f:
                f.write(data)
        except OSError:
            self.path.unlink(missing_ok=True)
            raise


_WRITERS: dict[int, _FileWriter] = {}


def open_recording(run_id: str, path: Path, blueprint: rrb.Blueprint | None = None) -> rr.RecordingStream:
    """A recording stream saving to ``path``, with the run's recording id so stage files merge in the viewer.

    Close it with :func:`close_recording`, which raises the ``OSError`` of a failed write.
    """
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=run_id, send_properties=False)
    _WRITERS[id(rec)] = _FileWriter(rr.binary_stream(recording=rec), path)
    if blueprint is not None:
        rec.send_blueprint(blueprint, make_active=False, make_default=True)
    return rec


def run_blueprint(blueprints: Sequence[tuple[str, rrb.Blueprint]], active: str | None = None) -> rrb.Blueprint | None:
    """One blueprint for a whole run: a tab per stage (each stage's own layout), paused on ``time``.

    Every stage's recording carries it (with its own tab active), so however the viewer is given
    the run's files, the layout shows every stage.
    """
    import rerun.blueprint as rrb

    tabs: list[rrb.Container] = []
    active_index = None
    for name, bp in blueprints:
        root: rrb.Container | None = getattr(bp, "root_container", None)  # absent from an empty blueprint
        if root is None:
            continue
        root.name = name
        if name == active:
            active_index = len(tabs)
        tabs.append(root)
    if not tabs:
        return None
    return rrb.Blueprint(
        rrb.Tabs(*tabs, active_tab=active_index if active_index is not None else len(tabs) - 1),
        rrb.TimePanel(play_state="paused", timeline="time"),
        collapse_panels=True,
    )


def blueprint_bytes(blueprint: rrb.Blueprint) -> bytes:
    """A blueprint encoded as a ``.rbl`` file holds it (Rerun's encoding, made in memory)."""
    stream = rr.RecordingStream._from_native(  # what ``Blueprint.save`` makes, without Rerun's file sink
        rr.recording_stream.bindings.new_blueprint(
            application_id=APPLICATION_ID, make_default=False, make_thread_default=False, default_enabled=True
        )
    )
    out = rr.binary_stream(recording=stream)
    stream.set_time("blueprint", sequence=0)
    blueprint._log_to_stream(stream)
    return out.read(flush=True) or b""


def save_blueprint(blueprint: rrb.Blueprint, path: Path) -> None:
    """Write a blueprint file (``.rbl``) that the viewer opens beside the recordings.

    Python writes it under a temporary name and renames it, so a failed write raises ``OSError``
    naming ``path`` at once (Rerun's own ``Blueprint.save`` waits forever on a full disk) and the
    old file stays whole.
    """
    data = blueprint_bytes(blueprint)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        tmp.replace(path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise OSError(err.errno, err.strerror, str(path)) from err


def close_recording(rec: rr.RecordingStream) -> None:
    """Flush everything to the recording's file and close it; a failed write raises ``OSError`` naming the file."""
    writer = _WRITERS.pop(id(rec), None)
    try:
        if writer is not None:
            writer.close()
        else:
            rec.flush()
    except OSError as err:
        path = str(writer.path) if writer is not None else None
        raise OSError(err.errno, err.strerror, path) from err
    finally:
        rec.disconnect()


def set_stamp(rec: rr.RecordingStream, stamp_ns: int) -> None:
    """Place the following logs at the bag time ``stamp_ns`` on the ``time`` timeline."""
    rec.set_time("time", timestamp=np.datetime64(int(stamp_ns), "ns"))


def set_step(rec: rr.RecordingStream, step: int) -> None:
    """Place the following logs at greedy step ``step`` on the ``selection_step`` timeline."""
    rec.set_time("selection_step", sequence=int(step))


def quat_xyzw_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, for Rerun (which uses xyzw)."""
    R = np.asarray(R, dtype=float)
    w = np.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    x = np.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2.0
    y = np.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2.0
    z = np.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2.0
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    q = np.array([x, y, z, w])
    return q / np.linalg.norm(q)


def covariance_axes(cov: np.ndarray, n_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Half-sizes (n-sigma) and rotation of the ellipsoid of a 2x2 or 3x3 covariance.

    Returns the half sizes (length 3; a 2x2 covariance gets a zero third axis) and the 3x3
    rotation whose columns are the principal axes (a right-handed frame).
    """
    cov = np.asarray(cov, dtype=float)
    if cov.shape == (2, 2):
        full = np.zeros((3, 3))
        full[:2, :2] = cov
        cov = full
    cov = 0.5 * (cov + cov.T)
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    return n_sigma * np.sqrt(vals), vecs


def ellipsoids(
    centers: np.ndarray,
    covariances: Sequence[np.ndarray] | np.ndarray,
    n_sigma: float,
    colors: Rgba32ArrayLike | None = None,
    labels: Sequence[str] | None = None,
) -> rr.Ellipsoids3D:
    """An ``Ellipsoids3D`` with one n-sigma ellipsoid per (center, 2x2 or 3x3 covariance)."""
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    half_sizes = np.zeros((len(centers), 3))
    quats = np.zeros((len(centers), 4))
    for i, cov in enumerate(covariances):
        half_sizes[i], R = covariance_axes(np.asarray(cov), n_sigma)
        quats[i] = quat_xyzw_from_matrix(R)
    return rr.Ellipsoids3D(
        centers=centers,
        half_sizes=half_sizes,
        quaternions=quats,
        colors=colors,
        labels=list(labels) if labels is not None else None,
        fill_mode="majorwireframe",
    )


def ellipses_2d(
    centers: npt.ArrayLike,
    covariances: Sequence[np.ndarray],
    n_sigma: float,
    colors: Rgba32ArrayLike | None = None,
    segments: int = 32,
) -> rr.LineStrips3D:
    """Planar n-sigma ellipses (from the xy block of each covariance) drawn as closed strips at z = 0."""
    t = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)
    strips = []
    for c, cov in zip(np.asarray(centers, dtype=float), covariances, strict=True):
        sizes, R = covariance_axes(np.asarray(cov)[:2, :2], n_sigma)
        pts = circle * sizes[:2] @ R[:2, :2].T + c[:2]
        strips.append(np.column_stack([pts, np.full(len(pts), c[2] if len(c) > 2 else 0.0)]))
    return rr.LineStrips3D(strips, colors=colors)


_RAMP = np.array(
    [
        [48, 18, 59],
        [70, 107, 227],
        [41, 187, 236],
        [49, 242, 153],
        [163, 253, 61],
        [237, 208, 58],
        [251, 128, 34],
        [208, 47, 5],
        [122, 4, 3],
    ],
    dtype=float,
)


def colormap(values: np.ndarray, vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """RGB colours (uint8, N x 3) for ``values`` on a turbo-like ramp from vmin (blue) to vmax (red)."""
    v = np.asarray(values, dtype=float)
    lo = np.nanmin(v) if vmin is None else vmin
    hi = np.nanmax(v) if vmax is None else vmax
    t = np.zeros_like(v) if hi <= lo else np.clip((v - lo) / (hi - lo), 0.0, 1.0)
    t = np.nan_to_num(t)
    x = t * (len(_RAMP) - 1)
    i = np.minimum(x.astype(int), len(_RAMP) - 2)
    f = (x - i)[..., None]
    return (_RAMP[i] * (1 - f) + _RAMP[i + 1] * f).astype(np.uint8)


def log_summary(rec: rr.RecordingStream, stage: str, summary: Summary) -> None:
    """The stage summary as a static markdown document at ``/<stage>/summary``."""
    body = json.dumps(summary, indent=2, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    text = f"# {stage}\n\n```json\n{body}\n```\n"
    rec.log(f"/{stage}/summary", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
