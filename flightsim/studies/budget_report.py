"""`flightsim budget`: the galvo imager's full-link error budget written to a directory: budget.json,
deviation maps (PNG) and REPORT.md with every number beside the seed paper's."""
from __future__ import annotations

import dataclasses
import json
import math
import platform
import time
from pathlib import Path

import numpy as np

from flightsim.core.atomic import write_atomic
from flightsim.core.constants import ARCSEC
from flightsim.instrument import galvo_model
from flightsim.instrument.ranging import RangingErrors
from flightsim.studies.budget import (ANGLE_SOURCES, AXES, PAPER_ALLOWED_ARCSEC, PAPER_TABLE1_CM, Frame, deterministic,
                                      draw_sigmas, frame_config, monte_carlo)
from flightsim.studies.budgets import sigma_relative_error

ANGLE_NAMES = tuple(ANGLE_SOURCES)
PAPER_IMPLIED_FIELD_DEG = 34.0  # horizontal beam field that reproduces the paper's Y, Z columns of B2, B3 [deg]
PAPER_RANGING_CM = {"tdc": 0.77, "jitter": 0.4, "cfd": 3.3, "random": 3.4, "sigma_r": 6.04}
PAPER_SIGMA_R_M = PAPER_RANGING_CM["sigma_r"] / 100.0
COMMAND = "flightsim budget --out results/change3 --draws {draws} --device {device}"


def run_budget(out: Path, device: str = "cpu", draws: int = 200, columns: int | None = None, seed: int = 0) -> dict:
    """Compute the budget of the Chang'e-3 preset at 100 m and write it under ``out``; return the numbers."""
    out.mkdir(parents=True, exist_ok=True)
    frame = Frame(frame_config(columns=columns, device=device))
    started = time.perf_counter()
    det = deterministic(frame)
    det_s = time.perf_counter() - started
    ranging_cfg = frame_config(device=device)  # the preset's ranging chain (frame_config zeroes it)
    from flightsim.engine.config_io import preset_config

    preset = preset_config("change3")
    ranging_cfg.parts["ranging"] = preset.ranging
    monte_carlo(frame, 2, seed=seed, ranging=ranging_cfg)  # compiles its kernels: the timing below excludes it
    mc = monte_carlo(frame, draws, seed=seed, ranging=ranging_cfg)
    sig = draw_sigmas(ranging_cfg, PAPER_ALLOWED_ARCSEC)
    analytic = galvo_model.analytic_sigma(frame.geometry, sig, frame.cfg.flight.altitude_m)
    allowed = {f"{name}_{k}": v for name, sigma_r in (("ours", sig["range"]), ("paper_sigma_r", PAPER_SIGMA_R_M))
               for k, v in galvo_model.allowed_errors(frame.geometry, sigma_r_m=sigma_r,
                                                      distance_m=frame.cfg.flight.altitude_m).items()}
    numbers = _numbers(frame, det, mc, analytic, allowed, ranging_cfg, device, det_s)
    numbers["table1_cm_34deg_model"] = _wide_field_table(frame)
    write_atomic(out / "budget.json", json.dumps(numbers, indent=2) + "\n")
    _maps(frame, det, mc, analytic, out)
    write_atomic(out / "REPORT.md", _report(numbers))
    return numbers


def _numbers(frame, det, mc, analytic, allowed, ranging_cfg, device, det_s) -> dict:
    ok = mc.hits > 1
    ratio = mc.std[ok] / np.where(analytic[ok] > 0, analytic[ok], np.nan)
    s = RangingErrors(ranging_cfg.ranging).sigmas()
    return {
        "device": device, "host": platform.node(),
        "frame": {"strips": frame.cfg.galvo.strips, "columns": frame.cfg.galvo.columns, "channels": frame.beams,
                  "slots": frame.pulses * frame.beams, "distance_m": frame.cfg.flight.altitude_m,
                  "b_mm": frame.cfg.galvo.b_mm, "e_mm": frame.cfg.galvo.e_mm},
        "table1_cm": {src: {"device": {a: [round(v * 100, 3) for v in r["device"][a]] for a in AXES},
                            "model": ({a: [round(v * 100, 3) for v in r["model"][a]] for a in AXES}
                                      if r["model"] else None),
                            "paper": PAPER_TABLE1_CM.get(src)}
                      for src, r in det.items()},
        "deterministic_wall_s": round(det_s, 3),
        "ranging_cm": {"tdc": s.tdc * 100, "jitter": s.jitter * 100, "cfd": s.cfd * 100, "random": s.random * 100,
                       "delay": ranging_cfg.ranging.channel_delay_m * 100,
                       "sigma_r": math.hypot(ranging_cfg.ranging.channel_delay_m, s.random) * 100,
                       "clock_drift_at_100m_mm": ranging_cfg.ranging.clock_drift * 100.0 * 1000.0,
                       "paper": PAPER_RANGING_CM},
        "allowed": {k: (float(v) if np.ndim(v) == 0 else np.asarray(v, dtype=float).tolist())
                    for k, v in allowed.items()},
        "monte_carlo": {"draws": mc.draws, "wall_s": round(mc.wall_s, 3),
                        "draws_per_s": round(mc.draws / mc.wall_s, 2),
                        "slot_draws_per_s": round(mc.draws * frame.pulses * frame.beams / mc.wall_s),
                        "std_over_analytic_median": [float(np.nanmedian(ratio[:, k])) for k in range(3)],
                        "std_over_analytic_p05": [float(np.nanpercentile(ratio[:, k], 5)) for k in range(3)],
                        "std_over_analytic_p95": [float(np.nanpercentile(ratio[:, k], 95)) for k in range(3)],
                        "expected_relative_error": sigma_relative_error(mc.draws),
                        "drawn_sigma_arcsec": dict(zip(ANGLE_NAMES, np.std(mc.drawn, axis=0, ddof=1).round(2).tolist())),
                        "drawn_b1_b2_correlation": round(float(np.corrcoef(mc.drawn[:, 0], mc.drawn[:, 1])[0, 1]), 3),
                        "max_std_cm": [float(np.nanmax(mc.std[ok][:, k]) * 100) for k in range(3)],
                        "max_analytic_cm": [float(np.max(analytic[ok][:, k]) * 100) for k in range(3)]},
    }


def _wide_field_table(frame) -> dict:
    """The float64 model's Table 1 with a 34° horizontal field: the field the paper's Y and Z columns imply."""
    geometry = dataclasses.replace(frame.geometry, field_deg=(PAPER_IMPLIED_FIELD_DEG, frame.geometry.field_deg[1]))
    values = {k.lower(): v * ARCSEC for k, v in PAPER_ALLOWED_ARCSEC.items()}
    tables = galvo_model.table1(geometry, frame.cfg.flight.altitude_m, values)
    return {src.upper(): {a: [round(v * 100, 3) for v in t[a]] for a in AXES} for src, t in tables.items()}


def _maps(frame, det, mc, analytic, out: Path) -> None:
    """Deviation maps over the field (the paper's Figs. 5–8) and the σ maps of the Monte Carlo."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, truth = frame.deviations(frame.cfg)
    u = np.degrees(np.arctan2(truth[:, 0], truth[:, 2]))
    v = np.degrees(np.arctan2(truth[:, 1], truth[:, 2]))
    panels = [(f"{src} = {PAPER_ALLOWED_ARCSEC.get(src, 0):g}″" if src != "all" else "B1+B2+B3+C1",
               r["deviation"]) for src, r in det.items()]
    panels.append((f"Monte Carlo σ, {mc.draws} draws", mc.std))
    panels.append(("first-order σ (J Σ Jᵀ)", analytic))
    fig, axes = plt.subplots(len(panels), 3, figsize=(12, 3.2 * len(panels)), constrained_layout=True)
    for row, (title, values) in enumerate(panels):
        for k, axis in enumerate(AXES):
            ax = axes[row, k]
            sc = ax.scatter(u, v, c=values[:, k] * 100, s=0.3, cmap="coolwarm" if "σ" not in title else "viridis")
            fig.colorbar(sc, ax=ax, label=f"Δ{axis} [cm]")
            ax.set_title(f"{title}: Δ{axis}", fontsize=9)
            ax.set_aspect("equal")
            if row == len(panels) - 1:
                ax.set_xlabel("horizontal angle [deg]")
            if k == 0:
                ax.set_ylabel("vertical angle [deg]")
    fig.savefig(out / "deviation_maps.png", dpi=90)
    plt.close(fig)


def _report(n: dict) -> str:
    """REPORT.md of the Chang'e-3 budget from its numbers (budget.json): the instrument, Table 1 beside the
    paper's, the ranging chain, the allowed errors and the Monte Carlo against first-order propagation."""
    return (_report_heading(n) + _table1_section(n) + _ranging_section(n) + _allowed_section(n)
            + _monte_carlo_section(n))


def _report_heading(n: dict) -> str:
    """The title, the command that regenerates the report, and the instrument and frame simulated."""
    mc, f = n["monte_carlo"], n["frame"]
    return f"""# Chang'e-3 laser 3D imager: full-link error budget

Regenerate: `{COMMAND.format(draws=mc['draws'], device=n['device'])}` (device `{n['device']}`).
Seed: `../shared/seeds/change3-imager-full-link-error-paper.txt`. Instrument: the `change3` preset
(16 channels θ_i = 17 − 2i mrad, two galvo mirrors b = {f['b_mm']:g} mm, e = {f['e_mm']:g} mm,
{f['strips']} strips × {f['columns']} columns, one frame = {f['slots']:,} beams), hovering {f['distance_m']:g} m over a
plane square to its optical axis. Deviation = processed point − true hit; X horizontal, Y vertical,
Z along the optical axis (the paper's frame). Each angle source alone at the paper's allowed 1σ
(B1 = B2 = B3 = 42.9″, C1 = 94.5″), as the paper's Table 1 does ("1倍中误差为误差量").

"""


def _table1_section(n: dict) -> str:
    """Table 1 (each angle source alone: max / min |deviation| [cm], device, float64 model and paper), explained."""
    t = n["table1_cm"]
    rows = []
    for src in ("B1", "B2", "B3", "C1"):
        for axis in AXES:
            d, m, p = t[src]["device"][axis], t[src]["model"][axis], t[src]["paper"][axis]
            rows.append(f"| {src} | {axis} | {d[0]:.2f} / {d[1]:.2f} | {m[0]:.2f} / {m[1]:.2f} | "
                        f"{p[0]:.2f} / {p[1]:.2f} |")
    allx = t["all"]["device"]
    w = n["table1_cm_34deg_model"]
    return f"""## Table 1: max / min |deviation| over the frame [cm]

| source | axis | device (Warp, exact reflection) | float64 model (NumPy) | paper |
| --- | --- | --- | --- | --- |
{chr(10).join(rows)}

All four together (device): X {allx['X'][0]:.2f} / {allx['X'][1]:.2f}, Y {allx['Y'][0]:.2f} / {allx['Y'][1]:.2f},
Z {allx['Z'][0]:.2f} / {allx['Z'][1]:.2f} cm.

Differences, explained:
- **B1**: the paper's Table 1 row for B1 repeats its C1 row (Y 9.17 cm constant, X 0), while its own
  text (§3.2, Fig. 5) says B1 moves the points mostly along X, odd and even strips in opposite
  directions, with small Y and Z effects. A horizontal encoder zero error turns the horizontal
  mirror, so it moves points along X: we get |ΔX| = 2·B1·D / cos 2γ (D = 100 m along the axis, 2γ the
  beam's vertical angle: 4.16–4.33 cm), the sign flipping
  strip by strip (tests/test_galvo.py checks the flip), small Y and Z. We read the table row as a
  copy of the C1 row.
- **B2, B3: Y and Z**: ours are 12–16 % below the paper's. These columns grow as tan 2δ with the
  horizontal beam angle, and X does not depend on it. With a {PAPER_IMPLIED_FIELD_DEG:g}° horizontal field instead of
  30° the float64 model gives B2 Y {w['B2']['Y'][0]:.2f}, Z {w['B2']['Z'][0]:.2f} and B3 Y {w['B3']['Y'][0]:.3f}, Z {w['B3']['Z'][0]:.2f} cm
  (paper 0.34, 1.28, 0.04, 0.17), X unchanged: the paper's simulated frame was about ±17° wide
  horizontally. We keep the 30°×30° field the paper states and the issue asks for.
- **B2, B3: X; C1**: within 1 % of the paper.
- Device against the float64 model: the device traces float32 rays and writes float32 points; the
  two tables agree to the rounding of float32 coordinates at 100 m (a few µm).

"""


def _ranging_section(n: dict) -> str:
    """The ranging chain's terms [cm] beside the paper's (§2.1)."""
    r = n["ranging_cm"]
    return f"""## Ranging chain (§2.1) [cm]

| source | ours | paper | formula |
| --- | --- | --- | --- |
| TDC quantisation (τ = 125 ps) | {r['tdc']:.3f} | {r['paper']['tdc']} | (c/2)·τ/√6 |
| rising-edge jitter (20 ps per stamp) | {r['jitter']:.3f} | {r['paper']['jitter']} | (c/2)·√2·σ_t |
| constant-fraction timing (k 0.3, t_r 7 ns, SNR 31) | {r['cfd']:.3f} | {r['paper']['cfd']} | (c/2)·(t_r/SNR)·√(1+k²) |
| random total | {r['random']:.3f} | {r['paper']['random']} | root sum of squares |
| fixed delay after calibration | {r['delay']:.3f} | 5 | config `ranging.channel_delay_m` |
| σ_r | {r['sigma_r']:.3f} | {r['paper']['sigma_r']} | √(delay² + random²) |

- Jitter: the paper's 0.4 cm is (c/2)·20 ps·√2 rounded (start and stop each jitter).
- Constant-fraction timing: the paper's eq. (5) is not in the text we have; our standard
  leading-edge form gives {r['cfd']:.2f} cm against its 3.3 cm ({(r['cfd'] / 3.3 - 1) * 100:+.0f} %).
- Clock drift e_df = 2×10⁻⁶: {r['clock_drift_at_100m_mm']:.2f} mm at 100 m (R·e_df). The paper calls it
  negligible; its "order of 10⁻⁷ m" does not follow from its own formula (R·e_df = 0.2 mm at 100 m).

"""


def _allowed_section(n: dict) -> str:
    """The allowed angle errors [arcsec] for σz = 20 cm / 3 (§3.3), with the paper's and our σ_r."""
    r, a = n["ranging_cm"], n["allowed"]
    return f"""## Allowed errors (§3.3)

σz = 20 cm / 3 = {a['ours_sigma_z_m'] * 100:.2f} cm must hold at every point of the frame; with equal angle errors on both
mirrors (eq. 20) the binding point is a corner, and σB = σθ / (1 + sec γ + tan γ) (eq. 22) at its
vertical angle observation γ = {a['ours_gamma_deg']:.2f}°:

| σ_r | σθ = σ_C1 | σB |
| --- | --- | --- |
| paper's 6.04 cm | {a['paper_sigma_r_sigma_theta_arcsec']:.1f}″ | {a['paper_sigma_r_sigma_b_arcsec']:.1f}″ |
| ours {r['sigma_r']:.2f} cm | {a['ours_sigma_theta_arcsec']:.1f}″ | {a['ours_sigma_b_arcsec']:.1f}″ |
| paper | 94.5″ | 42.9″ |

With the paper's σ_r, σθ is within 0.5 % of its 94.5″; σB is 3 % above its 42.9″: the paper does
not state the γ it used, and 42.9″ = 94.5″ / (1 + sec γ + tan γ) needs γ = 10.5° rather than the
binding corner's 7.9°.

"""


def _monte_carlo_section(n: dict) -> str:
    """The device's Monte Carlo σ against the float64 model's first-order σ, slot by slot."""
    mc = n["monte_carlo"]
    ds = mc["drawn_sigma_arcsec"]
    return f"""## Monte Carlo (device) against first-order propagation (float64)

{mc['draws']} draws of every source at once (B1, B2, B3, C1 ~ N(0, allowed σ); each channel's
delay ~ N(0, 5 cm); TDC, jitter and constant-fraction noise per return) in {mc['wall_s']:.2f} s (compilation excluded)
({mc['draws_per_s']:.1f} draws/s, {mc['slot_draws_per_s']:,} beam-draws/s) on `{n['device']}`.
Per slot, Monte Carlo σ ÷ analytic σ (J Σ Jᵀ of the NumPy model): median X {mc['std_over_analytic_median'][0]:.3f},
Y {mc['std_over_analytic_median'][1]:.3f}, Z {mc['std_over_analytic_median'][2]:.3f}; 5–95 % range
X {mc['std_over_analytic_p05'][0]:.3f}–{mc['std_over_analytic_p95'][0]:.3f}, Y {mc['std_over_analytic_p05'][1]:.3f}–{mc['std_over_analytic_p95'][1]:.3f},
Z {mc['std_over_analytic_p05'][2]:.3f}–{mc['std_over_analytic_p95'][2]:.3f}; the expected relative error of a σ from
{mc['draws']} draws is {mc['expected_relative_error']:.3f}. The angle errors are drawn once per draw for every slot, so
the per-slot ratios move together: the drawn values' sample σ are B1 {ds['B1']:.1f}″, B2 {ds['B2']:.1f}″, B3 {ds['B3']:.1f}″,
C1 {ds['C1']:.1f}″ (Y follows C1's), and the drawn B1 and B2 correlate by {mc['drawn_b1_b2_correlation']:+.3f}, which
bands the Monte Carlo ΔX σ strip by strip (B1's sign flips between strips; first-order propagation
takes them as uncorrelated). Largest σ over the field: MC
X {mc['max_std_cm'][0]:.2f}, Y {mc['max_std_cm'][1]:.2f}, Z {mc['max_std_cm'][2]:.2f} cm; analytic
X {mc['max_analytic_cm'][0]:.2f}, Y {mc['max_analytic_cm'][1]:.2f}, Z {mc['max_analytic_cm'][2]:.2f} cm.

Maps: `deviation_maps.png` (rows: each source alone, all together, MC σ, analytic σ; columns ΔX, ΔY, ΔZ
over the field's horizontal and vertical angles).
"""


RISLEY_COMMAND = "flightsim budget --instrument risley --out results/paper/budget --draws {draws} --device {device}"


def run_risley_budget(out: Path, device: str = "cpu", draws: int = 200, seed: int = 0, turns: int = 5) -> dict:
    """The seed paper's Risley instrument's budget (``studies.risley_budget``) written under ``out``."""
    from flightsim.studies import risley_budget as rb

    out.mkdir(parents=True, exist_ok=True)
    cfg = rb.frame_config(device=device, turns=turns)
    frame = Frame(cfg, pulses=round(cfg.flight.duration_s * cfg.risley.prf_hz))
    det = rb.deterministic(frame)
    rb.monte_carlo(frame, 2, seed=seed)  # compiles its kernels: the timing below excludes it
    mc = rb.monte_carlo(frame, draws, seed=seed)
    numbers = rb.budget_numbers(frame, det, mc, device)
    write_atomic(out / "budget.json", json.dumps(numbers, indent=2) + "\n")
    _risley_maps(frame, det, mc, rb, out)
    write_atomic(out / "REPORT.md", _risley_report(numbers, rb))
    return numbers


def _risley_maps(frame, det, mc, rb, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    _, truth, _ = frame.local_deviations(frame.cfg)
    panels = [(f"{name} +1σ", det[name]["deviation"], "coolwarm") for name, s in rb.SOURCES.items() if s.systematic]
    panels += [(f"Monte Carlo σ, {mc.draws} draws", mc.std, "viridis"),
               ("linearised σ", rb.linearised_sigma(det), "viridis")]
    fig, axes = plt.subplots(len(panels), 3, figsize=(12, 2.6 * len(panels)), constrained_layout=True)
    for row, (title, values, cmap) in enumerate(panels):
        for k, axis in enumerate(rb.ENU):
            ax = axes[row, k]
            sc = ax.scatter(truth[:, 0], truth[:, 1], c=values[:, k] * 100, s=0.5, cmap=cmap)
            fig.colorbar(sc, ax=ax, label=f"Δ{axis} [cm]")
            ax.set_title(f"{title}: Δ{axis}", fontsize=9)
            ax.set_aspect("equal")
    fig.savefig(out / "deviation_maps.png", dpi=80)
    plt.close(fig)


def _risley_report(n: dict, rb) -> str:
    """REPORT.md of the Risley budget from its numbers (budget.json): the sources, each systematic one alone,
    then every source at once (first-order shares and the Monte Carlo)."""
    return _risley_sources_section(n) + _risley_combined_section(n)


def _risley_sources_section(n: dict) -> str:
    """The title, the instrument, the sources and their 1σ, and each systematic source alone at +1σ [cm]."""
    f, mc = n["frame"], n["monte_carlo"]
    sources = "\n".join(f"| {name} | {s['sigma']:g} {s['unit']} | {'per run' if s['systematic'] else 'per pulse'} | "
                        f"{s['basis']} |" for name, s in n["sources"].items())
    rows = "\n".join(f"| {r['source']} | {r['E'][0]:.2f} / {r['E'][1]:.2f} | {r['N'][0]:.2f} / {r['N'][1]:.2f} | "
                     f"{r['U'][0]:.2f} / {r['U'][1]:.2f} | {r['horizontal_max_cm']:.2f} |"
                     for r in n["deterministic_cm"])
    return f"""# Error budget of the airborne Risley instrument (seed 001)

Regenerate: `{RISLEY_COMMAND.format(draws=mc['draws'], device=n['device'])}`.
No paper has this budget: it is new. The instrument is the default (3×3 DOE fan through one
rotating wedge, cone {f['cone_half_angle_deg']:g}°, apex {f['apex_angle_deg']:.4f}°), flying level at 200 km/h,
{f['altitude_m']:g} m over a flat plane, {f['pulses']:,} pulses × {f['beams']} beams (five prism turns).
Deviation = processed point − true hit, local frame: E (across track), N (along track), U (up).

## Sources and their 1σ

| source | 1σ | drawn | basis |
| --- | --- | --- | --- |
{sources}

The processing believes the catalogue wedge (apex, index), the encoder's reading, the calibrated
boresight and the POS trajectory; the truth carries the errors (`risley.encoder_arcsec`,
`encoder_noise_arcsec`; `pose.boresight_arcsec`, `position_noise_m`, `attitude_noise_arcsec`;
`ranging.noise_m`; and `risley.believed_apex_angle_deg`, `believed_refractive_index` off the true wedge's).

## Each systematic source alone at +1σ: max / min |deviation| [cm]

| source | E | N | U | horizontal max |
| --- | --- | --- | --- | --- |
{rows}

Checks against closed forms (tests/test_pose_errors.py): a boresight error turns every ray about the
sensor origin, believed − true = R (Mᵀ − I) Rᵀ (T − O) to float32 rounding; an encoder zero error
turns the on-axis beam about the vertical by exactly the error (no height change in level flight);
the noise sources have their σ.

"""


def _risley_combined_section(n: dict) -> str:
    """Every source at once: each one's first-order share of the variance, and the Monte Carlo σ [cm] against
    the linearised σ."""
    mc = n["monte_carlo"]
    shares = "\n".join(f"| {name} | " + " | ".join(f"{100 * v:.1f} %" for v in s) + " |"
                       for name, s in n["linearised_share_of_variance"].items())
    return f"""## Every source at once

Share of the frame-mean variance, first order (E, N, U):

| source | E | N | U |
| --- | --- | --- | --- |
{shares}

Monte Carlo: {mc['draws']} draws on `{n['device']}` in {mc['wall_s']:.2f} s (compilation excluded). RMS over the frame of the per-point σ:
E {mc['rms_cm'][0]:.2f}, N {mc['rms_cm'][1]:.2f}, U {mc['rms_cm'][2]:.2f} cm (linearised: E {mc['linearised_rms_cm'][0]:.2f},
N {mc['linearised_rms_cm'][1]:.2f}, U {mc['linearised_rms_cm'][2]:.2f} cm); largest σ E {mc['max_cm'][0]:.2f}, N {mc['max_cm'][1]:.2f},
U {mc['max_cm'][2]:.2f} cm. Per point, Monte Carlo σ ÷ linearised σ: median E {mc['std_over_linearised_median'][0]:.3f},
N {mc['std_over_linearised_median'][1]:.3f}, U {mc['std_over_linearised_median'][2]:.3f} (5–95 %: E {mc['std_over_linearised_p05'][0]:.3f}–{mc['std_over_linearised_p95'][0]:.3f},
N {mc['std_over_linearised_p05'][1]:.3f}–{mc['std_over_linearised_p95'][1]:.3f}, U {mc['std_over_linearised_p05'][2]:.3f}–{mc['std_over_linearised_p95'][2]:.3f}); the expected relative
error of a σ from {mc['draws']} draws is {mc['expected_relative_error']:.3f}, and the systematic sources are drawn
once per draw for every point, so the per-point ratios move together.

The linearisation is the device's own (central differences at ±1σ of each systematic source; the
noise sources reuse the Jacobians of their systematic twins; position and range noise exactly), so
this comparison checks linearity and the Monte Carlo, not the optics: those are checked against
independent float64 math in the tests.

Reading: the refractive-index tolerance dominates (it changes the cone angle: Δn = 5×10⁻⁴ moves a
point by about {next(r for r in n['deterministic_cm'] if r['source'] == 'index')['horizontal_max_cm']:.0f} cm at 500 m), then the IMU's attitude, the boresight
residual and the apex tolerance; the encoder's 20″ step costs about a centimetre. A wedge whose
index is measured to 1×10⁻⁴ removes most of the budget.

Maps: `deviation_maps.png` (rows: each systematic source at +1σ, the Monte Carlo σ and the linearised σ;
columns ΔE, ΔN, ΔU over the true hit positions).
"""
