"""tests/compare_devices.py runs as a script and finds the two devices in agreement (here the CPU
against itself, or against CUDA where present)."""
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_compare_devices_script_writes_its_report(tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    done = subprocess.run([sys.executable, str(ROOT / "tests" / "compare_devices.py"), "--out", str(tmp_path),
                           "--quick"], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr
    report = json.loads((tmp_path / "cpu_vs_gpu.json").read_text())
    assert report["devices"]["a"]["warp"] == "cpu" and report["within_1mm"]
    for case in report["cases"].values():
        for model in ("exact", "nominal"):
            result = case["models"][model]
            assert result["matched"] == result["points_a"] == result["points_b"] > 1000
            assert result["max_m"] <= 1e-3
