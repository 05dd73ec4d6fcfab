"""The parameter sweep: the seed paper's regression numbers, device statistics, resumability."""
import csv
import subprocess
import sys

import numpy as np
import pytest

from flightsim.studies import sweep as sweep_module
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.world import edge_buffer_m
from host_reference import HostPlaneStatistics
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.scoring.planes import pooled_rms
from flightsim.engine.tracer import Tracer
from flightsim.studies.sweep import SweepGrid, run_sweep
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.readouts.points import Points

DELTA = "2.314"


def read_rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def rms_of(rows, model, **match):
    return [float(r["rms_m"]) for r in rows if r["model"] == model and all(r[k] == v for k, v in match.items())]


def plane_grid(**axes) -> SweepGrid:
    base = RunConfig()
    set_value(base, "scene.name", "plane")
    set_value(base, "flight.duration_s", 1.0)
    return SweepGrid(base, [(key, values) for key, values in axes.items()])


@pytest.fixture(scope="module")
def altitude_rows(tmp_path_factory):
    out = tmp_path_factory.mktemp("altitude")
    altitudes = [str(500 * k) for k in range(1, 11)]
    run_sweep(plane_grid(**{"flight.altitude_m": altitudes}), out)
    return read_rows(out / "sweep.csv")


def test_rms_at_half_a_kilometre_matches_the_seed_paper(altitude_rows):
    (rms,) = rms_of(altitude_rows, "nominal", altitude_m="500.0")
    assert rms == pytest.approx(0.05, rel=0.10)  # paper: 0.0498 m


def test_rms_grows_linearly_with_altitude_at_the_papers_slope(altitude_rows):
    h_km = np.array([float(r["altitude_m"]) for r in altitude_rows if r["model"] == "nominal"]) / 1000
    rms = np.array(rms_of(altitude_rows, "nominal"))
    slope, intercept = np.polyfit(h_km, rms, 1)
    r2 = 1 - np.sum((rms - (slope * h_km + intercept)) ** 2) / np.sum((rms - rms.mean()) ** 2)
    assert slope == pytest.approx(0.1, rel=0.15)  # paper: ≈ 0.1 m/km
    assert r2 > 0.99 and abs(intercept) < 0.01
    assert max(rms_of(altitude_rows, "exact")) < 0.002


def test_rms_increases_strictly_with_array_size_and_spacing(tmp_path):
    run_sweep(plane_grid(**{"fan.array": ["2", "3", "4", "5", "6"]}), tmp_path / "a")
    by_array = rms_of(read_rows(tmp_path / "a" / "sweep.csv"), "nominal")
    spacings = [f"{k * 2.314:.3f}" for k in range(1, 6)]
    run_sweep(plane_grid(**{"fan.spacing_mrad": spacings}), tmp_path / "s")
    rows = read_rows(tmp_path / "s" / "sweep.csv")
    by_spacing = rms_of(rows, "nominal")
    assert np.all(np.diff(by_array) > 0) and np.all(np.diff(by_spacing) > 0)
    assert max(rms_of(rows, "exact")) < 0.002


@pytest.mark.parametrize("replicas", [None, 7])
def test_device_statistics_equal_the_point_path(device, replicas, monkeypatch):
    if replicas:  # a GPU's copies of the sums, added on the device, also where the device is the CPU
        monkeypatch.setattr(Tracer, "sum_replicas", lambda self, groups=None: replicas)
    cfg = RunConfig()
    set_value(cfg, "flight.duration_s", 3.0)
    set_value(cfg, "run.device", device)
    cfg = validate(cfg)
    scene = build_scene(cfg)
    buffer = edge_buffer_m(cfg)
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene), edge_buffer_m=buffer)
    host = HostPlaneStatistics(scene, simulator.models, buffer)
    point_counts = simulator.run(Points(), host)
    device_moments, device_counts = run_statistics(simulator)
    assert device_counts.returns == point_counts.returns
    assert device_counts.edge_excluded == point_counts.returns - int(host.moments["exact"].count.sum()) > 0
    for model, tolerance in (("nominal", dict(rel=1e-6)), ("exact", dict(abs=1e-7))):
        a, b = host.moments[model], device_moments[model]
        assert np.array_equal(a.count, b.count)
        fits_a, fits_b = a.fits(), b.fits()
        assert len(fits_a) > 20  # roofs, walls, roads and ground of the calibration field
        for fa, fb in zip(fits_a, fits_b):
            assert fb.rms_m == pytest.approx(fa.rms_m, **tolerance)
        assert pooled_rms(fits_b) == pytest.approx(pooled_rms(fits_a), **tolerance)


def test_a_crashed_sweep_resumes_without_losing_or_duplicating_rows(tmp_path, monkeypatch):
    grid = plane_grid(**{"fan.array": ["2", "3", "4"], "flight.altitude_m": ["500", "900"]})
    run_sweep(grid, tmp_path / "clean")
    real = sweep_module.run_configuration
    calls = []

    def crash_on_fourth(*args):
        calls.append(1)
        if len(calls) == 4:
            raise RuntimeError("simulated crash")
        return real(*args)

    monkeypatch.setattr(sweep_module, "run_configuration", crash_on_fourth)
    with pytest.raises(RuntimeError):
        run_sweep(grid, tmp_path / "crashed")
    assert len(read_rows(tmp_path / "crashed" / "sweep.csv")) == 2 * 3  # three finished configurations
    monkeypatch.setattr(sweep_module, "run_configuration", real)
    run_sweep(grid, tmp_path / "crashed")
    strip = lambda rows: [{k: v for k, v in r.items() if k != "wall_s"} for r in rows]
    assert strip(read_rows(tmp_path / "crashed" / "sweep.csv")) == strip(read_rows(tmp_path / "clean" / "sweep.csv"))
    assert len(read_rows(tmp_path / "crashed" / "planes.csv")) == len(read_rows(tmp_path / "clean" / "planes.csv"))


def test_sweep_command_sweeps_any_setting_and_plots(tmp_path):
    out = tmp_path / "sweep"
    result = subprocess.run(
        [sys.executable, "-m", "flightsim", "sweep", "--scene", "plane", "--duration", "0.5", "--arrays", "2,3",
         "--set", "prism.refractive_index=1.45,1.5066", "--out", str(out)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    rows = read_rows(out / "sweep.csv")
    assert list(rows[0])[:6] == ["altitude_m", "array", "spacing_mrad", "model", "rms_m", "points"]
    assert {(r["array"], r["risley.refractive_index"]) for r in rows} == {
        ("2", "1.45"), ("2", "1.5066"), ("3", "1.45"), ("3", "1.5066")}
    assert len(rows) == 8 and (out / "rms_vs_array.png").stat().st_size > 1000
    bad = subprocess.run([sys.executable, "-m", "flightsim", "sweep", "--arrays", "2,65", "--out", str(tmp_path / "x")],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "fan.array" in bad.stderr and not (tmp_path / "x").exists()


def test_a_grids_configurations_are_made_once_and_again_when_the_grid_changes(monkeypatch):
    made = []
    validate_once = sweep_module.validate
    monkeypatch.setattr(sweep_module, "validate", lambda cfg: made.append(1) or validate_once(cfg))
    grid = SweepGrid(RunConfig(), [("flight.altitude_m", [500.0, 1000.0]), ("fan.array", [2, 3])])
    first = grid.configurations()
    again = grid.configurations()
    assert len(made) == 4 and [c for _, c in again] == [c for _, c in first]  # the command line asks four times
    assert [(labels["altitude_m"], labels["array"]) for labels, _ in first] == [(500.0, 2), (500.0, 3), (1000.0, 2),
                                                                                 (1000.0, 3)]
    set_value(grid.base, "run.seed", 7)  # the base changed: made again from it
    assert [c.run.seed for _, c in grid.configurations()] == [7] * 4 and len(made) == 8
    grid.axes.append(("run.seed", [1, 2]))  # so did the axes
    assert len(grid.configurations()) == 8 and len(made) == 16


def test_sweep_cost_times_the_studys_configurations_and_can_keep_a_grid_per_cap(monkeypatch, capsys):
    from flightsim.engine import meshes
    from flightsim.studies import sweep_cost

    monkeypatch.setattr(meshes, "EDGE_GRID_SPAN", meshes.EDGE_GRID_SPAN)  # restored after the test
    assert sweep_cost.main(["--device", "cpu", "--configs", "2", "--duration", "0.01", "--separate-edge-grids"]) == 0
    assert meshes.EDGE_GRID_SPAN == 1.0
    line = capsys.readouterr().out.splitlines()[0]
    assert line.startswith("cpu: ") and line.endswith("ms per configuration (2 configurations, a grid per edge cap)")
    assert 0.0 < float(line.split()[1]) < 5000.0


def test_the_risley_fans_angles_are_traced_once_per_fan_and_are_the_traces(monkeypatch):
    """The edge buffer's distortion and the cone's off-axis angle come from the float64 exit fan over a turn; a
    sweep's configurations that share a fan (array, spacing, prism) share its trace."""
    import math

    from flightsim.engine.instrument import Instrument
    from flightsim.instrument import risley, risley_model

    traced = []
    trace = risley_model.trace_fan
    monkeypatch.setattr(risley_model, "trace_fan", lambda *a, **k: traced.append(a[1]) or trace(*a, **k))
    risley.turn_angles.cache_clear()
    grid = SweepGrid(RunConfig(), [("flight.altitude_m", [500.0, 2000.0]), ("fan.array", [3, 5])])
    buffers = {(labels["altitude_m"], labels["array"]): edge_buffer_m(cfg) for labels, cfg in grid.configurations()}
    assert sorted(traced) == [3, 5]  # two fans, each traced once (360 angles) for four configurations
    cfg = grid.configurations()[3][1]
    deflector = Instrument(cfg).deflector
    s = deflector.s
    fan = trace(np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False), 5, deflector.emitter.spacing_rad,
                s.refractive_index, math.radians(s.apex_angle_deg), s.thickness_mm * 1e-3, precision="float64")
    angle = np.arctan2(np.linalg.norm(np.cross(fan.directions, fan.nominal), axis=-1),
                       np.sum(fan.directions * fan.nominal, axis=-1))
    slant = 2000.0 / math.cos(math.radians(s.cone_half_angle_deg))
    divergence = Instrument(cfg).emitter.divergence_mrad
    assert buffers[(2000.0, 5)] == slant * (0.5 * divergence * 1e-3 + float(angle[fan.ok].max()))
    assert buffers[(2000.0, 5)] / buffers[(500.0, 5)] == pytest.approx(4.0, rel=1e-12)


def test_a_sweep_hashes_each_configuration_once(tmp_path, monkeypatch):
    hashed = []
    key = sweep_module.config_key
    monkeypatch.setattr(sweep_module, "config_key", lambda cfg: hashed.append(1) or key(cfg))
    base = RunConfig()
    set_value(base, "scene.name", "plane")
    set_value(base, "flight.duration_s", 0.05)
    grid = SweepGrid(validate(base), [("fan.array", [2, 3])])
    path = run_sweep(grid, tmp_path / "sweep")
    assert len(hashed) == 2 and len(list(csv.DictReader(open(path)))) == 4
    assert sorted(p.stem for p in (tmp_path / "sweep" / "rows").glob("*.json")) == sorted(
        key(cfg) for _, cfg in grid.configurations())


def test_planes_csv_is_written_once_at_the_end_and_sweep_csv_as_rows_come(tmp_path, monkeypatch):
    written = []
    write = sweep_module.write_atomic
    monkeypatch.setattr(sweep_module, "write_atomic", lambda path, text: written.append(path.name) or write(path, text))
    monkeypatch.setattr(sweep_module, "TABLES_INTERVAL_S", 0.0)  # the tables after every configuration
    base = RunConfig()
    set_value(base, "scene.name", "plane")
    set_value(base, "flight.duration_s", 0.05)
    grid = SweepGrid(validate(base), [("fan.array", [2, 3, 4])])
    run_sweep(grid, tmp_path / "sweep")
    assert written.count("sweep.csv") == 4 and written.count("planes.csv") == 1  # three as rows came, one at the end
    planes = list(csv.DictReader(open(tmp_path / "sweep" / "planes.csv")))
    assert {r["array"] for r in planes} == {"2", "3", "4"} and {r["model"] for r in planes} == {"exact", "nominal"}
