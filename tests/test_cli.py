"""The command line contract (SPEC §10): outputs, exit status and one-line errors."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def flightsim(*args, cwd=None):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    return subprocess.run([sys.executable, "-m", "flightsim", *args], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=600)


def error_lines(result) -> list[str]:
    return [line for line in result.stderr.splitlines() if "CUDA" not in line]


@pytest.mark.parametrize("args, field", [
    (["--altitude", "-5"], "flight.altitude_m"),
    (["--altitude", "nan"], "flight.altitude_m"),
    (["--array", "0"], "fan.array"),
    (["--array", "65"], "fan.array"),
    (["--spacing-mrad", "inf"], "fan.spacing_mrad"),
    (["--spacing-mrad", "-1"], "fan.spacing_mrad"),
    (["--duration", "0"], "flight.duration_s"),
    (["--scene", "nowhere"], "scene.name"),
    (["--models", "exact,fancy"], "output.models"),
    (["--set", "sensor.colour=red"], "sensor.colour"),
    (["--set", "scene.crs=EPSG:4326"], "scene.crs"),
    (["--set", "risley.apex_angle_deg=45"], "risley.apex_angle_deg"),
    (["--instrument", "spad", "--set", "run.host_photons=0"], "run.host_photons"),
    (["--instrument", "atlas", "--set", "run.host_photons=1e9"], "run.host_photons"),
])
def test_invalid_input_exits_2_with_one_line_naming_the_field(tmp_path, args, field):
    result = flightsim("simulate", *args, "--out", str(tmp_path / "out"))
    lines = error_lines(result)
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


def test_output_path_that_is_a_file_is_refused(tmp_path):
    target = tmp_path / "taken"
    target.write_text("not a directory")
    result = flightsim("simulate", "--duration", "0.1", "--out", str(target))
    assert result.returncode == 2 and "--out" in error_lines(result)[0]
    assert target.read_text() == "not a directory"


def test_simulate_writes_the_documented_layout_and_refuses_to_clobber(tmp_path):
    out = tmp_path / "run"
    result = flightsim("simulate", "--scene", "plane", "--duration", "0.2", "--out", str(out))
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    for key in ("points", "pulses", "beams_fired", "tir_dropped", "misses", "wall_s", "rms_m"):
        assert key in summary
    assert (out / "run.toml").is_file()
    assert sorted(p.name for p in out.iterdir()) == ["exact", "nominal", "run.toml", "summary.json"]
    again = flightsim("simulate", "--scene", "plane", "--duration", "0.2", "--out", str(out))
    assert again.returncode == 2 and "--overwrite" in error_lines(again)[0]
    forced = flightsim("simulate", "--scene", "plane", "--duration", "0.2", "--out", str(out), "--overwrite")
    assert forced.returncode == 0, forced.stderr


def test_info_reports_versions_devices_and_cache():
    result = flightsim("info")
    assert result.returncode == 0
    info = json.loads(result.stdout)
    assert info["warp"].startswith("1.19") and any(d["name"] == "cpu" for d in info["devices"])
    assert info["kernel_cache"]


def test_the_entry_point_runs_the_command_line_and_leaves_the_collector_on(capsys):
    """``flightsim.entry.main`` (the console script and ``python -m flightsim``) imports the command line with the
    garbage collector paused, freezes what the imports made and turns the collector back on for the run."""
    import gc

    from flightsim import entry

    try:
        assert entry.main(["info"]) == 0
        assert gc.isenabled()
        assert json.loads(capsys.readouterr().out)["warp"].startswith("1.19")
        assert gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()
