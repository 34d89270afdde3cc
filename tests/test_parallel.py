"""Threads never change a result: thread_map, the slab filters and the lookup's blocks."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from conftest import blas_threads
from scipy import ndimage

from segsnake import cancel, parallel
from segsnake.errors import ConfigError
from segsnake.features import gaussian_derivatives
from segsnake.lookup import Lookup


@pytest.fixture
def two_threads():
    parallel.set_threads(2)
    yield
    parallel.set_threads(None)


def test_thread_map_keeps_order_and_uses_the_pool(two_threads):
    names = parallel.thread_map(lambda i: (i, threading.current_thread().name), range(7))
    assert [i for i, _ in names] == list(range(7))
    assert all(n.startswith("segsnake-worker") for _, n in names)
    # A nested call runs in the pool thread that made it (it would otherwise wait on itself).
    nested = parallel.thread_map(lambda i: parallel.thread_map(lambda j: i * j, range(3)), [1, 2])
    assert nested == [[0, 1, 2], [0, 2, 4]]


def test_one_thread_runs_in_one_pool_thread_off_the_main_thread():
    """With one thread the items run one after the other in a single pool thread, so that the
    main thread waits interruptibly (Ctrl-C reaches it during a long C call); from any other
    thread they run in the caller."""
    parallel.set_threads(1)
    try:
        names = parallel.thread_map(lambda i: threading.current_thread().name, range(3))
        other: list[list[str]] = []
        t = threading.Thread(target=lambda: other.append(parallel.thread_map(
            lambda i: threading.current_thread().name, range(3))), name="not-main")
        t.start()
        t.join()
    finally:
        parallel.set_threads(None)
    assert len(set(names)) == 1 and names[0].startswith("segsnake-worker")
    assert other == [["not-main"] * 3]


def test_thread_count_from_the_environment(monkeypatch):
    monkeypatch.setenv(parallel.ENV, "3")
    assert parallel.threads() == 3
    for bad in ("0", "-2", "many"):
        monkeypatch.setenv(parallel.ENV, bad)
        with pytest.raises(ConfigError, match=parallel.ENV):
            parallel.threads()
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError):
            parallel.set_threads(bad)


@pytest.mark.parametrize("shape,axis", [((9, 5, 4), 0), ((2, 7, 30), 2), ((1, 1, 5), 2)])
def test_slabs_tile_the_array_once(two_threads, shape, axis):
    count = np.zeros(shape, dtype=int)
    pieces = parallel.slabs(shape, axis)
    for sl in pieces:
        count[sl] += 1
        assert sl[axis] == slice(None)  # never cut along the filtered axis
    assert np.all(count == 1)
    assert len(pieces) == min(2, max(n for a, n in enumerate(shape) if a != axis))


def test_slab_filters_equal_scipy(two_threads):
    rng = np.random.default_rng(4)
    a = rng.standard_normal((23, 17, 11)).astype(np.float32)
    expected = ndimage.gaussian_filter(a, (1.5, 0.7, 2.0), mode="nearest", output=np.float32)
    got = parallel.gaussian_filter(a, (1.5, 0.7, 2.0), mode="nearest")
    assert got.dtype == np.float32 and np.array_equal(got, expected)
    expected = ndimage.spline_filter(a.astype(np.float64), order=3, mode="mirror")
    got = parallel.spline_filter(a)
    assert got.dtype == np.float64 and np.array_equal(got, expected)
    # An axis of one sample: smoothed like scipy does (mode constant scales it), or skipped
    # with sigma 0; the spline prefilter leaves it alone (a mirror boundary needs two).
    thin = a[:, :1, :]
    for sigma in [(1.0, 0.8, 1.2), (1.0, 0.0, 1.2)]:
        expected = ndimage.gaussian_filter(thin, sigma, mode="constant", output=np.float32)
        assert np.array_equal(parallel.gaussian_filter(thin, sigma, mode="constant"), expected)
    flat = a[:, :1, :]
    expected = ndimage.spline_filter1d(flat.astype(np.float64), order=3, axis=0, mode="mirror")
    expected = ndimage.spline_filter1d(expected, order=3, axis=2, mode="mirror")
    assert np.array_equal(parallel.spline_filter(flat), expected)


def test_a_joined_map_keeps_order_runs_in_the_caller_too_and_stops_at_an_error(two_threads):
    # (join: the caller takes items beside threads() - 1 pool threads)
    main = threading.main_thread()
    helper_took = threading.Event()

    def square(i):
        if threading.current_thread() is main:
            assert helper_took.wait(10)  # (so that both take items, whatever the timing)
        else:
            helper_took.set()
        return i * i, threading.current_thread().name

    out = parallel.thread_map(square, range(20), join=True)
    assert [v for v, _ in out] == [i * i for i in range(20)]
    names = {n for _, n in out}
    assert main.name in names and len(names) == 2
    assert all(n.startswith("segsnake-worker") for n in names - {main.name})

    # A helper's error reaches the caller, and no one takes a new item after it.
    helper_took.clear()
    taken = []

    def fails_in_a_helper(i):
        taken.append(i)
        if threading.current_thread() is main:
            assert helper_took.wait(10)
            time.sleep(0.01)
            return i
        helper_took.set()
        raise ValueError(f"piece {i}")

    with pytest.raises(ValueError, match="piece"):
        parallel.thread_map(fails_in_a_helper, range(50), join=True)
    assert len(taken) == 2

    # A cancellation (Ctrl-C, SIGTERM) stops both at their next item.
    taken.clear()

    def cancels(i):
        taken.append(i)
        if i == 0:
            cancel.request()
        else:
            time.sleep(0.05)  # (the request comes first: at most this one item more)
        return i

    try:
        with pytest.raises(KeyboardInterrupt):
            parallel.thread_map(cancels, range(50), join=True)
    finally:
        cancel.reset()
    assert len(taken) <= 2

    # one thread: no helper, the pool as before
    parallel.set_threads(1)
    assert {n for _, n in parallel.thread_map(square, range(3), join=True)} == {
        n for _, n in parallel.thread_map(square, range(3))}


def test_lookup_and_derivatives_do_not_depend_on_threads():
    rng = np.random.default_rng(5)
    f = ndimage.gaussian_filter(rng.standard_normal((30, 26, 22)), 2.0)
    pts = rng.uniform(1.0, 20.0, size=(20000, 3))  # five blocks of Lookup.sample
    results = []
    for n in (1, 2, 3):
        parallel.set_threads(n)
        try:
            lk = Lookup.from_field(f, (1.0, 0.8, 1.2))
            d = gaussian_derivatives(f, (1.0, 0.8, 1.2), 1.5, [(2, 0, 0), (1, 1, 0), (0, 0, 1)])
            results.append((lk.coef, *lk.sample(pts), *d.values()))
        finally:
            parallel.set_threads(None)
    for other in results[1:]:
        for x, y in zip(results[0], other):
            assert np.array_equal(x, y)


@pytest.mark.parametrize("n,size", [(0, 5), (1, 1), (10, 4), (9, 3), (4097, 4096), (3, 100)])
def test_pieces_are_few_equal_and_cover_the_range(n, size):
    got = parallel.pieces(n, size)
    assert len(got) == max(-(-n // size), 1)
    lengths = [s.stop - s.start for s in got]
    assert max(lengths) <= size and max(lengths) - min(lengths) <= 1
    assert [i for s in got for i in range(s.start, s.stop)] == list(range(n))


def test_a_segmentation_runs_blas_in_one_thread_and_restores_it_after():
    # OpenBLAS splits products by the core count and its rounding follows the split: while a
    # segmentation runs it keeps to one thread (parallel.one_blas_thread), and the limit the
    # caller had comes back after, also after an error.
    from threadpoolctl import threadpool_limits

    from segsnake.config import SegmentConfig
    from segsnake.phantoms import make_phantom
    from segsnake.pipeline import segment_volume

    ph = make_phantom("blob", shape=(40, 40, 40), seed=0, noise=0.05)
    seen = []
    config = SegmentConfig.from_mapping({**ph.init, "coarse_to_fine": False})
    with threadpool_limits(limits=2, user_api="blas"):
        if blas_threads() != {2}:
            pytest.skip("the BLAS here does not take two threads")
        segment_volume(ph.image, ph.spacing, config,
                       progress=lambda stage, frac: seen.append(blas_threads()))
        assert seen and all(s == {1} for s in seen)
        assert blas_threads() == {2}

        def stop(stage, frac):
            raise RuntimeError("stopped")

        with pytest.raises(RuntimeError, match="stopped"):
            segment_volume(ph.image, ph.spacing, config, progress=stop)
        assert blas_threads() == {2}


def test_overlapping_limited_calls_share_one_limit_and_restore_it_at_the_last_end():
    # A enters, B enters, A ends, B ends: B still runs in one thread after A has ended, and the
    # process's own count comes back once both have (threadpoolctl's own limits would restore
    # A's "before" while B runs, and B's "before", one thread, at the end). (No limit is set
    # around them: OpenBLAS then ignores a count set in another thread.)
    before = blas_threads()
    if before == {1}:
        pytest.skip("the BLAS here runs one thread already")
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen = {}

    @parallel.one_blas_thread
    def a():
        a_in.set()
        b_in.wait(10)
        seen["a"] = blas_threads()

    @parallel.one_blas_thread
    def b():
        b_in.set()
        a_out.wait(10)
        seen["b after a"] = blas_threads()

    ta = threading.Thread(target=a)
    ta.start()
    a_in.wait(10)
    tb = threading.Thread(target=b)
    tb.start()
    ta.join(10)
    a_out.set()
    tb.join(10)
    assert seen == {"a": {1}, "b after a": {1}}
    assert blas_threads() == before
