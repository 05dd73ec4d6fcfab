"""The budgets of spad, change1 and atlas (flightsim/studies/budgets.py): for each instrument a source where the
simulator (Monte Carlo through the real path) and the float64 first-order model must agree within a stated
statistical tolerance, one where first order is known to break and the simulator must break it in the known
direction, and bad input. Small sample counts: the whole file runs in well under a minute on a CPU."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from flightsim.studies import budget_photons as bp
from flightsim.studies.budget_catalog import instrument_budget
from flightsim.studies.budgets import sigma_interval, statistics

C = 299_792_458.0


def _sigma_within_chi2(errors: np.ndarray, expected_sigma: float, confidence: float = 0.999) -> None:
    """The sample σ's χ² interval (n − 1 degrees of freedom) at ``confidence`` holds the expected σ."""
    e = errors[np.isfinite(errors)]
    lo, hi = sigma_interval(float(e.std(ddof=1)), e.size, confidence)
    assert lo <= expected_sigma <= hi, (lo, expected_sigma, hi, e.size)


def test_spad_jitter_matches_c_sigma_over_2(device):
    """Jitter alone: each photon's height error over the 0.2 slope is (c/2)·σ_t·g·d, σ = (c/2)·σ_t·√⟨(g·d)²⟩ with
    g·d computed here from the photons' beams (|g·d| ≈ 1.02): the sample σ's χ² interval holds it."""
    b = instrument_budget("spad")
    sim = b.simulate(("jitter",), device, 6, 0)
    assert sim.errors.size > 3000
    gd = sim.geometry["directions"] @ np.array([0.0, 0.2, 1.0])
    expected = 0.5 * C * 1.0e-10 * math.sqrt(np.mean(gd ** 2))
    _sigma_within_chi2(sim.errors, expected)
    assert abs(sim.errors.mean()) < 4.0 * expected / math.sqrt(sim.errors.size)
    mean, sigma = b.first_order("jitter", sim)
    assert sigma == pytest.approx(expected, rel=1e-6) and mean == 0.0


def test_spad_pile_up_reads_high_and_first_order_overstates_it(device):
    """Pile-up at ~5 signal photo-electrons per shot: the surface reads high (positive bias), and the first-order
    (linear in n) bias is larger than the simulated one beyond its 99.9 % interval (the exact bias saturates)."""
    b = instrument_budget("spad")
    cfg = bp.configured(b.config(("pile_up",), device, 6, 0), {"photon.pulse_energy_j": 5.0e-9})
    sim = bp.simulate_photons(cfg)
    sim.geometry["cfg"] = cfg
    s = statistics(sim.errors)
    half = 3.29 * s["sigma_m"] / math.sqrt(s["n"])
    assert s["mean_m"] - half > 0.0
    model_mean, _ = b.first_order("pile_up", sim)
    assert model_mean > s["mean_m"] + half
    from flightsim.instrument.photon import first_photon_bias_s, sigma_t

    n = float(np.mean(bp.expected_signal(cfg, sim)))  # the exact closed form lies between
    exact = -0.5 * C * first_photon_bias_s(n, sigma_t(cfg.photon)) * 1.02
    assert abs(s["mean_m"] - exact) < 0.25 * exact


def test_atlas_jitter_matches_c_sigma_over_2(device):
    """ATLAS, jitter alone at nadir over the 0.1 slope: g·d = −1, so the height σ is exactly (c/2)·σ_t = 1.50 cm."""
    b = instrument_budget("atlas")
    sim = b.simulate(("jitter",), device, 600, 0)
    assert sim.errors.size > 1000
    _sigma_within_chi2(sim.errors, 0.5 * C * 1.0e-10)


def test_atlas_first_photon_bias_is_high_and_below_first_order(device):
    """The dead time keeps a shot's first photo-electron: the surface reads high; linear in n ≈ 2 the first-order
    bias exceeds the simulated one."""
    b = instrument_budget("atlas")
    sim = b.simulate(("first_photon",), device, 1000, 0)
    s = statistics(sim.errors)
    half = 3.29 * s["sigma_m"] / math.sqrt(s["n"])
    assert s["mean_m"] - half > 0.0
    model_mean, _ = b.first_order("first_photon", sim)
    assert model_mean > s["mean_m"] + half


def test_change1_small_slope_matches_first_order(device):
    """A 0.005 slope: the half-power range's early shift −(c/2)·√(2 ln 2)·κ₂/(2σ_p) (plus the flat footprint's κ₁)
    holds to the neglected O(κ₂²/σ_p⁴) term, κ₂/σ_p² ≈ 0.08: within 5 %; the closed form with the truncated
    Gaussian footprint's variance (0.687·(Hα/2)² along the slope) agrees with the model's footprint to 2 %."""
    b = instrument_budget("change1")
    sim = b.simulate(("slope",), device, 1, 0)
    mean, _ = b.first_order("slope", sim)
    assert sim.errors[0] == pytest.approx(mean, rel=0.05)
    flat = 1237.0 / (2.0 * 200_000.0)  # ⟨ρ²⟩/(2H), ⟨ρ²⟩ = 1.374·(Hα/2)²
    sigma_p = 7.0e-9 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    k2 = (2.0 / C) ** 2 * 0.005 ** 2 * 0.687 * 30.0 ** 2
    closed = flat - 0.5 * C * math.sqrt(2.0 * math.log(2.0)) * k2 / (2.0 * sigma_p)
    assert mean == pytest.approx(closed, rel=0.02)


def test_change1_patent_slope_breaks_first_order_early(device):
    """At the patent's 0.20 slope the echo is early (negative range error) but much less than the linear
    first-order shift, which grows with κ₂ while the true one grows with √κ₂."""
    b = instrument_budget("change1")
    sim = b.simulate(("patent_slope",), device, 1, 0)
    mean, _ = b.first_order("patent_slope", sim)
    assert mean < sim.errors[0] < 0.0
    assert abs(mean) > 3.0 * abs(sim.errors[0])


@pytest.mark.parametrize("argv, word", [
    (["--instrument", "nope"], "--instrument"),
    (["--instrument", "spad", "--sources", "pulse,nope"], "--sources"),
    (["--instrument", "change3", "--sources", "pulse"], "--sources"),
    (["--instrument", "atlas", "--draws", "1"], "--draws"),
])
def test_bad_input_is_one_line_exit_2(tmp_path, argv, word):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "flightsim", "budget", *argv, "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and word in r.stderr
    assert not out.exists()


def test_cli_writes_budget_json_and_report(tmp_path):
    """A two-source spad budget through the CLI: budget.json holds the rows, the all-sources run and their
    root-sum-square (recomputed here from the rows' means and σ's); REPORT.md names the command."""
    import json

    out = tmp_path / "spad"
    r = subprocess.run([sys.executable, "-m", "flightsim", "budget", "--instrument", "spad", "--sources",
                        "jitter,fsm_zero", "--draws", "2", "--out", str(out)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    n = json.loads((out / "budget.json").read_text())
    assert [row["source"]["name"] for row in n["sources"]] == ["jitter", "fsm_zero"]
    rss = math.sqrt(sum(row["monte_carlo"]["mean_m"] ** 2 + row["monte_carlo"]["sigma_m"] ** 2 for row in n["sources"]))
    assert n["all_sources"]["rss_of_sources_m"]["monte_carlo"] == pytest.approx(rss, rel=1e-12)
    assert n["all_sources"]["names"] == ["jitter", "fsm_zero"]
    assert "flightsim budget --instrument spad --device cpu --draws 2 --sources jitter,fsm_zero" in \
        (out / "REPORT.md").read_text()


def test_api_refuses_an_unknown_instrument(tmp_path):
    from flightsim import api
    from flightsim.core.errors import InputError

    with pytest.raises(InputError):
        api.budget(tmp_path / "x", instrument="nope")
