"""Corner-cube retroreflectors in the photon detector: a CCR returns photons whenever a footprint's
Gaussian lights it, as many as the profile at its offset says (seed:
corner-cube-single-photon-calibration-patent.txt)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from flightsim.cli import main
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.engine.readouts.points import Points
from flightsim.engine.readouts.photons import Photons

FOOTPRINT = 0.5 * 0.035e-3  # e⁻² half angle of a 0.035 mrad beam [rad]: w = 8.75 m at 500 km
CCR_PHOTONS = 3.0


def _pass(detector: str, ccr=(0.0, 0.0, 1.0), **settings) -> RunConfig:
    cfg = RunConfig()
    photon = {"photon.gate_m": [499000.0, 501000.0], "photon.noise_hz": 1.0e3, "photon.dead_time_s": 3e-9,
              "photon.pulse_fwhm_s": 1.5e-9, "photon.pulse_energy_j": 1e-4}
    for key, value in {"instrument.deflector": "fixed", "fan.array": 1, "flight.platform": "orbit",
                       "flight.altitude_m": 500e3, "flight.duration_s": 0.01, "fixed.prf_hz": 1.0e4,
                       "instrument.max_range_m": 6e5, "fan.divergence_mrad": 0.035, "scene.name": "plane",
                       "instrument.detector": detector, "scene.ccrs": [list(ccr)], "scene.ccr_photons": CCR_PHOTONS,
                       **(photon if detector == "photon" else {"output.models": ["exact"]}), **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


@pytest.mark.parametrize("ccr", [(0.0, 0.0, 1.0), (5.0, 0.0, 1.0)])  # on the track, and 5 m east of it
def test_ccr_photons_follow_the_footprint_profile_along_the_track(ccr):
    """The shots that see a CCR form its track: a chord of the footprints whose Gaussian reaches it, as
    long as Σ_k 1 − exp(−n_k) shots with n_k = N0·exp(−2 d_k²/w²), d_k the footprint centre's distance."""
    discrete = _pass("discrete", ccr)
    scene = build_scene(discrete)
    sim = Tracer(discrete, scene, flight_trajectories(discrete, scene), with_truth=True)
    hits = []
    sim.run(Points(), hits.append)
    truth = np.concatenate([c.true_points for c in hits])  # footprint centres (the beam's true hits)
    offset = np.linalg.norm(truth[:, :2] - np.asarray(ccr[:2]), axis=1)  # footprint centre to the CCR
    expected = CCR_PHOTONS * np.exp(-2.0 * offset ** 2 / (FOOTPRINT * 500e3) ** 2)
    p = 1.0 - np.exp(-expected)  # the CCR's echo comes 6.7 ns before the ground's: its first photon counts

    cfg = _pass("photon", ccr)
    chunks = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Photons(), chunks.append)
    pulse = np.concatenate([c.pulse for c in chunks])
    flag = np.concatenate([c.signal for c in chunks])  # bool: signal of any kind
    kinds = np.concatenate([c.kind for c in chunks])
    assert set(np.unique(kinds)) <= {0, 1, 2} and (flag == (kinds > 0)).all()
    per_shot = np.bincount(pulse[kinds == 2], minlength=len(p))[:len(p)]
    assert per_shot.max() <= 1  # a 3 ns dead time: one CCR photo-electron per shot at most
    z = (per_shot.sum() - p.sum()) / math.sqrt(np.sum(p * (1 - p)))
    assert abs(z) < 4
    assert per_shot[offset > 3.0 * FOOTPRINT * 500e3].sum() == 0  # none beyond 3 e⁻² radii
    assert per_shot.sum() > (10 if ccr[0] == 0 else 3)


def test_bad_ccr_entries_exit_2_naming_the_field(tmp_path, capsys):
    assert main(["simulate", "--set", "scene.ccrs=[[0, 0]]", "--out", str(tmp_path / "c")]) == 2
    assert "scene.ccrs" in capsys.readouterr().err


def _events(device: str):
    cfg = _pass("photon", **{"run.device": device})
    scene = build_scene(cfg)
    chunks = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Photons(), chunks.append)
    return {k: np.concatenate([getattr(c, k) for c in chunks]) for k in ("pulse", "kind", "time_of_flight_s")}


@pytest.mark.skipif(not __import__("warp").is_cuda_available(), reason="needs a GPU")
def test_cpu_and_gpu_give_the_same_ccr_photons():
    cpu, gpu = _events("cpu"), _events("cuda")
    assert np.array_equal(cpu["pulse"], gpu["pulse"]) and np.array_equal(cpu["kind"], gpu["kind"])
    # float32 ray casts differ in the last bits between devices: times agree to a picosecond
    assert np.abs(cpu["time_of_flight_s"] - gpu["time_of_flight_s"]).max() < 1e-12
