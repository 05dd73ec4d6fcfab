"""`flightsim calibrate`: a simulated pass of the spaceborne single-photon altimeter (the `atlas` preset)
over a corner-cube field, with pointing and ranging biases injected into the truth, calibrated by the
seed patent's method and by least squares (seed: corner-cube-single-photon-calibration-patent.txt).

The pass is the straight, level track of the calibration model (flightsim.calibration.geolocation): the
`lines` platform at the orbit's ground speed and altitude over flat ground, so the simulator's photons and
the calibration's geolocation describe the same instrument. Pointing biases enter as the boresight error
of the true sensor axes (pitch: along track, forward; roll: across track, positive to the left, so
δ_across = −roll); the ranging bias as ranging.range_bias_m.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.calibration import CcrField, calibrate_least_squares, calibrate_patent, design_field
from flightsim.calibration.geolocation import Bias, Track, footprint_offset, theoretical_radius
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.core.errors import InputError
from flightsim.core.process_map import ProcessMap, map_rows, usable_cores
from flightsim.instrument.pairs import SINGLE_BEAM

GROUND_SPEED_MPS = 7000.0  # ICESat-2-like
CCR_PHOTONS = math.exp(2.0)  # photo-electrons a CCR returns at a footprint's centre (e²: 1 at its e⁻² edge)
LEAD_M = 100.0  # ground track before the first CCR [m]
GATE_HALF_M = 150.0  # the range window around the surface: a telemetry band of 300 m, as ATLAS sends down
MAX_EVENTS = 64  # detections kept per shot: 20 MHz of background puts ~40 in the band


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
    least_squares: object  # flightsim.calibration.ccr_likelihood.LeastSquaresCalibration
    range_bias_m: tuple[float, float]  # the ranging bias with the CCR echoes' first-photon pile-up removed, σ [m]


def pass_config(truth: Bias, field: CcrField, shots: int, device: str = "cpu", seed: int = 0,
                background_hz: float = 1.0e6, platform: str = "lines", six: bool = False) -> RunConfig:
    """The atlas preset over flat ground with CCRs in the scene: flown as a straight level line north at
    the orbit's ground speed (``lines``) or on its orbit, the pass above the scene origin at mid-run
    (``orbit``); its six beams (``six``) or the one nadir strong beam (SINGLE_BEAM)."""
    cfg = preset_config("atlas")
    h = cfg.flight.altitude_m
    settings = {**({} if six else SINGLE_BEAM), "flight.duration_s": (shots - 0.5) / cfg.fixed.prf_hz,
                "scene.ccrs": [list(p) for p in field.positions_m], "scene.ccr_photons": CCR_PHOTONS,
                "instrument.errors": ["ranging", "pose"],
                "pose.boresight_arcsec": [-truth.across_arcsec, truth.along_arcsec, 0.0],
                "ranging.range_bias_m": truth.range_m, "photon.noise_hz": background_hz,
                "photon.gate_m": [h - GATE_HALF_M, h + GATE_HALF_M], "photon.max_events": MAX_EVENTS,
                "run.device": device, "run.seed": seed}
    if platform == "lines":
        settings.update({"flight.platform": "lines", "flight.speed_kmh": GROUND_SPEED_MPS * 3.6,
                         "flight.heading_deg": 0.0, "flight.lines": 1})
    for key, value in settings.items():
        set_value(cfg, key, value)
    return validate(cfg)


def simulate_pass(truth: Bias, min_triggered: int = 16, device: str = "cpu", seed: int = 0,
                  background_hz: float = 1.0e6, platform: str = "lines") -> CalibrationPass:
    """Fly the one nadir strong beam (the atlas preset's SINGLE_BEAM) over a field designed for ``min_triggered``
    CCRs (design_field) and calibrate it. On the ``orbit`` platform the calibration takes each shot's believed laser
    position and body axes from the simulator (the pass curves and its nadir turns by ~0.5 mrad over 3.5 km); the
    field is laid out along the straight line through the pass's first and last nadir points."""
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    radius, design, shots = _design(min_triggered)
    # the track from a config without CCRs (the flight does not depend on them)
    probe = pass_config(truth, CcrField(np.zeros((1, 3)), np.zeros(1)), shots, device, seed, background_hz, platform)
    scene = build_scene(probe)
    track = _track(Tracer(probe, scene, flight_trajectories(probe, scene)), shots, platform)
    field = _field(track, design)
    cfg = pass_config(truth, field, shots, device, seed, background_hz, platform)
    shot, range_m, kind, _ = _photons(cfg, scene)
    return _calibrate(truth, track, field, shot, range_m, kind, radius, cfg, 1.0)


def simulate_beams(truth: Bias, min_triggered: int = 16, device: str = "cpu", seed: int = 0,
                   background_hz: float = 1.0e6, platform: str = "lines") -> dict:
    """The atlas preset's six beams over six CCR fields, one designed as simulate_pass's under each beam's ground
    track, flown once; each beam calibrated from its own photons (the weak beams' CCR echoes are the strong
    ones' ÷ pairs.energy_ratio, as their ground echoes). Every beam's track takes each shot's believed laser
    position and its axes turned to the beam's nominal direction. {ground track: CalibrationPass, or the
    InputError of a beam whose calibration found too little}."""
    names, beams = _fly_beams(truth, min_triggered, device, seed, background_hz, platform)
    return {name: beam.calibrated(_calibrate_beam(*beam.arguments())) for name, beam in zip(names, beams)}


@dataclass
class _BeamPhotons:
    """One beam's photons of a flown pass and what its calibration needs."""

    truth: Bias
    track: Track
    field: CcrField
    shot: np.ndarray
    range_m: np.ndarray  # [m]
    kind: np.ndarray
    radius_m: float
    cfg: RunConfig
    energy: float

    def arguments(self) -> tuple:
        """:func:`_calibrate_beam`'s arguments (what a worker process needs: no truth)."""
        return self.track, self.field, self.shot, self.range_m, self.radius_m, self.cfg, self.energy

    def calibrated(self, result) -> "CalibrationPass | InputError":
        """The pass of :func:`_calibrate_beam`'s result, or its error."""
        if isinstance(result, InputError):
            return result
        return CalibrationPass(self.truth, self.track, self.field, self.shot, self.range_m, self.kind, *result)


def _fly_beams(truth: Bias, min_triggered: int, device: str, seed: int, background_hz: float,
               platform: str) -> tuple[tuple[str, ...], list[_BeamPhotons]]:
    """simulate_beams' pass flown: its beams' names and photons."""
    radius, emitter, tracks, fields, cfg, (shot, range_m, kind, pixel) = _six_beam_pass(
        truth, min_triggered, device, seed, background_hz, platform)
    energy = emitter.energy_scale()
    beams = [_BeamPhotons(truth, tracks[b], fields[b], shot[pixel == b], range_m[pixel == b], kind[pixel == b], radius,
                          cfg, float(energy[b])) for b in range(len(emitter.beam_names))]
    return tuple(emitter.beam_names), beams


def _calibrate_beam(*arguments) -> "tuple | InputError":
    """:func:`_calibrations`, or the InputError of a beam whose calibration found too little (recorded, not
    fatal): what a worker process sends back, without the photons its parent holds."""
    try:
        return _calibrations(*arguments)
    except InputError as exc:
        return exc


def _six_beam_pass(truth: Bias, min_triggered: int, device: str, seed: int, background_hz: float, platform: str):
    """simulate_beams' pass flown: (footprint radius [m], the emitter, each beam's track and CCR field, the config,
    the photons' (shot, range [m], kind, beam))."""
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    radius, design, shots = _design(min_triggered)
    probe = pass_config(truth, CcrField(np.zeros((1, 3)), np.zeros(1)), shots, device, seed, background_hz, platform,
                        six=True)
    scene = build_scene(probe)
    sim = Tracer(probe, scene, flight_trajectories(probe, scene))
    emitter = sim.instrument.emitter
    tracks = _beam_tracks(sim, shots, emitter.angles_mrad * 1e-3)
    fields = [_field(t, design) for t in tracks]
    every = CcrField(np.concatenate([f.positions_m for f in fields]), np.concatenate([f.heights_m for f in fields]))
    cfg = pass_config(truth, every, shots, device, seed, background_hz, platform, six=True)
    return radius, emitter, tracks, fields, cfg, _photons(cfg, scene)


def _design(min_triggered: int):
    """(theoretical footprint radius [m], the CCR field's design, shots over it) of the atlas preset."""
    base = preset_config("atlas")
    h = base.flight.altitude_m
    radius = theoretical_radius(h, base.pairs.divergence_mrad * 1e-3)
    design = design_field(radius, 2.0, h, min_triggered=min_triggered)
    span = LEAD_M * 2 + float(np.ptp(design.along_m))
    return radius, design, int(span / (GROUND_SPEED_MPS / base.fixed.prf_hz))


def _field(track: Track, design) -> CcrField:
    return CcrField.from_track_frame(track, LEAD_M + design.along_m, design.across_m,
                                     np.resize([1.0, 1.5, 2.0], design.n_ccr))


def _photons(cfg, scene) -> tuple:
    """(shot, measured range [m], truth kind, beam) of every photon of the pass."""
    from flightsim.engine.readouts.photons import Photons
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import flight_trajectories

    chunks = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Photons(), chunks.append)
    return (np.concatenate([c.pulse for c in chunks]),
            np.concatenate([c.time_of_flight_s for c in chunks]) * (299_792_458.0 / 2.0),
            np.concatenate([c.kind for c in chunks]), np.concatenate([c.pixel for c in chunks]))


def _calibrate(truth: Bias, track: Track, field: CcrField, shot, range_m, kind, radius: float, cfg,
               energy: float) -> CalibrationPass:
    """The pass of one beam's photons with its calibrations (:func:`_calibrations`)."""
    return CalibrationPass(truth, track, field, shot, range_m, kind,
                           *_calibrations(track, field, shot, range_m, radius, cfg, energy))


def _calibrations(track: Track, field: CcrField, shot, range_m, radius: float, cfg, energy: float) -> tuple:
    """Both calibrations and the pile-up-corrected ranging bias of one beam's photons (``energy``: the beam's share
    of the strong beam's pulse energy, scaling its CCR return): (patent, least squares, (bias [m], σ [m]))."""
    patent = calibrate_patent(track, shot, range_m, field, footprint_radius_m=radius)
    lsq = calibrate_least_squares(track, shot, range_m, field, patent.identification, footprint_radius_m=radius,
                                  start=patent.coarse.solution.bias)
    pile_up = pile_up_corrected_range_bias(track, shot, range_m, field, patent.identification, lsq.bias, radius, cfg,
                                           energy)
    return patent, lsq, pile_up


def _beam_tracks(sim, shots: int, angles_rad) -> list[Track]:
    """Each beam's calibration track: every shot's believed laser position, and its body axes turned about the
    along-track axis to the beam's across-track angle θ (body +z to (0, sin θ, cos θ)); the along/across frame the
    beam's field is laid out in is the straight line through its first and last footprints on z = 0."""
    poses = sim.poses64(sim.trajectories[0].line_id, 0, shots).numpy()
    origin, rot = np.asarray(poses["origin"], dtype=np.float64), np.asarray(poses["rot"], dtype=np.float64)
    h, rate = float(sim.cfg.flight.altitude_m), sim.cfg.fixed.prf_hz
    tracks = []
    for theta in angles_rad:
        c, s = math.cos(theta), math.sin(theta)
        axes = rot @ np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
        foot = origin - (origin[:, 2] / axes[:, 2, 2])[:, None] * axes[:, :, 2]
        step = (foot[-1, :2] - foot[0, :2]) / (shots - 1)
        tracks.append(Track(altitude_m=h, ground_speed_mps=float(np.hypot(*step)) * rate, rate_hz=rate,
                            azimuth_deg=float(np.degrees(np.arctan2(step[0], step[1]))),
                            origin_m=(float(foot[0, 0]), float(foot[0, 1])), shot_positions=origin, shot_axes=axes))
    return tracks


def _track(sim, shots: int, platform: str) -> Track:
    """The calibration's laser track of the simulator's (believed) pulses: straight at the configured speed
    for ``lines``; for ``orbit`` each shot's position and axes, the straight line through the first and
    last nadir points giving the along/across frame the field is laid out in."""
    poses = sim.poses64(sim.trajectories[0].line_id, 0, shots).numpy()
    origin, rot = np.asarray(poses["origin"], dtype=np.float64), np.asarray(poses["rot"], dtype=np.float64)
    nadir = origin - (origin[:, 2] / rot[:, 2, 2])[:, None] * rot[:, :, 2]  # the beam axis on the ground z = 0
    h, rate = float(sim.cfg.flight.altitude_m), sim.cfg.fixed.prf_hz
    if platform == "lines":
        return Track(altitude_m=h, ground_speed_mps=GROUND_SPEED_MPS, rate_hz=rate, azimuth_deg=0.0,
                     origin_m=(float(nadir[0, 0]), float(nadir[0, 1])))
    step = (nadir[-1, :2] - nadir[0, :2]) / (shots - 1)
    return Track(altitude_m=h, ground_speed_mps=float(np.hypot(*step)) * rate, rate_hz=rate,
                 azimuth_deg=float(np.degrees(np.arctan2(step[0], step[1]))),
                 origin_m=(float(nadir[0, 0]), float(nadir[0, 1])), shot_positions=origin, shot_axes=rot)


def pile_up_corrected_range_bias(track: Track, shot, range_m, field: CcrField, identification, pointing: Bias,
                                 radius_m: float, cfg: RunConfig, energy: float = 1.0) -> tuple[float, float]:
    """(ranging bias [m], its σ) from the CCR photons with each one's first-photon pile-up taken out.

    A detector whose dead time outlasts the echo keeps a shot's first CCR photo-electron, which comes
    early by first_photon_bias_s(n, σ_t) for n expected photo-electrons (flightsim.instrument.photon):
    n = N0 exp(−2r²/R²) with N0 the CCR's return from the link budget (scene.ccr_photons, times the beam's
    share ``energy`` of the strong beam's pulse energy), R the beam's
    theoretical footprint radius and r the CCR's offset from the footprint centre under the calibrated
    pointing; σ_t the echo's spread. (The least-squares count fit cannot give N0: with the dead time a
    shot holds at most one CCR photon, so its Poisson counts saturate.) The bias is then the mean of
    measured − geometric − pile-up range over the CCR photons."""
    from flightsim.instrument.photon import first_photon_bias_s, sigma_t

    spread = sigma_t(cfg.photon)
    measured, geometric, n = [], [], []
    for t in identification.tracks:
        shots = np.asarray(shot)[t.photons]
        ccr = np.broadcast_to(field.positions_m[t.ccr], (len(shots), 3))
        measured.append(np.asarray(range_m)[t.photons])
        geometric.append(np.linalg.norm(ccr - track.position(shots), axis=1))
        n.append(energy * cfg.scene.ccr_photons
                 * np.exp(-2.0 * footprint_offset(track, shots, ccr, pointing) ** 2 / radius_m ** 2))
    early = first_photon_bias_s(np.concatenate(n), spread) * (299_792_458.0 / 2.0)  # every track's at once
    r = np.concatenate(measured) - early - np.concatenate(geometric)
    return float(r.mean()), float(r.std(ddof=1) / math.sqrt(r.size))


SEEDS = (0, 1, 2)
TRIGGERED = (4, 8, 16)  # design_field's guaranteed triggered CCRs
BACKGROUNDS_HZ = (1.0e6, 5.0e6, 2.0e7)
SETTINGS = [(t, b, "lines") for t in TRIGGERED for b in BACKGROUNDS_HZ] + [(16, 1.0e6, "orbit")]  # the sweep


def run_calibration(out, device: str = "cpu", truth: Bias = Bias(3.0, -2.0, 0.25)) -> dict:
    """The six-beam pass at the defaults (figures: its central strong beam gt2l) and the sweep over field size,
    background and seeds into ``out``, every beam calibrated: calibration.json, REPORT.md, pass.png, radius.png."""
    import json
    from pathlib import Path

    from flightsim.calibration.geolocation import ground_shift_m
    from flightsim.core.atomic import write_atomic
    from flightsim.instrument.pairs import is_strong
    from flightsim.studies.spaceborne_report import report

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sc_orient = preset_config("atlas").pairs.sc_orient
    runs = [(triggered, background, platform, seed) for triggered, background, platform in SETTINGS for seed in SEEDS]
    flown = []  # (run, beam names, beams) as the passes are flown: while the workers calibrate the earlier ones
    workers = _calibration_workers()  # they start while the first passes are flown

    def beams():
        for triggered, background, platform, seed in runs:
            names, mine = _fly_beams(truth, triggered, device, seed, background, platform)
            flown.append(((triggered, background, platform, seed), names, mine))
            yield from (beam.arguments() for beam in mine)

    try:
        results = iter(map_rows(_calibrate_beam, beams(), workers))
    finally:
        if workers is not None:
            workers.stop()
    rows = []
    for (triggered, background, platform, seed), names, mine in flown:
        for beam, photons in zip(names, mine):
            p = photons.calibrated(next(results))
            about = {"min_triggered": triggered, "background_hz": background, "platform": platform, "seed": seed,
                     "beam": beam, "strong": is_strong(beam, sc_orient)}
            if isinstance(p, InputError):  # recorded, not fatal
                rows.append({**about, "failed": str(p)})
                continue
            rows.append({**_row(p, triggered, background, seed), **about})
            if (triggered, background, seed, platform, beam) == (16, 1.0e6, 0, "lines", "gt2l"):
                _figures(p, out)
    numbers = {"device": device, "truth": [truth.along_arcsec, truth.across_arcsec, truth.range_m],
               "one_arcsec_at_500km_m": ground_shift_m(500e3, 1.0), "passes": rows}
    write_atomic(out / "calibration.json", json.dumps(numbers, indent=2) + "\n")
    write_atomic(out / "REPORT.md", report(numbers))
    return numbers


CALIBRATION_WORKERS = 16  # the most worker processes calibrating the sweep's beams


def _calibration_workers():
    """Worker processes for the sweep's beam calibrations (host work: its least squares and pile-up integrals), one
    a core up to CALIBRATION_WORKERS; None on one core."""
    count = min(usable_cores(), CALIBRATION_WORKERS)
    return ProcessMap(count, ("flightsim.studies.spaceborne",)) if count > 1 else None


def compile_calibration(device: str = "cpu") -> int:
    """Compile into Warp's kernel cache (or load from it) the kernels `flightsim calibrate` launches (``flightsim
    compile --for calibrate``): one pass of its sweep flown on each platform, whose kernels are the whole sweep's (its
    fields and backgrounds are the kernels' inputs; the calibrations run on the host); returns the modules loaded."""
    from flightsim.core.warp_runtime import loaded_modules

    for platform in sorted({platform for _, _, platform in SETTINGS}):
        _six_beam_pass(Bias(3.0, -2.0, 0.25), 16, device, 0, 1.0e6, platform)
    return loaded_modules()


def _row(p: CalibrationPass, triggered: int, background: float, seed: int) -> dict:
    t = p.truth
    lsq, pat = p.least_squares, p.patent.bias
    return {"min_triggered": triggered, "background_hz": background, "seed": seed, "ccrs": len(p.field),
            "tracks": len(p.patent.identification.tracks), "ccr_photons": int((p.kind == 2).sum()),
            "patent_error_arcsec": [pat.along_arcsec - t.along_arcsec, pat.across_arcsec - t.across_arcsec],
            "lsq_error_arcsec": [lsq.bias.along_arcsec - t.along_arcsec, lsq.bias.across_arcsec - t.across_arcsec],
            "lsq_sigma_arcsec": [float(lsq.sigma[0]), float(lsq.sigma[1])],
            "range_error_m": p.range_bias_m[0] - t.range_m, "range_sigma_m": p.range_bias_m[1],
            "range_error_uncorrected_m": lsq.bias.range_m - t.range_m}


def _figures(p: CalibrationPass, out) -> None:
    """pass.png: photon heights along track, CCR photons marked; radius.png: step 5's azimuth difference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flightsim.calibration.geolocation import Bias as Nominal, geolocate
    from flightsim.core.atomic import save_figure

    points = geolocate(p.track, p.shot, p.range_m, Nominal())
    along, _ = p.track.to_track_frame(points)
    fig, ax = plt.subplots(figsize=(10, 3.6))
    for kind, colour, label in ((0, "0.7", "background"), (1, "tab:blue", "ground"), (2, "tab:red", "corner cubes")):
        m = p.kind == kind
        ax.scatter(along[m], points[m, 2], s=1 if kind < 2 else 6, c=colour, label=label)
    ax.set(xlabel="along track [m]", ylabel="height, nominal geolocation [m]", ylim=(-4, 6),
           title="photons of the pass (truth colours), geolocated with the nominal instrument")
    ax.legend(markerscale=4, fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "pass.png", dpi=120)
    plt.close(fig)
    r = p.patent.radius
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(r.radii_m, r.azimuth_difference_deg, ".-")
    ax.axvline(r.radius_m, color="r", lw=0.8, label=f"chosen R = {r.radius_m:.1f} m")
    ax.set(xlabel="footprint radius tried [m]", ylabel="|azimuth − coarse line's| [deg]",
           title="step 5: radius iteration")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "radius.png", dpi=120)
    plt.close(fig)
