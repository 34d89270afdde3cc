"""Cancellation: Ctrl-C and SIGTERM reach every thread, and never land inside a commit.

A signal handler in Python runs only in the main thread, between bytecodes: a main thread inside
a long C call (a filter, the compiled kernel), or waiting for pool threads that are, would not see
it for minutes, and a ``KeyboardInterrupt`` raised inside a library destructor is printed and
dropped ("Exception ignored in ..."), so the run goes on. Hence:

* The handler first sets a process-wide flag (:func:`requested`), which the thread pool
  (:func:`segsnake.parallel.thread_map`) checks between work pieces and :func:`check` turns into a
  ``KeyboardInterrupt`` at the places where a run must not go on (before a commit, at the end of
  a command): a swallowed interrupt is raised again there.
* Inside :func:`deferred` (the commit of the outputs) the handler only records the signal; it is
  raised when the block ends, so the commit is all or nothing.
* A watchdog thread ends the process (exit 130) when the main thread has not finished within
  :data:`GRACE_S` of the first signal (it is stuck in C code), and a second signal ends it at
  once: never a traceback, never minutes. A process that ends this way first removes what
  :func:`cleanup_on_exit` registered (its staging directory, an output directory it created and
  left empty: :mod:`segsnake.outdir`).
* A signal that lands in an import is not raised there (it can crash the interpreter): it is
  left to the next check or the watchdog, unless nothing is registered to undo yet (the
  start-up's imports), when the process ends at once.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from typing import Any, Callable, Iterator

__all__ = ["GRACE_S", "EXIT_INTERRUPTED", "requested", "check", "request", "reset", "install",
           "deferred", "exit_now", "cleanup_on_exit"]

# Time the main thread gets to unwind (cleanup of staging files, the "interrupted" line) after the
# first signal before the watchdog ends the process: well under the promised second.
GRACE_S = 0.6
EXIT_INTERRUPTED = 130

_flag = threading.Event()
_state_lock = threading.RLock()
_deferring = 0
_pending = False
_signals = 0
_on_exit: Callable[[], None] | None = None
_cleanups: list[Callable[[], None]] = []


def requested() -> bool:
    """True once SIGINT or SIGTERM arrived (or :func:`request` was called)."""
    return _flag.is_set()


def check() -> None:
    """Raise ``KeyboardInterrupt`` if cancellation was requested (an interrupt that a destructor
    swallowed, or one that arrived in another thread's C call, is raised here)."""
    if _flag.is_set():
        raise KeyboardInterrupt


def request() -> None:
    """Ask every loop that checks the flag to stop (what the signal handler does first)."""
    _flag.set()


def reset() -> None:
    """Forget an earlier request (a new command run in the same process, tests)."""
    global _pending, _signals
    with _state_lock:
        _flag.clear()
        _pending = False
        _signals = 0


def exit_now(code: int = EXIT_INTERRUPTED) -> None:
    """Flush stdout/stderr and end the process at once with ``code``, without waiting for pool
    threads still inside a C call (``sys.exit`` would join them)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


def _watchdog(grace: float) -> None:
    time.sleep(grace)
    # Never end the process inside a commit: wait for it to finish (it takes milliseconds).
    while True:
        with _state_lock:
            if _deferring == 0:
                break
        time.sleep(0.01)
    _forced_exit()


def _forced_exit() -> None:
    """End the process now (the watchdog, a second signal; neither inside a commit): what
    :func:`cleanup_on_exit` registered is undone first, then the ``on_exit`` report."""
    for cleanup in reversed(list(_cleanups)):
        with contextlib.suppress(Exception):
            cleanup()
    if _on_exit is not None:
        with contextlib.suppress(Exception):
            _on_exit()
    exit_now(EXIT_INTERRUPTED)


@contextlib.contextmanager
def cleanup_on_exit(cleanup: Callable[[], None]) -> Iterator[None]:
    """Within the block, ``cleanup`` runs if the process is ended by the watchdog or a second
    signal (which skip the ``finally`` blocks): the block's own ``finally`` covers every other
    way out. (Measured: an interrupt during the start-up's imports, which the handler leaves to
    the watchdog, left an empty output directory in 2 of 30 runs.)"""
    _cleanups.append(cleanup)
    try:
        yield
    finally:
        with contextlib.suppress(ValueError):
            _cleanups.remove(cleanup)


def _in_import(frame: Any) -> bool:
    """True when ``frame`` (the main thread's, where the handler runs) is inside an import."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _handler(signum: int, frame: Any) -> None:
    global _pending, _signals
    _flag.set()
    with _state_lock:
        _signals += 1
        first = _signals == 1
        if _deferring:
            _pending = True  # raised by deferred() when the commit is complete
            if first and _grace is not None:
                threading.Thread(target=_watchdog, args=(_grace,), daemon=True,
                                 name="segsnake-cancel-watchdog").start()
            return
    if first:
        if _grace is not None:
            threading.Thread(target=_watchdog, args=(_grace,), daemon=True,
                             name="segsnake-cancel-watchdog").start()
        if _in_import(frame):
            # An exception inside the import of a compiled module (pyvista loads VTK's lazily)
            # can crash the interpreter (measured: SIGSEGV in 2 of 25 Ctrl-C): leave it to the
            # next check() (the thread pool checks before each piece) or the watchdog. Unless
            # the run has nothing of its own to undo yet (its start-up's imports): it ends now.
            # (The watchdog can wait for a module's initialization, which holds the GIL: a batch
            # signalled 0.2-0.7 s after its start took up to 1.6 s to end, measured.)
            if _grace is not None and not _cleanups:
                _forced_exit()
            return
        raise KeyboardInterrupt
    # A second signal: the user does not want to wait for the main thread's cleanup.
    _forced_exit()


_grace: float | None = None


def install(*, grace: float | None = GRACE_S, on_exit: Callable[[], None] | None = None) -> None:
    """Handle SIGINT and SIGTERM as described above (main thread only; a no-op elsewhere).

    Parameters
    ----------
    grace : float or None
        Seconds after the first signal before the watchdog ends the process (None: no watchdog,
        for a process that must return rather than exit, such as a test calling ``main``).
    on_exit : callable, optional
        Called once before the process is ended by the watchdog or a second signal (prints the
        "interrupted" line when the main thread has not).
    """
    global _grace, _on_exit
    if threading.current_thread() is not threading.main_thread():
        return
    _grace, _on_exit = grace, on_exit
    reset()
    signal.signal(signal.SIGINT, _handler)
    signal.signal(signal.SIGTERM, _handler)
    sys.unraisablehook = _unraisable


def _unraisable(unraisable: Any) -> None:
    """An interrupt the handler raised inside a destructor is not printed ("Exception ignored
    in ...", a traceback on stderr): the flag is set, and :func:`check` raises it again where the
    run stops. Anything else goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt) and _flag.is_set():
        return
    sys.__unraisablehook__(unraisable)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """A block that a signal does not interrupt: a signal arriving inside it is recorded and
    raised as ``KeyboardInterrupt`` when the block ends (and when it was requested before the
    block, the block does not start)."""
    global _deferring, _pending
    check()
    with _state_lock:
        _deferring += 1
    try:
        yield
    finally:
        with _state_lock:
            _deferring -= 1
            raise_now = _deferring == 0 and _pending
            if raise_now:
                _pending = False
    if raise_now:
        raise KeyboardInterrupt
