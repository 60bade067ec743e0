"""The stage contract: a stage is a value with a name, a settings model, its inputs and a run function.

A stage's ``run(ctx, cfg)`` reads the artifacts of its input stages through ``ctx.input(name)``,
writes its own through ``ctx.output``, logs to ``ctx.rec`` and returns a small JSON-able summary
(counts, timings, headline metrics) that goes into ``summary.json`` and the run's manifest.

A stage value is cheap to build: its run function (and anything else that needs the heavy libraries)
can be named by an import path with :func:`~pipeline.lazy.lazy`, imported on first call, so listing the
stages (``focusmap --help``) imports no numerics. A stage also says how the command line shows it:
its command's options, the line printed after it ran and, for a report, what ``focusmap run`` prints last.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Generic, TypeAlias, TypeVar

from pydantic import BaseModel

from pipeline.json_types import JSONObject, JSONValue
from pipeline.lazy import lazy

if TYPE_CHECKING:
    import rerun.blueprint as rrb

    from pipeline.context import StageContext

Summary: TypeAlias = JSONObject
"""A stage's summary: small JSON-able figures (counts, timings, headline metrics, ``notes``)."""

C = TypeVar("C", bound=BaseModel)

__all__ = [
    "AnyStage",
    "JSONValue",
    "Option",
    "Stage",
    "Summary",
    "lazy",
    "run_options",
    "summary_figures",
    "summary_notes",
]


@dataclass(frozen=True)
class Option:
    """A command-line option of a stage's command that sets one key of the stage's settings section.

    Attributes:
        flag: the option as typed, e.g. ``"--budget"``.
        key: the settings key it sets (in the stage's section), e.g. ``"budget"``.
        help: one line for ``--help``.
        kind: type of the value (``str``, ``int``, ``float``, ``pathlib.Path``); ``bool`` makes a flag that,
            when given, sets the key to true.
        min: smallest accepted value (numbers).
        value: turns the given value into the YAML text of the setting (default ``str(value)``); may raise
            :class:`~pipeline.errors.InputError` for a value the user can fix.
        on_run: also an option of ``focusmap run`` and ``batch`` (and a key of a batch file's entries), though the
            stage does not read the recording; stages that declare the same flag share it there: one value sets
            the key of each (:func:`run_options`).
    """

    flag: str
    key: str
    help: str
    kind: type = str
    min: float | None = None
    value: Callable[[Any], str] | None = None  # takes a value of type ``kind``, which only the option knows
    on_run: bool = False

    def override(self, section: str, given: object) -> str | None:
        """The ``SECTION.KEY=VALUE`` override for a given value, None when the option was not given."""
        if given is None or given is False:
            return None
        text = self.value(given) if self.value is not None else ("true" if given is True else str(given))
        return f"{section}.{self.key}={text}"


def run_options(stages: Iterable[AnyStage]) -> list[tuple[str, Option]]:
    """The options of ``focusmap run`` and ``batch`` as ``(stage name, option)``: every option of the stages that
    read the recording, and the options other stages mark ``on_run`` (one flag may appear for several stages)."""
    return [(s.name, o) for s in stages for o in s.options if s.needs_source or o.on_run]


def summary_figures(summary: Summary, hidden: Sequence[str] = ("seconds", "notes"), limit: int = 6) -> str:
    """``key=value`` of the first ``limit`` figures of a summary (leaving out ``hidden`` keys, nulls and nesting)."""
    keys = [k for k, v in summary.items() if k not in hidden and v is not None][:limit]
    return "  ".join(f"{k}={summary[k]}" for k in keys if not isinstance(summary[k], dict | list))


def summary_notes(summary: Summary) -> list[tuple[str, str]]:
    """The summary's notes, as ``("note", text)`` remarks."""
    notes = summary.get("notes")
    return [("note", str(note)) for note in notes] if isinstance(notes, list) else []


@dataclass(frozen=True)
class Stage(Generic[C]):
    """One step of the pipeline, whose settings are a ``C``.

    Attributes:
        name: snake_case name; also the artifact folder and the ``<name>.rrd`` file.
        config_type: pydantic settings model (``extra="forbid"``); its YAML section is ``name``.
        inputs: stages whose artifacts this one reads (all must have run first).
        run: ``run(ctx, cfg) -> summary`` (usually ``lazy("stages.<name>.stage:run")``).
        version: bump when the stage's code changes its outputs, so cached results are recomputed.
        needs_source: the stage reads the run's source file (only ingest does).
        source_kinds: kinds of run source (``run.json``'s ``source_kind``) that the stage reads directly instead of
            its inputs: on such a run it has no inputs and its fingerprint covers the source file (the graph
            stage of a run made by ``import-graph`` reads the graph file).
        blueprint: optional ``() -> rerun.blueprint.Blueprint`` for the stage's recording.
        help: one line for ``--help``.
        options: the options of the stage's command, each setting one key of its settings.
        summary_line: ``summary -> str``: the figures printed on the stage's line after it ran.
        remarks: ``summary -> [(label, text)]``: lines printed under it after it ran (notes, ...).
        report_lines: ``summary -> [str]``: what ``focusmap run`` prints at its end when this stage has run.
    """

    name: str
    config_type: type[C]
    run: Callable[[StageContext, C], Mapping[str, JSONValue] | None]
    inputs: tuple[str, ...] = ()
    version: str = "1"
    needs_source: bool = False
    blueprint: Callable[[], rrb.Blueprint] | None = None
    help: str = ""
    optional_inputs: tuple[str, ...] = field(default=())
    options: tuple[Option, ...] = ()
    summary_line: Callable[[Summary], str] = summary_figures
    remarks: Callable[[Summary], list[tuple[str, str]]] = summary_notes
    report_lines: Callable[[Summary], list[str]] | None = None
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


AnyStage: TypeAlias = Stage[Any]
"""A stage whose settings model is not known statically (the registry holds stages of every kind)."""
