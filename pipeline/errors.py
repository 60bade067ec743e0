"""Errors a user can fix. The CLI prints them as one line starting with ``error:`` and exits 1."""

from __future__ import annotations


class PipelineError(Exception):
    """A failure the user can act on; its message names the problem and the way out."""


class InputError(PipelineError):
    """The input (a bag, a file, a run folder) is missing, broken or lacks what a stage needs."""


class ConfigError(PipelineError):
    """A setting is unknown, of the wrong type or out of range."""


class StageError(PipelineError):
    """A stage could not produce a meaningful result (no detections, a singular graph, ...)."""
