"""Options shared by the commands, as ``Annotated`` aliases."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

RunDirArg = Annotated[
    Path,
    typer.Argument(
        help="A run folder made by 'focusmap ingest' or 'focusmap run' (OUT/<run name>).", show_default=False
    ),
]
BagArg = Annotated[
    Path,
    typer.Argument(
        help="The recording: a ROS 1 .bag, a ROS 2 bag folder (SQLite or MCAP storage), a .db3 or a .mcap file.",
        show_default=False,
    ),
]
OutOpt = Annotated[Path, typer.Option("--out", "-o", help="Folder that holds the run folders (created if absent).")]
NameOpt = Annotated[
    str | None, typer.Option("--name", help="Run folder name; default: the recording's file name without extension.")
]
ConfigOpt = Annotated[
    Path | None, typer.Option("--config", "-c", help="YAML settings file (sections as in configs/default.yaml).")
]
SetOpt = Annotated[
    list[str] | None,
    typer.Option(
        "--set", "-s", help="Override one setting: SECTION.KEY=VALUE (repeatable), e.g. detect.tag_size_m=0.16."
    ),
]
ForceOpt = Annotated[bool, typer.Option("--force", "-f", help="Re-run even if the results are up to date.")]
SalvageOpt = Annotated[
    bool, typer.Option("--salvage", help="Read a damaged bag up to the damage and say how much was recovered.")
]
ResetOpt = Annotated[
    bool,
    typer.Option(
        "--reset-settings",
        help="Start from the default settings instead of those the run folder keeps from earlier commands.",
    ),
]
StrictOpt = Annotated[
    bool,
    typer.Option(
        "--strict",
        help="Stop with an error when a health check of graph or optimize fails (graph.strict, optimize.strict).",
    ),
]
