"""What select_measurements writes into ``RUN/select_measurements/``: the kept measurements and how they were chosen.

``selected.parquet`` (:data:`SELECTED`) lists the kept tag measurements, one row per pick; ``selection.json``
(:data:`SELECTION`) holds the whole :class:`~stages.select_measurements.core.MeasurementChoice` and the
select_measurements settings that made it. optimize and evaluate read K, the focus and the strategy from here,
never from the settings section.

```python
SELECTION.write(ctx.output, SelectedMeasurements.of(choice, cfg))
selection = SELECTION.read(ctx.input("select_measurements"))   # a MeasurementChoice with .settings
```
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

import numpy as np
import pyarrow as pa
from pydantic import Field

from pipeline.contracts import ArtifactSet, Column, JsonSpec, TableSpec
from stages.columns import STAMP_NS, TAG_ID
from stages.select_measurements.config import SelectMeasurementsConfig
from stages.select_measurements.core import MeasurementChoice

if TYPE_CHECKING:
    from stages.graph.load import LoadedGraph


# selection.json ----------------------------------------------------------------------------------------
class SelectedMeasurements(MeasurementChoice):
    """What select_measurements chose, and with which settings."""

    settings: SelectMeasurementsConfig = Field(
        description="the select_measurements settings that made the selection (later stages read K here)"
    )

    @classmethod
    def of(cls, choice: MeasurementChoice, cfg: SelectMeasurementsConfig) -> SelectedMeasurements:
        """The record of ``choice`` made with ``cfg``."""
        return cls(**dict(choice), settings=cfg)


SELECTION: Final = JsonSpec(
    "selection.json", "the whole measurement choice and the settings that made it", SelectedMeasurements
)


# selected.parquet --------------------------------------------------------------------------------------
FACTOR_INDEX = Column("factor_index", pa.int64(), "the kept factor: its row of `graph/factors.parquet`")
STEP = Column("step", pa.int64(), "pick order, from 0")
GAIN = Column("gain", pa.float64(), "entropy reduction (information, nats), sampling probability (leverage), else NaN")
SELECTED: Final = TableSpec(
    "selected.parquet",
    "one row per kept tag measurement, in pick order",
    [FACTOR_INDEX, STEP, GAIN, TAG_ID, STAMP_NS],
)


def selected_table(choice: MeasurementChoice, loaded: LoadedGraph) -> pa.Table:
    """:data:`SELECTED` of a choice on the full graph ``loaded`` (tag and stamp of each kept factor)."""
    rows = [loaded.rows[i] for i in choice.factor_indices]
    return SELECTED.table(
        {
            FACTOR_INDEX: choice.factor_indices,
            STEP: np.arange(len(choice.factor_indices)),
            GAIN: choice.gains,
            TAG_ID: [r.tag_id for r in rows],
            STAMP_NS: [r.stamp_ns for r in rows],
        }
    )


ARTIFACTS: Final = ArtifactSet(
    "select_measurements",
    "Stage two of focused inference: the tag measurements of the focused landmarks worth keeping.",
    [SELECTED, SELECTION],
)
