"""`flightsim selfcal`: Risley self-calibration over the calibration field for a grid of arrays and altitudes —
plane-fit RMS before and after, the recovered parameters with their 1-σ, the correlation matrix — into
DIR/selfcal.json, DIR/REPORT.md and DIR/selfcal_rms.png.

Per configuration (:mod:`flightsim.studies.selfcal_flight`): fly the nominal-model flight with the injected errors,
corrupt 10 % of the roof planes, segment the nominal points blindly and calibrate (round 1); re-georeference every
point with the estimate, segment those points blindly again (the two lines' views of a roof now agree, so they fall
in one segment) and calibrate again from the round-1 estimate (round 2).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from flightsim.core.atomic import save_figure, write_atomic
from flightsim.core.errors import InputError
from flightsim.studies import selfcal as sc
from flightsim.studies import selfcal_flight as sf

FULL_GRID = {"arrays": (3, 8), "altitudes_m": (500.0, 1000.0, 2000.0, 5000.0)}
QUICK_GRID = {"arrays": (3,), "altitudes_m": (1000.0,)}
CONTROL = (3, 2000.0)  # the configuration also run with a plain loss and without outliers
MAX_ROUNDS = 5  # segment-and-calibrate rounds at most
SETTLED_ARCSEC = 0.5  # converged: no observable combination moved more than this in the last round [arcsec]
MAX_SEGMENTED_POINTS = 400_000  # points given to the blind finder, a seeded choice of whole pulses beyond this
RECOVERED_FACTOR = 1.5  # truth check: exact-true RMS on the final segments within this factor of the estimate's
OUTLIER_WEIGHT = 0.5  # a segment whose median IRLS weight is below this counts as rejected by the robust loss


def run_configuration(altitude_m: float, array: int, device: str = "cpu", ladder: np.ndarray | None = None,
                      injected=sf.Injected(), control: bool = False) -> list[dict]:
    """Self-calibrate one configuration from the believed values, and also from ``ladder`` (the estimate of a lower
    flight) when given; return its rows of selfcal.json (one per start). ``control`` adds two rows from the believed
    values: with a plain (linear) loss, and on the same flight without the outlier planes."""
    started = time.perf_counter()
    cfg = sf.flight_config(altitude_m, array, device, injected)
    truth, believed = sf.parameters(cfg)
    flight = sf.fly(cfg)
    clean = (flight.range_m.copy(), flight.nominal.copy())
    outliers = sf.inject_outliers(flight)
    inside = _decimated(flight, sf.crop(flight))
    everything = sf.observations(flight, inside)
    nominal_segments = sf.segment_blindly(flight, inside, flight.nominal[inside])[:2]
    flown = time.perf_counter() - started
    rows = []
    starts = [("believed", believed, "soft_l1"), ("ladder", ladder, "soft_l1")]
    for start, x0, loss in starts + ([("control: linear loss", believed, "linear")] if control else []):
        if x0 is None:
            continue
        began = time.perf_counter()
        cal, obs, rounds, converged = _rounds(flight, inside, everything, x0, nominal_segments if start != "ladder"
                                              else None, device, loss)
        cal.x0 = believed  # the combinations are reported from the believed values
        row = _row(flight, cfg, obs, cal, rounds, converged, start, outliers, nominal_segments, device)
        rows.append(row | {"recovered": recovered(row), "wall_s": time.perf_counter() - began + flown})
    if control:
        flight.range_m, flight.nominal = clean
        rows += run_clean(flight, cfg, inside, believed, device)
    return rows


def run_clean(flight, cfg, inside, believed, device) -> list[dict]:
    """The control row on the flight without outlier planes."""
    began = time.perf_counter()
    everything = sf.observations(flight, inside)
    segments = sf.segment_blindly(flight, inside, flight.nominal[inside])[:2]
    cal, obs, rounds, converged = _rounds(flight, inside, everything, believed, segments, device)
    cal.x0 = believed
    row = _row(flight, cfg, obs, cal, rounds, converged, "control: no outliers", np.zeros(0, np.int64), segments,
               device)
    return [row | {"recovered": recovered(row), "wall_s": time.perf_counter() - began}]


def _rounds(flight, inside, everything, x, segments, device, loss="soft_l1"):
    """Segment blindly and calibrate until the observable combinations settle (or MAX_ROUNDS); ``segments``: the
    first round's (index, ids), else segmented from the points of ``x``."""
    rounds, previous = [], None
    for _ in range(MAX_ROUNDS):
        if segments is None:
            segments = sf.segment_blindly(flight, inside, sc.georeference(everything, x, device))[:2]
        index, segment = segments
        obs = sf.observations(flight, index, segment)
        cal = sc.calibrate(sf.solver_subset(obs), x, loss=loss, device=device)
        now = np.array([sc.cone_angle(cal.x), cal.x[2] + cal.x[5], cal.x[3], cal.x[4]]) / sc.ARCSEC
        rounds.append({"segments": int(segment.max() + 1), "points": cal.points, "evaluations": cal.evaluations})
        settled = previous is not None and np.abs(now - previous).max() < SETTLED_ARCSEC
        x, previous, segments = cal.x, now, None
        if settled:
            break
    obs.index = index
    return cal, obs, rounds, bool(settled)


def _row(flight, cfg, obs, cal, rounds, converged, start, outliers, nominal_segments, device) -> dict:
    truth, believed = sf.parameters(cfg)
    index, segment = obs.index, obs.segment
    bad = np.isin(flight.scene.plane_id[flight.face[index]], outliers)
    return {"altitude_m": cfg.flight.altitude_m, "array": cfg.fan.array, "start": start, "converged": converged,
            "truth": truth.tolist(), "believed": believed.tolist(), "estimate": cal.x.tolist(),
            "sigma": cal.sigma.tolist(), "correlation": cal.correlation.tolist(),
            "combinations": _combinations(cal, truth, believed), "sigma0_m": cal.sigma0_m,
            "rms_m": _rms(flight, obs, index, segment, bad, cal, truth, believed, nominal_segments, device),
            "outliers": _outlier_counts(obs, cal, bad, outliers), "rounds": rounds, "returns": len(flight.range_m)}


def recovered(row: dict) -> bool:
    """The truth check of a row (scoring only, never seen by the estimator): converged, and the exact model with the
    true parameters fits the final segments about as well as the estimate (else the segments and the estimate are
    a self-consistent false minimum)."""
    m = row["rms_m"]
    return row["converged"] and m["exact_true"] <= RECOVERED_FACTOR * m["exact_selfcal"]


def _decimated(flight: sf.Flight, inside: np.ndarray, seed: int = 0) -> np.ndarray:
    """``inside``, or the returns of a seeded choice of its pulses holding at most MAX_SEGMENTED_POINTS."""
    if len(inside) <= MAX_SEGMENTED_POINTS:
        return inside
    keep = np.random.default_rng(seed).random(len(flight.phi)) < MAX_SEGMENTED_POINTS / len(inside)
    return inside[keep[flight.pulse[inside]]]


def _combinations(cal: sc.Calibration, truth: np.ndarray, believed: np.ndarray) -> dict:
    injected = {"cone_half_angle": (sc.cone_angle(truth) - sc.cone_angle(believed)) / sc.ARCSEC,
                "encoder_plus_yaw": (truth[2] + truth[5]) / sc.ARCSEC}
    return {k: {"injected": injected[k], "recovered": v, "sigma": s} for k, (v, s) in sc.combinations(cal).items()}


def _rms(flight, obs, index, segment, bad, cal, truth, believed, first, device) -> dict:
    """Pooled plane-fit RMS [m] over the final blind segments without injected outlier points (and with them),
    per model; and the nominal cloud's RMS over its own (round-1) segments."""
    clean = np.bincount(segment, bad, segment.max() + 1) == 0
    clouds = {"nominal_believed": flight.nominal[index], "exact_believed": sc.georeference(obs, believed, device),
              "exact_selfcal": sc.georeference(obs, cal.x, device), "exact_true": sc.georeference(obs, truth, device)}
    out = {name: sc.pooled_rms(p, segment, clean) for name, p in clouds.items()}
    out.update({f"{name}_all": sc.pooled_rms(p, segment) for name, p in clouds.items()})
    i0, s0 = first
    out["nominal_believed_own_segments"] = sc.pooled_rms(flight.nominal[i0], s0)
    return out


def _outlier_counts(obs, cal, bad, outliers) -> dict:
    """Injected outlier planes, final segments holding their points, and segments the robust loss rejected."""
    sub = sf.solver_subset(obs)
    r = sc.plane_residuals(sc.georeference(sub, cal.x), sub.segment)
    w = 1.0 / np.sqrt(1.0 + (r / cal.f_scale_m) ** 2)
    median_w = np.array([np.median(w[sub.segment == s]) for s in range(sub.segment.max() + 1)])
    return {"injected_planes": len(outliers), "segments_with_outlier_points": int(np.unique(obs.segment[bad]).size),
            "segments": int(obs.segment.max() + 1), "rejected_segments": int(np.sum(median_w < OUTLIER_WEIGHT))}


def run_selfcal(out: Path, device: str = "cpu", quick: bool = False, grid: dict | None = None,
                progress=None) -> dict:
    """Run the grid into ``out``: selfcal.json, REPORT.md and the figure; ``progress(row)`` after each one."""
    grid = grid or (QUICK_GRID if quick else FULL_GRID)
    if not grid["arrays"] or not grid["altitudes_m"]:
        raise InputError("selfcal.grid", grid, "at least one array and one altitude")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    rows = []
    for n in grid["arrays"]:
        ladder = None
        for h in sorted(grid["altitudes_m"]):
            made = run_configuration(h, n, device, ladder, control=(n, h) == CONTROL)
            settled = [r for r in made if r["converged"] and r["start"] in ("believed", "ladder")]  # blind: the truth check is not used
            ladder = np.array(settled[-1]["estimate"]) if settled else ladder
            rows += made
            for row in made if progress else ():
                progress(row)
    command = f"flightsim selfcal --out {out} --device {device}" + (" --quick" if quick else "")
    results = {"command": command, "device": device, "parameters": list(sc.PARAMETERS),
               "units": ["", "rad", "rad", "rad", "rad", "rad"], "injected": sf.Injected().__dict__,
               "rows": rows, "wall_s": time.perf_counter() - started}
    write_atomic(out / "selfcal.json", json.dumps(results, indent=1, default=_plain))
    figure = _figure(rows, out)
    from flightsim.studies.selfcal_text import report

    write_atomic(out / "REPORT.md", report(results, figure))
    return results


def _plain(value):
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if isinstance(value, tuple):
        return list(value)
    raise TypeError(type(value))


def _figure(rows: list[dict], out: Path) -> str | None:
    """RMS against altitude before and after, one panel per array."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arrays = sorted({r["array"] for r in rows})
    fig, axes = plt.subplots(1, len(arrays), figsize=(5 * len(arrays), 4), squeeze=False)
    for ax, n in zip(axes[0], arrays):
        mine = sorted((r for r in rows if r["array"] == n and r["start"] == "believed"), key=lambda r: r["altitude_m"])
        ladder = sorted((r for r in rows if r["array"] == n and r["start"] == "ladder"), key=lambda r: r["altitude_m"])
        h = [r["altitude_m"] / 1000 for r in mine]
        for key, label, style in (("nominal_believed", "before: nominal, believed", "o-"),
                                  ("exact_believed", "exact, believed", "s--"),
                                  ("exact_selfcal", "after: from the believed values", "^-"),
                                  ("exact_true", "exact, true parameters (same segments)", "k:")):
            ax.plot(h, [r["rms_m"][key] * 100 for r in mine], style, label=label)
        if ladder:
            hl = [r["altitude_m"] / 1000 for r in ladder]
            ax.plot(hl, [r["rms_m"]["exact_selfcal"] * 100 for r in ladder], "v-", color="C3",
                    label="after: from the lower flight's estimate")
            ax.plot(hl, [r["rms_m"]["exact_true"] * 100 for r in ladder], ":", color="C3",
                    label="exact, true parameters (ladder's segments)")
        for r in mine:
            if not r["recovered"]:
                ax.annotate("false minimum", (r["altitude_m"] / 1000, r["rms_m"]["exact_selfcal"] * 100),
                            textcoords="offset points", xytext=(-60, 8), fontsize=8, color="C2")
        ax.set_yscale("log")
        ax.set_xlabel("altitude [km]")
        ax.set_ylabel("plane-fit RMS [cm]")
        ax.set_title(f"{n}×{n} array")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "selfcal_rms.png", dpi=110)
    plt.close(fig)
    return "selfcal_rms.png"

