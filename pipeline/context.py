"""What a running stage gets: its run folder, settings, inputs, output folder and recording."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import rerun as rr

from pipeline.artifacts import StageInput, StageOutput
from pipeline.config import Settings
from pipeline.errors import StageError
from pipeline.progress import track
from pipeline.run_folder import RunFolder, outside_identity
from pipeline.stage import Stage

T = TypeVar("T")


@dataclass
class StageContext:
    """Everything a stage's ``run`` function may touch.

    ``settings`` holds the stage's own section and the shared ``rerun`` section only: what a stage needs from
    an upstream stage it reads from that stage's artifacts, whose fingerprint its own covers.
    """

    run: RunFolder
    stage: Stage
    settings: Settings
    output: StageOutput
    rec: rr.RecordingStream
    outside_files: dict[str, str | None] = field(default_factory=dict)
    """Files outside the run folder the stage read (resolved path to identity; None: looked for, absent)."""
    show_progress: bool = False

    def outside_file(self, path: Path | str) -> Path | None:
        """Declare a file outside the run folder that the stage reads (or would read, if it existed).

        Its identity goes into the stage's manifest entry, so the stage re-runs when the file changes, appears
        or disappears. Returns the path when the file exists, else None.
        """
        p = Path(path).resolve()
        self.outside_files[str(p)] = outside_identity(str(p))
        return p if p.exists() else None

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
