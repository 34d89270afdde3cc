"""Threads for the heavy array work (lookup sampling, separable filters).

numpy's gathers and contractions and scipy.ndimage's filters release the GIL, so independent
blocks of one computation run in parallel in threads (measured on 2 cores: 1.6x on lookup
sampling, 1.9x on six Gaussian passes). Every result is computed block by block exactly as in
one thread, so the number of threads never changes a result.

The number of threads is, in order: :func:`set_threads`, the environment variable
``SEGSNAKE_NUM_THREADS``, or the CPUs this process may run on (as ITK does). ``segsnake batch``
divides the CPUs between its worker processes.

The BLAS library numpy and scipy call (the optimizer's Cholesky solves, the metric's
contractions) keeps its own threads to one while a segmentation or any ``segsnake`` command
runs (:func:`one_blas_thread`): its threads split a product differently on another number of
cores, which changed results, and they competed with these.
"""

from __future__ import annotations

import functools
import os
import threading
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Callable, Iterable, Sequence, TypeVar

import numpy as np

from segsnake import cancel
from segsnake.errors import ConfigError

__all__ = ["threads", "set_threads", "thread_map", "pieces", "slabs", "gaussian_filter",
           "spline_filter", "one_blas_thread", "ENV"]

ENV = "SEGSNAKE_NUM_THREADS"

T = TypeVar("T")
R = TypeVar("R")

_lock = threading.Lock()
_requested: int | None = None
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
# one_blas_thread's limit, shared by the calls running at once
_blas_lock = threading.Lock()
_blas_depth = 0
_blas_limits = None


def _available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not on Linux
        return os.cpu_count() or 1


def threads() -> int:
    """The number of threads segsnake uses (at least 1)."""
    if _requested is not None:
        return _requested
    value = os.environ.get(ENV, "").strip()
    if value:
        try:
            n = int(value)
        except ValueError:
            n = 0
        if n < 1:
            raise ConfigError(f"environment variable {ENV} must be a positive integer, "
                              f"got {value!r}")
        return n
    return _available_cpus()


def set_threads(n: int | None) -> None:
    """Use ``n`` threads from now on (``None``: back to the environment / CPU default)."""
    global _requested
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"the number of threads must be a positive integer, got {n!r}")
    _requested = n


def one_blas_thread(fn: Callable[..., R]) -> Callable[..., R]:
    """``fn`` with the BLAS libraries' threads (numpy's and scipy's) limited to one while it
    runs (threadpoolctl), and the limits they had before restored after.

    OpenBLAS splits a product or a triangular solve between as many threads as the machine
    has cores, and the split changes its rounding: the Colin27 brain's energy read -1112044.45
    with two BLAS threads and -1112105.47 with one, its mask 1 855 352 and 1 855 077 voxels.
    A result then depended on the machine's core count, which :func:`thread_map`'s blocks
    never let it do. Its threads also competed with these for the cores: the brain without a
    click took 21.7 s with two BLAS threads and 16.7 s with one (2 cores, medians of three
    alternating runs; docs/benchmarks.md, session 27). The matrices are small (at most a few
    thousand rows: a finer grid's metric), so one thread loses little.

    The limit is the process's: calls that overlap in threads share it, set by the first to
    begin and restored by the last to end (threadpoolctl's own limits do not nest across
    threads); BLAS called from other threads meanwhile runs in one thread too.
    """
    @functools.wraps(fn)
    def limited(*args, **kwargs):
        global _blas_depth, _blas_limits
        with _blas_lock:
            if _blas_depth == 0:
                import scipy.linalg  # noqa: F401  (its BLAS, loaded before the limit is set)
                from threadpoolctl import threadpool_limits

                _blas_limits = threadpool_limits(limits=1, user_api="blas")
            _blas_depth += 1
        try:
            return fn(*args, **kwargs)
        finally:
            with _blas_lock:
                _blas_depth -= 1
                if _blas_depth == 0:
                    _blas_limits.restore_original_limits()
                    _blas_limits = None

    return limited


def thread_map(fn: Callable[[T], R], items: Iterable[T], *, join: bool = False) -> list[R]:
    """``[fn(x) for x in items]``, in up to :func:`threads` threads, in order.

    Cancellation (:mod:`segsnake.cancel`) is checked before each item, so a Ctrl-C or SIGTERM
    stops the remaining pieces of every thread. Called from the main thread, the work always runs
    in the pool (with one thread too) while the main thread waits in an interruptible wait: a
    signal then reaches it at once even while a piece is inside a long C call. Called from a pool
    thread (nested calls would wait on their own pool) or another thread, with one thread or one
    item, it runs in the calling thread.

    ``join``: for short pieces (a signal waits for the one running), the calling thread takes
    items too, with ``threads() - 1`` pool threads beside it (a single item it runs alone: a
    hand-off to the pool costs about what the lookup's kernel takes for a thousand points,
    docs/benchmarks.md session 22): it starts at once, while a pool
    thread idle since the last call wakes late (measured on a 2-core VM, lookup sampling of
    62 000 points: 41 ns a point in the pool called back to back, 55-62 ns after 5-10 ms of
    other work in between; with the caller taking blocks 36 and 46-56 ns; docs/benchmarks.md,
    session 23).
    """
    items = list(items)
    n = threads()
    current = threading.current_thread()
    if current.name.startswith("segsnake-worker") or (
            min(n, len(items)) <= 1 and current is not threading.main_thread()):
        out = []
        for x in items:
            cancel.check()
            out.append(fn(x))
        return out
    if not items:
        return []
    if join and len(items) == 1:
        cancel.check()
        return [fn(items[0])]
    if join and n > 1:
        return _joined_map(fn, items, n, min(n, len(items)) - 1)

    def run(x: T) -> R:
        cancel.check()
        return fn(x)

    futures = [_executor(n).submit(run, x) for x in items]
    try:
        return [f.result() for f in futures]
    finally:
        for f in futures:  # after an error or an interrupt: the pieces not started never start
            f.cancel()


def _joined_map(fn: Callable[[T], R], items: list[T], n: int, helpers: int) -> list[R]:
    # The caller and ``helpers`` threads of the pool of ``n`` take the items in order, one index
    # at a time; each result lands in its own slot.
    out: list = [None] * len(items)
    lock = threading.Lock()
    taken = 0
    failed = threading.Event()  # (after an error anywhere the others take no new item)

    def drain() -> None:
        nonlocal taken
        try:
            while not failed.is_set():
                with lock:
                    i, taken = taken, taken + 1
                if i >= len(items):
                    return
                cancel.check()
                out[i] = fn(items[i])
        except BaseException:
            failed.set()
            raise

    futures = [_executor(n).submit(drain) for _ in range(helpers)]
    try:
        drain()
    finally:
        # A helper that has not started by now finds nothing left: it is not waited for (its
        # thread may still be waking). One that has started is, and its error is raised.
        for f in futures:
            f.cancel()
        started = [f for f in futures if not f.cancelled()]
        if started:
            wait(started)
    for f in started:
        f.result()
    return out


def _forget_pool() -> None:
    # A forked child has the pool object but not its threads.
    global _pool, _pool_size, _lock
    _pool, _pool_size, _lock = None, 0, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _executor(size: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _lock:
        if _pool is None or _pool_size != size:
            # The old pool is not shut down: another thread may still be submitting to it (its
            # idle threads end when it is garbage collected).
            _pool = ThreadPoolExecutor(max_workers=size, thread_name_prefix="segsnake-worker")
            _pool_size = size
        return _pool


def pieces(n: int, max_size: int) -> list[slice]:
    """``range(n)`` cut into the fewest slices of equal sizes (within one) of at most
    ``max_size`` items (one empty slice for ``n = 0``)."""
    count = max(-(-n // max(int(max_size), 1)), 1)
    bounds = np.linspace(0, n, count + 1).astype(int)
    return [slice(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:])]


def slabs(shape: Sequence[int], axis: int,
          max_voxels: int | None = None) -> list[tuple[slice, ...]]:
    """Index tuples cutting an array of ``shape`` into :func:`threads` slabs, across the longest
    axis other than ``axis`` (so a 1D pass along ``axis`` runs on each slab independently);
    with ``max_voxels``, into more slabs where needed so that none holds more voxels than that
    (at least one plane each)."""
    others = [a for a in range(len(shape)) if a != axis]
    if not others:
        return [tuple(slice(None) for _ in shape)]
    cut = max(others, key=lambda a: shape[a])
    planes = -(-shape[cut] // threads())
    if max_voxels is not None:
        plane = int(np.prod(shape)) // max(shape[cut], 1)
        planes = min(planes, max(max_voxels // max(plane, 1), 1))
    return [tuple(sl if a == cut else slice(None) for a in range(len(shape)))
            for sl in pieces(shape[cut], planes)]


def _along_axes(out: np.ndarray, axes: Sequence[int],
                pass_1d: Callable[[np.ndarray, int, np.ndarray], None]) -> np.ndarray:
    for axis in axes:
        thread_map(lambda sl, axis=axis: pass_1d(out[sl], axis, out[sl]), slabs(out.shape, axis))
    return out


def gaussian_filter(array: np.ndarray, sigma: Sequence[float], *, mode: str = "reflect",
                    truncate: float = 4.0, dtype=np.float32, copy: bool = True) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter`` (per-axis ``sigma`` in voxels), in threads, as ``dtype``.

    Each axis' 1D pass runs on slabs cut across another axis, in place: the same numbers as one
    ``gaussian_filter`` call on a ``dtype`` copy (axes with ``sigma`` about 0 are skipped, as
    scipy does). ``copy=False`` filters ``array`` itself when it is a C-ordered ``dtype`` array.
    """
    from scipy import ndimage  # here: `segsnake batch`'s parent imports this module, never filters

    def pass_1d(src: np.ndarray, axis: int, dst: np.ndarray) -> None:
        ndimage.gaussian_filter1d(src, sigma[axis], axis=axis, mode=mode, truncate=truncate,
                                  output=dst)

    out = np.array(array, dtype=dtype, order="C", copy=True if copy else None)
    return _along_axes(out, [a for a in range(out.ndim) if sigma[a] > 1e-15], pass_1d)


def spline_filter(array: np.ndarray, *, dtype=np.float64, out: np.ndarray | None = None) -> np.ndarray:
    """Cubic B-spline coefficients (``scipy.ndimage.spline_filter``, mirror boundary), in
    threads, as ``dtype`` (an axis of one sample is left as it is: it cannot be mirrored).

    ``out``: an array (or a view) of ``array``'s shape to write the coefficients into.
    """
    from scipy import ndimage

    def pass_1d(src: np.ndarray, axis: int, dst: np.ndarray) -> None:
        ndimage.spline_filter1d(src, order=3, axis=axis, mode="mirror", output=dst)

    if out is None:
        out = np.array(array, dtype=dtype, order="C")
    else:
        out[...] = array
    return _along_axes(out, [a for a in range(out.ndim) if out.shape[a] > 1], pass_1d)
