"""REPORT.md and the figure of the TLS-reference experiment (:mod:`flightsim.studies.spad_tls_run`)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from flightsim.studies import spad_tls as st

COMMAND = "flightsim spad --reference tls --device {device} --out results/spad"


def write_figure(path: Path, scan: st.TlsScan) -> Path:
    """Top view of the TLS cloud of the MODE-A setup: mean height per 2 cm cell."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = scan.points
    edges = np.arange(-st.SANDBOX_HALF_M, st.SANDBOX_HALF_M + 1e-9, 0.02)
    total, _, _ = np.histogram2d(p[:, 1], p[:, 0], bins=(edges, edges), weights=p[:, 2])
    count, _, _ = np.histogram2d(p[:, 1], p[:, 0], bins=(edges, edges))
    with np.errstate(invalid="ignore"):
        mean = total / count
    fig, ax = plt.subplots(figsize=(5.5, 4.6), dpi=110)
    image = ax.imshow(mean, origin="lower", extent=(edges[0], edges[-1], edges[0], edges[-1]), cmap="terrain")
    fig.colorbar(image, ax=ax, label="height [m]")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(f"VZ-2000 scan of the sandbox from 100 m: {len(p):,} points", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _cell(m: dict) -> str:
    return f"{m['three_sigma_cm']:.2f} / {m['rmse_cm']:.2f}"


def _rows_a(n: dict) -> str:
    return "\n".join(
        f"| {r['label']} | {r['photons_per_shot_set']:.2f} | {r['signal_per_shot']:.2f} | {r['mesh']['three_sigma_cm']:.2f} | "
        f"{_cell(r['tls']['c2c'])} | {_cell(r['tls']['plane'])} | {_cell(r['tls_perfect']['plane'])} |"
        for r in n["mode_a"])


def expected_registration_cm(distance_m: float, baseline_m: float = st.MARKER_BASELINE_M) -> float:
    """Closed-form RMS registration error [cm] at the sandbox's centre, ``distance_m`` below the lidar, from the
    markers' total-station noise (:func:`cloud_compare.rigid_fit_error`)."""
    from flightsim.studies import cloud_compare as cc

    reach = math.sqrt(st.STATION_M[0] ** 2 + st.STATION_M[1] ** 2 + (distance_m - st.STATION_M[2]) ** 2)
    centre = np.array([0.0, 0.0, distance_m])
    return 100.0 * math.sqrt(cc.rigid_fit_error(st.markers(baseline_m), st.ts_sigma_m(reach), centre))


def _rows_b(n: dict) -> str:
    paper = st.PAPER["mode_b_table3_cm"]
    return "\n".join(
        f"| {r['label']} | {r['tls_points']:,} | {expected_registration_cm(r['distance_m']):.1f} | "
        f"{r['mesh']['three_sigma_cm']:.2f} | {_cell(r['tls']['c2c'])} | "
        f"{_cell(r['tls']['plane'])} | {_cell(r['tls_perfect']['plane'])} | {p:.2f} |"
        for r, p in zip(n["mode_b"], paper))


def _rows_sensitivity(n: dict) -> str:
    return "\n".join(
        f"| {r['spacing_mm']:g} | {r['marker_baseline_m'] if r['marker_baseline_m'] else 'perfect'} | "
        f"{r['expected_registration_cm']:.2f} | {_cell(r['c2c'])} | {_cell(r['plane'])} |"
        for r in n["sensitivity"])


def _ratio(m3: float, rmse: float) -> float:
    return rmse / (m3 / 3.0) if m3 > 0 else math.nan


def _beside(n: dict) -> str:
    s, p = n["summary"], st.PAPER
    lines = []
    for key, name in (("mesh", "against the true surface (signed)"), ("tls_c2c", "TLS, C2C nearest neighbour"),
                      ("tls_plane", "TLS, local plane (M3C2-style)"), ("tls_perfect_c2c", "TLS perfectly registered, C2C"),
                      ("tls_perfect_plane", "TLS perfectly registered, local plane")):
        a3, ar = s[f"mode_a_{key}_three_sigma_cm"], s[f"mode_a_{key}_rmse_cm"]
        b3 = s[f"mode_b_{key}_three_sigma_cm"]
        lines.append(f"| {name} | {a3:.2f} ({100 * (a3 / p['mode_a_three_sigma_cm'] - 1):+.0f} %) | {ar:.2f} | "
                     f"{_ratio(a3, ar):.2f} | {b3:.2f} ({100 * (b3 / p['mode_b_three_sigma_cm'] - 1):+.0f} %) |")
    paper_ratio = _ratio(p["mode_a_three_sigma_cm"], p["mode_a_rmse_cm"])
    lines.append(f"| **paper** | **{p['mode_a_three_sigma_cm']:.2f}** | **{p['mode_a_rmse_cm']:.2f}** | "
                 f"**{paper_ratio:.2f}** | **{p['mode_b_three_sigma_cm']:.2f}** |")
    return "\n".join(lines)


def _unknowns() -> str:
    """The table of the values the paper does not give."""
    return f"""| unknown | value | reason |
| --- | --- | --- |
| TLS position | {st.TLS_OFFSET_M:g} m north of the lidar's station, same height, on a tilt mount (head axis horizontal) | one TLS scan per test case: the TLS beside the lidar, looking at the sandbox as it does |
| TLS spacing on the sandbox | {1e3 * st.TLS_SPACING_M:g} mm (angle step = spacing / distance) | half the MODE-A cell, a reference finer than the cloud it scores; sensitivity below |
| TLS range errors | 5 mm precision per shot, 8 mm accuracy (6.2 mm offset per scan) | the VZ-2000 datasheet (`vz2000` preset) |
| control points | 4, {st.CONTROL_INSET_M:g} m inside the sandbox's corners | at least 3 non-collinear points fix a rigid transform; 4 is the usual minimum with a check |
| TLS target-centre fit | {1e3 * st.TARGET_SIGMA_M:g} mm per axis | ≈ 5 mm precision over ~6 points on a target |
| total station | {st.TS_CLASS[0]:g} mm + {st.TS_CLASS[1]:g} ppm, {st.TS_CLASS[2]:g}" angles, at ({st.STATION_M[0]:g}, {st.STATION_M[1]:g}) m, {st.STATION_M[2]:g} m high | a 2" instrument class; a station seeing the sandbox and the lidar |
| lidar markers | 4 at the corners of a {st.MARKER_BASELINE_M:g} m square on the mount, alternate ones {100 * st.MARKER_DEPTH_M:g} cm proud | the size of a "三维安装平台" (3D mounting platform); sensitivity below |
| laser powers | {st.POWER_LEVELS} levels, {st.POWER_PHOTONS[0]:g} … {st.POWER_PHOTONS[1]:g} signal photo-electrons per shot at 100 m, log-spaced | "different powers (different echo photon numbers)"; the paper gives no values |"""


def _closest(n: dict, mode: str) -> tuple[str, float]:
    """(metric, its mean 3σ [cm]) of ours closest to the paper's mean 3σ of ``mode`` (mode_a or mode_b)."""
    target = st.PAPER[f"{mode}_three_sigma_cm"]
    options = {k: n["summary"][f"{mode}_{k}_three_sigma_cm"] for k in METRICS}
    best = min(options, key=lambda k: abs(options[k] - target))
    return best, options[best]


def _baseline_needed(n: dict) -> str:
    """The smallest marker baseline whose plane 3σ is within 10 % of the perfect registration's, at 5 mm spacing."""
    rows = [r for r in n["sensitivity"] if r["spacing_mm"] == 1e3 * st.TLS_SPACING_M]
    perfect = next((r["plane"]["three_sigma_cm"] for r in rows if not r["marker_baseline_m"]), math.nan)
    ok = [r["marker_baseline_m"] for r in rows if r["marker_baseline_m"]
          and r["plane"]["three_sigma_cm"] <= 1.1 * perfect]
    return f"{min(ok):g} m" if ok else f"more than {max(st.MARKER_BASELINES):g} m"


def _added(total: float, base: float) -> float:
    """The part of a 3σ beyond ``base``, in quadrature [cm] (0 when there is none)."""
    return math.sqrt(max(total ** 2 - base ** 2, 0.0))


def _implied(n: dict) -> str:
    """The registration term the paper's numbers leave beside our perfect-registration 3σ, and the marker baseline
    whose term (sensitivity table, 5 mm spacing) comes closest to it."""
    s, p = n["summary"], st.PAPER
    need_b = _added(p["mode_b_three_sigma_cm"], s["mode_b_tls_perfect_plane_three_sigma_cm"])
    need_a = _added(p["mode_a_three_sigma_cm"], s["mode_a_tls_perfect_plane_three_sigma_cm"])
    rows = [r for r in n["sensitivity"] if r["spacing_mm"] == 1e3 * st.TLS_SPACING_M]
    perfect = next((r["plane"]["three_sigma_cm"] for r in rows if not r["marker_baseline_m"]), math.nan)
    terms = {r["marker_baseline_m"]: _added(r["plane"]["three_sigma_cm"], perfect) for r in rows if r["marker_baseline_m"]}
    table = ", ".join(f"{b:g} m → {t:.2f} cm" for b, t in terms.items())
    best = min(terms, key=lambda b: abs(terms[b] - need_b)) if terms else math.nan
    return (f"Beside our perfect-registration 3σ, the paper's MODE-B mean leaves {need_b:.2f} cm (in quadrature) "
            f"for the registration and the TLS; its MODE-A mean leaves {need_a:.2f} cm"
            f"{' (ours is already above it: the photon noise of the assumed echo)' if need_a == 0.0 else ''}. "
            f"The registration term of the sensitivity table (MODE-A frame, plane) per marker baseline (one draw each) is {table}: "
            f"a term of the MODE-B size takes a baseline near {best:g} m with our total station, or, equivalently, a "
            f"registration error at the sandbox of the size its \"expected\" column gives there.")


def _findings(n: dict) -> str:
    """What the numbers say, beside the paper's."""
    s, p = n["summary"], st.PAPER
    best_a, value_a = _closest(n, "mode_a")
    best_b, value_b = _closest(n, "mode_b")
    within = lambda v, t: "within" if abs(v / t - 1.0) <= 0.1 else "outside"  # noqa: E731
    return f"""## What it shows

- **Registration dominates when it goes through markers on the lidar.** With the chosen 0.5 m marker square,
  the total station's ~2 mm on markers 0.5 m apart turns into a rotation of the lidar frame of a few mrad, and
  at 100 m into decimetres at the sandbox (the "expected" column): MODE-A 3σ against the registered TLS is
  {s['mode_a_tls_plane_three_sigma_cm']:.2f} cm (plane) and {s['mode_a_tls_c2c_three_sigma_cm']:.2f} cm (C2C), against
  {s['mode_a_tls_perfect_plane_three_sigma_cm']:.2f} cm with a perfect registration and {s['mode_a_mesh_three_sigma_cm']:.2f} cm
  against the true surface. The paper's {p['mode_a_three_sigma_cm']:.2f} cm therefore needs a registration good to
  about a centimetre at the sandbox: in the sensitivity table a marker baseline of at least {_baseline_needed(n)}
  (or control points the lidar itself sees, or a fine alignment the paper does not mention).
- **MODE-A** (mean of the {len(n['mode_a'])} power levels): closest of ours is {METRICS[best_a]}, {value_a:.2f} cm,
  {within(value_a, p['mode_a_three_sigma_cm'])} 10 % of the paper's {p['mode_a_three_sigma_cm']:.2f} cm. C2C is unsigned: for a
  zero-mean Gaussian error of σ its spread is that of |d|, 0.60σ (plus the reference's spacing), so its 3σ sits
  below a signed one (perfect registration: C2C {s['mode_a_tls_perfect_c2c_three_sigma_cm']:.2f}, plane
  {s['mode_a_tls_perfect_plane_three_sigma_cm']:.2f}, true surface {s['mode_a_mesh_three_sigma_cm']:.2f} cm). The signed
  scores stay above the paper's by the photon noise of our assumed echo (`../REPORT.md`: a single photon's σ of
  6.6 cm from the assumed 1 ns pulse; the paper's number needs ≈ 4.8 cm), and the TLS adds little to them
  (its 5 mm precision, averaged over the plane fit's 12 points).
- **MODE-B** (mean of the six distances): closest is {METRICS[best_b]}, {value_b:.2f} cm,
  {within(value_b, p['mode_b_three_sigma_cm'])} 10 % of the paper's {p['mode_b_three_sigma_cm']:.2f} cm. Our MODE-B cells
  average so many photons that their own noise is {s['mode_b_tls_perfect_plane_three_sigma_cm']:.2f} cm (plane, perfect
  registration); with the chosen chain, {s['mode_b_tls_plane_three_sigma_cm']:.2f} cm, one draw of the total-station
  noise per setup, so it scatters from case to case as Table 3 does (2.58–3.92 cm).
- **Which unknown would have to take which value.** {_implied(n)}
- **C2C or plane?** C2C adds the TLS spacing (5 mm → 2 cm rows of the sensitivity table) and folds the sign;
  the plane distance does neither. The paper's RMSE/σ is {_ratio(p['mode_a_three_sigma_cm'], p['mode_a_rmse_cm']):.2f};
  ours with a perfect registration: C2C {_ratio(s['mode_a_tls_perfect_c2c_three_sigma_cm'], s['mode_a_tls_perfect_c2c_rmse_cm']):.2f},
  plane {_ratio(s['mode_a_tls_perfect_plane_three_sigma_cm'], s['mode_a_tls_perfect_plane_rmse_cm']):.2f} — our RMSE carries the
  first-photon pile-up bias (`../REPORT.md`), which the paper may have calibrated out, so the ratio does not
  settle it; the 3σ alone is closest to the paper's with C2C. No parameter here was tuned to a paper number:
  every value is the table's above, once.
"""


METRICS = {"mesh": "against the true surface", "tls_c2c": "TLS C2C (registered)",
           "tls_plane": "TLS local plane (registered)", "tls_perfect_c2c": "TLS C2C (perfect registration)",
           "tls_perfect_plane": "TLS local plane (perfect registration)"}


def report(n: dict) -> str:
    """REPORT.md from the numbers (tls.json)."""
    cut = "" if n["pulses_per_frame"] == 43000 else f" (frames cut to {n['pulses_per_frame']} pulses)"
    return f"""# SPAD small-body lidar against a simulated RIEGL VZ-2000 reference

Regenerate: `{COMMAND.format(device=n['device'])}`{cut} (writes `results/spad/tls/`; the against-the-mesh
report `../REPORT.md` is `flightsim spad` without `--reference`). Seed: `spad-fsm-small-body-lidar-paper.txt`
§2.2–2.3. Figure: `vz2000_sandbox.png` (the TLS cloud of the MODE-A setup).

## What the paper did, and what we simulate

The paper scores its clouds against "RIEGL VZ2000所测量的沙盘点云" (the sandbox cloud the VZ-2000 measured),
unified into the lidar frame O-XYZ by registering control points on the sandbox and marker points on the lidar,
both measured with a total station, in every test case. MODE-A: 18 clouds at different laser powers, mean 3σ
2.86 cm, RMSE 1.47 cm; MODE-B: six distances (Table 2), mean 3σ 3.10 cm (Table 3). It gives none of the
following; each is our choice, with its reason:

{_unknowns()}

Distances: **C2C** = distance to the nearest TLS point (unsigned; CloudCompare's C2C without a local model);
**plane** = signed distance along the normal of the plane through the 12 nearest TLS points (M3C2-style, no
projection cylinder). Each cell: 3σ / RMSE [cm]. "Perfect" drops the registration (the TLS cloud where the
simulator put it). "Mesh" is today's score: signed distance to the true surface.

## Beside the paper

| metric | MODE-A mean 3σ [cm] | MODE-A mean RMSE [cm] | RMSE / σ | MODE-B mean 3σ [cm] |
| --- | --- | --- | --- | --- |
{_beside(n)}

The paper's RMSE/σ = 1.47 / (2.86 / 3) = 1.54 says its distances were not zero-mean: an unsigned distance
(C2C gives a half-normal-like spread, RMSE/σ ≈ 1.66 for a 1-D error, more with the reference's spacing) or a
signed one with a mean of √(1.47² − 0.95²) = 1.12 cm. The column shows which of ours comes close.

## MODE-A, 100 m, the power series (TLS: {n['tls_mode_a']['points']:,} points, {n['tls_mode_a']['scan_s']:.1f} s to simulate; expected registration error {expected_registration_cm(100.0):.1f} cm)

| frame | photons/shot set | detected | mesh 3σ | C2C | plane | plane, perfect |
| --- | --- | --- | --- | --- | --- | --- |
{_rows_a(n)}

## MODE-B, the six distances (one TLS setup and registration each)

| frame | TLS points | expected registration error [cm] | mesh 3σ | C2C | plane | plane, perfect | paper 3σ (Table 3) |
| --- | --- | --- | --- | --- | --- | --- | --- |
{_rows_b(n)}

## Sensitivity: the registration's marker baseline and the TLS spacing (MODE-A, power level {st.POWER_LEVELS // 2 + 1})

"expected" is the closed-form RMS registration error at the sandbox's centre from the markers alone
(`rigid_fit_error`: translation 3σ²/n plus the rotation's lever to the sandbox, σ the total station's noise
at the lidar); one draw of the total station and target noise per baseline, reused for every spacing.

| TLS spacing [mm] | marker baseline [m] | expected [cm] | C2C 3σ / RMSE | plane 3σ / RMSE |
| --- | --- | --- | --- | --- |
{_rows_sensitivity(n)}

{_findings(n)}"""
