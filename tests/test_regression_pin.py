"""Regression pin of the airborne Risley instrument: outputs recorded at commit cbd2e3b, before the
instrument became a composition of parts, must not change.

``data/regression_pin.json`` holds the SHA-256 of every LAS tile of two short runs (the default
run, and a variant that exercises range noise, a believed prism that differs from the true one,
two lines, boresight, lever arm and the position-error extra, given today through the ranging error model,
the wedge's ``believed_*`` settings and ``[instrument]``), their summary counts and RMS, and the rows of a small sweep. The LAS bytes
and the counts must match exactly; RMS values to float64 rounding of a different summation order.
"""
import csv
import hashlib
import json
import math
from pathlib import Path

import pytest

from flightsim.cli import main

PIN = json.loads((Path(__file__).parent / "data" / "regression_pin.json").read_text())
RUNS = {
    "default": ["--duration", "0.3"],
    "variant": ["--duration", "0.2", "--array", "4", "--altitude", "700", "--seed", "3",
                "--set", "instrument.errors=ranging", "--set", "ranging.noise_m=0.05",
                "--set", "risley.believed_refractive_index=1.50",
                "--set", "flight.lines=2", "--set", "instrument.boresight_deg=0.1,-0.2,0.3",
                "--set", "instrument.lever_arm_m=0.5,0.2,-1", "--set", "output.position_error=true"],
}
COUNTS = ("points", "pulses", "pulses_culled", "beams_fired", "tir_dropped", "misses")


def _close(value: float, pinned: float) -> bool:
    """Equal to float64 rounding of a different summation order. The exact model's RMS sits at the float32
    floor of the points (~0.5 µm), where the variance Σd²/n − mean² cancels ~1e4 m² down to ~1e-13 m²:
    summing on the device instead of the host moves it by ~0.2 nm, so 1 nm absolute is allowed (any
    change of the simulation moves it by orders of magnitude more)."""
    return math.isclose(value, pinned, rel_tol=1e-9, abs_tol=1e-9)


@pytest.mark.parametrize("name", sorted(RUNS))
def test_simulate_writes_the_pinned_las_bytes(tmp_path, name):
    out = tmp_path / name
    assert main(["simulate", *RUNS[name], "--out", str(out)]) == 0
    pinned = dict(PIN[name])
    summary_pin = pinned.pop("summary")
    tiles = {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(out.rglob("*.las"))}
    assert tiles == pinned
    summary = json.loads((out / "summary.json").read_text())
    assert {k: summary[k] for k in COUNTS} == {k: summary_pin[k] for k in COUNTS}
    for model, rms in summary_pin["rms_m"].items():
        assert _close(summary["rms_m"][model], rms), (model, summary["rms_m"][model], rms)


def test_sweep_gives_the_pinned_rows(tmp_path):
    out = tmp_path / "sweep"
    assert main(["sweep", "--scene", "plane", "--altitudes", "500,1500", "--arrays", "2,3", "--duration", "0.2",
                 "--out", str(out)]) == 0
    with open(out / "sweep.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(PIN["sweep"])
    for row, pinned in zip(rows, PIN["sweep"]):
        for key in ("altitude_m", "array", "spacing_mrad", "model", "points"):
            assert row[key] == pinned[key]
        assert _close(float(row["rms_m"]), float(pinned["rms_m"])), (row, pinned)
