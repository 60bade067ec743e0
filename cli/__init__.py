"""The focusmap command line (typer)."""
