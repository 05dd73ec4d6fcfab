"""`flightsim calibrate`: a simulated pass of the spaceborne single-photon altimeter (the `atlas` preset)
over a corner-cube field, with pointing and ranging biases injected into the truth, calibrated by the
seed patent's method and by least squares (seed: corner-cube-single-photon-calibration-patent.txt).

The pass is the straight, level track of the calibration model (flightsim.calibration.geolocation): the
`lines` platform at the orbit's ground speed and altitude over flat ground, so the simulator's photons and
the calibration's geolocation describe the same instrument. Pointing biases enter as the boresight error
of the true sensor axes (pitch: along track, forward; roll: across track, positive to the left, so
δ_across = −roll); the ranging bias as errors.range_bias_m.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.calibration.ccr import CcrField, calibrate_least_squares, calibrate_patent, design_field
from flightsim.calibration.geolocation import Bias, Track, footprint_offset, theoretical_radius
from flightsim.core.config import RunConfig, preset_config, set_value, validate

GROUND_SPEED_MPS = 7000.0  # ICESat-2-like
CCR_PHOTONS = math.exp(2.0)  # photo-electrons a CCR returns at a footprint's centre (e²: 1 at its e⁻² edge)
LEAD_M = 100.0  # ground track before the first CCR [m]


@dataclass
class CalibrationPass:
    """A simulated pass and both calibrations of it."""

    truth: Bias
    track: Track
    field: CcrField
    shot: np.ndarray  # pulse index of every photon
    range_m: np.ndarray  # measured one-way range of every photon [m]
    kind: np.ndarray  # truth: 0 noise, 1 ground, 2 CCR
    patent: object  # flightsim.calibration.ccr.PatentCalibration
    least_squares: object  # flightsim.calibration.ccr.LeastSquaresCalibration
    range_bias_m: tuple[float, float]  # the ranging bias with the CCR echoes' first-photon pile-up removed, σ [m]


def pass_config(truth: Bias, field: CcrField, shots: int, device: str = "cpu", seed: int = 0,
                background_hz: float = 1.0e6) -> RunConfig:
    """The atlas preset flown as a straight level line north over flat ground, CCRs in the scene."""
    cfg = preset_config("atlas")
    h = cfg.flight.altitude_m
    settings = {"flight.platform": "lines", "flight.speed_kmh": GROUND_SPEED_MPS * 3.6, "flight.heading_deg": 0.0,
                "flight.duration_s": (shots - 0.5) / cfg.sensor.prf_hz, "flight.lines": 1,
                "scene.ccrs": [list(p) for p in field.positions_m], "scene.ccr_photons": CCR_PHOTONS,
                "errors.boresight_arcsec": [-truth.across_arcsec, truth.along_arcsec, 0.0],
                "errors.range_bias_m": truth.range_m, "photon.noise_hz": background_hz,
                "photon.gate_m": [h - 1000.0, h + 1000.0], "run.device": device, "run.seed": seed}
    for key, value in settings.items():
        set_value(cfg, key, value)
    return validate(cfg)


def simulate_pass(truth: Bias, min_triggered: int = 16, device: str = "cpu", seed: int = 0,
                  background_hz: float = 1.0e6) -> CalibrationPass:
    """Fly the pass over a field designed for ``min_triggered`` CCRs (design_field) and calibrate it."""
    from flightsim.engine.simulate import Simulator
    from flightsim.platforms.plan import build_scene, flight_trajectories

    base = preset_config("atlas")
    h = base.flight.altitude_m
    radius = theoretical_radius(h, base.sensor.divergence_mrad * 1e-3)
    design = design_field(radius, 2.0, h, min_triggered=min_triggered)
    span = LEAD_M * 2 + float(np.ptp(design.along_m))
    shots = int(span / (GROUND_SPEED_MPS / base.sensor.prf_hz))
    # the track's first nadir point, from a config without CCRs (the line plan does not depend on them)
    probe = pass_config(truth, CcrField(np.zeros((1, 3)), np.zeros(1)), shots, device, seed, background_hz)
    scene = build_scene(probe)
    (line,) = flight_trajectories(probe, scene)
    start = scene.world_to_local(line.position[:1])[0]
    track = Track(altitude_m=h, ground_speed_mps=GROUND_SPEED_MPS, rate_hz=base.sensor.prf_hz, azimuth_deg=0.0,
                  origin_m=(float(start[0]), float(start[1])))
    field = CcrField.from_track_frame(track, LEAD_M + design.along_m, design.across_m,
                                      np.resize([1.0, 1.5, 2.0], design.n_ccr))
    cfg = pass_config(truth, field, shots, device, seed, background_hz)
    chunks = []
    Simulator(cfg, scene, flight_trajectories(cfg, scene)).run_photons(chunks.append)
    shot = np.concatenate([c.pulse for c in chunks])
    range_m = np.concatenate([c.time_of_flight_s for c in chunks]) * (299_792_458.0 / 2.0)
    kind = np.concatenate([c.kind for c in chunks])
    patent = calibrate_patent(track, shot, range_m, field, footprint_radius_m=radius)
    lsq = calibrate_least_squares(track, shot, range_m, field, patent.identification, footprint_radius_m=radius,
                                  start=patent.coarse.solution.bias)
    pile_up = pile_up_corrected_range_bias(track, shot, range_m, field, patent.identification, lsq.bias, radius, cfg)
    return CalibrationPass(truth, track, field, shot, range_m, kind, patent, lsq, pile_up)


def pile_up_corrected_range_bias(track: Track, shot, range_m, field: CcrField, identification, pointing: Bias,
                                 radius_m: float, cfg: RunConfig) -> tuple[float, float]:
    """(ranging bias [m], its σ) from the CCR photons with each one's first-photon pile-up taken out.

    A detector whose dead time outlasts the echo keeps a shot's first CCR photo-electron, which comes
    early by first_photon_bias_s(n, σ_t) for n expected photo-electrons (flightsim.instrument.photon):
    n = N0 exp(−2r²/R²) with N0 the CCR's return from the link budget (scene.ccr_photons), R the beam's
    theoretical footprint radius and r the CCR's offset from the footprint centre under the calibrated
    pointing; σ_t the echo's spread. (The least-squares count fit cannot give N0: with the dead time a
    shot holds at most one CCR photon, so its Poisson counts saturate.) The bias is then the mean of
    measured − geometric − pile-up range over the CCR photons."""
    from flightsim.instrument.photon import first_photon_bias_s, sigma_t

    spread = sigma_t(cfg.photon)
    residuals = []
    for t in identification.tracks:
        shots = np.asarray(shot)[t.photons]
        ccr = np.broadcast_to(field.positions_m[t.ccr], (len(shots), 3))
        geometric = np.linalg.norm(ccr - track.position(shots), axis=1)
        n = cfg.scene.ccr_photons * np.exp(-2.0 * footprint_offset(track, shots, ccr, pointing) ** 2 / radius_m ** 2)
        early = np.array([first_photon_bias_s(float(k), spread) for k in n]) * (299_792_458.0 / 2.0)
        residuals.append(np.asarray(range_m)[t.photons] - early - geometric)
    r = np.concatenate(residuals)
    return float(r.mean()), float(r.std(ddof=1) / math.sqrt(r.size))
