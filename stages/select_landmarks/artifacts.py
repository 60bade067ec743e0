"""``focused.json``: the focused landmarks and everything a later stage needs to know about how they were chosen.

Downstream stages (select_measurements, optimize, evaluate) read the landmark budget α, the strategy and the
collision-risk model from here, never from the ``select_landmarks`` settings section: the artifact's fingerprint
is part of theirs, so a new α or robot radius re-runs them, and what they report is what this stage did.

Keys: ``strategy``, ``budget`` (α), ``tag_ids`` (pick order), ``scores``, ``status``, ``message``,
``n_landmarks``, ``seconds``, ``settings`` (the select_landmarks settings that made the selection, which include
the risk model of :class:`stages.risk.RiskParams`) and ``noise`` (the noise the risk model resolved from the
graph: bearing and range sigma of the tag measurements, odometry sigmas per keyframe step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.artifacts import StageInput, StageOutput
from pipeline.errors import InputError
from stages.risk import PathGeometry, RiskParams
from stages.select_landmarks.config import SelectLandmarksConfig
from stages.select_landmarks.core import LandmarkChoice

FOCUSED_FILE = "focused.json"


@dataclass(frozen=True)
class FocusedLandmarks:
    """What select_landmarks chose, and with which settings."""

    strategy: str
    budget: int
    tag_ids: list[int]
    """In the order picked."""
    status: str
    message: str
    n_landmarks: int
    seconds: float
    settings: SelectLandmarksConfig
    noise: dict[str, float]

    @property
    def risk_params(self) -> RiskParams:
        """The collision-risk model the selection used."""
        return self.settings.risk_params()


def write_focused(out: StageOutput, choice: LandmarkChoice, cfg: SelectLandmarksConfig, geo: PathGeometry) -> None:
    """Write ``focused.json`` for a selection made with ``cfg`` on a path of geometry ``geo``."""
    doc: dict[str, Any] = choice.focused_json()
    doc["seconds"] = choice.seconds
    doc["settings"] = cfg.model_dump(mode="json")
    doc["noise"] = {
        "bearing_sigma_rad": float(geo.sigmas[0]),
        "range_sigma_m": float(geo.sigmas[1]),
        "odometry_sigma_m": float(np.sqrt(geo.Q[0, 0])),
        "odometry_sigma_rad": float(np.sqrt(geo.Q[2, 2])),
    }
    out.write_json(FOCUSED_FILE, doc)


def read_focused(inp: StageInput) -> FocusedLandmarks:
    """Read ``focused.json`` of a finished select_landmarks stage."""
    doc = inp.read_json(FOCUSED_FILE)
    if "settings" not in doc:
        raise InputError(f"{inp.path / FOCUSED_FILE} predates the settings record; re-run 'focusmap select-landmarks'")
    return FocusedLandmarks(
        strategy=str(doc["strategy"]),
        budget=int(doc["budget"]),
        tag_ids=[int(t) for t in doc["tag_ids"]],
        status=str(doc["status"]),
        message=str(doc["message"]),
        n_landmarks=int(doc["n_landmarks"]),
        seconds=float(doc.get("seconds", 0.0)),
        settings=SelectLandmarksConfig.model_validate(doc["settings"]),
        noise={k: float(v) for k, v in doc.get("noise", {}).items()},
    )
