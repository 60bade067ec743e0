"""``focusmap export``: a run's reduced map (or full graph) as g2o, GTSAM, TUM, YAML or CSV."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cli.options import RunDirArg

EXPORT_HELP = (
    "Export the map of a finished run for other tools: optimize's reduced map (default) or the graph stage's full "
    "graph.\n\n"
    "Formats: g2o (the graph at its solution; gtsam.readG2o reads every edge but the priors; metadata in "
    "OUT.json), gtsam (GTSAM's own serialization of the graph and values, lossless), tum (the trajectory, "
    "'t x y z qx qy qz qw'), yaml (the landmarks as tag poses in TagSLAM's layout, with their covariance), csv "
    "(a folder with landmarks.csv and poses.csv). Writes only to --out (default: RUN-NAME_STAGE.<format> in the "
    "current folder), never into the run folder's stages."
)

StageOpt = Annotated[str, typer.Option("--stage", help="optimize (the reduced map) or graph (the full graph).")]
FormatOpt = Annotated[str, typer.Option("--format", "-f", help="g2o, gtsam, tum, yaml or csv.", show_default=False)]
ExportOutOpt = Annotated[
    Path | None,
    typer.Option("--out", "-o", help="File (csv: folder) to write; default RUN-NAME_STAGE.<format> here."),
]


def export(run_dir: RunDirArg, format_: FormatOpt, stage: StageOpt = "optimize", out: ExportOutOpt = None) -> None:
    """Export the map of a finished run."""
    from stages.export.writers import export_run

    for path in export_run(run_dir, stage, format_, out):
        typer.echo(f"wrote {path}")


def register(app: typer.Typer) -> None:
    """Add the ``export`` command to the focusmap application."""
    from cli.app import handled  # cli.app calls register() at its end, after defining handled

    app.command(name="export", help=EXPORT_HELP)(handled(export))
