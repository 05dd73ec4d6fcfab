"""Error budget of the seed paper's airborne Risley instrument (new: the paper has none).

The frame is the default instrument (3×3 fan, 15° cone, 500 m, 200 km/h, level flight) over a flat
plane for ``turns`` prism turns. Deviation = processed point − true hit in the local frame (E, N, U).

Sources and their 1σ (``SOURCES``): the prism-angle encoder's zero error and per-pulse noise, the
wedge's apex-angle and refractive-index errors (the processing believes the catalogue wedge), the
residual boresight error about each sensor axis, the POS position and attitude noise per pulse and
the range noise.

- :func:`deterministic`: each systematic source alone at +1σ on the device, and its linearisation
  (central difference at ±1σ) per slot;
- :func:`linearised_sigma`: first-order 1σ per slot of every source at once, from those
  linearisations (the noise sources reuse the Jacobians of their systematic twins, position and
  range noise are exact);
- :func:`monte_carlo`: N device draws of every source at once, per-slot statistics on the device.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from flightsim.engine.config import RunConfig, copy_config, validate
from flightsim.studies.budget import AXES, MonteCarlo, Frame, table
from flightsim.studies.budgets import SlotMoments, sigma_relative_error

ENU = ("E", "N", "U")


@dataclass(frozen=True)
class Source:
    sigma: float  # 1σ in ``unit``
    unit: str
    systematic: bool  # one value per run (drawn per Monte Carlo draw) or noise per pulse / return
    basis: str  # where the value comes from


SOURCES = {
    "encoder": Source(20.0, "arcsec", True, "a 16-bit absolute encoder's step, 360°/2¹⁶ = 19.8″"),
    "apex": Source(30.0, "arcsec", True, "precision wedge tolerance ±30″"),
    "index": Source(5e-4, "", True, "glass melt tolerance of the refractive index, ±5×10⁻⁴"),
    "roll": Source(18.0, "arcsec", True, "residual boresight after calibration, 0.005° per axis"),
    "pitch": Source(18.0, "arcsec", True, "residual boresight after calibration, 0.005° per axis"),
    "yaw": Source(18.0, "arcsec", True, "residual boresight after calibration, 0.005° per axis"),
    "encoder_noise": Source(5.0, "arcsec", False, "encoder read-out jitter per pulse (assumed)"),
    "position": Source(0.03, "m", False, "post-processed GNSS/IMU position per axis"),
    "attitude": Source(18.0, "arcsec", False, "navigation-grade IMU, 0.005° per axis"),
    "range": Source(0.02, "m", False, "range noise per return"),
}


def frame_config(device: str = "cpu", turns: int = 5) -> RunConfig:
    """The default instrument over the plane, ``turns`` prism turns of one line, every error off."""
    cfg = RunConfig()
    cfg.scene.name = "plane"
    cfg.output.models = ("exact",)
    cfg.run.device = device
    cfg.run.cull = False
    cfg.flight.duration_s = turns / cfg.risley.rotation_hz
    cfg.instrument.errors = ("ranging", "pose")
    return validate(cfg)


def with_sources(cfg: RunConfig, values: dict[str, float]) -> RunConfig:
    """A validated copy of ``cfg`` with each source of ``values`` ({name: value in its unit}) applied."""
    out = copy_config(cfg)
    v = {name: 0.0 for name in SOURCES} | values
    s = out.risley
    out.parts["pose"] = dataclasses.replace(out.pose, boresight_arcsec=(v["roll"], v["pitch"], v["yaw"]),
                                            position_noise_m=v["position"], attitude_noise_arcsec=v["attitude"])
    out.parts["ranging"] = dataclasses.replace(out.ranging, noise_m=v["range"])
    # the wedge is made off its catalogue values; the processing believes the catalogue
    out.parts["risley"] = dataclasses.replace(s, encoder_arcsec=v["encoder"], encoder_noise_arcsec=v["encoder_noise"],
                                              believed_apex_angle_deg=s.apex_angle_deg - v["apex"] / 3600.0,
                                              believed_refractive_index=s.refractive_index - v["index"])
    return validate(out)


def deterministic(frame: Frame) -> dict:
    """Each systematic source alone at +1σ: {name: {"table": {axis: (max, min)}, "deviation": (slots, 3),
    "per_sigma": (slots, 3) central-difference deviation per +1σ}} [m]; and the returning slots' unit
    ray directions and ranges, for the range column."""
    out = {}
    for name, source in SOURCES.items():
        if not source.systematic:
            continue
        plus, truth, sim = frame.local_deviations(with_sources(frame.cfg, {name: source.sigma}))
        minus, *_ = frame.local_deviations(with_sources(frame.cfg, {name: -source.sigma}))
        out[name] = {"table": table(plus), "deviation": plus, "per_sigma": (plus - minus) / 2.0}
    origin, _ = frame.poses(sim)
    ray = truth - origin.repeat(frame.beams, axis=0)
    out["_rays"] = ray / np.linalg.norm(ray, axis=1, keepdims=True)
    return out


def linearised_sigma(det: dict) -> np.ndarray:
    """First-order 1σ (slots, 3) [m] of every source of SOURCES at once, independent and zero-mean."""
    variance = sum(det[name]["per_sigma"] ** 2 for name, s in SOURCES.items() if s.systematic)
    ratio = SOURCES["encoder_noise"].sigma / SOURCES["encoder"].sigma
    variance = variance + (det["encoder"]["per_sigma"] * ratio) ** 2
    ratio = SOURCES["attitude"].sigma / SOURCES["roll"].sigma
    variance = variance + sum((det[axis]["per_sigma"] * ratio) ** 2 for axis in ("roll", "pitch", "yaw"))
    variance = variance + SOURCES["position"].sigma ** 2 + (det["_rays"] * SOURCES["range"].sigma) ** 2
    return np.sqrt(variance)


def monte_carlo(frame: Frame, draws: int, seed: int = 0) -> MonteCarlo:
    """N draws on the device of every source at once: the systematic ones ~ N(0, σ) per draw, the noise
    per pulse (or return) with a new seed per draw. One simulator serves every draw."""
    import warp as wp

    rng = np.random.default_rng(seed)
    noise = {name: s.sigma for name, s in SOURCES.items() if not s.systematic}
    systematic = {name: s.sigma for name, s in SOURCES.items() if s.systematic}
    sim = frame.simulator(with_sources(frame.cfg, noise | systematic))  # compiles every error path
    d = sim.device
    slots = SlotMoments(frame.pulses * frame.beams, d)
    started = time.perf_counter()
    for i in range(draws):
        drawn = {name: float(rng.normal(0.0, sigma)) for name, sigma in systematic.items()}
        sim.set_errors(with_sources(frame.cfg, noise | drawn))
        sim.lines.seed.assign(np.array([(seed * 1_000_003 + i + 1) % (1 << 31)], dtype=np.int32))
        sim.run(slots.readout())
    wp.synchronize_device(d)
    wall = time.perf_counter() - started
    mean, std, n = slots.moments()
    return MonteCarlo(draws, mean, std, n.astype(np.int64), wall)


def horizontal(deviation: np.ndarray) -> np.ndarray:
    return np.hypot(deviation[:, 0], deviation[:, 1])


def summary_rows(det: dict) -> list[dict]:
    """One row per systematic source: its 1σ and max/min |Δ| per axis [cm]."""
    rows = []
    for name, source in SOURCES.items():
        if source.systematic:
            t = det[name]["table"]
            rows.append({"source": name, "sigma": source.sigma, "unit": source.unit,
                         **{ax: [round(100 * v, 3) for v in t[axis]] for ax, axis in zip(ENU, AXES)},
                         "horizontal_max_cm": round(100 * float(np.nanmax(horizontal(det[name]["deviation"]))), 3)})
    return rows


def budget_numbers(frame: Frame, det: dict, mc: MonteCarlo, device: str) -> dict:
    analytic = linearised_sigma(det)
    ok = mc.hits > 1
    ratio = mc.std[ok] / analytic[ok]
    return {
        "device": device,
        "frame": {"pulses": frame.pulses, "beams": frame.beams, "altitude_m": frame.cfg.flight.altitude_m,
                  "cone_half_angle_deg": frame.cfg.risley.cone_half_angle_deg,
                  "apex_angle_deg": frame.cfg.risley.apex_angle_deg},
        "sources": {name: dataclasses.asdict(s) for name, s in SOURCES.items()},
        "deterministic_cm": summary_rows(det),
        "monte_carlo": {"draws": mc.draws, "wall_s": round(mc.wall_s, 3),
                        "std_over_linearised_median": [float(np.median(ratio[:, k])) for k in range(3)],
                        "std_over_linearised_p05": [float(np.percentile(ratio[:, k], 5)) for k in range(3)],
                        "std_over_linearised_p95": [float(np.percentile(ratio[:, k], 95)) for k in range(3)],
                        "expected_relative_error": sigma_relative_error(mc.draws),
                        "rms_cm": [float(100 * np.sqrt(np.mean(mc.std[ok][:, k] ** 2))) for k in range(3)],
                        "linearised_rms_cm": [float(100 * np.sqrt(np.mean(analytic[ok][:, k] ** 2)))
                                              for k in range(3)],
                        "max_cm": [float(100 * mc.std[ok][:, k].max()) for k in range(3)]},
        "linearised_share_of_variance": _shares(det),
    }


def _shares(det: dict) -> dict[str, list[float]]:
    """Each source's share of the frame-mean variance per axis (E, N, U), first order."""
    parts = {name: det[name]["per_sigma"] ** 2 for name, s in SOURCES.items() if s.systematic}
    parts["encoder_noise"] = (det["encoder"]["per_sigma"] * SOURCES["encoder_noise"].sigma
                              / SOURCES["encoder"].sigma) ** 2
    parts["attitude"] = sum((det[a]["per_sigma"] * SOURCES["attitude"].sigma / SOURCES["roll"].sigma) ** 2
                            for a in ("roll", "pitch", "yaw"))
    parts["position"] = np.full_like(det["encoder"]["per_sigma"], SOURCES["position"].sigma ** 2)
    parts["range"] = (det["_rays"] * SOURCES["range"].sigma) ** 2
    means = {name: np.nanmean(v, axis=0) for name, v in parts.items()}
    total = sum(means.values())
    return {name: [round(float(x), 4) for x in m / total] for name, m in means.items()}
