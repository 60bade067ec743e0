"""Progress bars for long loops (rich, on stderr), drawn only when the caller asks for them.

Whether to draw is decided by the program's entry point (the command line: when stderr is a
:func:`terminal`) and handed down explicitly: to :func:`pipeline.runner.run_stage`, which gives it to the stage's
context, and to :func:`pipeline.batch.run_batch`. Batch workers are never asked to draw.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import TypeVar

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

T = TypeVar("T")

_console = Console(stderr=True)


def terminal() -> bool:
    """Whether stderr, where bars are drawn, is a terminal (the command line draws bars only then)."""
    return _console.is_terminal


def new_progress(show: bool) -> Progress:
    """A rich Progress with the columns every focusmap bar uses (drawing nothing unless ``show``)."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=_console,
        transient=True,
        disable=not show,
    )


def track(items: Iterable[T], description: str, total: int | None = None, *, show: bool) -> Iterator[T]:
    """Iterate over ``items``, with a progress bar when ``show``."""
    if not show:
        yield from items
        return
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with new_progress(show) as progress:
        task = progress.add_task(description, total=total)
        for item in items:
            yield item
            progress.advance(task)
