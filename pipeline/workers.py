"""Worker processes that die with the process that started them and leave Ctrl-C to it.

Every process focusmap starts for parallel work (the detect stage's pool, the local workers of
``focusmap batch``) is started through this module, so that:

- a worker never outlives its parent: killed with ``kill -9``, the parent takes its workers with it
  (Linux: the kernel sends them SIGKILL, ``PR_SET_PDEATHSIG``; elsewhere a thread in each worker
  waits on the pipe to its parent and exits when the pipe closes). Without this, the idle workers of
  a process pool wait forever on their task queue, and the multiprocessing resource tracker, whose
  pipe they hold, waits with them;
- a Ctrl-C is handled by the parent alone. A terminal sends SIGINT to the whole foreground process
  group; a worker interrupted in the middle of starting up (importing its libraries) prints a
  ``KeyboardInterrupt`` traceback of dozens of lines. So workers are started with SIGINT held
  (:func:`interrupts_held`, inherited across the ``spawn`` start) and, once running, either ignore
  it (pool workers: the parent cancels their work) or take it where they can handle it
  (:func:`start_worker` with ``interrupts=True``: a batch worker that aborts its stage cleanly).

Processes are started with ``spawn``: fresh interpreters, no locks inherited from the parent's
threads, and no fork server that would outlive a killed parent (``forkserver``).
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from multiprocessing.context import SpawnContext
from typing import Any, ParamSpec, TypeVar

P = ParamSpec("P")
R = TypeVar("R")

_PR_SET_PDEATHSIG = 1
_HELD = {signal.SIGINT}


def spawn_context() -> SpawnContext:
    """The start method of every worker process (``spawn``)."""
    return multiprocessing.get_context("spawn")


@contextlib.contextmanager
def interrupts_held() -> Iterator[None]:
    """Hold SIGINT in the calling thread while processes (or threads) are started inside the block.

    A process started meanwhile begins with SIGINT held, so a Ctrl-C cannot interrupt it before
    :func:`start_worker` decides what it does with one. A Ctrl-C that reaches the caller meanwhile is
    not lost: it is delivered (``KeyboardInterrupt``) when the block ends, after the caller has
    recorded the process it started. Does nothing where signal masks do not exist.
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    # The first process started would start the resource tracker, whose start unblocks SIGINT instead of
    # restoring the mask it found (CPython 3.11): start it before holding.
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    # The mask holds SIGINT in this thread only; the kernel may hand it to another thread of the process, whose
    # C handler then makes the main thread raise KeyboardInterrupt in the middle of starting a process (which then
    # dies on a half-written pipe with a traceback). So, in the main thread, the Python handler is deferred too.
    pending: list[int] = []
    deferred = threading.current_thread() is threading.main_thread()
    handler: Any = signal.signal(signal.SIGINT, lambda signum, frame: pending.append(signum)) if deferred else None
    before = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
    try:
        yield
    finally:
        if deferred:
            signal.signal(signal.SIGINT, handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, before)
        if pending:
            _deliver(handler)


def _deliver(handler: Any) -> None:
    """Give a Ctrl-C that arrived while interrupts were held to the handler that was in place."""
    if handler is signal.default_int_handler:
        raise KeyboardInterrupt
    if callable(handler):
        handler(signal.SIGINT, None)
    elif handler == signal.SIG_DFL:
        os.kill(os.getpid(), signal.SIGINT)


def die_with_parent() -> None:
    """End this process when the process that started it ends (also by ``kill -9``).

    For a process started by :mod:`multiprocessing`; does nothing in any other process. If the parent
    is already gone (it died while this process was starting), this process exits at once.
    """
    parent = multiprocessing.parent_process()
    if parent is None or parent.pid is None:
        return
    if _kernel_kills_orphans():
        if os.getppid() != parent.pid:  # the parent died before the request took effect
            os._exit(1)
        return
    sentinel = parent.sentinel
    threading.Thread(target=_exit_when_closed, args=(sentinel,), name="die-with-parent", daemon=True).start()


def _kernel_kills_orphans() -> bool:
    """Ask Linux to SIGKILL this process when its parent thread ends; whether it agreed."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0)
    except (OSError, AttributeError):
        return False


def _exit_when_closed(sentinel: int) -> None:
    """Wait until the pipe to the parent closes (the parent ended), then end this process at once."""
    multiprocessing.connection.wait([sentinel])
    os._exit(1)


def start_worker(*, interrupts: bool = False) -> None:
    """The first thing a worker process does: die with its parent, then decide about Ctrl-C.

    Args:
        interrupts: take Ctrl-C from here on (``KeyboardInterrupt``, also for one that arrived while
            the worker was starting), for a worker that handles it; otherwise ignore it, and leave it
            to the parent.
    """
    die_with_parent()
    if not interrupts:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _HELD)


def ignore_interrupts() -> None:
    """Ignore Ctrl-C from here on (a worker about to hand its result back)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _init_pool_worker(initializer: Callable[..., object] | None, initargs: tuple[Any, ...]) -> None:
    start_worker()
    if initializer is not None:
        initializer(*initargs)


class WorkerPool(ProcessPoolExecutor):
    """A process pool whose workers die with this process and never see a Ctrl-C.

    The same as ``ProcessPoolExecutor(workers, spawn, initializer, initargs)``; the workers run
    :func:`start_worker` before ``initializer``. A Ctrl-C interrupts the caller only: its
    ``KeyboardInterrupt`` leaves the workers running their current task until ``shutdown``.
    """

    def __init__(
        self,
        max_workers: int,
        initializer: Callable[..., object] | None = None,
        initargs: tuple[Any, ...] = (),
    ) -> None:
        super().__init__(
            max_workers,
            mp_context=spawn_context(),
            initializer=_init_pool_worker,
            initargs=(initializer, initargs),
        )

    def submit(self, fn: Callable[P, R], /, *args: P.args, **kwargs: P.kwargs) -> Future[R]:
        """Submit a task; workers are started here (and by the pool's thread, started here too)."""
        with interrupts_held():
            return super().submit(fn, *args, **kwargs)
