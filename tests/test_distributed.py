"""Sweeps on a Dask cluster: the same rows as the serial sweep, also when a worker dies mid-task."""
import csv
import functools
import os
import sys

import cloudpickle
import pytest

from flightsim.engine import distributed
from flightsim.engine.config import RunConfig, set_value
from flightsim.core.errors import InputError
from flightsim.studies import sweep
from flightsim.studies.sweep import SweepGrid, run_sweep

cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test module


@pytest.fixture(scope="module")
def client():
    with distributed.open_client(workers=2) as client:
        yield client


def grid() -> SweepGrid:
    base = RunConfig()
    set_value(base, "scene.name", "plane")
    set_value(base, "flight.duration_s", 0.5)
    return SweepGrid(base, [("fan.array", ["2", "3", "4"]), ("flight.altitude_m", ["500", "900"])])


def rows(path, drop=("wall_s",)):
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(fh)]


def claim(marker: str) -> bool:
    """True for exactly one caller across processes: the one that creates ``marker``."""
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    with open(marker, "w") as fh:
        fh.write(str(os.getpid()))
    return True


def die_after_the_work(marker: str, real, *args):
    """A task that, the first time anywhere, does its work and kills its worker before handing it back."""
    result = real(*args)
    if claim(marker):
        os._exit(1)
    return result


def test_distributed_sweep_equals_the_serial_sweep_though_a_worker_is_killed(client, tmp_path, monkeypatch):
    run_sweep(grid(), tmp_path / "serial")
    marker = tmp_path / "killed"
    monkeypatch.setattr(sweep, "configuration_task",
                        functools.partial(die_after_the_work, str(marker), sweep.configuration_task))
    workers = set(client.scheduler_info()["workers"])
    run_sweep(grid(), tmp_path / "dask", client=client)
    assert int(marker.read_text()) != os.getpid()  # a worker process ran the first task and died
    client.wait_for_workers(2)
    assert len(set(client.scheduler_info()["workers"]) - workers) == 1  # and was restarted
    serial = rows(tmp_path / "serial" / "sweep.csv")
    assert len(serial) == 2 * 6 and rows(tmp_path / "dask" / "sweep.csv") == serial
    assert rows(tmp_path / "dask" / "planes.csv") == rows(tmp_path / "serial" / "planes.csv")
    assert len(list((tmp_path / "dask" / "rows").iterdir())) == 6


def test_batched_tasks_and_a_resumed_sweep_give_the_same_rows(client, tmp_path):
    run_sweep(grid(), tmp_path / "serial")
    out = tmp_path / "dask"
    run_sweep(grid(), out, client=client, batch=4)
    assert rows(out / "sweep.csv") == rows(tmp_path / "serial" / "sweep.csv")
    first = sorted(out.glob("rows/*.json"))[0]
    first.unlink()
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("rows/*.json")}
    run_sweep(grid(), out, client=client)  # only the missing configuration runs again
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("rows/*.json") if p.name in before} == before
    assert first.is_file() and rows(out / "sweep.csv") == rows(tmp_path / "serial" / "sweep.csv")


def test_a_sweep_runs_on_a_running_cluster_given_by_its_scheduler_address(client, tmp_path):
    run_sweep(grid(), tmp_path / "serial")
    with distributed.open_client(scheduler=client.scheduler.address) as other:
        assert other is not client and set(other.scheduler_info()["workers"]) == set(client.scheduler_info()["workers"])
        run_sweep(grid(), tmp_path / "dask", client=other)
    assert rows(tmp_path / "dask" / "sweep.csv") == rows(tmp_path / "serial" / "sweep.csv")


def test_workers_are_single_threaded_processes_pinned_one_per_gpu(monkeypatch):
    gpus = distributed.worker_options(0, [0, 3])
    assert {name: o["env"] for name, o in gpus.items()} == {"gpu0": {"FLIGHTSIM_DEVICE": "cuda:0"},
                                                             "gpu3": {"FLIGHTSIM_DEVICE": "cuda:3"}}
    shared = distributed.worker_options(4, [0, 3])
    assert {name: o["env"]["FLIGHTSIM_DEVICE"] for name, o in shared.items()} == {
        "gpu0-0": "cuda:0", "gpu0-1": "cuda:0", "gpu3-0": "cuda:3", "gpu3-1": "cuda:3"}
    cpus = distributed.worker_options(3)
    assert list(cpus) == ["cpu0", "cpu1", "cpu2"] and all(o["env"] == {} for o in cpus.values())
    assert all(o["nthreads"] == 1 for o in [*gpus.values(), *cpus.values()])
    cfg = RunConfig()
    monkeypatch.setenv(distributed.DEVICE_ENV, "cuda:3")
    pinned = distributed.worker_device(cfg)
    assert pinned.run.device == "cuda:3" and cfg.run.device == "cpu"
    monkeypatch.delenv(distributed.DEVICE_ENV)
    assert distributed.worker_device(cfg) is cfg


@pytest.mark.parametrize("kwargs, field", [
    (dict(workers=0), "--workers"),
    (dict(workers=2, scheduler="tcp://127.0.0.1:1"), "--scheduler"),
    (dict(gpus="0,0"), "--gpus"),
])
def test_bad_cluster_flags_name_the_flag(kwargs, field):
    with pytest.raises(InputError, match=field):
        with distributed.open_client(**kwargs):
            pass


def test_one_worker_runs_serially():
    with distributed.open_client(workers=1) as client:
        assert client is None
