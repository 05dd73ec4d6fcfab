"""REPORT.md of `flightsim selfcal`: the RMS table, the recovered parameters with their 1-σ, the observable
combinations and the correlation matrix, with the command that regenerates them."""
from __future__ import annotations

import numpy as np

from flightsim.studies import selfcal as sc

NAMES = ("refractive index n", "apex angle α", "encoder offset δφ", "boresight roll", "boresight pitch",
         "boresight yaw")
SHORT = ("n", "α", "δφ", "roll", "pitch", "yaw")


def _value(k: int, x: float) -> str:
    return f"{x:.6f}" if k == 0 else f"{x * sc.REPORT_SCALE[k]:.2f}″"


def _delta(k: int, x: float) -> str:
    return f"{x:+.2e}" if k == 0 else f"{x * sc.REPORT_SCALE[k]:+.2f}″"


def _rms_table(rows: list[dict]) -> list[str]:
    lines = ["| array | altitude | segments (outlier) | rejected | before: nominal, believed | exact, believed | "
             "after: exact, self-cal | exact, true | nominal on its own segments |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        m, o = r["rms_m"], r["outliers"]
        lines.append(f"| {r['array']}×{r['array']} | {r['altitude_m'] / 1000:g} km | {o['segments']} "
                     f"({o['segments_with_outlier_points']}) | {o['rejected_segments']} | "
                     f"{m['nominal_believed'] * 100:.2f} cm | {m['exact_believed'] * 100:.2f} cm | "
                     f"**{m['exact_selfcal'] * 100:.2f} cm** | {m['exact_true'] * 100:.2f} cm | "
                     f"{m['nominal_believed_own_segments'] * 100:.2f} cm |")
    return lines


def _parameter_table(r: dict) -> list[str]:
    truth, believed, est, sig = (np.array(r[k]) for k in ("truth", "believed", "estimate", "sigma"))
    lines = [f"#### {r['array']}×{r['array']} at {r['altitude_m'] / 1000:g} km",
             "", "| parameter | injected (true) | believed (start) | recovered | recovered − true | 1-σ | "
                 "(rec − true)/σ |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for k, name in enumerate(NAMES):
        z = (est[k] - truth[k]) / sig[k] if sig[k] > 0 else float("nan")
        lines.append(f"| {name} | {_value(k, truth[k])} | {_value(k, believed[k])} | {_value(k, est[k])} | "
                     f"{_delta(k, est[k] - truth[k])} | {_delta(k, sig[k]).lstrip('+')} | {z:+.2f} |")
    for name, c in r["combinations"].items():
        z = (c["recovered"] - c["injected"]) / c["sigma"] if c["sigma"] > 0 else float("nan")
        label = {"cone_half_angle": "cone half-angle θ(n, α) − believed", "encoder_plus_yaw": "δφ + yaw"}[name]
        lines.append(f"| **{label}** | {c['injected']:+.2f}″ | 0 | {c['recovered']:+.2f}″ | "
                     f"{c['recovered'] - c['injected']:+.2f}″ | {c['sigma']:.2f}″ | {z:+.2f} |")
    return lines + [""]


def _correlation(r: dict) -> list[str]:
    c = np.array(r["correlation"])
    lines = [f"Correlation matrix ({r['array']}×{r['array']}, {r['altitude_m'] / 1000:g} km):", "",
             "| | " + " | ".join(SHORT) + " |", "|---" * (len(SHORT) + 1) + "|"]
    lines += [f"| {SHORT[i]} | " + " | ".join(f"{v:+.3f}" for v in c[i]) + " |" for i in range(len(SHORT))]
    return lines + [""]


def report(results: dict, figure: str | None) -> str:
    rows = results["rows"]
    inj = results["injected"]
    lines = [
        "# Risley self-calibration from blindly segmented planes",
        "",
        f"Regenerate: `{results['command']}` ({results['wall_s']:.0f} s on {results['device']}).",
        "",
        "The seed paper's stated future work (§5: the array-beam distortion known, the airborne data still to be "
        "corrected): estimate the wedge's refractive index n and apex angle α, the prism-angle encoder's zero offset "
        "δφ and the boresight (roll, pitch, yaw of the true sensor axes in the believed ones) from the planes a "
        "nominal-model flight finds **blindly** (no plane ids, no truth), then re-georeference every point with the "
        "exact vector-optics model and the estimate.",
        "",
        "## Set-up",
        "",
        f"- Injected through the settings: `risley.believed_refractive_index` = true + {inj['refractive_index_error']:g}, "
        f"`risley.believed_apex_angle_deg` = true + {inj['apex_error_arcsec']:g}″, `risley.encoder_arcsec` = "
        f"{inj['encoder_arcsec']:g}, `pose.boresight_arcsec` = {tuple(inj['boresight_arcsec'])}, `ranging.noise_m` = "
        f"{inj['range_noise_m']:g}.",
        "- Flight: the `calibration` scene (24 gable-roof houses of every ridge orientation, roads, ground); two lines "
        "with reciprocal headings 100 m apart over the field's centre at 200 km/h; only the pulses of the conical "
        "scan's front and back sweeps over the house block are traced, and the points over the block (+25 m) are "
        "used, as a user crops a calibration field. Beyond 400,000 points a seeded choice of whole pulses is kept.",
        "- Outliers: the ranges of 10 % of the roof planes hit (seeded) are corrupted before anything sees them — "
        "every other one by a vegetation-like roughness (Gaussian, 0.25 m 1σ), the others by a smooth 0.6 m dome "
        "(non-planar patches); all georeferencing models see the same corrupted range.",
        "- Blind planes: `flightsim.scoring.blind.extract_planes` on the nominal-model points (round 1); then on the "
        "points re-georeferenced with the round-1 estimate (round 2), where the two lines' views of a roof agree and "
        "fall into one segment.",
        "- Estimator: `scipy.optimize.least_squares` (trf, soft_l1 loss, its scale 2.5× the residuals' robust σ, "
        "re-estimated three times), point-to-plane distances with each segment's plane refitted (TLS) at every "
        "evaluation (variable projection); each point re-georeferenced in float64 from its raw observables (pulse "
        "pose, prism-angle reading, beam, range) through `risley_model.trace_fan` (the project's one wedge "
        "refraction) and the pose error model's boresight rotation. At most 1,500 points per segment and 40,000 in "
        "all, chosen by whole pulses. 1-σ: s²(JᵀWJ)⁻¹ with the loss's IRLS weights W.",
        "- RMS columns: pooled plane-fit RMS over the final blind segments holding no corrupted point (the same "
        "points for every model); 'segments (outlier)' counts the segments and those holding corrupted points; "
        "'rejected' the segments whose median IRLS weight is below 0.5.",
        "",
        "## Plane-fit RMS before and after",
        "",
    ]
    lines += _rms_table(rows)
    if figure:
        lines += ["", f"![RMS before and after]({figure})"]
    lines += ["", "## Recovered parameters", ""]
    for r in rows:
        lines += _parameter_table(r)
    lines += ["## Correlations and what is observable", ""]
    lines += _correlation(rows[0]) + (_correlation(rows[-1]) if len(rows) > 1 else [])
    lines += _findings()
    return "\n".join(lines) + "\n"


def _findings() -> list[str]:
    return [
        "- **n and α are not separately observable** (correlation −1.000 in every configuration): both change the "
        "on-axis deviation θ at first order (dθ/dn = sin α / cos(θ + α), dθ/dα = n cos α / cos(θ + α) − 1), and what "
        "tells them apart — the off-axis sub-beams' distortion at fixed θ — moves points by far less than the range "
        "noise for Δ = 2.314 mrad. Their individual σ are large and their values land anywhere along the valley; "
        "the **cone half-angle θ(n, α)** is the observable combination and is recovered (table rows in bold).",
        "- **δφ and yaw are not separately observable** (correlation −1.000): both turn the scan pattern about the "
        "prism axis; they differ only in whether the DOE fan turns too, which moves a corner beam by Δ·(N−1)/2 "
        "times the angle times the range (sub-millimetre for arc-minute errors). **δφ + yaw** is recovered.",
        "- **roll and pitch are separable** with two lines flown in opposite directions: on one straight line a "
        "roll error is a rigid rotation of the whole cloud about the line (invisible to any plane fit); pitch "
        "shifts points vertically by v·t·pitch, seen between the front and back sweeps.",
        "- The re-georeferenced cloud does not depend on where along the two valleys the estimate lands, so the "
        "RMS after self-calibration reaches the exact model with the true parameters.",
        "",
    ]
