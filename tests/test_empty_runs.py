"""Zero output is never silent: a run that yields no return, photon or waveform says why on stderr in one line,
exits 2, and summary.json records the reason."""
from __future__ import annotations

import json

import pytest

import flightsim
from flightsim.cli import main


def _nothing(args: list[str], out, capsys) -> str:
    assert main([*args, "--out", str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("flightsim: nothing made: "), lines
    summary = json.loads((out / "summary.json").read_text())
    assert summary["empty"] in lines[0]
    return summary["empty"]


def _square_obj(path, half_m: float) -> str:
    h = half_m
    path.write_text(f"v {-h} {-h} 0\nv {h} {-h} 0\nv {h} {h} 0\nv {-h} {h} 0\nf 1 2 3 4\n")
    return str(path)


def test_a_waveform_altimeter_beyond_its_maximum_range(tmp_path, capsys):
    reason = _nothing(["waveform", "--set", "flight.altitude_m=400000"], tmp_path / "w", capsys)
    assert "flight.altitude_m = 400000 m" in reason and "instrument.max_range_m = 300000 m" in reason


def test_a_small_object_inside_the_conical_scan_s_ring(tmp_path, capsys):
    scene = _square_obj(tmp_path / "tiny.obj", 0.5)
    reason = _nothing(["simulate", "--scene", scene, "--duration", "0.5"], tmp_path / "r", capsys)
    assert "1.00 m across" in reason and "scan pattern leaves it uncovered" in reason
    nearest = float(reason.split("the nearest beam landing ")[1].split(" m")[0])
    assert 100.0 < nearest < 134.0  # the ring's radius, h·tan 15°, less the half line and the object


def _track(path, northing: float, easting: float = 408990.0) -> str:
    """A level line flown east at 500 m above the scenes' ground (origin height 450 m), 2 s at 10 m/s."""
    lines = ["gps_time,easting,northing,height,roll,pitch,heading"]
    lines += [f"{450000000.0 + t},{easting + 10.0 * t},{northing},950.0,0,0,90" for t in (0.0, 1.0, 2.0)]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def test_a_small_object_between_the_beams(tmp_path, capsys):
    scene = _square_obj(tmp_path / "tiny.obj", 0.01)  # the scan ring (radius 134 m) sweeps over it
    track = _track(tmp_path / "track.csv", 3393000.0 - 134.0)
    reason = _nothing(["simulate", "--scene", scene, "--trajectory", track], tmp_path / "r", capsys)
    assert "0.02 m across" in reason and "falls between them" in reason


def test_a_flight_whose_swath_misses_the_scene(tmp_path, capsys):
    track = _track(tmp_path / "far.csv", 3393000.0, easting=420000.0)
    reason = _nothing(["simulate", "--scene", "plane", "--trajectory", track], tmp_path / "r", capsys)
    assert reason.startswith("the swath misses the scene by ")
    miss = float(reason.split("by ")[1].split(" m")[0])
    assert 10000.0 < miss < 11000.0  # 11 km east of the origin, less the plane's half side and the cone's reach


def test_a_photon_gate_that_holds_no_range(tmp_path, capsys):
    reason = _nothing(["simulate", "--instrument", "spad", "--duration", "0.0004", "--set", "photon.gate_m=5,50",
                       "--set", "photon.noise_hz=0"], tmp_path / "p", capsys)
    assert "photon.gate_m = [5, 50] m" in reason


def test_the_api_warns_and_records_the_reason(tmp_path):
    cfg = flightsim.load_config(overrides={"scene.name": _square_obj(tmp_path / "tiny.obj", 0.5),
                                           "flight.duration_s": 0.5})
    with pytest.warns(RuntimeWarning, match="the run made nothing: all .* beams missed the scene"):
        result = flightsim.simulate(cfg)
    assert "missed the scene" in result.stats["empty"]
