"""The focusmap command line: one command per stage, plus info, run, view and show-config.

Every failure the user can fix is one line on stderr starting with ``error:`` and exit code 1
(``--debug`` shows the traceback instead).

The stage commands are built from the stage registry: a stage brings its help line, its options
(each sets one of its settings) and how its result is printed. Importing this module imports no
numerics: a stage's code is imported when it runs.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import json
import operator
import os
import subprocess
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ParamSpec, TypeVar

import click
import typer
from typer.core import TyperGroup

try:  # Typer 0.2x raises its option errors from its own copy of click
    from typer._click.exceptions import BadParameter, MissingParameter
except ImportError:  # older Typer: click itself
    from click.exceptions import BadParameter, MissingParameter  # type: ignore[assignment]

from cli.options import (
    BagArg,
    ConfigOpt,
    ForceOpt,
    NameOpt,
    OutOpt,
    ResetOpt,
    RunDirArg,
    SalvageOpt,
    SetOpt,
    StrictOpt,
)
from pipeline.errors import InputError, PipelineError, one_line, write_error
from pipeline.stage import run_options

if TYPE_CHECKING:
    from typer._click import Context as _VendoredContext

    from pipeline.config import Settings
    from pipeline.registry import Registry
    from pipeline.run_folder import RunFolder
    from pipeline.runner import StageResult
    from pipeline.stage import AnyStage, Option


class _Group(TyperGroup):
    """The root group: a bad option value is one ``error:`` line, not Click's usage box.

    Click checks ``min=``/``max=`` and types while it parses a command's options, outside the
    command's :func:`handled`; a bad value (``--stride 0``, ``--at 2``, ``--budget x``) ends here. A
    missing argument, an unknown option or command keep Click's usage box: that is about how the
    command is called, which the usage shows.
    """

    def invoke(self, ctx: Any) -> Any:
        try:
            return super().invoke(ctx)
        except BadParameter as err:
            if isinstance(err, MissingParameter):
                raise
            message = err.format_message().removeprefix("Invalid value for ").rstrip(".")
            typer.echo(f"error: invalid value for {message}{_option_setting(err)}", err=True)
            raise typer.Exit(1) from None


def _option_setting(err: BadParameter) -> str:
    """`` (setting SECTION.KEY)`` when the bad value was given to a stage option, else empty."""
    command = err.ctx.info_name if err.ctx is not None else None
    name = err.param.name if err.param is not None else None
    stages = [s for s in _registry() if s.command == command]
    options = [(s.name, o) for s in stages for o in s.options] if stages else run_options(_registry())
    settings = [f"{section}.{option.key}" for section, option in options if _param_name(option) == name]
    return f" (setting {', '.join(settings)})" if settings else ""


app = typer.Typer(
    cls=_Group,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    help="Turn recorded robot runs into small, task-focused AprilTag maps, logged to Rerun.",
)

P = ParamSpec("P")
R = TypeVar("R")


@dataclass(frozen=True)
class CliState:
    """What the root options decided, for every command of one invocation (typer's context object).

    Attributes:
        debug: show tracebacks instead of one-line errors (``--debug``, or ``FOCUSMAP_DEBUG=1``).
    """

    debug: bool = False


def _context() -> click.Context | _VendoredContext | None:
    """The running command's context, None outside one.

    Typer 0.2x runs its commands on its own copy of click (``typer._click``), whose context stack
    ``click.get_current_context`` does not see: look there too.
    """
    ctx = click.get_current_context(silent=True)
    if ctx is not None:
        return ctx
    try:
        from typer._click.globals import get_current_context
    except ImportError:
        return None
    return get_current_context(silent=True)


def _state() -> CliState:
    """The state of the running invocation (defaults outside one)."""
    ctx = _context()
    state = ctx.find_object(CliState) if ctx is not None else None
    return state if state is not None else CliState()


def handled(func: Callable[P, R]) -> Callable[P, R]:
    """Turn known failures into one ``error:`` line and a non-zero exit."""

    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return func(*args, **kwargs)
        except PipelineError as err:
            if _state().debug:
                raise
            problems = getattr(err, "problems", None)  # a batch file's problems: one error line each
            lines = [str(p) for p in problems] if isinstance(problems, list) and problems else [str(err)]
            for line in lines:
                typer.echo(f"error: {one_line(line)}", err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.echo("error: interrupted; finished stages are kept, the interrupted one left no output", err=True)
            raise typer.Exit(130) from None
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except Exception as err:
            if _state().debug:
                raise
            # a write that failed outside a stage (settings, the manifest): a full or read-only disk
            failed = write_error(err, Path.cwd()) if isinstance(err, OSError) and err.filename else None
            if failed is not None:
                typer.echo(f"error: {failed}", err=True)
                raise typer.Exit(1) from None
            typer.echo(
                f"error: internal error {type(err).__name__}: {one_line(str(err), 200)} (re-run with --debug for the "
                "traceback and report it)",
                err=True,
            )
            raise typer.Exit(2) from None

    return wrapper


@app.callback()
def _root(
    ctx: typer.Context,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks instead of one-line errors.")] = False,
) -> None:
    ctx.obj = CliState(debug=debug or os.environ.get("FOCUSMAP_DEBUG", "") not in ("", "0"))


# --- helpers ---------------------------------------------------------------------------------------
def _registry() -> Registry:
    from stages import REGISTRY

    return REGISTRY


def _settings(
    config: Path | None,
    sets: list[str] | None,
    extra: list[str] | None = None,
    run_dir: Path | None = None,
    reset: bool = False,
    running: list[str] | None = None,
) -> Settings:
    """Resolve the settings; on a run folder, on top of the settings it keeps, printing what differs."""
    from pipeline.config import load_settings

    overrides = [*(sets or []), *(extra or [])]
    if run_dir is None:
        return load_settings(_registry().models(), config, overrides)
    from pipeline.run_settings import resolve_run_settings

    settings, lines = resolve_run_settings(_registry().models(), run_dir, config, overrides, reset, running)
    for line in lines:
        typer.echo(line)
    return settings


def _run_name(bag: Path, name: str | None) -> str:
    """The run folder's name: ``--name`` (a plain folder name, checked) or the recording's name."""
    from pipeline.run_folder import check_run_name

    if name is not None:
        return check_run_name(name)
    base = bag.resolve()
    return base.name if base.is_dir() else base.stem


def _open_run(run_dir: Path) -> RunFolder:
    """An existing run folder, to read (:func:`_locked_run` to write in it)."""
    from pipeline.run_folder import RunFolder

    if not run_dir.exists():
        raise InputError(f"run folder {str(run_dir)!r} does not exist; create it with 'focusmap ingest BAG --out DIR'")
    return RunFolder(run_dir)


def _who() -> str:
    """The running command as the busy message of another command shows it (``focusmap run``)."""
    ctx = _context()
    return f"focusmap {ctx.info_name}" if ctx is not None and ctx.info_name else "focusmap"


@contextlib.contextmanager
def _locked_run(run_dir: Path) -> Iterator[RunFolder]:
    """An existing run folder, locked for this command (another one on it says the folder is busy).

    No waiting: a stage can take minutes, and a command that fails at once says more than one that
    waits a while and fails anyway; the user runs it again when the other has finished.
    """
    run = _open_run(run_dir)
    with run.lock(who=_who()):
        yield run


@contextlib.contextmanager
def _new_run(path: Path, source: Path, kind: str = "bag") -> Iterator[RunFolder]:
    """The run folder ``path`` for ``source``, created or reused, locked for this command."""
    from pipeline.run_folder import RunFolder, check_out_dir, run_folder_lock

    check_out_dir(path.parent)
    with run_folder_lock(path, who=_who()):
        yield RunFolder.create(path, source, kind)


def _print_result(stage: AnyStage, result: StageResult) -> None:
    """The stage's line (name, status, its figures) and, when it ran, its remarks (notes, ...).

    ``note:`` and ``warning:`` lines go to stderr (diagnostics), the stage's line and its other remarks to stdout.
    """
    from rich.console import Console

    console = Console(stderr=False, highlight=False, soft_wrap=True)
    diagnostics = Console(stderr=True, highlight=False, soft_wrap=True)
    status = "up to date" if result.status == "skipped" else f"done in {result.seconds:.1f} s"
    console.print(f"[bold]{result.stage:<20}[/bold] {status:<16} {stage.summary_line(result.summary)}")
    for label, text in stage.remarks(result.summary) if result.status == "done" else []:
        (diagnostics if label in ("note", "warning") else console).print(f"  [yellow]{label}:[/yellow] {text}")
    for text in result.warnings:
        diagnostics.print(f"  [yellow]warning:[/yellow] {text}")


def _run_stages(run: RunFolder, names: list[str], settings: Settings, force: bool) -> list[StageResult]:
    from pipeline.progress import terminal
    from pipeline.run_settings import store_run_settings
    from pipeline.runner import run_stage

    registry = _registry()
    results = []
    for name in names:
        result = run_stage(run, registry, name, settings, force=force, progress=terminal())
        store_run_settings(run.path, settings, [name])  # the folder keeps the settings its stages ran with
        _print_result(registry[name], result)
        results.append(result)
    return results


def _run_on_bag(
    bag: Path, out: Path, name: str | None, stages: list[str], settings: Settings, force: bool
) -> tuple[RunFolder, list[StageResult]]:
    """Check the recording (and ingest's input files when ingest runs), create (or reuse) its run folder and run
    ``stages`` in it, holding its lock."""
    from stages.ingest.bags import detect_format

    detect_format(bag)
    if "ingest" in stages:
        from stages.ingest.config import IngestConfig
        from stages.ingest.stage import check_input_files

        ingest = settings["ingest"]
        assert isinstance(ingest, IngestConfig)
        check_input_files(ingest)  # a tags file that does not read, or a static camera rig: before any folder
    with _new_run(out / _run_name(bag, name), bag) as run:
        results = _run_stages(run, stages, settings, force)
    typer.echo(f"run folder: {run.path}")
    return run, results


def _param_name(option: Option) -> str:
    return option.flag.lstrip("-").replace("-", "_")


def _stage_options(stage: AnyStage) -> list[tuple[str, Option]]:
    """A stage command's options, as ``(section, option)``."""
    return [(stage.name, o) for o in stage.options]


def _overrides(options: Iterable[tuple[str, Option]], given: Mapping[str, object]) -> list[str]:
    """The ``--set`` overrides of the stage options given on the command line (a flag shared by several stages
    sets the key of each)."""
    out = []
    for section, option in options:
        override = option.override(section, given.get(_param_name(option)))
        if override is not None:
            out.append(override)
    return out


def _option_parameter(option: Option) -> inspect.Parameter:
    """A stage option as a typer parameter: a flag for a yes/no option, else a value that defaults to unset."""
    keyword = inspect.Parameter.KEYWORD_ONLY
    if option.kind is bool:
        flag = Annotated[bool, typer.Option(option.flag, help=option.help)]
        return inspect.Parameter(_param_name(option), keyword, default=False, annotation=flag)
    # Annotated[kind | None, ...] built at run time: the option's type is a value here, not a static type
    value = operator.getitem(
        Annotated, (option.kind | None, typer.Option(option.flag, help=option.help, min=option.min))
    )
    return inspect.Parameter(_param_name(option), keyword, default=None, annotation=value)


def _with_options(
    func: Callable[..., None], options: Iterable[tuple[str, Option]], after: str | None = None
) -> Callable[..., None]:
    """``func`` with its ``**options`` replaced by stage ``options`` (``(section, option)``), as typer parameters.

    The options go right after the parameter ``after`` (at the end when None); ``func`` gets them in
    ``**options``, by parameter name. A flag several stages share is one parameter.
    """
    fixed = [
        p.replace(kind=inspect.Parameter.KEYWORD_ONLY)
        for p in inspect.signature(func, eval_str=True).parameters.values()
        if p.kind is not inspect.Parameter.VAR_KEYWORD
    ]
    unique = {_param_name(o): o for _, o in options}
    extra = [_option_parameter(o) for o in unique.values()]
    clash = {p.name for p in fixed} & {p.name for p in extra}
    if clash:
        raise ValueError(f"stage options {sorted(clash)} clash with the parameters of {func.__name__}")
    at = len(fixed) if after is None else [p.name for p in fixed].index(after) + 1
    params = [*fixed[:at], *extra, *fixed[at:]]

    @functools.wraps(func)
    def command(**kwargs: object) -> None:
        func(**kwargs)

    command.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
    command.__annotations__ = {p.name: p.annotation for p in params}
    return command


def _stage_command(stage: AnyStage) -> None:
    """The command of one stage: on a recording for a stage that reads it (ingest), else on a run folder."""
    if stage.needs_source:

        def on_source(
            bag: BagArg,
            out: OutOpt = Path("runs"),
            name: NameOpt = None,
            config: ConfigOpt = None,
            set_: SetOpt = None,
            force: ForceOpt = False,
            reset: ResetOpt = False,
            **options: object,
        ) -> None:
            overrides = _overrides(_stage_options(stage), options)
            settings = _settings(config, set_, overrides, out / _run_name(bag, name), reset, [stage.name])
            _run_on_bag(bag, out, name, [stage.name], settings, force)

        command = _with_options(handled(on_source), _stage_options(stage))
    else:

        def on_run_folder(
            run_dir: RunDirArg,
            config: ConfigOpt = None,
            set_: SetOpt = None,
            force: ForceOpt = False,
            reset: ResetOpt = False,
            **options: object,
        ) -> None:
            overrides = _overrides(_stage_options(stage), options)
            with _locked_run(run_dir) as run:
                settings = _settings(config, set_, overrides, run.path, reset, [stage.name])
                results = _run_stages(run, [stage.name], settings, force)
            _print_headline(results)  # evaluate: its report's path and headline row, as run prints them

        command = _with_options(handled(on_run_folder), _stage_options(stage), after="run_dir")
    help_text = stage.help or f"Run the {stage.command} stage on a run folder."
    command.__doc__ = help_text
    app.command(name=stage.command, help=help_text)(command)


# --- commands --------------------------------------------------------------------------------------
@app.command()
@handled
def info(
    bag: BagArg,
    as_json: Annotated[bool, typer.Option("--json", help="Print the same as JSON.")] = False,
    salvage: SalvageOpt = False,
) -> None:
    """Topics, message types, counts, rates, duration and start time of a recording (counts read from the file)."""
    from stages.ingest.info import bag_info, format_info

    data = bag_info(bag, salvage=salvage)
    typer.echo(json.dumps(data, indent=2) if as_json else format_info(data))


for _stage in _registry():
    _stage_command(_stage)


@app.command(name="import-graph")
@handled
def import_graph_command(
    graph_file: Annotated[
        Path,
        typer.Argument(
            help="A g2o file (2D or 3D, with landmark vertices and edges) or a GTSAM text dataset (.graph).",
            show_default=False,
        ),
    ],
    out: OutOpt = Path("runs"),
    name: NameOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: ForceOpt = False,
    reset: ResetOpt = False,
) -> None:
    """Make a run folder whose graph stage comes from an existing factor graph instead of a bag."""
    from stages.graph.config import GRAPH_SOURCE

    if not graph_file.is_file():
        raise InputError(f"{str(graph_file)!r} does not exist; pass a .g2o or GTSAM .graph file")
    run_dir = out / (graph_file.stem if name is None else _run_name(graph_file, name))
    settings = _settings(config, set_, None, run_dir, reset, ["graph"])
    with _new_run(run_dir, graph_file, GRAPH_SOURCE) as run:
        _run_stages(run, ["graph"], settings, force)
    typer.echo(f"run folder: {run.path}")
    typer.echo(_import_hint(run))


def _import_hint(run: RunFolder) -> str:
    """What can run on an imported graph: landmark selection needs landmarks, a pose graph sparsifies loop closures."""
    entry = run.stage_entry("graph") or {}
    summary = entry.get("summary")
    summary = summary if isinstance(summary, dict) else {}
    by_kind = summary.get("factors_by_kind")
    landmarks = summary.get("landmarks")
    loops = by_kind.get("loop", 0) if isinstance(by_kind, dict) else 0
    landmarks = landmarks if isinstance(landmarks, int) else 0
    loops = loops if isinstance(loops, int) else 0
    if landmarks:
        return (
            f"next: focusmap select-landmarks {run.path} (no laser here: its strategy auto runs mutual information, "
            "or uniform on long trajectories), then select-measurements and optimize"
        )
    if loops:
        return (
            f"a pose graph ({loops} loop closures, no landmarks): keep the K that best localise the poses with "
            f"focusmap select-measurements {run.path} --budget K --set select_measurements.focus=poses, then "
            f"focusmap optimize {run.path}"
        )
    return "a pose graph without loop closures or landmarks: there is nothing to select; export it with focusmap export"


def run_pipeline(
    bag: BagArg,
    out: OutOpt = Path("runs"),
    name: NameOpt = None,
    start_stage: Annotated[
        str | None, typer.Option("--from", help="First stage to run (earlier ones must exist).")
    ] = None,
    until: Annotated[str | None, typer.Option("--until", help="Last stage to run.")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: ForceOpt = False,
    reset: ResetOpt = False,
    strict: StrictOpt = False,
    **options: object,
) -> None:
    """Run the stages in order on a recording, skipping those whose inputs and settings have not changed."""
    registry = _registry()
    stages = [s.name for s in registry.between(start_stage, until)]
    overrides = _overrides(run_options(registry), options) + _strict_overrides(registry, strict)
    settings = _settings(config, set_, overrides, out / _run_name(bag, name), reset, stages)
    run, results = _run_on_bag(bag, out, name, stages, settings, force)
    _print_headline(results)
    typer.echo(f"open it with: focusmap view {run.path}")


def _strict_overrides(registry: Registry, strict: bool) -> list[str]:
    """``--strict``: the ``strict`` setting of every stage that has one."""
    return [f"{s.name}.strict=true" for s in registry if strict and any(o.key == "strict" for o in s.options)]


app.command(name="run")(_with_options(handled(run_pipeline), run_options(_registry())))


def _print_headline(results: list[StageResult]) -> None:
    """What the stages with a report print at the end of a run (evaluate: its report's path and headline row).

    Only for stages this command ran or found current, never an older result left in the folder.
    """
    registry = _registry()
    for result in results:
        stage = registry[result.stage]
        if stage.report_lines is None:
            continue
        for line in stage.report_lines(result.summary):
            typer.echo(line)


@app.command()
@handled
def view(
    run_dir: RunDirArg,
    print_only: Annotated[bool, typer.Option("--print", help="Only print the viewer command.")] = False,
    screenshot: Annotated[
        Path | None,
        typer.Option(
            "--screenshot",
            help="Save a PNG of the recordings from a headless viewer instead of opening a window "
            "(needs a Vulkan driver, e.g. Debian's mesa-vulkan-drivers).",
        ),
    ] = None,
    at: Annotated[
        float, typer.Option("--at", min=0.0, max=1.0, help="With --screenshot: time cursor, as a fraction of the run.")
    ] = 0.5,
    stage: Annotated[
        str | None,
        typer.Option("--stage", help="The stage whose tab to show (default: the last stage that has run)."),
    ] = None,
) -> None:
    """Open every stage recording of a run in the Rerun viewer, as one recording."""
    from pipeline.viewer import display_problem, rerun_executable, viewer_files
    from pipeline.viewer import screenshot as take_screenshot

    run = _open_run(run_dir)
    shown = None if stage is None else _registry()[stage].name
    paths, tab = viewer_files(run.path, _registry().names, shown)
    files = [str(p) for p in paths]
    if screenshot is not None:
        typer.echo(f"picture: {take_screenshot(paths, screenshot, at=at, tab=tab)}")
        return
    cmd = [rerun_executable(), *files]
    if print_only:
        typer.echo(" ".join(cmd))
        return
    no_screen = display_problem()
    if no_screen is not None:
        raise InputError(
            f"cannot open the viewer window: {no_screen}; open the run folder on a machine with a screen "
            "(focusmap view RUN), or save a picture here with --screenshot PNG"
        )
    raise typer.Exit(subprocess.call(cmd))


@app.command("show-config")
@handled
def show_config(
    config: ConfigOpt = None,
    set_: SetOpt = None,
    defaults: Annotated[
        bool, typer.Option("--defaults", help="Print configs/default.yaml: every key with its description.")
    ] = False,
) -> None:
    """Print the resolved settings (defaults, then --config, then --set) as YAML."""
    import yaml

    from pipeline.config import defaults_yaml

    if defaults:
        typer.echo(defaults_yaml(_registry().models()), nl=False)
        return
    settings = _settings(config, set_)
    typer.echo(yaml.safe_dump(settings.dump(), sort_keys=False), nl=False)


from cli import batch as _batch  # noqa: E402
from cli import export as _export  # noqa: E402

_batch.register(app)
_export.register(app)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
