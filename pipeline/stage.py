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
        source_kinds: kinds of run source (``run.json``'s ``source_kind``) that the stage reads directly instead of
            its inputs: on such a run it has no inputs and its fingerprint covers the source file (the graph
            stage of a run made by ``import-graph`` reads the graph file).
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
    source_kinds: tuple[str, ...] = field(default=())

    def reads_source(self, source_kind: str) -> bool:
        """Whether the stage reads the run's source on a run whose source is of this kind."""
        return self.needs_source or source_kind in self.source_kinds

    def inputs_on(self, source_kind: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """Required and optional inputs on a run whose source is of this kind."""
        if source_kind in self.source_kinds:
            return (), ()
        return self.inputs, self.optional_inputs

    @property
    def command(self) -> str:
        """The CLI command name (dashes instead of underscores)."""
        return self.name.replace("_", "-")
