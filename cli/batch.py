"""``focusmap batch``: the pipeline over many recordings, in local worker processes or on a Dask cluster."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from cli.options import ConfigOpt, ForceOpt, SetOpt, StrictOpt

REGISTRY_SPEC = "stages:REGISTRY"
PREFLIGHT_SPEC = "stages.ingest.bags:detect_format"

RecordingsArg = Annotated[
    list[str] | None,
    typer.Argument(
        help="Recordings (ROS 1 .bag, ROS 2 bag folder, .db3, .mcap) or glob patterns such as 'bags/**/*.bag' "
        "(quote a pattern to let focusmap expand it); optional with --file.",
        show_default=False,
    ),
]
BatchFileOpt = Annotated[
    Path | None,
    typer.Option(
        "--file",
        help="Batch file (.yaml or .csv) listing recordings, each with its run folder name and its own settings "
        "(recording, name, config, camera, start, end, stride, salvage, SECTION.KEY): see docs/batch.md.",
    ),
]
BatchOutOpt = Annotated[
    Path,
    typer.Option(
        "--out",
        "-o",
        help="Folder that holds one run folder per recording and batch_summary.parquet (created if absent). "
        "With --scheduler, the Dask workers write here: it must be storage every worker shares, at the same path.",
    ),
]
FromOpt = Annotated[
    str | None, typer.Option("--from", help="First stage to run (earlier ones must exist in every run folder).")
]
UntilOpt = Annotated[str | None, typer.Option("--until", help="Last stage to run (default: every stage).")]
WorkersOpt = Annotated[
    int | None,
    typer.Option("--workers", "-j", min=1, help="Recordings processed at once on this machine; default: CPU cores."),
]
SchedulerOpt = Annotated[
    str | None,
    typer.Option(
        "--scheduler",
        help="Address of a running dask.distributed scheduler (tcp://host:8786): run the recordings on its workers "
        "instead of locally. Recordings and --out must be on storage the workers share, at the same paths.",
    ),
]


BATCH_HELP = (
    "Run the pipeline over many recordings: one run folder each, a summary table, resumable.\n\n"
    "Each recording gets the run folder 'focusmap run' would give it (OUT/<file name without extension>, or the "
    "folder's name for a ROS 2 bag); recordings that share a name get the shortest end of their paths that tells "
    "them apart (a/run_bag and b/run_bag: OUT/a_run_bag and OUT/b_run_bag), the same every time the batch runs. "
    "A batch file (--file) names each recording's run folder and gives it its own settings (tag size, camera "
    "file, topics) on top of --config, --set and the options below; it is checked whole before anything runs. "
    "The settings a run folder keeps from earlier commands are not used: a batch's settings are its own. "
    "Stages already up to date are skipped, so running the same batch again finishes what an interrupted one left "
    "and skips what is complete. A broken recording is listed as failed with its reason and the others go on; "
    "the exit code is 1 if any failed. The table is also written to OUT/batch_summary.parquet.\n\n"
    "Locally, --workers recordings run at once, each in its own process. With --scheduler they run on an existing "
    "dask.distributed cluster, whose workers write the run folders: recordings and --out must be on storage every "
    "worker shares, at the same paths."
)


def batch(
    recordings: RecordingsArg = None,
    batch_file: BatchFileOpt = None,
    out: BatchOutOpt = Path("runs"),
    start_stage: FromOpt = None,
    until: UntilOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    workers: WorkersOpt = None,
    scheduler: SchedulerOpt = None,
    force: ForceOpt = False,
    strict: StrictOpt = False,
    **options: object,
) -> None:
    """Run the pipeline over many recordings: one run folder each, a summary table, resumable."""
    from rich.console import Console

    from cli.app import _overrides, _strict_overrides
    from pipeline.batch import (
        collect_recordings,
        plan_tasks,
        print_summary,
        run_batch,
        summary_table,
        write_errors,
        write_summary,
    )
    from pipeline.batch_file import BatchEntry, read_batch_file
    from pipeline.config import load_settings
    from pipeline.errors import InputError
    from pipeline.progress import terminal
    from pipeline.stage import run_options
    from stages import REGISTRY

    if not recordings and batch_file is None:
        raise InputError("no recordings given; pass bag files, ROS 2 bag folders, glob patterns or --file FILE")
    overrides = _overrides(run_options(REGISTRY), options) + _strict_overrides(REGISTRY, strict)
    settings = load_settings(REGISTRY.models(), config, [*(set_ or []), *overrides])
    stages = [s.name for s in REGISTRY.between(start_stage, until)]
    entries: list[BatchEntry] = [BatchEntry(r) for r in collect_recordings(recordings)] if recordings else []
    problems: list[str] = []
    if batch_file is not None:
        listed, problems = read_batch_file(batch_file, REGISTRY, settings)
        entries += listed
    tasks = plan_tasks(
        entries,
        out,
        stages,
        settings,
        force=force,
        registry=REGISTRY_SPEC,
        preflight=PREFLIGHT_SPEC,
        problems=problems,
    )
    where = (
        f"on the Dask cluster at {scheduler}" if scheduler else f"with {min(workers or _cores(), len(tasks))} workers"
    )
    console = Console(highlight=False, soft_wrap=False, width=None if sys.stdout.isatty() else 200)
    console.print(f"batch: {len(tasks)} recordings, stages {', '.join(stages)}, {where}")
    result = run_batch(tasks, workers=workers, scheduler=scheduler, progress=terminal())
    table = summary_table(result.outcomes, stages, REGISTRY)
    path = write_summary(table, out.expanduser().resolve())
    write_errors(result.outcomes, out.expanduser().resolve())
    print_summary(table, REGISTRY, console)
    console.print(f"summary: {path}")
    if result.interrupted:
        typer.echo("error: interrupted; finished stages are kept, run the same batch again to finish", err=True)
        raise typer.Exit(130)
    if result.failed:
        typer.echo(f"error: {result.failed} of {len(tasks)} recordings failed (see the table above)", err=True)
        raise typer.Exit(1)


def _cores() -> int:
    import os

    return os.cpu_count() or 1


def register(app: typer.Typer) -> None:
    """Add the ``batch`` command to the focusmap application."""
    # cli.app calls register() at its end, after defining these; batch takes run's input options (--camera, ...)
    from cli.app import _registry, _with_options, handled
    from pipeline.stage import run_options

    app.command(name="batch", help=BATCH_HELP)(_with_options(handled(batch), run_options(_registry())))
