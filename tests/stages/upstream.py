"""Run folders whose ingest and detect stages are filled from a synthetic run, for tests of the later stages."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import BaseModel, ConfigDict

from pipeline.artifacts import StageOutput
from pipeline.run_folder import RunFolder
from pipeline.stage import Stage
from stages.graph.synthetic import SyntheticRun
from stages.ingest.artifacts import EXTRINSICS, SensorMount


class Unconfigured(BaseModel):
    """Settings of a stand-in stage: none."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def stand_in(name: str, *inputs: str) -> Stage:
    """A stage that does nothing, standing in for one whose artifacts a test writes itself."""
    return Stage(name=name, config_type=Unconfigured, run=lambda ctx, cfg: {}, inputs=inputs)


def seed_upstream(run: RunFolder, sim: SyntheticRun, scans: pa.Table | None = None) -> None:
    """Write ingest (odometry, extrinsics; with ``scans``, also them and a laser at the base origin) and detect
    (the run's detections) into ``run``, each recorded as finished."""
    extrinsics = sim.extrinsics
    ingest = {"odometry.parquet": sim.odometry}
    if scans is not None:
        ingest["scans.parquet"] = scans
        laser = SensorMount(frame_id="laser", T_base_sensor=np.eye(4).tolist())
        extrinsics = extrinsics.model_copy(update={"sensors": {**extrinsics.sensors, "laser": laser}})
    for name, files in (("ingest", ingest), ("detect", {"detections.parquet": sim.detections})):
        d = run.stage_dir(name)
        d.mkdir()
        for fname, table in files.items():
            pq.write_table(table, d / fname)
        if name == "ingest":
            EXTRINSICS.write(StageOutput(d), extrinsics)
        run.record(name, {"fingerprint": name, "summary": {}})
