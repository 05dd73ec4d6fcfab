"""Full-link error budget of the galvo imager (seed paper §2–§3): each error source alone and all
together, on the device and by first-order propagation in float64, side by side.

The frame is one full raster of the instrument hovering ``distance_m`` over a plane square to its
optical axis (the paper's test case). Deviations are the processing's point minus the true hit,
in the sensor frame of the paper: X horizontal, Y vertical, Z along the optical axis.

- :func:`deterministic`: every source set to its value, alone (the paper's Table 1 and Figs. 2–8);
- :func:`monte_carlo`: N draws on the device of every source at once (systematic angle errors and
  channel delays drawn per draw, noise per pulse), per-slot float64 sums accumulated on the device;
- the analytic side: ``galvo_model.analytic_sigma`` (J Σ Jᵀ of the float64 reference model).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from flightsim.core.constants import ARCSEC
from flightsim.engine.config import RunConfig, copy_config, validate
from flightsim.engine.config_io import preset_config
from flightsim.engine.instrument import Instrument
from flightsim.engine.readouts.points import Points
from flightsim.instrument import galvo_model
from flightsim.instrument.galvo import ANGLE_ERRORS
from flightsim.instrument.ranging import RangingErrors, RangingSettings
from flightsim.studies.budgets import SlotMoments

ANGLE_SOURCES = {"B1": "b1_arcsec", "B2": "b2_arcsec", "B3": "b3_arcsec", "C1": "c1_arcsec"}
PAPER_ALLOWED_ARCSEC = {"B1": 42.9, "B2": 42.9, "B3": 42.9, "C1": 94.5}  # seed paper §3.3
PAPER_TABLE1_CM = {  # seed paper Table 1: (max, min) |deviation| per axis [cm]
    "B1": {"X": (0.0, 0.0), "Y": (9.17, 9.17), "Z": (2.61, 0.0)},
    "B2": {"X": (4.34, 4.17), "Y": (0.34, 0.0), "Z": (1.28, 0.0)},
    "B3": {"X": (0.57, 0.0), "Y": (0.04, 0.0), "Z": (0.17, 0.0)},
    "C1": {"X": (0.0, 0.0), "Y": (9.17, 9.17), "Z": (2.61, 0.0)},
}
AXES = ("X", "Y", "Z")


def frame_config(base: RunConfig | None = None, distance_m: float = 100.0, columns: int | None = None,
                 device: str = "cpu") -> RunConfig:
    """The budget's run: the Chang'e-3 preset (or ``base``) hovering ``distance_m`` over the plane, one
    frame, every error source off. ``columns`` thins the raster (tests)."""
    cfg = copy_config(base) if base is not None else preset_config("change3")
    cfg.scene.name = "plane"
    cfg.flight.platform = "hover"
    cfg.flight.altitude_m = distance_m
    cfg.flight.roll_deg = cfg.flight.pitch_deg = cfg.flight.heading_deg = 0.0
    cfg.instrument.boresight_deg = (0.0, 0.0, 0.0)
    cfg.instrument.lever_arm_m = (0.0, 0.0, 0.0)
    if columns:
        cfg.galvo.columns = columns
    cfg.flight.duration_s = cfg.galvo.frame_s
    cfg.output.models = ("exact",)
    cfg.run.device = device
    for name in ANGLE_ERRORS:  # every source off
        setattr(cfg.galvo, name, 0.0)
    cfg.parts["ranging"] = RangingSettings(cfd_fraction=cfg.ranging.cfd_fraction, snr=cfg.ranging.snr)
    if "ranging" not in cfg.instrument.errors:
        cfg.instrument.errors = (*cfg.instrument.errors, "ranging")
    return cfg


def with_errors(cfg: RunConfig, **errors: float) -> RunConfig:
    """A validated copy of ``cfg`` with error sources set: the galvo's angle errors (``[galvo]``) and the ranging
    chain's (``[ranging]``), by their settings' names."""
    out = copy_config(cfg)
    galvo = {k: v for k, v in errors.items() if k in ANGLE_ERRORS}
    out.parts["galvo"] = dataclasses.replace(out.galvo, **galvo)
    out.parts["ranging"] = dataclasses.replace(out.ranging, **{k: v for k, v in errors.items() if k not in galvo})
    return validate(out)


class Frame:
    """The first ``pulses`` pulses of an instrument's first line on the device (default: one galvo
    frame): the scene, the trajectory and simulators with truth."""

    def __init__(self, cfg: RunConfig, pulses: int | None = None):
        from flightsim.engine.meshes import SceneMeshes
        from flightsim.engine.world import build_scene, flight_trajectories
        from flightsim.core.warp_runtime import resolve_device

        self.cfg = validate(cfg)
        self.scene = build_scene(self.cfg)
        self.trajectories = flight_trajectories(self.cfg, self.scene)
        instrument = Instrument(self.cfg)
        g = self.cfg.galvo
        self.pulses = pulses or g.strips * g.columns
        self.beams = instrument.beams_per_pulse
        self.meshes = SceneMeshes(self.scene, resolve_device(self.cfg.run.device))
        self.geometry = instrument.deflector.geometry() if self.cfg.instrument.deflector == "galvo" else None

    def simulator(self, cfg: RunConfig):
        from flightsim.engine.tracer import Tracer

        return Tracer(cfg, self.scene, self.trajectories, with_truth=True, meshes=self.meshes,
                         pulse_limits={self.trajectories[0].line_id: (0, self.pulses)})

    def poses(self, sim) -> tuple[np.ndarray, np.ndarray]:
        """(origin (pulses, 3) [m, local], R_local←sensor (pulses, 3, 3)) of the frame's pulses, float64."""
        pose = sim.poses64(self.trajectories[0].line_id, 0, self.pulses).numpy()
        return (np.asarray(pose["origin"], dtype=np.float64),
                np.asarray(pose["rot"], dtype=np.float64).reshape(-1, 3, 3))

    def sensor_rotation(self, sim) -> np.ndarray:
        """R_local←sensor of the first pulse, as a float64 3×3 matrix (constant for a hover)."""
        return self.poses(sim)[1][0]

    def local_deviations(self, cfg: RunConfig):
        """(deviation, true point, simulator): the points (slots, 3) in the local frame [m], NaN where a
        slot did not return."""
        sim = self.simulator(cfg)
        slots = self.pulses * self.beams
        deviation = np.full((slots, 3), np.nan)
        truth = np.full((slots, 3), np.nan)

        def consume(chunk):
            index = chunk.pulse * self.beams + chunk.beam
            deviation[index] = chunk.points["exact"] - chunk.true_points
            truth[index] = chunk.true_points

        sim.run(Points(), consume)
        return deviation, truth, sim

    def deviations(self, cfg: RunConfig) -> tuple[np.ndarray, np.ndarray]:
        """(deviation, true point − sensor origin), each (slots, 3) in the first pulse's sensor frame [m]."""
        deviation, truth, sim = self.local_deviations(cfg)
        origin, rot = self.poses(sim)
        return deviation @ rot[0], (truth - origin[0]) @ rot[0]


def table(deviation: np.ndarray) -> dict[str, tuple[float, float]]:
    """{axis: (max, min) of |deviation|} over the returning slots [m]."""
    a = np.abs(deviation[np.isfinite(deviation[:, 0])])
    return {axis: (float(a[:, k].max()), float(a[:, k].min())) for k, axis in enumerate(AXES)}


def deterministic(frame: Frame, values_arcsec: dict[str, float] | None = None) -> dict:
    """Each angle source alone at its value, and all together, on the device and in the float64 model.

    Returns {source: {"device": table, "model": table, "deviation": (slots, 3)}} [m].
    """
    values = values_arcsec or PAPER_ALLOWED_ARCSEC
    model_tables = galvo_model.table1(frame.geometry, frame.cfg.flight.altitude_m,
                                      {k.lower(): v * ARCSEC for k, v in values.items()})
    out = {}
    for source, value in values.items():
        deviation, _ = frame.deviations(with_errors(frame.cfg, **{ANGLE_SOURCES[source]: value}))
        out[source] = {"device": table(deviation), "model": _model_table(model_tables[source.lower()]),
                       "deviation": deviation}
    together = with_errors(frame.cfg, **{ANGLE_SOURCES[s]: v for s, v in values.items()})
    deviation, _ = frame.deviations(together)
    out["all"] = {"device": table(deviation), "model": None, "deviation": deviation}
    return out


def _model_table(entry) -> dict[str, tuple[float, float]]:
    """galvo_model.table1's entry for one source as {axis: (max, min)} [m]."""
    if isinstance(entry, dict) and set(entry) >= set(AXES):
        return {axis: tuple(float(v) for v in entry[axis]) for axis in AXES}
    arr = np.asarray(entry, dtype=np.float64).reshape(3, 2)
    return {axis: (float(arr[k, 0]), float(arr[k, 1])) for k, axis in enumerate(AXES)}


@dataclass
class MonteCarlo:
    """Per-slot statistics of N device draws, in the sensor frame [m]."""

    draws: int
    mean: np.ndarray  # (slots, 3)
    std: np.ndarray  # (slots, 3), sample standard deviation
    hits: np.ndarray  # (slots,) draws in which the slot returned
    wall_s: float  # the draws' wall time (device work and host loop) [s]
    drawn: np.ndarray | None = None  # (draws, sources) systematic values drawn [arcsec or as the source's unit]


def draw_sigmas(cfg: RunConfig, allowed_arcsec: dict[str, float]) -> dict[str, float]:
    """1σ of every source of a Monte Carlo budget: the angle errors [rad], the range [m] and the noise [rad]."""
    s = RangingErrors(cfg.ranging).sigmas()
    return {"b1": allowed_arcsec["B1"] * ARCSEC, "b2": allowed_arcsec["B2"] * ARCSEC,
            "b3": allowed_arcsec["B3"] * ARCSEC, "c1": allowed_arcsec["C1"] * ARCSEC,
            "n_h": cfg.galvo.h_noise_arcsec * ARCSEC, "n_v": cfg.galvo.v_noise_arcsec * ARCSEC,
            "range": math.hypot(cfg.ranging.channel_delay_m, s.random)}


def monte_carlo(frame: Frame, draws: int, allowed_arcsec: dict[str, float] | None = None, seed: int = 0,
                ranging: RunConfig | None = None) -> MonteCarlo:
    """N draws of every source at once, on the device: per draw the four angle errors ~ N(0, σ) and
    each channel's fixed delay ~ N(0, channel_delay_m); per pulse the angle noise (of ``ranging``'s [galvo]) and
    per return the random ranging errors of ``ranging``'s [ranging] (default: the frame's config's).

    One simulator serves every draw: only its truth struct, its delays and its noise seed change.
    """
    import warp as wp

    allowed = allowed_arcsec or PAPER_ALLOWED_ARCSEC
    source = ranging or frame.cfg
    base = with_errors(frame.cfg, **{ANGLE_SOURCES[s]: v for s, v in allowed.items()},
                       **{k: getattr(source.galvo, k) for k in ("h_noise_arcsec", "v_noise_arcsec")},
                       **{k: getattr(source.ranging, k) for k in ("channel_delay_m", "clock_drift", "tdc_bin_s",
                                                                  "jitter_s", "rise_time_s", "cfd_fraction", "snr")})
    sim = frame.simulator(base)
    d = sim.device
    slots = SlotMoments(frame.pulses * frame.beams, d)
    rng = np.random.default_rng(seed)
    delay_sigma = base.ranging.channel_delay_m
    deflector = sim.instrument.deflector
    started = time.perf_counter()
    drawn_values = np.empty((draws, len(ANGLE_SOURCES)))
    for i in range(draws):
        drawn = {ANGLE_SOURCES[s]: float(rng.normal(0.0, allowed[s])) for s in ANGLE_SOURCES}
        drawn_values[i] = list(drawn.values())
        sim.scan.truth = type(deflector)(dataclasses.replace(base.galvo, **drawn), sim.instrument.emitter).params(
            believed=False)
        sim.scan.ranging.delays.assign(rng.normal(0.0, delay_sigma, frame.beams).astype(np.float32))
        sim.lines.seed.assign(np.array([(seed * 1_000_003 + i + 1) % (1 << 31)], dtype=np.int32))
        sim.run(slots.readout())
    wp.synchronize_device(d)
    wall = time.perf_counter() - started
    mean, std, n = slots.moments()
    rot = frame.sensor_rotation(sim)
    if not np.allclose(np.abs(rot), np.round(np.abs(rot)), atol=1e-12):
        raise ValueError("the budget frame's sensor axes must be the local axes up to sign")
    perm = np.abs(rot)  # local axis of each sensor axis
    return MonteCarlo(draws, mean @ rot, std @ perm, n.astype(np.int64), wall, drawn_values)
