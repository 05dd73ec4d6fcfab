"""Sweeps and surveys on a Dask cluster (dask.distributed): local worker processes, one worker per
GPU, or an existing scheduler.

Workers are processes with one thread each (Warp's runtime is not to be shared between threads);
each keeps what it builds — scenes, BVHs, compiled kernels — for every task it runs. A worker's
device is named by ``FLIGHTSIM_DEVICE`` in its environment: :func:`local_cluster` gives the worker
of GPU i ``cuda:i``, and a task runs there whatever device its config names (a worker started by
hand, ``FLIGHTSIM_DEVICE=cuda:1 dask worker ADDRESS --nthreads 1``, is pinned the same way).

A worker that dies mid-task loses nothing: the scheduler hands the task to another worker (up to
``distributed.scheduler.allowed-failures`` times), the client records only results that arrived,
and tasks write files only under names of their own, renamed into place when complete.
"""
from __future__ import annotations

import contextlib
import logging
import os
import resource
import uuid
from collections.abc import Iterator

from flightsim.engine.config import RunConfig, copy_config
from flightsim.core.errors import InputError

DEVICE_ENV = "FLIGHTSIM_DEVICE"  # a worker's device, set per worker process
CONNECT_TIMEOUT_S = 30.0
# Settings of the workers of a local cluster, measured on 2 CPU cores: Dask's statistical profiler
# samples each task thread every 10 ms and costs a sweep ~15 %; the MALLOC_TRIM_THRESHOLD_ Dask
# sets in workers turns off glibc's adaptive mmap threshold, so every large numpy array of a
# points-mode run is mapped and faulted in anew, doubling the kernel time of a survey.
WORKER_CONFIG = {"distributed.worker.profile.enabled": False,
                 "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}

# ---------------------------------------------------------------------------------------------
# the cluster


def parse_gpus(text: str) -> list[int]:
    """GPU ordinals of ``--gpus``: "all" (every CUDA device here) or a comma-separated list."""
    from flightsim.core.warp_runtime import init_warp
    import warp as wp

    init_warp()
    count = wp.get_cuda_device_count()
    ordinals_here = ", ".join(map(str, range(count))) or "(none: no CUDA device here)"
    allowed = f"all, or distinct GPU ordinals among {ordinals_here}"
    if text.strip() == "all":
        if count == 0:
            raise InputError("--gpus", text, "a machine with CUDA devices (none found)")
        return list(range(count))
    try:
        ordinals = [int(item) for item in text.split(",")]
    except ValueError:
        raise InputError("--gpus", text, allowed) from None
    if not ordinals or len(set(ordinals)) != len(ordinals) or any(not 0 <= i < count for i in ordinals):
        raise InputError("--gpus", text, allowed)
    return ordinals


def worker_options(workers: int, gpus: list[int] | None = None) -> dict[str, dict]:
    """Name and Nanny options of each worker of a local cluster: one thread each, an equal share of
    this machine's memory. With ``gpus``, one worker ``gpu<i>`` per GPU pinned to ``cuda:<i>``, or
    ``workers`` of them dealt out over the GPUs (``gpu<i>-<m>``: the host's part of a survey, the LAS
    writing, then runs on more cores); otherwise ``workers`` workers ``cpu<k>`` that run on the
    device their tasks' configs name."""
    from distributed.system import MEMORY_LIMIT

    if gpus:
        share = max(1, -(-workers // len(gpus)))  # workers per GPU
        names = {(f"gpu{i}" if share == 1 else f"gpu{i}-{m}"): f"cuda:{i}" for i in gpus for m in range(share)}
    else:
        names = {f"cpu{k}": None for k in range(workers)}
    return {name: dict(nthreads=1, memory_limit=MEMORY_LIMIT // len(names), host="127.0.0.1", dashboard=False,
                       silence_logs=logging.ERROR, env={DEVICE_ENV: device} if device else {})
            for name, device in names.items()}


def local_cluster(workers: int, gpus: list[int] | None = None):
    """A Dask cluster of worker processes on this machine (:func:`worker_options`)."""
    import dask
    from distributed import Nanny, Scheduler, SpecCluster

    specs = {name: {"cls": Nanny, "options": options} for name, options in worker_options(workers, gpus).items()}
    scheduler = {"cls": Scheduler, "options": dict(host="127.0.0.1", port=0, dashboard=False, dashboard_address=None)}
    with dask.config.set(WORKER_CONFIG):  # each Nanny keeps the config it was made with, also for restarts
        return SpecCluster(workers=specs, scheduler=scheduler, silence_logs=logging.ERROR, name="flightsim")


@contextlib.contextmanager
def open_client(workers: int | None = None, scheduler: str | None = None, gpus: str | None = None):
    """The Dask client a command runs on, or None to run serially in this process.

    ``scheduler`` connects to a running cluster; ``gpus`` starts one worker per GPU (or ``workers`` of
    them, an equal number per GPU); ``workers`` > 1 alone starts that many workers; otherwise there
    is no cluster (and Dask is not imported).
    """
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InputError("--workers", workers, "an integer >= 1")
    if scheduler and (gpus or workers):
        raise InputError("--scheduler", scheduler, "no --workers or --gpus with it (the cluster has its own workers)")
    if scheduler:
        from distributed import Client

        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError) as exc:
            raise InputError("--scheduler", scheduler, f"the address of a running Dask scheduler ({exc})") from None
        with client:
            threads = {w["name"]: w["nthreads"] for w in client.scheduler_info()["workers"].values()}
            if any(n != 1 for n in threads.values()):
                raise InputError("--scheduler", scheduler, "a cluster whose workers run one thread each "
                                 f"(dask worker ... --nthreads 1; Warp is not shared between threads): {threads}")
            yield client
        return
    ordinals = parse_gpus(gpus) if gpus else None
    if ordinals and workers is not None and workers % len(ordinals):
        raise InputError("--workers", workers, f"a multiple of the {len(ordinals)} GPU(s) of --gpus {gpus}, "
                                               "or nothing (one worker per GPU)")
    if not ordinals and (workers or 1) <= 1:
        yield None
        return
    from distributed import Client

    with local_cluster(workers or 0, ordinals) as cluster, Client(cluster) as client:
        client.wait_for_workers(len(cluster.worker_spec))
        yield client


def worker_device(cfg: RunConfig) -> RunConfig:
    """``cfg`` on this worker's device (``FLIGHTSIM_DEVICE``), or unchanged where none is set."""
    device = os.environ.get(DEVICE_ENV)
    if not device or device == cfg.run.device:
        return cfg
    pinned = copy_config(cfg)
    pinned.run.device = device
    return pinned


def worker_stats() -> dict:
    """Who ran a task, and this process's peak resident memory so far [MiB]."""
    try:
        from distributed import get_worker

        name = str(get_worker().name)
    except ValueError:  # not on a Dask worker
        name = "local"
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # Linux: KiB
    return {"worker": name, "pid": os.getpid(), "peak_rss_mb": peak_kib / 1024}


def run_futures(client, submitted: list) -> Iterator[tuple[object, object]]:
    """(future, result) of each future as it completes; the rest are cancelled if the caller stops
    early (a task failed, or the caller did)."""
    from distributed import as_completed

    try:
        for future in as_completed(submitted):
            yield future, future.result()
            future.release()
    finally:
        client.cancel([f for f in submitted if not f.done()])


# ---------------------------------------------------------------------------------------------
# batches of work


def run_batches(client, task, items: list, *args, batch: int = 1,
                name: str = "batch") -> Iterator[tuple[object, object]]:
    """(item, result) of every item of ``items`` as its batch finishes on the cluster.

    One task ``task(batch_items, *args)`` per ``batch`` consecutive items, returning one result per item
    (a study's worker side, such as a sweep's configurations); each task's key is ``<name>-<token>-<k>``.
    """
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise InputError("--batch", batch, "an integer >= 1")
    token = uuid.uuid4().hex[:8]
    batches = [items[k:k + batch] for k in range(0, len(items), batch)]
    futures = {client.submit(task, chunk, *args, key=f"{name}-{token}-{k}"): chunk for k, chunk in enumerate(batches)}
    for future, results in run_futures(client, list(futures)):
        yield from zip(futures[future], results)
