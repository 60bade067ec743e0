"""Errors a user can fix. The CLI prints them as one line starting with ``error:`` and exits 1."""

from __future__ import annotations

import errno
import os


class PipelineError(Exception):
    """A failure the user can act on; its message names the problem and the way out."""


class InputError(PipelineError):
    """The input (a bag, a file, a run folder) is missing, broken or lacks what a stage needs."""


class ConfigError(PipelineError):
    """A setting is unknown, of the wrong type or out of range."""


class StageError(PipelineError):
    """A stage could not produce a meaningful result (no detections, a singular graph, ...)."""


class WriteError(PipelineError):
    """A file could not be written: the disk is full, read-only, over its quota or failing."""


# errno values that mean "this file system will not take the write", not a bug of the program
_FULL = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
_READ_ONLY = frozenset({errno.EROFS})
_AMBIGUOUS = frozenset({errno.EACCES, errno.EPERM, errno.EIO})  # reads fail so too


def write_error(err: BaseException, folder: str | os.PathLike[str]) -> WriteError | None:
    """The one-line error for a failed write into ``folder``, or None when ``err`` is not one.

    An error naming no file (a write to an open file carries no name) is put on ``folder``.
    Permission and I/O errors count only for files inside ``folder``: elsewhere they come from reading.
    """
    if not isinstance(err, OSError) or err.errno is None:
        return None
    code = err.errno
    if code not in _FULL | _READ_ONLY | _AMBIGUOUS:
        return None
    named = err.filename if isinstance(err.filename, str | os.PathLike) else None
    inside = named is None or _is_inside(named, folder)
    if code in _AMBIGUOUS and not inside:
        return None
    where = os.fspath(named if named is not None else folder)
    why = os.strerror(code)  # not the library's wording (pyarrow wraps it in its own)
    if code in _FULL:
        way = "free space on that disk or choose another --out"
    elif code == errno.EIO:
        way = "check that disk or choose another --out"
    else:
        way = "make it writable or choose another --out"
    return WriteError(f"cannot write {where!r} ({why}); {way}")


def _is_inside(path: str | os.PathLike[str], folder: str | os.PathLike[str]) -> bool:
    try:
        return os.path.commonpath([os.path.abspath(path), os.path.abspath(folder)]) == os.path.abspath(folder)
    except ValueError:
        return False


ERROR_LINE_MAX = 1000
"""Characters of an ``error:`` line; a longer message (a library's text quoting a whole message definition) is cut."""


def one_line(message: str, limit: int = ERROR_LINE_MAX) -> str:
    """``message`` on one line (runs of whitespace and line breaks made one space), cut to ``limit`` characters."""
    text = " ".join(message.split())
    return text if len(text) <= limit else text[: limit - 1].rstrip() + "…"
