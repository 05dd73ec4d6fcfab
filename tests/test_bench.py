"""Benchmark plumbing and the float64 reference path (no timing is asserted: machines are noisy)."""
import json
import os
import sys

import numpy as np
import pytest

from flightsim.studies.accuracy import measure_errors
from flightsim.studies.bench import run_bench
from flightsim.studies.bench_common import simulator, workload


@pytest.mark.parametrize("altitude", [500.0, 5000.0])
def test_float64_pipeline_matches_the_reference_to_a_tenth_of_a_millimetre(device, altitude):
    errors = measure_errors(simulator(workload(device, 3, 1e5, **{"flight.altitude_m": altitude}), with_truth=True))
    assert errors.returns > 50_000
    assert errors.max_pointing_rad < 1e-7
    assert max(errors.max_point_error_m.values()) < 1e-4


def test_the_reference_sees_what_a_coarse_exit_table_costs(device):
    coarse = workload(device, 3, 5e4, **{"run.optics": "lut", "run.lut_samples": 64})
    errors = measure_errors(simulator(coarse, with_truth=True))
    # linear interpolation over 5.6° steps of φ: the chord error of a 15° cone, ~0.26·(Δφ)²/8 rad
    assert 2e-4 < errors.max_pointing_rad < 4e-4


def test_bench_writes_records_with_the_fields_the_issue_names(tmp_path):
    run_bench("cpu", quick=True, out=tmp_path, sections=("throughput",))
    bench = json.loads((tmp_path / "bench.json").read_text())
    record = bench["cpu"]["throughput"][0]
    for key in ("device", "gpu_name", "scene", "triangles", "array", "pulses", "returns", "wall_s", "returns_per_s",
                "raycast_returns_per_s", "ratio", "git_commit"):
        assert key in record
    assert record["returns_per_s"] == pytest.approx(record["returns"] / record["wall_s"])
    assert record["ratio"] == pytest.approx(record["returns_per_s"] / record["raycast_returns_per_s"])
    assert "| 3×3 | 1 |" in (tmp_path / "bench.md").read_text()


def test_stage_report_names_each_kernel_and_accounts_for_the_wall_time():
    from flightsim.studies.bench_common import kernel_name
    from flightsim.studies.bench_report import markdown

    assert kernel_name("forward kernel records_kernel__locals__trace_records_1a2b3c4") == "trace_records"
    assert kernel_name("forward kernel pulse_poses_0f3a9e1") == "pulse_poses"
    stage = {"array": 3, "slots": 1000, "returns": 990, "wall_s": 1e-6, "bare_raycast_s": 2e-7,
             "kernels_s": {"trace_records": 6e-7, "reduce_records": 2e-7}}
    text = markdown({"cuda": {"gpu_name": "GPU", "device": "cuda:0", "git_commit": "x", "date": "d",
                              "stages": [stage]}})
    rows = {line.split(" | ")[1]: line.split(" | ")[2:] for line in text.splitlines() if line.startswith("| 3×3 |")}
    assert rows["trace_records"][:2] == ["6e-07", "0.600"]  # seconds, ns per slot
    assert rows["host work and gaps (wall − kernels)"][0] == "2e-07"  # 1e-6 − 6e-7 − 2e-7
    assert rows["wall"][2].strip(" |") == "100%"


def test_reduce_report_has_a_column_per_setting_and_says_where_memory_capped_the_copies():
    from flightsim.studies.bench_report import markdown

    ratios = [{"sum_replicas": 64, "slots_per_thread": 16, "replicas_used": 64, "ratio": 0.5},
              {"sum_replicas": 2048, "slots_per_thread": 32, "replicas_used": 1000, "ratio": 0.625}]
    row = {"case": "terrain 1e+06", "triangles": 999698, "planes": 1, "returns": 10, "raycast_returns_per_s": 6e9,
           "ratios": ratios}
    text = markdown({"cuda": {"gpu_name": "GPU", "device": "cuda:0", "git_commit": "x", "date": "d", "reduce": [row]}})
    lines = text.splitlines()
    header = next(line for line in lines if line.startswith("| case |"))
    assert header.endswith("| R 64, 16 slots | R 2048, 32 slots |")
    assert "| terrain 1e+06 | 1e+06 | 1 | 6e+09 | 0.500 | 0.625 (R 1000) |" in lines


def test_scale_section_las_run_counts_every_byte_of_its_tiles(tmp_path):
    """The scale section's LAS run (records packed by the device writer): what it reports as written is the
    tiles' size on disk, the header and LAS 1.4 format-6 records with flightsim's extra bytes of every point."""
    import laspy

    from flightsim.studies import bench_scale

    cfg = workload("cpu", 3, 2e4, **{"scene.name": "plane", "flight.duration_s": 0.2})
    wall, counts, written = bench_scale._las_run_into(simulator(cfg), cfg, tmp_path / "las")
    tiles = sorted((tmp_path / "las").rglob("*.las"))
    headers = [laspy.open(t).header for t in tiles]
    assert wall > 0 and counts.returns > 5000
    assert sum(h.point_count for h in headers) == 2 * counts.returns  # both models
    assert written == sum(h.offset_to_point_data + h.point_count * h.point_format.size for h in headers)
    assert written == sum(t.stat().st_size for t in tiles)


def test_waveform_report_gives_end_to_end_over_accumulation():
    from flightsim.studies.bench_report import markdown

    row = {"scene": "slope", "shots": 20000, "subrays": 144000000, "samples": 32768, "wall_s": 0.04,
           "subray_returns_per_s": 3.6e9, "raycast_returns_per_s": 3.0e10, "ratio": 0.12,
           "accumulation_returns_per_s": 1.2e10, "kernels_s": {"deposit": 0.012, "convolve_fft": 0.025}}
    cpu_row = {**row, "accumulation_returns_per_s": None, "kernels_s": {}}
    text = markdown({"cuda": {"gpu_name": "GPU", "device": "cuda:0", "git_commit": "x", "date": "d",
                              "waveform": [row, cpu_row]}})
    rows = [line.split(" | ") for line in text.splitlines() if line.startswith("| slope | 20,000 |")]
    assert [r[9] for r in rows] == ["0.30", "n/a"]  # 3.6e9 ÷ 1.2e10; no kernels' times on the CPU
    assert rows[0][10] == "25.0 |"  # the FFTs' 25 ms


def test_the_forest_scene_build_is_measured_through_its_own_cache_folder(tmp_path, monkeypatch):
    from flightsim.studies.bench_forest import scene_build
    from flightsim.studies.bench_report import markdown

    monkeypatch.setenv("FLIGHTSIM_CACHE", str(tmp_path / "users"))
    b = scene_build(30.0)
    assert set(b) == {"forest_size_m", "voxels", "threads", "computed_s", "stored_s", "cached_s"}
    assert len(b["voxels"]) == 3 and b["voxels"][2] > 1 and b["threads"] >= 1
    assert not (tmp_path / "users").exists()  # its entries went to a folder of its own, and the user's is set back
    text = markdown({"cpu": {"gpu_name": "none", "device": "cpu", "git_commit": "x", "date": "d", "forest": {
        "cloud": {"samples": 1000, "points": 1, "footprints": 1, "device_s": 1.0, "footprints_per_s": 1.0,
                  "numpy_footprints_per_s": 1.0, "speedup": 1.0, "min_correlation": 1.0, "prepare_s": 1.0,
                  "numpy_footprints": 1},
        "voxels": {"rays": 1, "grid": [1, 1, 1], "steps": 1, "wall_s": 1.0, "steps_per_s": 1.0},
        "scene": {**b, "computed_s": 17.25, "stored_s": 18.0, "cached_s": 0.5, "device": {
            "computed_s": 0.734, "voxels_differing": 1234, "max_difference": 3.1e-14, "max_lad": 1.96}},
        "als": {"forest_size_m": 30.0, "forest": {"beams": 1, "returns": 1, "wall_s": 1.0, "beams_per_s": 1.0},
                "bare": {"beams": 1, "returns": 1, "wall_s": 1.0, "beams_per_s": 1.0}, "ratio": 1.0}}}})
    assert "17.2 s with its voxels computed, 18.0 s computed and stored in the scene cache, 0.50 s from it" in text
    assert ("for a run on the GPU, its voxels integrated there: 0.73 s; 1,234 of the voxels differ from the host's, by at "
            "most 3.1e-14 m²/m³ (densities up to 1.96)") in text


def test_the_forest_breakdown_runs_its_variants_over_one_stand():
    from flightsim.studies.forest_events import forest_events

    rows = forest_events("cpu", 3e3, 150.0, ["as is", "no blind stretch", "no echo reaches the threshold"], runs=1)
    assert [r["variant"] for r in rows] == ["as is", "no blind stretch", "no echo reaches the threshold"]
    assert len({r["beams"] for r in rows}) == 1 and rows[0]["beams"] > 0
    assert rows[0]["returns"] > rows[0]["beams"]  # leaf returns besides the ground's
    assert rows[1]["returns"] > rows[0]["returns"]  # a detector that is never blind misses no leaf echo
    assert rows[2]["returns"] == 0  # no echo reaches a white target's: ρ_l (1 − T) < 1 and T ρ cos θ < 1


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="the child's own high-water mark is read from /proc")
def test_a_benchmark_process_peak_memory_is_its_own_not_the_benchmarks():
    from flightsim.studies.bench_common import run_measured

    held = np.ones(600 << 17)  # 600 MiB resident here, in the process that starts the child
    child = [sys.executable, "-c", "import time; b = bytearray(150 << 20); time.sleep(0.3)"]  # 150 MiB
    wall, code, peak_mib, _ = run_measured(child)
    assert code == 0 and wall >= 0.3
    assert 150 <= peak_mib < 250, peak_mib  # wait4's ru_maxrss alone gives > 600 here (the fork's pages)
    assert held[-1] == 1.0


def test_the_benchmarks_children_read_and_write_their_bytecode(monkeypatch):
    import subprocess

    from flightsim.studies.bench_common import child_bytecode

    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")  # as on the GPU machines
    monkeypatch.setenv("PYTHONPYCACHEPREFIX", "/elsewhere")
    probe = [sys.executable, "-c", "import sys; print(sys.dont_write_bytecode, sys.pycache_prefix)"]
    with child_bytecode() as folder:
        seen = subprocess.run(probe, capture_output=True, text=True, check=True).stdout.split()
        assert seen == ["False", folder] and os.path.isdir(folder)
    assert not os.path.exists(folder)
    assert os.environ["PYTHONDONTWRITEBYTECODE"] == "1" and os.environ["PYTHONPYCACHEPREFIX"] == "/elsewhere"


def test_the_build_once_row_takes_each_ways_best_of_rounds_in_turn(monkeypatch):
    """The sweep row of the skip section: shared scene and rebuilt scenes alternate, and each way's wall is its best
    round (a single timing each charged the first way with the process's first-use costs)."""
    from flightsim.studies import bench_savings

    calls = []
    monkeypatch.setattr(bench_savings, "run_statistics", lambda sim: calls.append(sim.meshes))
    clock = iter([0.0, 9.0, 10.0, 12.0, 20.0, 21.0, 30.0, 35.0])  # shared 9, rebuilt 2, shared 1, rebuilt 5
    monkeypatch.setattr(bench_savings.time, "perf_counter", lambda: next(clock))
    row = bench_savings._build_once_saving(workload("cpu", 3, 2e4), rounds=2)
    rounds = [calls[k:k + 5] for k in range(0, 20, 5)]  # shared, rebuilt, shared, rebuilt: one BVH or five
    assert [len({id(m) for m in r}) for r in rounds] == [1, 5, 1, 5]
    assert (row["variant_s"], row["baseline_s"]) == (1.0, 2.0)
    assert row["saving"] == pytest.approx(0.5)


def test_gedi_shots_are_timed_end_to_end_over_a_cloud_written_as_las(tmp_path, monkeypatch):
    import laspy

    from flightsim.studies import bench_shots
    from flightsim.studies.bench_report import _forest_shots

    from flightsim.instrument.cloud_waveform_model import synthetic_forest

    cloud, shots, written = bench_shots.write_shots(tmp_path / "c", 60_000, 7)
    assert written == len(synthetic_forest(60_000, seed=1).xyz)
    with laspy.open(cloud) as reader:  # a LAS 1.4 file a user's reader takes, with its CRS
        assert (reader.header.point_count, str(reader.header.version)) == (written, "1.4")
        assert reader.header.parse_crs().to_epsg() == 32648
        xy = reader.read().xyz[:, :2]
    centres = np.loadtxt(shots, delimiter=",", skiprows=1)
    assert centres.shape == (7, 3) and np.all(np.diff(centres[:, 2]) > 0)
    assert np.all(centres[:, :2] >= xy.min(axis=0) + 30.0) and np.all(centres[:, :2] <= xy.max(axis=0) - 30.0)
    monkeypatch.setattr(bench_shots, "WARM_POINTS", 60_000)
    r = bench_shots.cloud_shots("cpu", 60_000, 7)
    assert r["waveforms"] == r["footprints"] == 7 and r["points"] == written
    assert 0.0 < sum(r["stages_s"].values()) < r["wall_s"] and r["footprints_per_s"] == pytest.approx(7 / r["wall_s"])
    assert 50.0 < r["peak_rss_mib"] < 4096.0
    text = "\n".join(_forest_shots(r))
    assert f"7 footprints over {written:,} points" in text and "stages [s]: scene " in text


def test_the_photon_section_writes_a_runs_photons_again_in_its_parts_of_whole_pulses(tmp_path):
    """The LAS writer's record of the photons section: the photons of a SPAD run read back from photons.h5 in parts of
    whole pulses, each part's points, pulse times and truth those of photons.h5; every photon written on one thread
    and on two; the report's line says so."""
    import h5py

    import flightsim.studies.bench_photon_runs as section
    import flightsim.studies.bench_photon_writers as writers
    from flightsim.api import load_config
    from flightsim.engine.instrument import Instrument
    from flightsim.engine.run import simulate_to_directory
    from flightsim.engine.world import build_scene

    cfg = load_config(instrument="spad", overrides={"flight.duration_s": 0.002, "run.host_photons": 5000})
    summary = simulate_to_directory(cfg, tmp_path / "spad")
    scene, timing = build_scene(cfg), Instrument(cfg).deflector.timing()
    parts = writers.run_parts(tmp_path / "spad" / "photons.h5", scene.origin, timing.prf_hz, cfg.run.host_photons)
    with h5py.File(tmp_path / "spad" / "photons.h5") as f:
        h5 = {name: f["photons"][name][:] for name in ("pulse", "delta_time", "signal", "x", "y", "z")}
    assert len(parts) > 3 and sum(len(p) for p in parts) == summary["photons"] == len(h5["pulse"])
    assert all(a.pulse[-1] != b.pulse[0] for a, b in zip(parts, parts[1:]))  # no pulse split
    joined = {name: np.concatenate([getattr(p, name) for p in parts]) for name in ("pulse", "kind", "points")}
    np.testing.assert_array_equal(joined["pulse"], h5["pulse"])
    np.testing.assert_array_equal(joined["kind"], h5["signal"])
    np.testing.assert_allclose(joined["points"] + scene.origin, np.column_stack([h5["x"], h5["y"], h5["z"]]),
                               rtol=0, atol=1e-9)
    times = np.concatenate([timing.pulse_times(p.start_time, p.pulse) for p in parts])
    np.testing.assert_allclose(times, h5["delta_time"], rtol=0, atol=1e-9)
    record = writers.las_writer(tmp_path / "spad", threads=2)
    assert record["photons"] == summary["photons"] and record["parts"] == len(parts) and record["threads"] == 2
    assert record["one_thread_s"] > 0 and record["threads_s"] > 0
    lines = section.markdown({"photons": {"runs": [], "las_writer": record}})
    assert any(f"{record['photons']:.3g} photons ({len(parts)} parts)" in line for line in lines)
    assert not any("writers_s" in line for line in lines)  # records without the writers' times: no table
    run = {"instrument": "spad", "command": "flightsim simulate", "photons": summary["photons"], "wall_s": 1.0,
           "photons_per_s": 1.0, "peak_rss_mib": 1.0, "stages_s": summary["stages_s"],
           "writers_s": summary["writers_s"]}
    lines = section.markdown({"photons": {"runs": [run], "las_writer": record}})
    las = summary["writers_s"]["photons/"]
    assert f"| spad | photons/ | {las['busy']:.2f} | {las['cpu']:.2f} | {las['prepare']:.2f} |" in "\n".join(lines)


def test_the_photon_section_times_each_atlas_product_alone_on_a_runs_photons(tmp_path):
    """ATLAS's products alone: photons.h5, the tiles and atl03.h5 each handed every photon of a short pass (the run's
    parts), ATL08 on the beam of most photons of the atl03.h5 written; the report has a row for each."""
    import h5py

    import flightsim.studies.bench_photon_writers as writers
    from flightsim.api import load_config
    from flightsim.engine.run import simulate_to_directory

    cfg = load_config(instrument="atlas", overrides={"flight.duration_s": 0.05, "run.host_photons": 4000})
    summary = simulate_to_directory(cfg, tmp_path / "atlas")
    record = writers.atlas_products(tmp_path / "atlas")
    with h5py.File(tmp_path / "atlas" / "atl03.h5") as f:
        beams = {name: f[f"{name}/heights/h_ph"].shape[0] for name in f if name.startswith("gt")}
    steps = {step["step"]: step for step in record["steps"]}
    assert record["parts"] > 3 and list(steps)[:3] == ["photons.h5", "photons/ (one thread)", "atl03.h5"]
    assert all(steps[name]["photons"] == summary["photons"] for name in list(steps)[:3])
    beam = max(beams, key=beams.get)
    assert steps[f"atl08.h5, beam {beam}"]["photons"] == beams[beam] and len(steps) == 4
    assert all(step["calls_s"] >= 0.0 and step["close_s"] > 0.0 for step in record["steps"])
    las = {"photons": 1, "parts": 1, "threads": 2, "one_thread_photons_per_s": 1.0, "threads_photons_per_s": 2.0,
           "speedup": 2.0}
    text = "\n".join(writers.writer_lines(las, record))
    assert all(f"| {name} | {step['photons']:.3g} | {step['calls_s']:.2f} | {step['close_s']:.2f} |" in text
               for name, step in steps.items())


def test_the_bench_commands_help_names_every_section():
    from flightsim.cli import make_parser
    from flightsim.studies.bench import SECTIONS

    parser = make_parser()
    bench = parser._subparsers._group_actions[0].choices["bench"]
    sections = next(a for a in bench._actions if a.dest == "sections").help
    listed = sections.split("subset of ")[1].split(" ")[0].split(",")
    assert listed == list(SECTIONS)
