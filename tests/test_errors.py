"""Bad input through the command line: exit status 2 and one line naming the field, the value and
what is allowed, no traceback, and nothing written (SPEC §10). tests/test_cli.py covers the first
few flags; these are the rest: files, CRSs, trajectories, terrain clearance, devices, sweeps.

Every case is a real `python -m flightsim` subprocess; the processes of all cases are started
together (a few at a time) once per module, so the interpreter start-ups overlap.
"""
import math
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
WARP_NO_DRIVER = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"

TRAJECTORY_HEADER = "gps_time,easting,northing,height,roll,pitch,heading\n"


def _files(d: Path) -> None:
    """The bad (and the good-but-unflyable) input files the cases refer to."""
    (d / "afile").write_text("not a directory\n")
    (d / "dir.obj").mkdir()
    (d / "bad_altitude.toml").write_text("[flight]\naltitude_m = -1.0\n")
    (d / "broken.toml").write_text("[flight\naltitude_m = 500\n")
    (d / "junk.ply").write_bytes(bytes(np.random.default_rng(5).integers(0, 256, 300, dtype=np.uint8)))
    (d / "truncated.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n")
    (d / "nan.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 nan\n0 1 0\n3 0 1 2\n")
    (d / "bad_vertex.obj").write_text("v 0 0 0\nv 1 0 zero\nv 0 1 0\nf 1 2 3\n")
    (d / "bad_index.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    (d / "binary.obj").write_bytes(b"v 0 0 0\x00\x01\x02\nf 1 1 1\n")
    (d / "no_faces.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    (d / "zero_area.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 3 3\nf 1 2 3\nf 4 4 4\n")
    # a 600 m tower in the middle of a 1 km ground square: a 500 m flight over the centre hits it
    (d / "tower.obj").write_text(
        "v -500 -500 0\nv 500 -500 0\nv 500 500 0\nv -500 500 0\ng ground\nf 1 2 3 4\n"
        "v -5 -5 0\nv 5 -5 0\nv 5 5 0\nv -5 5 0\nv -5 -5 600\nv 5 -5 600\nv 5 5 600\nv -5 5 600\n"
        "g roof\nf 9 10 11 12\ng wall\nf 5 6 10 9\nf 6 7 11 10\nf 7 8 12 11\nf 8 5 9 12\n")
    rows = {
        "unsorted": [(450000001.0, 950.0), (450000000.0, 950.0), (450000002.0, 950.0)],
        "duplicate": [(450000000.0, 950.0), (450000000.0, 950.0), (450000001.0, 950.0)],
        "nan_height": [(450000000.0, 950.0), (450000001.0, math.nan)],
        "below_ground": [(450000000.0, 950.0), (450000001.0, 300.0)],  # calibration ground: 450 m
    }
    for name, samples in rows.items():
        lines = [f"{t!r},409000.0,{3393000.0 + 50 * k!r},{h!r},0,0,0\n" for k, (t, h) in enumerate(samples)]
        (d / f"{name}.csv").write_text(TRAJECTORY_HEADER + "".join(lines))


# (id, command line (DIR = the files' folder, OUT = a fresh output path), field, value as printed)
CASES = [
    ("config_file_value", ["simulate", "--config", "DIR/bad_altitude.toml"], "flight.altitude_m", "-1.0"),
    ("config_file_missing", ["simulate", "--config", "DIR/missing.toml"], "--config", "missing.toml"),
    ("config_file_broken", ["simulate", "--config", "DIR/broken.toml"], "--config", "broken.toml"),
    ("spacing_nan", ["simulate", "--spacing-mrad", "nan"], "fan.spacing_mrad", "nan"),
    ("duration_negative", ["simulate", "--duration", "-1"], "flight.duration_s", "-1.0"),
    ("array_fraction", ["simulate", "--array", "1.5"], "fan.array", "'1.5'"),
    ("fan_past_80_degrees", ["simulate", "--array", "64", "--spacing-mrad", "100"], "fan.spacing_mrad", "100.0"),
    ("apex_at_critical", ["simulate", "--set", "risley.apex_angle_deg=41.6"], "risley.apex_angle_deg", "41.6"),
    ("believed_apex_past_critical", ["simulate", "--set", "risley.believed_apex_angle_deg=42"],
     "risley.believed_apex_angle_deg", "42.0"),
    ("cone_past_grazing", ["simulate", "--set", "risley.cone_half_angle_deg=60"], "risley.cone_half_angle_deg",
     "60.0"),
    ("glass_below_air", ["simulate", "--set", "risley.refractive_index=0.9"], "risley.refractive_index", "0.9"),
    ("noise_negative", ["simulate", "--set", "instrument.errors=ranging", "--set", "ranging.noise_m=-0.1"],
     "ranging.noise_m", "-0.1"),
    ("seed_negative", ["simulate", "--seed", "-1"], "run.seed", "-1"),
    ("tile_size_zero", ["simulate", "--set", "output.tile_size_m=0"], "output.tile_size_m", "0"),
    ("patches_too_many", ["simulate", "--set", "scoring.patch_m=0.05"], "scoring.patch_m", "0.05"),
    ("patch_negative", ["simulate", "--set", "scoring.patch_m=-5"], "scoring.patch_m", "-5"),
    ("no_lines", ["simulate", "--set", "flight.lines=0"], "flight.lines", "0"),
    ("no_models", ["simulate", "--models", ","], "output.models", "''"),
    ("origin_two_numbers", ["simulate", "--set", "scene.origin=1,2"], "scene.origin", "(1.0, 2.0)"),
    ("set_without_value", ["simulate", "--set", "flight.altitude_m"], "--set", "'flight.altitude_m'"),
    ("crs_unknown_code", ["simulate", "--set", "scene.crs=EPSG:999999"], "scene.crs", "'EPSG:999999'"),
    ("crs_gibberish", ["simulate", "--set", "scene.crs=not-a-crs"], "scene.crs", "'not-a-crs'"),
    ("crs_without_wkt1", ["simulate", "--scene", "plane", "--set", "scene.crs=EPSG:3993"], "scene.crs",
     "'EPSG:3993'"),
    ("mesh_missing", ["simulate", "--scene", "DIR/missing.obj"], "scene.name", "missing.obj"),
    ("mesh_is_a_directory", ["simulate", "--scene", "DIR/dir.obj"], "scene.name", "dir.obj"),
    ("ply_random_bytes", ["simulate", "--scene", "DIR/junk.ply"], "scene.path", "junk.ply"),
    ("ply_truncated", ["simulate", "--scene", "DIR/truncated.ply"], "scene.path", "truncated.ply"),
    ("ply_nan_vertex", ["simulate", "--scene", "DIR/nan.ply"], "scene.path", "nan.ply"),
    ("obj_bad_vertex", ["simulate", "--scene", "DIR/bad_vertex.obj"], "scene.path", "bad_vertex.obj"),
    ("obj_index_out_of_range", ["simulate", "--scene", "DIR/bad_index.obj"], "scene.path", "bad_index.obj"),
    ("obj_binary", ["simulate", "--scene", "DIR/binary.obj"], "scene.path", "binary.obj"),
    ("empty_scene_no_faces", ["simulate", "--scene", "DIR/no_faces.obj"], "scene.path", "no_faces.obj"),
    ("empty_scene_zero_area", ["simulate", "--scene", "DIR/zero_area.obj"], "scene.path", "zero_area.obj"),
    ("tower_above_flight", ["simulate", "--scene", "DIR/tower.obj", "--duration", "0.2"], "flight.altitude_m",
     "500.0"),
    ("altitude_below_clearance", ["simulate", "--altitude", "0.5", "--duration", "0.2"], "flight.altitude_m",
     "0.5"),
    ("trajectory_unsorted", ["simulate", "--trajectory", "DIR/unsorted.csv"], "trajectory.gps_time",
     "450000000.0"),
    ("trajectory_duplicate_time", ["simulate", "--trajectory", "DIR/duplicate.csv"], "trajectory.gps_time",
     "450000000.0"),
    ("trajectory_nan_height", ["simulate", "--trajectory", "DIR/nan_height.csv"], "trajectory.height", "nan"),
    ("trajectory_missing", ["simulate", "--trajectory", "DIR/missing.csv"], "trajectory.file", "missing.csv"),
    ("trajectory_below_ground", ["simulate", "--trajectory", "DIR/below_ground.csv"], "flight.trajectory",
     "below_ground.csv"),
    ("out_under_a_file", ["simulate", "--scene", "plane", "--duration", "0.1", "--out", "DIR/afile/sub"], "--out",
     "afile/sub"),
    ("device_absent", ["simulate", "--scene", "plane", "--duration", "0.1", "--device", "cuda:99"], "run.device",
     "'cuda:99'"),
    ("sweep_empty_axis_value", ["sweep", "--altitudes", "500,,1000"], "--altitudes", "'500,,1000'"),
    ("sweep_array_zero", ["sweep", "--arrays", "0,3"], "fan.array", "0"),
    ("sweep_out_is_a_file", ["sweep", "--scene", "plane", "--duration", "0.1", "--out", "DIR/afile"], "--out",
     "afile"),
    ("sweep_out_under_a_file", ["sweep", "--scene", "plane", "--duration", "0.1", "--out", "DIR/afile/sub"],
     "--out", "afile/sub"),
    # the SPAD lidar, the waveform altimeter, the spaceborne altimeter and their scenes and platforms
    ("photon_pde_above_one", ["simulate", "--instrument", "spad", "--set", "photon.pde=1.5"], "photon.pde", "1.5"),
    ("spin_under_lines", ["simulate", "--set", "flight.body_rotation_period_s=600"],
     "flight.body_rotation_period_s", "600"),
    ("waveform_alpha_zero", ["waveform", "--set", "waveform.half_divergence_rad=0"],
     "waveform.half_divergence_rad", "0"),
    ("waveform_interval_above_pulse", ["waveform", "--set", "waveform.sample_interval_s=1e-8"],
     "waveform.sample_interval_s", "1e-08"),
    ("waveform_empty_footprint", ["waveform", "--set", "waveform.n_rings=0"], "waveform.n_rings", "0"),
    ("waveform_digitiser_without_scale", ["waveform", "--set", "waveform.bits=12"], "waveform.full_scale_w", "0"),
    ("dem_missing", ["simulate", "--scene", "DIR/missing.tif"], "scene.name", "missing.tif"),
    ("orbit_misses_the_scene", ["simulate", "--set", "flight.platform=orbit", "--altitude", "500000", "--set",
                                "flight.inclination_deg=20", "--set", "instrument.max_range_m=600000", "--duration",
                                "0.01"], "flight.inclination_deg", "20"),
    ("orbit_body_unknown", ["simulate", "--set", "flight.body=mars"], "flight.body", "mars"),
    ("ccr_two_coordinates", ["simulate", "--set", "scene.ccrs=[[0,0]]"], "scene.ccrs", "0.0"),
    ("calibrate_truth_short", ["calibrate", "--truth", "3,-2"], "--truth", "3,-2"),
]


PARAMS = [pytest.param(*case, id=case[0]) for case in CASES]


def _command(args: list[str], files: Path, out: Path) -> list[str]:
    args = [a.replace("DIR", str(files)) for a in args]
    if "--out" not in args:
        args += ["--out", str(out)]
    return [sys.executable, "-m", "flightsim", *args]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """(command, completed process, output path) of every case, run a few at a time."""
    files = tmp_path_factory.mktemp("inputs")
    _files(files)
    outs = tmp_path_factory.mktemp("outs")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))

    def run(case):
        name, args, _field, _value = case
        command = _command(args, files, outs / name)
        done = subprocess.run(command, capture_output=True, text=True, cwd=files, env=env, timeout=300)
        return name, (command, done, outs / name)

    with ThreadPoolExecutor(max_workers=4) as pool:
        return dict(pool.map(run, CASES))


def error_lines(stderr: str) -> list[str]:
    """stderr without Warp's notice that this machine has no CUDA driver (printed by Warp's C++ start-up)."""
    return [line for line in stderr.splitlines() if not line.startswith(WARP_NO_DRIVER)]


@pytest.mark.parametrize("name, args, field, value", PARAMS)
def test_bad_input_exits_2_with_one_line_naming_field_value_and_what_is_allowed(results, name, args, field, value):
    command, done, out = results[name]
    lines = error_lines(done.stderr)
    assert done.returncode == 2, f"{command}\n{done.stderr}"
    assert "Traceback" not in done.stderr and len(lines) == 1, done.stderr
    prefix = f"flightsim: error: invalid {field} = "
    assert lines[0].startswith(prefix), lines[0]
    given, sep, allowed = lines[0][len(prefix):].partition(": expected ")
    assert sep and len(allowed.strip()) > 3, lines[0]
    assert value in given, lines[0]
    if "--out" not in args:
        assert not out.exists(), f"{out} was created by a run that was refused"


def test_a_file_given_as_output_is_left_as_it_was(results):
    afile = Path(results["sweep_out_is_a_file"][0][-1])
    assert afile.name == "afile" and afile.read_text() == "not a directory\n"


# Real terrain (scenes.dem, scenes.raster, scenes.landcover, scenes.buildings): unreadable, empty, CRS-less and
# geographic GeoTIFFs, buildings outside the DEM, land cover in another CRS. These cases join the ones above
# (same fixture, same assertions); their files are written beside the others.
def _terrain_files(d: Path) -> None:
    import rasterio
    from rasterio.transform import from_origin

    def tif(name, crs, west, north, cell, values):
        with rasterio.open(d / name, "w", driver="GTiff", width=values.shape[1], height=values.shape[0], count=1,
                           dtype=values.dtype.name, crs=crs, transform=from_origin(west, north, cell, cell)) as dst:
            dst.write(values, 1)

    tif("dem.tif", "EPSG:32648", 408950.0, 3393050.0, 10.0, np.full((10, 10), 450.0, dtype=np.float32))
    tif("nocrs.tif", None, 0.0, 100.0, 1.0, np.full((5, 5), 450.0, dtype=np.float32))
    tif("wgs84.tif", "EPSG:4326", 105.0, 30.7, 1e-4, np.full((5, 5), 450.0, dtype=np.float32))
    tif("utm47.tif", "EPSG:32647", 408950.0, 3393050.0, 10.0, np.full((10, 10), 2, dtype=np.uint8))
    (d / "junk.tif").write_bytes(bytes(np.random.default_rng(6).integers(0, 256, 300, dtype=np.uint8)))
    (d / "empty.tif").write_bytes(b"")
    (d / "far.obj").write_text("v 409100 3393000 450\nv 409120 3393000 450\nv 409110 3393010 460\nf 1 2 3\n")


TERRAIN_CASES = [
    ("dem_unreadable", ["simulate", "--scene", "DIR/junk.tif"], "scene.name", "junk.tif"),
    ("dem_empty", ["simulate", "--scene", "DIR/empty.tif"], "scene.name", "empty.tif"),
    ("dem_without_crs", ["simulate", "--scene", "DIR/nocrs.tif"], "scene.name", "nocrs.tif"),
    ("dem_geographic", ["simulate", "--scene", "DIR/wgs84.tif"], "scene.name", "wgs84.tif"),
    ("buildings_outside_dem", ["simulate", "--scene", "DIR/dem.tif", "--set", "scene.buildings=DIR/far.obj"],
     "scene.buildings", "far.obj"),
    ("buildings_unreadable", ["simulate", "--scene", "DIR/dem.tif", "--set", "scene.buildings=DIR/junk.ply"],
     "scene.buildings", "junk.ply"),
    ("buildings_without_dem", ["simulate", "--set", "scene.buildings=DIR/far.obj"], "scene.buildings", "far.obj"),
    ("landcover_other_crs", ["simulate", "--scene", "DIR/dem.tif", "--set", "scene.landcover=DIR/utm47.tif"],
     "scene.landcover", "utm47.tif"),
    ("landcover_without_crs", ["simulate", "--scene", "DIR/dem.tif", "--set", "scene.landcover=DIR/nocrs.tif"],
     "scene.landcover", "nocrs.tif"),
    ("simplify_negative", ["simulate", "--scene", "DIR/dem.tif", "--set", "scene.simplify_m=-1"],
     "scene.simplify_m", "-1.0"),
]
CASES.extend(TERRAIN_CASES)  # collected after the module has run: the fixture and the parametrized test see them
PARAMS.extend(pytest.param(*case, id=case[0]) for case in TERRAIN_CASES)
_files_before_terrain = _files


def _files(d: Path) -> None:  # noqa: F811 - the fixture's inputs, terrain files included
    _files_before_terrain(d)
    _terrain_files(d)


# Keplerian orbits and the photon LAS points' CRS (platforms.orbit, outputs.photon_las): an open orbit, a
# perigee under the surface (e = 0.5 with the pass at apogee: perigee at a third of the pass's radius), an
# unknown and a geographic output CRS, and output.crs on a run that writes no photon tiles.
_ORBIT = ["simulate", "--set", "flight.platform=orbit", "--altitude", "500000", "--set", "instrument.max_range_m=600000",
          "--duration", "0.01"]
ORBIT_CASES = [
    ("orbit_open", _ORBIT + ["--set", "flight.eccentricity=1"], "flight.eccentricity", "1"),
    ("orbit_perigee_below_surface", _ORBIT + ["--set", "flight.eccentricity=0.5", "--set", "flight.perigee_arg_deg=210"],
     "flight.eccentricity", "0.5"),
    ("output_crs_unknown", ["simulate", "--instrument", "atlas", "--set", "output.crs=EPSG:99999"], "output.crs",
     "EPSG:99999"),
    ("output_crs_geographic", ["simulate", "--instrument", "atlas", "--set", "output.crs=EPSG:4326"], "output.crs",
     "EPSG:4326"),
    ("output_crs_without_photons", ["simulate", "--set", "output.crs=EPSG:32647"], "output.crs", "EPSG:32647"),
]
CASES.extend(ORBIT_CASES)
PARAMS.extend(pytest.param(*case, id=case[0]) for case in ORBIT_CASES)


def test_a_long_path_is_named_whole_and_a_long_list_is_cut():
    from flightsim.core.errors import InputError

    path = "/tmp/" + "deep/" * 30 + "notes.txt"  # 164 characters: the file's name at its end
    assert repr(path) in str(InputError("PATH", path, "a .las file"))
    huge = "x" * 5000 + "end.las"
    text = str(InputError("PATH", huge, "a .las file"))
    assert text.startswith("invalid PATH = 'xxx") and "end.las'" in text and "..." in text and len(text) < 1100
    listed = str(InputError("fan.angles", list(range(100)), "at most 8 angles"))
    assert "[0, 1, 2" in listed and "99" not in listed and len(listed.split(" = ", 1)[1].split(":")[0]) == 80
