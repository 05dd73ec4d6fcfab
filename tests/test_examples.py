"""Every script in examples/ runs as the documentation shows it (``python3 examples/NAME.py``), on each device,
exits 0, prints its summary line and, with ``--out``, writes the run's files."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = sorted(p for p in (ROOT / "examples").glob("*.py") if not p.name.startswith("_"))
NUMBER = r"-?\d+(\.\d+)?(e[-+]?\d+)?"
LINES = {  # what each example prints; an example not listed must print something
    "risley_airborne.py": rf"^risley: plane RMS exact {NUMBER} mm, nominal {NUMBER} mm; points exact \d+, nominal \d+$",
    "change3_lander.py": rf"^change3: \d+ points, exact plane RMS {NUMBER} mm$",
    "change1_waveforms.py": rf"^change1: 3 shots, half-power range {NUMBER}, {NUMBER}, {NUMBER} m$",
    "spad_small_body.py": rf"^spad: \d+ photons, {NUMBER}% signal$",
    "atlas_orbit.py": rf"^atlas: \d+ photons, \d+ on the ground at mean height {NUMBER} m$",
    "palmer_scanner.py": rf"^palmer: \d+ points, plane RMS exact {NUMBER} mm$",
}


def test_every_built_in_instrument_has_an_example():
    assert set(LINES) <= {p.name for p in EXAMPLES}


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs_and_prints_its_line(path, device, tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, str(path), "--device", device, "--out", str(out)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.strip().splitlines()
    assert lines, done.stderr
    assert re.match(LINES.get(path.name, r".+"), lines[-1]), lines[-1]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["device"].startswith(device.split(":")[0]), summary["device"]
