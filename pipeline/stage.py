"""The stage contract: a stage is a value with a name, a settings model, its inputs and a run function.

A stage's ``run(ctx, cfg)`` reads the artifacts of its input stages through ``ctx.input(name)``,
writes its own through ``ctx.output``, logs to ``ctx.rec`` and returns a small JSON-able summary
(counts, timings, headline metrics) that goes into ``summary.json`` and the run's manifest.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

if TYPE_CHECKING:
    from pipeline.context import StageContext

Summary = dict[str, Any]


@dataclass(frozen=True)
class Stage:
    """One step of the pipeline.

    Attributes:
        name: snake_case name; also the artifact folder and the ``<name>.rrd`` file.
        config_type: pydantic settings model (``extra="forbid"``); its YAML section is ``name``.
        inputs: stages whose artifacts this one reads (all must have run first).
        run: ``run(ctx, cfg) -> summary``.
        version: bump when the stage's code changes its outputs, so cached results are recomputed.
        needs_source: the stage reads the run's source file (only ingest does).
        blueprint: optional ``() -> rerun.blueprint.Blueprint`` for the stage's recording.
        help: one line for ``--help``.
    """

    name: str
    config_type: type[BaseModel]
    run: Callable[[StageContext, Any], Summary]
    inputs: tuple[str, ...] = ()
    version: str = "1"
    needs_source: bool = False
    blueprint: Callable[[], Any] | None = None
    help: str = ""
    optional_inputs: tuple[str, ...] = field(default=())

    @property
    def command(self) -> str:
        """The CLI command name (dashes instead of underscores)."""
        return self.name.replace("_", "-")
