"""Tags on a moving TagSLAM body (``is_static: false`` in ``tagslam.yaml``: a wand, a cube, a board carried
around): they move, so none of them is a landmark; the graph leaves their detections out and says so."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt


def moving_body_detections(
    tag_ids: Sequence[Any], keep: npt.NDArray[np.bool_], moving_tags: Mapping[str, Sequence[int]], info: dict[str, Any]
) -> npt.NDArray[np.bool_]:
    """Which detections are of a tag on a moving body; in ``info``, per body the tags seen and the detections left
    out (of those ``keep`` still holds: ``dropped_moving_body_tags``), and one note per body that had any."""
    ids = np.asarray(tag_ids, dtype=np.int64)
    out = np.zeros(len(ids), dtype=bool)
    dropped: dict[str, dict[str, Any]] = {}
    for body, tags in moving_tags.items():
        on = np.isin(ids, np.asarray(tags, dtype=np.int64)) & keep & ~out
        out |= on
        if not on.any():
            continue
        seen = sorted({int(t) for t in ids[on]})
        dropped[body] = {"tags": seen, "detections": int(on.sum())}
        info.setdefault("notes", []).append(
            f"{int(on.sum())} detections of tags {', '.join(map(str, seen))} left out: they are on the moving body "
            f"{body!r} (is_static: false in the tags file), and a tag that moves is no landmark"
        )
    info["dropped_moving_body_tags"] = dropped
    return out
