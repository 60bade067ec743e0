"""What a running stage gets: its run folder, settings, inputs, output folder and recording."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import rerun as rr

from pipeline.artifacts import StageInput, StageOutput
from pipeline.config import Settings
from pipeline.errors import StageError
from pipeline.progress import track
from pipeline.run_folder import RunFolder
from pipeline.stage import Stage

T = TypeVar("T")


@dataclass
class StageContext:
    """Everything a stage's ``run`` function may touch."""

    run: RunFolder
    stage: Stage
    settings: Settings
    output: StageOutput
    rec: rr.RecordingStream
    show_progress: bool = False

    @property
    def source(self) -> Path:
        """The recording the run was made from (only ingest reads it)."""
        src = self.run.source
        if src is None:
            raise StageError(f"run {self.run.path.name!r} has no source recording")
        return src

    def input(self, stage: str) -> StageInput:
        """The finished artifacts of an upstream stage."""
        return StageInput(stage, self.run.stage_dir(stage))

    def has_input(self, stage: str) -> bool:
        """Whether an (optional) upstream stage has finished."""
        return self.run.stage_entry(stage) is not None

    def progress(self, items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
        """Iterate, with a progress bar when the run was asked to show them."""
        return track(items, description, total, show=self.show_progress)

    @property
    def n_sigma(self) -> float:
        """Covariance ellipsoids are drawn at this many standard deviations."""
        return self.settings.rerun.n_sigma
