"""Worker interpreters that run a module-level function over chunks (flightsim/core/process_map.py): results in
the chunks' order and bit for bit the parent's, a worker's exception raised again with its traceback, a worker's
death reported, and the per-shot fits of l2a.h5 and waveforms.h5 spread over workers giving the same numbers."""
from __future__ import annotations

import os

import numpy as np
import pytest

from flightsim.core.process_map import MIN_ROWS_PER_CHUNK, ProcessMap, map_rows, row_chunks
from flightsim.outputs.l2a import l2a_metrics


def square_sum(values: np.ndarray, offset: float) -> float:
    return float(np.sum(np.sqrt(values) ** 3) + offset)


def refuse(value: int) -> int:
    raise ValueError(f"no {value}")


def leave(value: int) -> int:
    os._exit(3)


def doubled_in_place(arrays: dict) -> dict:
    """Each array doubled in place (they must arrive writable), with its layout."""
    for value in arrays.values():
        if value.dtype.names:
            value["X"] *= 2
        else:
            value *= 2
    return {name: (value, value.flags.c_contiguous, value.flags.f_contiguous) for name, value in arrays.items()}


@pytest.fixture(scope="module")
def workers():
    pool = ProcessMap(2)
    yield pool
    pool.stop()


def test_results_come_in_the_chunks_order_bit_for_bit(workers):
    rng = np.random.default_rng(2)
    chunks = [(rng.uniform(0.0, 9.0, int(n)), float(k)) for k, n in enumerate(rng.integers(1, 5000, 23))]
    assert workers.map(square_sum, chunks) == [square_sum(*chunk) for chunk in chunks]
    assert map_rows(square_sum, chunks, None) == [square_sum(*chunk) for chunk in chunks]
    assert workers.map(square_sum, []) == []


def test_arrays_travel_beside_the_pickle_and_arrive_writable_as_they_were(workers):
    """A message's arrays go after its pickle as they are (pickle protocol 5's buffers): the pickle holds none of their
    bytes; they arrive equal, writable, in their layout (C, Fortran, an empty one, a strided view, records), both ways."""
    import socket
    from multiprocessing.connection import Connection

    from flightsim.core.process_map import receive, send

    rng = np.random.default_rng(4)
    records = np.zeros(5, dtype=[("X", "<i4"), ("gps_time", "<f8"), ("bits", "u1")])
    records["X"], records["gps_time"] = np.arange(5), rng.uniform(size=5)
    arrays = {"c": rng.uniform(size=(300, 7)), "f": np.asfortranarray(rng.integers(0, 99, (40, 3))),
              "empty": np.zeros((0, 3), np.float32), "strided": rng.uniform(size=900)[::3], "records": records}
    left, right = (Connection(end.detach()) for end in socket.socketpair())
    sizes = []
    original = left.send_bytes
    left.send_bytes = lambda data: sizes.append(memoryview(data).nbytes) or original(data)
    send(left, ("m", "f", arrays))
    got = receive(right)[2]
    # the pickle holds the strided view's copy (not contiguous: pickled in it), the rest comes after it
    assert sizes[0] < arrays["strided"].nbytes + 1_000 and len(sizes) == 1 + 4 and sum(sizes) > arrays["c"].nbytes
    for name, value in arrays.items():
        np.testing.assert_array_equal(got[name], value)
        assert got[name].dtype == value.dtype and got[name].flags.writeable
    left.close()
    right.close()
    back = workers.map(doubled_in_place, [(arrays,)])[0]
    expected = doubled_in_place({name: value.copy() for name, value in arrays.items()})
    for name, (value, _, _) in back.items():
        np.testing.assert_array_equal(value, expected[name][0])
    assert back["c"][1:] == (True, False) and back["f"][1:] == (False, True)  # each in its own layout


def test_chunks_made_as_the_workers_take_them(workers):
    """A generator of chunks: each made when a worker frees to take it (at most one ahead of a worker's result here:
    two workers, so two made before the first result is back), the results in order."""
    rng = np.random.default_rng(4)
    chunks = [(rng.uniform(0.0, 9.0, 3000), float(k)) for k in range(9)]
    made, answered = [], []

    def lazily():
        for k, chunk in enumerate(chunks):
            made.append((k, len(answered)))
            yield chunk

    class Counting(ProcessMap):  # notes each answer as it comes
        def _answer(self, conn):
            answered.append(True)
            return super()._answer(conn)

    pool = Counting(2)
    try:
        assert pool.map(square_sum, lazily()) == [square_sum(*chunk) for chunk in chunks]
    finally:
        pool.stop()
    assert [k for k, _ in made] == list(range(9)) and [a for _, a in made[:2]] == [0, 0]
    assert all(a >= k - 1 for k, a in made[2:])  # chunk k made once k − 1 answers came
    assert map_rows(square_sum, iter(chunks), None) == [square_sum(*chunk) for chunk in chunks]


def test_each_result_handed_to_done_as_it_comes_back(workers):
    """With ``done``, each chunk's result goes to ``done(index, result)`` once, as its worker answers (a quick chunk
    given after a slow one comes back first), bit for bit the parent's; the list returned holds None."""
    rng = np.random.default_rng(5)
    chunks = [(rng.uniform(0.0, 9.0, n), float(k)) for k, n in enumerate([3_000_000, 10, 10, 10, 10])]
    got = []
    assert workers.map(square_sum, chunks, lambda index, result: got.append((index, result))) == [None] * 5
    assert sorted(got) == [(k, square_sum(*chunk)) for k, chunk in enumerate(chunks)]
    assert got[-1][0] == 0  # the slow first chunk last


def test_rows_are_cut_into_chunks_of_at_least_the_least_size(workers):
    assert row_chunks(1000, None) == [slice(0, 1000)]
    cuts = row_chunks(1000, workers)  # two workers: four chunks each
    assert cuts[0] == slice(0, 125) and cuts[-1].stop == 1000 and len(cuts) == 8
    assert all(a.stop == b.start for a, b in zip(cuts, cuts[1:]))
    assert row_chunks(100, workers) == [slice(0, MIN_ROWS_PER_CHUNK), slice(MIN_ROWS_PER_CHUNK, 100)]
    assert row_chunks(0, workers) == []


def test_a_workers_exception_is_raised_with_its_traceback_and_stops_the_workers():
    pool = ProcessMap(2)
    with pytest.raises(ValueError, match="no 7") as caught:
        pool.map(refuse, [(7,)])
    assert any("raised in worker" in note and "refuse" in note for note in caught.value.__notes__)
    assert all(p.poll() is not None for p in pool.processes)  # stopped
    pool.stop()  # again: nothing left to do


def test_a_chunk_that_cannot_be_made_stops_the_workers():
    """A generator of chunks failing while workers hold earlier chunks: its error raised, and the workers stopped
    (their answers would otherwise reach the next map)."""
    def failing():
        yield (np.ones(10), 0.0)
        yield (np.ones(10), 1.0)
        yield (np.ones(10), 2.0)
        raise OSError("cannot read the block")

    pool = ProcessMap(2)
    with pytest.raises(OSError, match="cannot read the block"):
        pool.map(square_sum, failing())
    assert all(p.poll() is not None for p in pool.processes)
    pool.stop()


def test_a_worker_that_dies_is_named():
    pool = ProcessMap(1)
    with pytest.raises(RuntimeError, match=r"worker 0 \(pid \d+\) ended with exit status 3"):
        pool.map(leave, [(1,)])


def test_l2a_metrics_over_workers_are_the_metrics_in_this_process(workers):
    """Noisy two-mode waveforms (test_l2a's GEDI-like shapes) in five chunks of rows: every metric the same bit for
    bit."""
    dt, n, pulse = 0.5e-9, 1000, 6e-9
    i = np.arange(n, dtype=np.float64)
    rng = np.random.default_rng(9)
    shots = 300
    centre = rng.uniform(600.0, 800.0, shots)[:, None]
    rx = (np.exp(-0.5 * ((i - centre) / 12.0) ** 2) + 0.4 * np.exp(-0.5 * ((i - centre + 280.0) / 24.0) ** 2)
          + rng.normal(0.0, 0.005, (shots, n)))
    z0 = np.full(shots, 100.0)
    args = (rx, dt, z0, z0 - (n - 1) * 0.075, np.full(shots, 10.0), np.full(shots, 20.0), np.full(shots, 10.001),
            np.full(shots, 20.002), pulse)
    alone, spread = l2a_metrics(*args), l2a_metrics(*args, workers=workers)
    assert sorted(alone) == sorted(spread)
    for name in alone:
        np.testing.assert_array_equal(alone[name], spread[name], err_msg=name)
    assert np.isfinite(alone["elev_lowestmode"]).all() and (alone["num_detectedmodes"] >= 2).mean() > 0.9


@pytest.mark.parametrize("bad", ["rx", "elevation_lastbin", "noise", "short"])
def test_l2a_metrics_over_workers_refuse_bad_input_as_this_process_does(workers, bad):
    """A NaN sample, a short column, a noise of the wrong shape or waveforms too short for their noise: the same
    InputError, naming the whole input."""
    from flightsim.core.errors import InputError

    shots, n = 200, 300
    rx = np.exp(-0.5 * ((np.arange(n) - 150.0) / 10.0) ** 2)[None, :].repeat(shots, axis=0)
    z0 = np.full(shots, 100.0)
    columns = [z0, z0 - 20.0, np.full(shots, 10.0), np.full(shots, 20.0), np.full(shots, 10.001), np.full(shots, 20.0)]
    noise = None
    if bad == "rx":
        rx[150, 7] = np.nan
    elif bad == "elevation_lastbin":
        columns[1] = columns[1][:-1]
    elif bad == "short":
        rx = rx[:, :100]  # fewer than 2 × 64 noise samples and one
    else:
        noise = (np.zeros(shots + 1), 0.01)
    messages = []
    for pool in (None, workers):
        with pytest.raises(InputError) as caught:
            l2a_metrics(rx, 1e-9, *columns, 6e-9, noise=noise, workers=pool)
        messages.append(str(caught.value))
    field = {"rx": "rx", "elevation_lastbin": "elevation_lastbin", "noise": "noise mean", "short": "rx"}[bad]
    assert messages[0] == messages[1] and messages[0].startswith(f"invalid {field} = ")
    assert bad == "rx" or f"({shots}," in messages[0]  # the whole input's rows, not a chunk's


def test_maps_asked_for_from_two_threads_at_once_each_get_their_results(workers):
    import threading

    rng = np.random.default_rng(5)
    asks = [[(rng.uniform(0.0, 9.0, 3000), float(k + 100 * t)) for k in range(9)] for t in range(2)]
    got = [None, None]

    def ask(t):
        got[t] = workers.map(square_sum, asks[t])

    threads = [threading.Thread(target=ask, args=(t,)) for t in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60.0)
    assert got == [[square_sum(*chunk) for chunk in chunks] for chunks in asks]


def loaded(module: str) -> bool:
    import sys
    return module in sys.modules


def test_preloaded_modules_are_imported_before_the_first_task():
    workers = ProcessMap(1, preload=("colorsys", "no_such_module_anywhere"))  # a missing one is left alone
    try:
        assert workers.map(loaded, [("colorsys",), ("wave",)]) == [True, False]
    finally:
        workers.stop()


def test_preloaded_functions_are_called_before_the_first_task():
    """``module:function`` entries are called once as the worker starts; a failing one is left alone."""
    workers = ProcessMap(1, preload=("os:getpid", "wave:no_such_function", f"{mark_started.__module__}:mark_started"))
    try:
        assert workers.map(started_marks, [()]) == [1]
        assert workers.map(loaded, [("wave",)]) == [True]  # imported, though its function was not there
    finally:
        workers.stop()


MARKS: list[int] = []


def mark_started() -> None:
    MARKS.append(1)


def started_marks() -> int:
    return len(MARKS)


@pytest.mark.parametrize("rows", [0, 1, 999, 1000, 10_001])
def test_by_pieces_covers_every_row_once_in_order(monkeypatch, rows):
    """Pieces of at least ``least`` rows (but the last), about two a thread, the results in the rows' order; a single
    piece worked out in the calling thread."""
    import threading

    from flightsim.core import process_map

    monkeypatch.setattr(process_map, "usable_cores", lambda: 4)
    threads = set()
    pieces = process_map.by_pieces(rows, lambda piece: threads.add(threading.get_ident()) or piece, least=1000)
    covered = np.concatenate([np.arange(rows)[piece] for piece in pieces] + [np.arange(0)])
    assert np.array_equal(covered, np.arange(rows))  # every row once, the pieces in order
    assert all(piece.stop - piece.start >= 1000 for piece in pieces[:-1])
    assert len(pieces) == (8 if rows == 10_001 else min(rows, 1))  # 10,001 rows: 4 threads, two pieces each
    assert threads == ({threading.get_ident()} if len(pieces) == 1 else threads - {threading.get_ident()})
