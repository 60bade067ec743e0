"""``selection.json``: the kept measurements with everything later stages need to know about how they were chosen.

``selected.parquet`` lists the kept tag measurements (one row per pick); ``selection.json`` holds the whole
:class:`~stages.select_measurements.core.MeasurementChoice` (strategy, budget K, focus, the focused landmarks,
the picks and gains, the candidates, the entropy before and after) and the select_measurements settings that
made it. Optimize and evaluate read K, the focus and the strategy from here, never from the settings section.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from pipeline.artifacts import StageInput, StageOutput
from pipeline.errors import InputError
from stages.select_measurements.config import SelectMeasurementsConfig
from stages.select_measurements.core import MeasurementChoice

SELECTION_FILE = "selection.json"


@dataclass(frozen=True)
class SelectedMeasurements:
    """What select_measurements chose, and with which settings."""

    choice: MeasurementChoice
    settings: SelectMeasurementsConfig


def write_selection(out: StageOutput, choice: MeasurementChoice, cfg: SelectMeasurementsConfig) -> None:
    """Write ``selection.json``."""
    doc: dict[str, Any] = dataclasses.asdict(choice)
    doc["settings"] = cfg.model_dump(mode="json")
    out.write_json(SELECTION_FILE, doc)


def read_selection(inp: StageInput) -> SelectedMeasurements:
    """Read ``selection.json`` of a finished select_measurements stage."""
    if not inp.exists(SELECTION_FILE):
        raise InputError(f"{inp.path} has no {SELECTION_FILE}; re-run 'focusmap select-measurements'")
    doc = inp.read_json(SELECTION_FILE)
    settings = SelectMeasurementsConfig.model_validate(doc.pop("settings"))
    names = {f.name for f in dataclasses.fields(MeasurementChoice)}
    choice = MeasurementChoice(**{k: v for k, v in doc.items() if k in names})
    return SelectedMeasurements(choice, settings)
