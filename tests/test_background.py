"""Background: a writer's chunks written on its own thread, in order; its error raised in the caller; close and
abort only once the chunks handed over have ended."""
import threading
import time

import pytest

from flightsim.core.background import Background


class _Writer:
    def __init__(self, fail_at=None, pause=0.0):
        self.seen, self.threads, self.closed, self.aborted = [], set(), False, False
        self.fail_at, self.pause = fail_at, pause

    def __call__(self, chunk):
        time.sleep(self.pause)
        if chunk == self.fail_at:
            raise ValueError(f"chunk {chunk}")
        self.seen.append(chunk)
        self.threads.add(threading.get_ident())

    def close(self):
        self.closed = True
        return list(self.seen)

    def abort(self):
        self.aborted = True


def test_chunks_are_written_in_order_on_another_thread():
    writer = _Writer(pause=0.002)
    background = Background(writer, "test")
    for k in range(20):
        background(k)
    assert background.close() == list(range(20))
    assert writer.closed and threading.get_ident() not in writer.threads and len(writer.threads) == 1


def test_the_caller_waits_when_the_writer_holds_enough_chunks():
    writer = _Writer(pause=0.05)
    background = Background(writer, "test", held=2)
    start = time.perf_counter()
    for k in range(4):
        background(k)
    assert time.perf_counter() - start >= 0.09  # the third and fourth chunks waited for the first two
    background.close()


def test_without_wait_the_caller_goes_on_however_many_chunks_the_writer_holds():
    writer = _Writer(pause=0.05)
    background = Background(writer, "test", held=1)
    start = time.perf_counter()
    for k in range(4):
        background(k, wait=False)
    assert time.perf_counter() - start < 0.04  # none waited (held 1: with wait, three would have)
    assert background.close() == list(range(4))


def test_the_writers_error_reaches_the_caller_and_abort_waits():
    writer = _Writer(fail_at=1)
    background = Background(writer, "test", held=1)
    background(0)
    background(1)
    with pytest.raises(ValueError, match="chunk 1"):
        background(2)  # waits for chunk 1, which failed
    background.abort()
    assert writer.aborted and not writer.closed and writer.seen == [0]


def test_close_raises_the_last_chunks_error():
    writer = _Writer(fail_at=3)
    background = Background(writer, "test")
    for k in range(4):
        background(k)
    with pytest.raises(ValueError, match="chunk 3"):
        background.close()
    assert not writer.closed


def test_a_chunk_handed_over_after_another_writers_waits_for_it():
    first, second = _Writer(pause=0.05), _Writer()
    a, b = Background(first, "a"), Background(second, "b")
    done_first = a(0)
    b(0, after=done_first)
    b.settle()
    assert done_first.done() and second.seen == [0]
    failing = Background(_Writer(fail_at=1), "c")
    b(1, after=failing(1))  # the other writer's error stays its own
    b.settle()
    assert second.seen == [0, 1]
    with pytest.raises(ValueError):
        failing.close()
    a.close(), b.close()


class _Staged(_Writer):
    """A writer whose chunks are prepared apart from their writing (``writer(chunk)`` is ``take(prepare(chunk))``)."""

    def __init__(self, fail_at=None, pause=0.0):
        super().__init__(fail_at, pause)
        self.lock, self.running, self.most, self.preparers = threading.Lock(), 0, 0, set()

    def prepare(self, chunk):
        with self.lock:
            self.running += 1
            self.most = max(self.most, self.running)
            self.preparers.add(threading.get_ident())
        time.sleep(self.pause * (1 + chunk % 3))  # later chunks may be prepared first
        with self.lock:
            self.running -= 1
        if chunk == self.fail_at:
            raise ValueError(f"chunk {chunk}")
        return chunk

    def take(self, prepared):
        self.seen.append(prepared)
        self.threads.add(threading.get_ident())

    def __call__(self, chunk):
        self.take(self.prepare(chunk))


def test_a_staged_writers_chunks_are_prepared_side_by_side_and_taken_in_order_on_one_thread():
    writer = _Staged(pause=0.01)
    background = Background(writer, "test", threads=3)
    for k in range(12):
        background(k)
    assert background.close() == list(range(12))
    assert writer.most == 3 and len(writer.threads) == 1 and not writer.threads & writer.preparers
    alone = _Staged(pause=0.01)
    Background(alone, "test").close()  # one thread: the writer called whole
    background = Background(alone, "test")
    for k in range(4):
        background(k)
    assert background.close() == list(range(4)) and alone.most == 1 and alone.threads == alone.preparers


def test_a_staged_writers_error_reaches_the_caller_and_abort_drops_the_rest():
    writer = _Staged(fail_at=2, pause=0.01)
    background = Background(writer, "test", threads=2)
    with pytest.raises(ValueError, match="chunk 2"):
        for k in range(40):
            background(k)
    background.abort()  # chunks 3 and 4 were handed over (held 2 + 2 − 1), none after: they may have been written
    assert writer.aborted and not writer.closed and writer.seen[:2] == [0, 1] and set(writer.seen) <= {0, 1, 3, 4}


def _burn(seconds):
    """Spend ``seconds`` of this thread's CPU time."""
    start = time.thread_time()
    while time.thread_time() - start < seconds:
        pass


class _Burner(_Writer):
    """20 ms of CPU a chunk, 50 ms asleep to close."""

    def __call__(self, chunk):
        _burn(0.02)

    def close(self):
        time.sleep(0.05)


def _timing(writer, chunks: int, **options) -> dict:
    """The Background's timing after ``chunks`` chunks handed over and the writer closed."""
    background = Background(writer, "test", **options)
    for k in range(chunks):
        background(k)
    background.close()
    return background.timing()


def test_a_writers_time_is_kept_where_it_went():
    """busy: the writer's calls (here at least their sleeps); cpu: its thread's CPU in them (a sleep spends almost
    none, a burn its own); held_back: the caller's waits, none while the writer holds few enough; close: its close."""
    t = _timing(_Writer(pause=0.03), 5, held=1)
    assert t["busy"] >= 0.15 and t["cpu"] < 0.05 and t["held_back"] >= 0.09 and t["prepare"] == 0.0
    t = _timing(_Writer(pause=0.01), 5, held=10)
    assert t["held_back"] == 0.0 and t["busy"] >= 0.05
    t = _timing(_Burner(), 3)
    assert t["cpu"] >= 0.06 and t["busy"] >= t["cpu"] - 0.002 and t["close"] >= 0.05


def test_a_staged_writers_preparing_time_is_summed_over_its_threads():
    t = _timing(_Staged(pause=0.01), 6, threads=3)
    assert t["prepare"] >= 0.01 * sum(1 + k % 3 for k in range(6)) and t["busy"] < t["prepare"]
