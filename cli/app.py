"""The focusmap command line: one command per stage, plus info, run, view and show-config.

Every failure the user can fix is one line on stderr starting with ``error:`` and exit code 1
(``--debug`` shows the traceback instead).
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import typer

from cli.options import (
    BagArg,
    CameraOpt,
    ConfigOpt,
    EndOpt,
    ForceOpt,
    NameOpt,
    OutOpt,
    ResetOpt,
    RunDirArg,
    SalvageOpt,
    SetOpt,
    StartOpt,
    StrideOpt,
)
from pipeline.errors import InputError, PipelineError

app = typer.Typer(
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    help="Turn recorded robot runs into small, task-focused AprilTag maps, logged to Rerun.",
)

_DEBUG = {"on": os.environ.get("FOCUSMAP_DEBUG", "") not in ("", "0")}

F = TypeVar("F", bound=Callable[..., Any])


def handled(func: F) -> F:
    """Turn known failures into one ``error:`` line and a non-zero exit."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except PipelineError as err:
            if _DEBUG["on"]:
                raise
            typer.echo(f"error: {err}", err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.echo("error: interrupted; finished stages are kept, the interrupted one left no output", err=True)
            raise typer.Exit(130) from None
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except Exception as err:
            if _DEBUG["on"]:
                raise
            typer.echo(
                f"error: internal error {type(err).__name__}: {err} (re-run with --debug for the traceback "
                "and report it)",
                err=True,
            )
            raise typer.Exit(2) from None

    return wrapper  # type: ignore[return-value]


@app.callback()
def _root(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks instead of one-line errors.")] = False,
) -> None:
    if debug:
        _DEBUG["on"] = True


# --- helpers ---------------------------------------------------------------------------------------
def _registry() -> Any:
    from stages import REGISTRY

    return REGISTRY


def _settings(
    config: Path | None,
    sets: list[str] | None,
    extra: list[str] | None = None,
    run_dir: Path | None = None,
    reset: bool = False,
    running: list[str] | None = None,
) -> Any:
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


def _ingest_overrides(
    start: float | None, end: float | None, stride: int | None, camera: Path | None, salvage: bool
) -> list[str]:
    out = []
    if start is not None:
        out.append(f"ingest.start_s={start}")
    if end is not None:
        out.append(f"ingest.end_s={end}")
    if stride is not None:
        out.append(f"ingest.frame_stride={stride}")
    if camera is not None:
        if not camera.is_file():
            raise InputError(f"camera file {str(camera)!r} not found; pass an existing calibration YAML to --camera")
        out.append(f"ingest.camera_file={json.dumps(str(camera.resolve()))}")
    if salvage:
        out.append("ingest.salvage=true")
    return out


def _run_name(bag: Path, name: str | None) -> str:
    if name:
        return name
    base = bag.resolve()
    return base.name if base.is_dir() else base.stem


def _open_run(run_dir: Path) -> Any:
    from pipeline.run_folder import RunFolder

    if not run_dir.exists():
        raise InputError(f"run folder {str(run_dir)!r} does not exist; create it with 'focusmap ingest BAG --out DIR'")
    return RunFolder(run_dir)


def _print_result(result: Any) -> None:
    from rich.console import Console

    console = Console(stderr=False, highlight=False, soft_wrap=True)
    keys = [
        k
        for k, v in result.summary.items()
        if k not in ("seconds", "topics", "camera", "notes", "read_seconds") and v is not None
    ][:6]
    figures = "  ".join(
        f"{k}={result.summary[k]}" for k in keys if not isinstance(result.summary[k], dict | list | None)
    )
    status = "up to date" if result.status == "skipped" else f"done in {result.seconds:.1f} s"
    console.print(f"[bold]{result.stage:<20}[/bold] {status:<16} {figures}")
    for note in result.summary.get("notes", []) if result.status == "done" else []:
        console.print(f"  [yellow]note:[/yellow] {note}")
    salvaged = result.summary.get("salvaged")
    if salvaged and result.status == "done":
        console.print(f"  [yellow]salvaged:[/yellow] {salvaged}")


def _run_stages(run: Any, names: list[str], settings: Any, force: bool) -> list[Any]:
    from pipeline.run_settings import store_run_settings
    from pipeline.runner import run_stage

    results = []
    for name in names:
        result = run_stage(run, _registry(), name, settings, force=force)
        store_run_settings(run.path, settings, [name])  # the folder keeps the settings its stages ran with
        _print_result(result)
        results.append(result)
    return results


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


@app.command()
@handled
def ingest(
    bag: BagArg,
    out: OutOpt = Path("runs"),
    name: NameOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: ForceOpt = False,
    start: StartOpt = None,
    end: EndOpt = None,
    stride: StrideOpt = None,
    camera: CameraOpt = None,
    salvage: SalvageOpt = False,
    reset: ResetOpt = False,
) -> None:
    """Read frames, odometry, laser scans, the camera model and extrinsics into OUT/<name>/ingest/."""
    overrides = _ingest_overrides(start, end, stride, camera, salvage)
    settings = _settings(config, set_, overrides, out / _run_name(bag, name), reset, ["ingest"])
    _run_on_bag(bag, out, name, ["ingest"], settings, force)


def _run_on_bag(
    bag: Path, out: Path, name: str | None, stages: list[str], settings: Any, force: bool
) -> tuple[Any, list[Any]]:
    """Check the recording, create (or reuse) its run folder and run ``stages`` in it."""
    from pipeline.run_folder import RunFolder
    from stages.ingest.bags import detect_format

    detect_format(bag)
    run = RunFolder.create(out / _run_name(bag, name), bag)
    results = _run_stages(run, stages, settings, force)
    typer.echo(f"run folder: {run.path}")
    return run, results


def _stage_command(stage_name: str, help_text: str) -> None:
    """A command that runs one stage on an existing run folder."""

    @handled
    def command(
        run_dir: RunDirArg,
        config: ConfigOpt = None,
        set_: SetOpt = None,
        force: ForceOpt = False,
        reset: ResetOpt = False,
    ) -> None:
        run = _open_run(run_dir)
        _run_stages(run, [stage_name], _settings(config, set_, None, run.path, reset, [stage_name]), force)

    command.__doc__ = help_text
    app.command(name=stage_name.replace("_", "-"), help=help_text)(command)


_SELECTION_STAGES = ("select_landmarks", "select_measurements")
for _stage in list(_registry())[1:]:
    if _stage.name not in _SELECTION_STAGES:
        _stage_command(_stage.name, _stage.help or f"Run the {_stage.command} stage on a run folder.")


def _selection_overrides(stage: str, strategy: str | None, budget: int | None, focus: str | None = None) -> list[str]:
    out = []
    if strategy is not None:
        out.append(f"{stage}.strategy={strategy}")
    if budget is not None:
        out.append(f"{stage}.budget={budget}")
    if focus is not None:
        out.append(f"{stage}.focus={focus}")
    return out


StrategyOpt = Annotated[
    str | None, typer.Option("--strategy", help="Selection strategy (see configs/default.yaml for the choices).")
]
BudgetOpt = Annotated[int | None, typer.Option("--budget", help="How many to keep.", min=0)]


@app.command(name="select-landmarks")
@handled
def select_landmarks_command(
    run_dir: RunDirArg,
    strategy: StrategyOpt = None,
    budget: BudgetOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: ForceOpt = False,
    reset: ResetOpt = False,
) -> None:
    """Stage one: keep the --budget (alpha) landmarks that matter most (collision | mutual-information | leverage |
    uniform | random | all)."""
    run = _open_run(run_dir)
    extra = _selection_overrides("select_landmarks", strategy, budget)
    _run_stages(run, ["select_landmarks"], _settings(config, set_, extra, run.path, reset, ["select_landmarks"]), force)


@app.command(name="select-measurements")
@handled
def select_measurements_command(
    run_dir: RunDirArg,
    strategy: StrategyOpt = None,
    budget: BudgetOpt = None,
    focus: Annotated[
        str | None,
        typer.Option("--focus", help="'selected': the focused landmarks of stage one; 'all': every landmark."),
    ] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: ForceOpt = False,
    reset: ResetOpt = False,
) -> None:
    """Stage two: keep the --budget (K) tag measurements that best localise the focused landmarks (information |
    leverage | uniform | random | all)."""
    run = _open_run(run_dir)
    extra = _selection_overrides("select_measurements", strategy, budget, focus)
    _run_stages(
        run, ["select_measurements"], _settings(config, set_, extra, run.path, reset, ["select_measurements"]), force
    )


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
    from stages.graph.imports import import_run

    if not graph_file.is_file():
        raise InputError(f"{str(graph_file)!r} does not exist; pass a .g2o or GTSAM .graph file")
    settings = _settings(config, set_, None, out / (name or graph_file.stem), reset, ["graph"])
    run = import_run(graph_file, out, name)
    _run_stages(run, ["graph"], settings, force)
    typer.echo(f"run folder: {run.path}")
    typer.echo("the stages after graph that need no camera or laser run on it, e.g. focusmap select-landmarks")


@app.command(name="run")
@handled
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
    start: StartOpt = None,
    end: EndOpt = None,
    stride: StrideOpt = None,
    camera: CameraOpt = None,
    salvage: SalvageOpt = False,
    reset: ResetOpt = False,
) -> None:
    """Run the stages in order on a recording, skipping those whose inputs and settings have not changed."""
    stages = [s.name for s in _registry().between(start_stage, until)]
    overrides = _ingest_overrides(start, end, stride, camera, salvage)
    settings = _settings(config, set_, overrides, out / _run_name(bag, name), reset, stages)
    run, results = _run_on_bag(bag, out, name, stages, settings, force)
    if any(r.stage == "evaluate" for r in results):  # done or current now: not an older evaluate's
        _print_headline(run)
    typer.echo(f"open it with: focusmap view {run.path}")


def _print_headline(run: Any) -> None:
    """The evaluation report's path and its headline row (focus, info), when evaluate has run."""
    entry = run.stage_entry("evaluate")
    if not entry:
        return
    summary = entry.get("summary", {})
    head = summary.get("headline") or {}
    if summary.get("report"):
        typer.echo(f"report: {summary['report']}")
    if head:
        typer.echo(
            f"headline ({head.get('case')}): focused entropy {head.get('focused_entropy', float('nan')):.1f} nats, "
            f"focused error {100 * head.get('focused_error_m', float('nan')):.1f} cm, "
            f"max P(collision) {head.get('max_collision_probability', float('nan')):.2g}, "
            f"collision rate {head.get('collision_rate', float('nan')):.3f} "
            f"[{head.get('collision_ci_low', float('nan')):.3f}, {head.get('collision_ci_high', float('nan')):.3f}]"
        )


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
) -> None:
    """Open every stage recording of a run in the Rerun viewer, as one recording."""
    from pipeline.viewer import rerun_executable
    from pipeline.viewer import screenshot as take_screenshot

    run = _open_run(run_dir)
    files = sorted(str(p) for p in run.path.glob("*.rrd"))
    if not files:
        raise InputError(f"no .rrd recordings in {str(run.path)!r}; run a stage first")
    if (run.path / "focusmap.rbl").is_file():
        files.append(str(run.path / "focusmap.rbl"))
    if screenshot is not None:
        typer.echo(f"picture: {take_screenshot([Path(f) for f in files], screenshot, at=at)}")
        return
    cmd = [rerun_executable(), *files]
    if print_only:
        typer.echo(" ".join(cmd))
        return
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

_batch.register(app)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
