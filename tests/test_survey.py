"""Surveys over a tiled scene: the plan, the task split against one undivided simulation, and the
same bytes on a Dask cluster whose workers die mid-write."""
import functools
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import cloudpickle
import numpy as np
import pytest

from flightsim.engine import distributed
from flightsim.studies import survey
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.core.errors import InputError
from flightsim.outputs.las_points import read_points
from host_reference import HostLasOutput
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.studies.survey import run_survey
from flightsim.studies.survey_plan import SurveySpec, plan_survey

cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test module

SPEC = SurveySpec(size_km=0.8, tile_m=400, lines=3, segment_m=300)


def small_config(**settings) -> RunConfig:
    cfg = RunConfig()
    for key, value in {"flight.altitude_m": 300, "risley.prf_hz": 1000, "output.tile_size_m": 200, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    return out, run_survey(plan_survey(small_config(), SPEC), out)


def tiles(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.glob("*/*.la[sz]"))}


def by_pulse_and_beam(points):
    order = np.lexsort((points.beam_col, points.beam_row, points.gps_time, points.point_source_id))
    return points.select(order)


def test_lines_are_spaced_by_the_swath_less_the_sidelap_and_every_pulse_has_one_task():
    cfg = small_config(**{"flight.altitude_m": 500})
    plan = plan_survey(cfg, SurveySpec(size_km=2.0, tile_m=500, sidelap=0.3, segment_m=450))
    swath = 2 * 500 * math.tan(math.radians(15.0))
    assert plan.cfg.flight.line_spacing_m == pytest.approx(0.7 * swath)
    assert plan.cfg.flight.lines == math.ceil(2000 / (0.7 * swath)) and plan.grid.n == 4
    pulses_per_line = math.floor(2000 / (200 / 3.6) * 1000 + 1e-6) + 1  # t_k = k / PRF ≤ 36 s
    for line_id in range(1, plan.cfg.flight.lines + 1):
        ranges = [t.pulses for t in plan.tasks if t.line.line_id == line_id]
        assert ranges[0][0] == 0 and ranges[-1][1] == pulses_per_line
        assert all(a[1] == b[0] for a, b in zip(ranges, ranges[1:]))  # contiguous, disjoint
    radius = 500 * math.tan(math.radians(15.0))  # the scan circle about the nadir point
    for task in plan.tasks:  # the tiles under the scan circle at both ends of a segment are loaded
        north = math.cos(math.radians(task.line.heading_deg))  # +1 or -1
        for k in (task.pulses[0], task.pulses[1] - 1):
            y = task.line.start_northing + north * task.line.speed_mps * k / 1000.0
            for dx, dy in ((-radius, 0), (radius, 0), (0, -radius), (0, radius)):
                i = math.floor((task.line.start_easting + dx - (409000 - 1000)) / 500)
                j = math.floor((y + dy - (3393000 - 1000)) / 500)
                if 0 <= i < 4 and 0 <= j < 4:
                    assert (i, j) in task.tiles


def test_tasks_give_the_points_of_one_undivided_simulation(serial, tmp_path):
    out, summary = serial
    plan = plan_survey(small_config(), SPEC)
    grid = plan.grid
    everything = [(i, j) for j in range(grid.n) for i in range(grid.n)]
    scene, global_plane = grid.assemble(everything, (1, 1))
    lines = {t.line.line_id: t.line for t in plan.tasks}
    trajectories = [line.trajectory(ground_height_m=grid.centre[2]) for line in lines.values()]
    simulator = Tracer(plan.cfg, scene, trajectories)
    las = HostLasOutput(tmp_path, plan.cfg, scene, simulator.timing, edge_distance=False, plane_ids=global_plane)
    counts = simulator.run(Points(), las)
    las.close()
    assert summary["pulses"] == counts.pulses and summary["points"]["exact"] == counts.returns > 300_000
    n_planes = len(grid.template().planes)
    for model in ("exact", "nominal"):
        tasks, _ = read_points(sorted((out / model).glob("*.las")))
        whole, _ = read_points(sorted((tmp_path / model).glob("*.las")))
        tasks, whole = by_pulse_and_beam(tasks), by_pulse_and_beam(whole)
        assert len(tasks) == len(whole) == counts.returns
        for field in ("gps_time", "point_source_id", "beam_row", "beam_col", "plane_id", "classification"):
            assert np.array_equal(getattr(tasks, field), getattr(whole, field)), field
        for axis in "xyz":  # float32 in different local frames: within the 1 mm grid
            assert np.abs(getattr(tasks, axis) - getattr(whole, axis)).max() <= 0.0015
    # a point's plane belongs to the tile under it: tile (i, j)'s planes are (j·n + i)·P ... (j·n + i + 1)·P − 1
    east, north = tasks.x - (409000 - 400), tasks.y - (3393000 - 400)  # from the grid's south-west corner
    i, j = np.floor(east / 400).astype(int), np.floor(north / 400).astype(int)
    seam = np.minimum(np.minimum(east % 400, 400 - east % 400), np.minimum(north % 400, 400 - north % 400))
    inside = (i >= 0) & (i < 2) & (j >= 0) & (j < 2) & (seam > 1.0)
    assert inside.sum() > 100_000 and np.array_equal((tasks.plane_id // n_planes)[inside], (j * 2 + i)[inside])


def die_once(marker: str, how: str, name: str, *args):
    """Run the survey task ``name``; the first time anywhere, kill the worker in the middle of it:
    ``write``: when the first part tile is written but not yet renamed; ``rename``: when a merged
    tile is complete but not yet renamed."""
    from flightsim.studies import survey  # on a worker: the module as it is, not as the test patched it

    if how == "rename":
        _out, _parts, model, tile, _compress, *results = args
        writes = any(tile in r["tiles"].get(model, {}) for r in results)
    if (how == "write" or writes) and claim(marker):
        if how == "write":
            from flightsim.outputs.las_tiles import TileWriter

            TileWriter.close = lambda self: os._exit(1)
        else:
            survey.os.replace = lambda *a: os._exit(1)
    return getattr(survey, name)(*args)


def claim(marker: str) -> bool:
    """True for exactly one caller across processes: the one that creates ``marker``."""
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    os.write(fd, str(os.getpid()).encode())
    os.close(fd)
    return True


def test_a_survey_on_a_cluster_whose_workers_die_mid_write_gives_the_same_bytes(serial, tmp_path, monkeypatch):
    out, summary = serial
    killed = {"write": tmp_path / "killed-writing", "rename": tmp_path / "killed-merging"}
    for name, how in (("segment_task", "write"), ("merge_task", "rename")):
        monkeypatch.setattr(survey, name, functools.partial(die_once, str(killed[how]), how, name))
    with distributed.open_client(workers=2) as client:
        dask_summary = run_survey(plan_survey(small_config(), SPEC), tmp_path / "dask", client=client)
        client.wait_for_workers(2)
        alive = set(client.run(os.getpid).values())
    dead = {int(marker.read_text()) for marker in killed.values()}
    assert len(dead) == 2 and not dead & alive  # two worker processes died (and were replaced)
    assert tiles(tmp_path / "dask") == tiles(out) and len(tiles(out)) == 20
    assert dask_summary["tiles"] == summary["tiles"] and set(dask_summary["workers"]) == {"cpu0", "cpu1"}
    left = sorted(p.name for p in (tmp_path / "dask").rglob("*") if p.is_file())
    assert [n for n in left if n.startswith(".")] == []  # no part file or temporary is left
    shared = [t for t in plan_survey(small_config(), SPEC).merges.values() if len(t) > 1]
    assert len(shared) > 10  # tiles that several tasks wrote parts of


def test_survey_command_on_two_workers_reports_points_per_second_and_memory(tmp_path):
    out = tmp_path / "survey"
    ram = tmp_path / "ram"  # the parts' folder, as a RAM disk would be given
    ram.mkdir()
    args = [sys.executable, "-m", "flightsim", "survey", "--size-km", "0.8", "--tile-m", "400", "--altitude", "300",
            "--models", "nominal", "--set", "risley.prf_hz=500", "--workers", "2", "--out", str(out),
            "--parts", str(ram)]
    done = subprocess.run(args, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert list(ram.iterdir()) == [] and not (out / ".parts").exists()
    summary = json.loads((out / "survey.json").read_text())
    points = sum(len(read_points(p)[0]) for p in (out / "nominal").glob("*.las"))
    assert summary["points"] == {"nominal": points} and summary["points_written"] == points > 0
    assert summary["points_per_s"] == pytest.approx(points / summary["wall_s"], rel=0.01)
    assert set(summary["workers"]) == {"cpu0", "cpu1"}
    assert all(0 < w["peak_rss_mb"] < 2048 for w in summary["workers"].values())
    busy = [w["busy_s"] for w in summary["workers"].values()]  # one task at a time per single-threaded worker
    assert all(0 < b <= summary["wall_s"] + 0.01 for b in busy)
    assert sum(busy) == pytest.approx(summary["segments_s"] + summary["merges_s"], abs=0.01)
    assert summary["segments_s"] > 0 and summary["merges_s"] > 0
    again = subprocess.run(args, capture_output=True, text=True)  # a finished survey is not replaced
    assert again.returncode == 2 and "--overwrite" in again.stderr


def test_parts_kept_in_another_folder_give_the_same_tiles(serial, tmp_path, monkeypatch):
    out, summary = serial
    ram = tmp_path / "ram"
    ram.mkdir()
    seen = []
    segment_task = survey.segment_task

    def spy(cfg, grid, task, parts):
        seen.append(Path(parts))
        return segment_task(cfg, grid, task, parts)

    monkeypatch.setattr(survey, "segment_task", spy)
    elsewhere = run_survey(plan_survey(small_config(), SPEC), tmp_path / "out", parts=ram)
    assert tiles(tmp_path / "out") == tiles(out) and elsewhere["tiles"] == summary["tiles"]
    assert set(seen) == {survey.parts_folder(tmp_path / "out", ram)} and seen[0].parent == ram
    assert list(ram.iterdir()) == [] and not (tmp_path / "out" / ".parts").exists()
    assert survey.parts_folder(tmp_path / "other", ram) != seen[0]  # two surveys sharing the folder never meet


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="names a synced descriptor through /proc")
def test_merges_start_their_tiles_write_back_and_the_survey_syncs_each_tile_once_before_survey_json(
        serial, tmp_path, monkeypatch):
    """A merge does not wait for the disk: it starts its tile's write-back; run_survey then syncs every tile (and the
    tiles' folders) once, all before survey.json is written; the same tiles as the serial fixture's."""
    events: list[tuple[str, str]] = []
    fsync, fadvise = os.fsync, getattr(os, "posix_fadvise", None)

    def spy(kind, call):
        def record(fd, *args):
            events.append((kind, os.readlink(f"/proc/self/fd/{fd}")))
            return call(fd, *args)
        return record

    monkeypatch.setattr(os, "fsync", spy("sync", fsync))
    if fadvise is not None:
        monkeypatch.setattr(os, "posix_fadvise", spy("write-back", fadvise))
    out, cfg = tmp_path / "out", small_config()
    run_survey(plan_survey(cfg, SPEC), out)
    final = sorted(str(p) for p in out.glob("*/*.las"))
    assert tiles(out) == tiles(serial[0]) and len(final) >= 4
    synced = [path for kind, path in events if kind == "sync"]
    assert sorted(path for path in synced if path in final) == final  # each tile once
    folders = {str(out / model) for model in cfg.output.models}
    merging = [path for path in synced if str(Path(path).parent) in folders and path.endswith(".part")]
    assert merging == []  # no merge waited for the disk
    json_at = synced.index(str(out / ".survey.json.part"))
    assert all(synced.index(path) < json_at for path in final)
    assert folders <= set(synced[:json_at])  # the renames too
    if fadvise is not None:
        started = {path for kind, path in events if kind == "write-back"}
        assert len([path for path in started if ".las." in path and path.endswith(".part")]) == len(final)


def test_a_failed_survey_leaves_no_parts_behind(tmp_path, monkeypatch):
    """A task that fails after others wrote their parts: the error reaches the caller, the parts' folder is gone."""
    ram = tmp_path / "ram"
    ram.mkdir()
    segment_task, done = survey.segment_task, []

    def fail_third(cfg, grid, task, parts):
        if len(done) == 2:
            raise RuntimeError("the third task failed")
        done.append(segment_task(cfg, grid, task, parts))
        return done[-1]

    monkeypatch.setattr(survey, "segment_task", fail_third)
    with pytest.raises(RuntimeError, match="the third task failed"):
        run_survey(plan_survey(small_config(), SPEC), tmp_path / "out", parts=ram)
    assert len(done) == 2 and sum(len(r["tiles"].get("exact", {})) for r in done) > 0
    assert list(ram.iterdir()) == []


@pytest.mark.parametrize("error, removed", [(RuntimeError("a worker failed"), True),
                                            (InputError("--out", "DIR", "an empty or new directory"), False)])
def test_the_survey_command_removes_the_parts_of_a_failed_survey_not_of_a_refused_one(tmp_path, monkeypatch, error,
                                                                                      removed):
    """A survey that fails leaves nothing under --parts once its workers are gone; a command refused before any task
    ran (its --out in use, maybe by a survey running into it) leaves that folder alone."""
    from flightsim import cli

    ram, out = tmp_path / "ram", tmp_path / "out"
    ram.mkdir()
    folder = survey.parts_folder(out, ram)

    def fails(*args, **kwargs):
        (folder / "task").mkdir(parents=True)  # what a last task wrote
        raise error

    monkeypatch.setattr(survey, "run_survey", fails)
    argv = ["survey", "--size-km", "0.8", "--tile-m", "400", "--out", str(out), "--parts", str(ram)]
    if removed:
        with pytest.raises(RuntimeError, match="a worker failed"):
            cli.main(argv)
    else:
        assert cli.main(argv) == 2
    assert folder.exists() is not removed


def test_a_parts_folder_that_does_not_exist_stops_the_survey_command(tmp_path):
    args = [sys.executable, "-m", "flightsim", "survey", "--size-km", "0.8", "--tile-m", "400", "--workers", "2",
            "--out", str(tmp_path / "out"), "--parts", str(tmp_path / "missing")]
    done = subprocess.run(args, capture_output=True, text=True)
    assert done.returncode == 2 and not (tmp_path / "out").exists()
    missing = tmp_path / "missing"
    assert done.stderr.strip().splitlines()[-1] == (f"flightsim: error: invalid --parts = '{missing}': expected an "
                                                    "existing directory that every worker can write to")


@pytest.mark.parametrize("settings, spec, field", [
    ({}, SurveySpec(size_km=0.0), "survey.size_km"),
    ({}, SurveySpec(sidelap=0.95), "survey.sidelap"),
    ({}, SurveySpec(tile_m=300), "survey.tile_m"),  # the calibration block does not fit
    ({"flight.heading_deg": 45.0}, SPEC, "flight.heading_deg"),
    ({"flight.altitude_m": 20.0}, SPEC, "flight.altitude_m"),  # below the roofs
])
def test_bad_survey_input_names_the_field(settings, spec, field):
    with pytest.raises(InputError, match=field):
        plan_survey(small_config(**settings), spec)



def _header(offsets=(408500.0, 3392500.0, 0.0), statistics: bool = False):
    """A LAS 1.4 header of point format 6 with a plane_id extra dimension, 1 mm scales; without ``statistics``
    its descriptor claims no minimum and maximum (as the tiles' do: flightsim.outputs.las_format)."""
    import laspy

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.array([0.001] * 3), np.array(offsets)
    header.add_extra_dims([laspy.ExtraBytesParams("plane_id", np.int32)])
    if not statistics:
        header.vlrs.get("ExtraBytesVlr")[0].extra_bytes_structs[0].options = 0
    return header


def _part(path: Path, header, rng, n: int, returns: int) -> np.ndarray:
    """A LAS part of ``n`` random points (return numbers 1 … ``returns``) written by laspy; its point records."""
    import laspy

    points = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    points.X = rng.integers(-10**6, 10**6, n)
    points.Y = rng.integers(-10**6, 10**6, n)
    points.Z = rng.integers(-10**4, 10**4, n)
    points.return_number = rng.integers(1, returns + 1, n)
    points.number_of_returns = np.full(n, returns)
    points.gps_time = rng.uniform(0.0, 100.0, n)
    points["plane_id"] = rng.integers(0, 50, n)
    with laspy.open(path, mode="w", header=header) as writer:
        writer.write_points(points)
    return points.array


@pytest.mark.parametrize("compress", [False, True])
def test_merged_tiles_are_the_bytes_laspy_writes_for_the_parts_points(tmp_path, compress):
    """The merge copies the parts' records after a header for them all (LAS) or compresses them (LAZ): the file is
    what laspy's writer makes of all the parts' points in order, and its header's counts and bounds are theirs."""
    import laspy

    header = _header()
    rng = np.random.default_rng(7)
    parts = [tmp_path / f"part{i}.las" for i in range(4)]
    records = [_part(p, header, rng, n, r) for p, n, r in zip(parts, (5000, 0, 61234, 777), (1, 1, 3, 2))]
    expected = tmp_path / ("expected.laz" if compress else "expected.las")  # LAZ: two chunks, compressed in turn
    with laspy.open(expected, mode="w", header=header, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs
                    if compress else None) as writer:
        for part in parts:
            writer.write_points(laspy.read(part).points)
    target = tmp_path / "tile" / expected.name
    assert survey.merge_tile(parts, target, compress) == 67011
    merged = laspy.read(target)
    assert np.array_equal(merged.points.array, np.concatenate(records))
    xyz = np.stack([merged.x, merged.y, merged.z], axis=1)
    assert np.array_equal(merged.header.mins, xyz.min(axis=0)) and np.array_equal(merged.header.maxs, xyz.max(axis=0))
    assert list(merged.header.number_of_points_by_return[:3]) == list(np.bincount(merged.return_number)[1:4])
    assert target.read_bytes() == expected.read_bytes()
    assert [p.name for p in target.parent.iterdir()] == [target.name]  # no temporary left


@pytest.mark.parametrize("second", [{"offsets": (408501.0, 3392500.0, 0.0)}, {"statistics": True}])
def test_parts_whose_headers_cannot_be_joined_are_not_concatenated(tmp_path, second):
    rng = np.random.default_rng(1)
    parts = [tmp_path / "a.las", tmp_path / "b.las"]
    _part(parts[0], _header(), rng, 10, 1)
    _part(parts[1], _header(**second), rng, 10, 1)
    with pytest.raises(RuntimeError, match="b.las: not the header of"):
        survey.merge_tile(parts, tmp_path / "t.las", False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.las", "b.las"]
