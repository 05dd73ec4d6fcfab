"""The seed paper's optics figures (Figs. 5a, 5c, 6b), each a PNG beside the CSV it plots.

They trace the fan in float64 with :func:`flightsim.instrument.risley_model.trace_fan`, using the default
fan and wedge (:class:`~flightsim.instrument.fan.FanSettings`, :class:`~flightsim.instrument.risley.RisleySettings`:
3×3 fan, Δ = 2.314 mrad, n = 1.5066, 15° cone, d1 = 10 mm). Every figure returns ``(png_path, csv_path)``;
beams are labelled 1-based like the paper, A_{i-j} for sub-beam (i − 1, j − 1) of SPEC §3 (i along the
sensor x axis, j along y).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.patches import Circle

from flightsim.core.atomic import save_figure
from flightsim.instrument.fan import FanSettings
from flightsim.instrument.risley import RisleySettings
from flightsim.instrument.risley_model import ExitFan, apex_for_cone, trace_fan
from flightsim.studies.figure_files import figure_paths, new_figure, write_csv

_FAN, _WEDGE = FanSettings(), RisleySettings()
ARRAY = _FAN.array
SPACING_MRAD = _FAN.spacing_mrad
N_GLASS = _WEDGE.refractive_index
CONE_RAD = math.radians(_WEDGE.cone_half_angle_deg)
THICKNESS_M = _WEDGE.thickness_mm * 1e-3


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors along the last axis [rad], accurate for small angles (atan2 form)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def default_fan(phi_rad, array: int = ARRAY, spacing_mrad: float = SPACING_MRAD) -> ExitFan:
    """The default instrument's exit fan at prism angles ``phi_rad`` [rad], traced in float64 on the CPU."""
    apex = apex_for_cone(CONE_RAD, N_GLASS)
    return trace_fan(phi_rad, array, spacing_mrad * 1e-3, N_GLASS, apex, THICKNESS_M,
                     precision="float64", device="cpu")


def beam_name(k: int, n: int) -> str:
    """Paper label of beam k = i·n + j: "1-1" … "n-n" (1-based)."""
    return f"{k // n + 1}-{k % n + 1}"


def _tex(k: int, n: int) -> str:
    return rf"$A_{{{beam_name(k, n)}}}$"


# ---------------------------------------------------------------------------------------------
# Fig. 5: angular distortion of the exit fan


def fig5a(out_dir, step_deg: float = 0.25) -> tuple[Path, Path]:
    """Fig. 5(a): ΔA_{i-j}, the angle between exit sub-beam A_{i-j} and the centre beam A_{2-2}, vs φ.

    CSV columns: phi_deg, dA_1-1_mrad … dA_3-3_mrad (one per beam, centre included) for
    φ = 0…360° in ``step_deg`` steps. The plot has the corner beams (radius R1) above and the
    edge-centre beams (R2) below, each with its incident angle (√2Δ, Δ) and its largest exit angle.
    """
    png, csv_path = figure_paths(out_dir, "fig5a_beam_angles")
    n, spacing = ARRAY, SPACING_MRAD * 1e-3
    phi_deg = np.linspace(0.0, 360.0, int(round(360.0 / step_deg)) + 1)
    fan = default_fan(np.radians(phi_deg))
    centre = (n * n) // 2
    d_a = angle_between(fan.directions, fan.directions[:, centre : centre + 1]) * 1e3  # [mrad]
    names = [beam_name(k, n) for k in range(n * n)]
    write_csv(csv_path, ["phi_deg"] + [f"dA_{s}_mrad" for s in names], np.column_stack([phi_deg, d_a]))

    corners = [0, n - 1, n * (n - 1), n * n - 1]
    edges = [1, n, 2 * n - 1, n * n - 2]
    groups = [(corners, math.sqrt(2.0) * spacing * 1e3, r"$\sqrt{2}\Delta$", "corner beams, radius $R_1$"),
              (edges, spacing * 1e3, r"$\Delta$", "edge-centre beams, radius $R_2$")]
    fig = new_figure(12.0, 8.0)
    grid = fig.add_gridspec(2, 2, width_ratios=(4.0, 1.0))
    axes = [fig.add_subplot(grid[0, 0])]
    axes.append(fig.add_subplot(grid[1, 0], sharex=axes[0]))
    colors, styles = ["tab:red", "tab:green", "tab:purple", "tab:orange"], ["-", "--", "-", "--"]
    summary = []
    for row, (ax, (beams, incident, symbol, what)) in enumerate(zip(axes, groups)):
        for beam, color, style in zip(beams, colors, styles):
            ax.plot(phi_deg, d_a[:, beam], style, color=color, lw=1.3, label=_tex(beam, n))
        top = d_a[:, beams].max()
        ax.axhline(incident, color="tab:olive", lw=1.5, ls=":",
                   label=f"incident spacing {symbol} = {incident:.4f} mrad")
        ax.axhline(top, color="k", lw=1.0, ls="-.", label=f"largest exit angle {top:.4f} mrad "
                   f"(+{(top - incident) * 1e3:.0f} µrad)")
        ax.axvline(45.0, color="0.6", lw=0.8)
        ax.set_ylabel(r"$\Delta A_{i-j}$ [mrad]")
        ax.set_title(what, fontsize=10)
        ax.set_ylim(incident - 0.25 * (top - incident), top + 0.55 * (top - incident))
        ax.legend(loc="upper right", ncol=3, fontsize=8)
        ax.grid(alpha=0.3)
        zoom = fig.add_subplot(grid[row, 1])
        _zoom_at_45(zoom, phi_deg, d_a, beams, colors, styles, n)
        summary.append(f"{what.split(',')[0]}: ΔA in [{d_a[:, beams].min():.4f}, {top:.4f}] mrad, "
                       f"incident {incident:.4f} mrad, largest deviation {(top - incident) * 1e3:.1f} µrad")
    axes[1].set_xlabel(r"prism angle $\varphi$ [deg]")
    axes[1].set_xticks(np.arange(0, 361, 45))
    axes[1].set_xlim(0, 360)
    fig.suptitle(r"Fig. 5(a): angle $\Delta A_{i-j}$ between exit sub-beam $A_{i-j}$ and centre beam $A_{2-2}$"
                 f"\n{n}×{n} fan, Δ = {SPACING_MRAD} mrad, n = {N_GLASS}, cone {math.degrees(CONE_RAD):g}°")
    fig.tight_layout()
    save_figure(fig, png)
    print("fig5a: " + "; ".join(summary))
    return png, csv_path


def _zoom_at_45(ax, phi_deg, d_a, beams, colors, styles, n) -> None:
    """Detail of the curves round φ = 45° (the paper's dashed box): ΔA of beams of equal radius part."""
    window = np.abs(phi_deg - 45.0) <= 1.0
    at = np.argmin(np.abs(phi_deg - 45.0))
    upper = d_a[at, beams] >= np.median(d_a[at, beams])  # the curves near the top at 45°
    for beam, color, style in zip(beams, colors, styles):
        ax.plot(phi_deg[window], d_a[window, beam], style, color=color, lw=1.5, label=_tex(beam, n))
    shown = d_a[window][:, np.array(beams)[upper]]
    pad = 0.15 * max(np.ptp(shown), 1e-4)
    ax.set_ylim(shown.min() - pad, shown.max() + pad)
    hidden = [b for b, up in zip(beams, upper) if not up and d_a[at, b] < shown.min() - pad]
    if hidden:
        ax.text(0.5, 0.55, "off scale at 45°:\n" + "\n".join(f"{_tex(b, n)} = {d_a[at, b]:.4f}" for b in hidden),
                transform=ax.transAxes, ha="center", va="center", fontsize=7)
    ax.set_xlim(44.0, 46.0)
    ax.axvline(45.0, color="0.6", lw=0.8)
    ax.set_title(r"detail at $\varphi$ = 45°", fontsize=9)
    ax.set_xlabel(r"$\varphi$ [deg]", fontsize=8)
    ax.set_ylabel(r"$\Delta A$ [mrad]", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="lower center")
    ax.grid(alpha=0.3)


def _tangent_angles(directions: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Gnomonic angles (x/z, y/z) [rad] of ``directions`` after the shortest rotation taking ``centre`` to +z."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(centre, z)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    rotation = np.eye(3) + vx + vx @ vx / (1.0 + centre @ z)
    r = directions @ rotation.T
    return r[:, :2] / r[:, 2:3]


def shape_change_urad(phi_deg: float, array: int = ARRAY, spacing_mrad: float = SPACING_MRAD) -> float:
    """Largest change of the angle between any two sub-beams, exit vs incident [µrad] (rotation invariant)."""
    fan = default_fan(np.radians([phi_deg]), array, spacing_mrad)
    exit_dirs = fan.directions[0]
    incident = _incident_directions(array, spacing_mrad * 1e-3)
    exit_pairs = angle_between(exit_dirs[:, None, :], exit_dirs[None, :, :])
    incident_pairs = angle_between(incident[:, None, :], incident[None, :, :])
    return float(np.abs(exit_pairs - incident_pairs).max() * 1e6)


def _incident_directions(n: int, spacing: float) -> np.ndarray:
    """S1 of SPEC §3: normalize(tan a_i, tan b_j, 1), beam index i·n + j."""
    offsets = (np.arange(n) - (n - 1) / 2.0) * spacing
    a, b = np.meshgrid(offsets, offsets, indexing="ij")
    s = np.stack([np.tan(a).ravel(), np.tan(b).ravel(), np.ones(n * n)], axis=1)
    return s / np.linalg.norm(s, axis=1, keepdims=True)


def fig5c(out_dir, phi_deg: float = 45.0) -> tuple[Path, Path]:
    """Fig. 5(c): the exit fan at prism angle φ against the incident fan, centred on A_{2-2}.

    Both fans are drawn as gnomonic angles about their centre beam: the incident fan about +z
    (x/z, y/z = tan a_i, tan b_j), the exit fan after the shortest rotation taking the exit
    centre beam to +z. CSV columns: beam, i, j, incident_x_mrad, incident_y_mrad,
    exit_x_mrad, exit_y_mrad, shift_urad.
    """
    png, csv_path = figure_paths(out_dir, "fig5c_exit_fan")
    n, spacing = ARRAY, SPACING_MRAD * 1e-3
    fan = default_fan(np.radians([phi_deg]))
    centre = fan.directions[0, (n * n) // 2]
    incident = _incident_directions(n, spacing)
    inc = incident[:, :2] / incident[:, 2:3] * 1e3  # [mrad]
    out = _tangent_angles(fan.directions[0], centre) * 1e3
    shift = np.linalg.norm(out - inc, axis=1) * 1e3  # [µrad]
    rows = [[beam_name(k, n), k // n + 1, k % n + 1, *inc[k], *out[k], shift[k]] for k in range(n * n)]
    write_csv(csv_path, ["beam", "i", "j", "incident_x_mrad", "incident_y_mrad", "exit_x_mrad", "exit_y_mrad",
                          "shift_urad"], rows)
    change = shape_change_urad(phi_deg)

    fig = new_figure(7.5, 7.5)
    ax = fig.subplots()
    radius = 0.3 * SPACING_MRAD
    for k in range(n * n):
        ax.add_patch(Circle(inc[k], radius, fill=False, ls="--", lw=1.2, color="0.3"))
        ax.add_patch(Circle(out[k], 0.5 * radius, color="tab:red", alpha=0.85, lw=0))
        ax.annotate(_tex(k, n), inc[k], xytext=(inc[k, 0], inc[k, 1] - 1.08 * radius), ha="center", va="top",
                    fontsize=9)
    azimuth = math.atan2(centre[1], centre[0])
    reach = 1.6 * SPACING_MRAD * (n - 1) / 2.0 + radius
    ax.plot([-reach * math.cos(azimuth), reach * math.cos(azimuth)],
            [-reach * math.sin(azimuth), reach * math.sin(azimuth)], ":", color="tab:blue", lw=1.0)
    ax.plot([], [], "o", mfc="none", mec="0.3", ls="none", ms=12, label="incident fan (dashed circles)")
    ax.plot([], [], "o", color="tab:red", ls="none", ms=7, label="exit fan")
    ax.plot([], [], ":", color="tab:blue",
            label=f"deviation plane of $A_{{2-2}}$ (azimuth {math.degrees(azimuth) % 360:.0f}°)")
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("angle about centre beam, sensor x direction [mrad]")
    ax.set_ylabel("angle about centre beam, sensor y direction [mrad]")
    ax.legend(loc="upper left", fontsize=8)
    ax.text(0.98, 0.02, f"largest shift of a beam: {shift.max():.0f} µrad\n"
            f"largest change of a beam-pair angle: {change:.0f} µrad",
            transform=ax.transAxes, ha="right", va="bottom", fontsize=9,
            bbox=dict(boxstyle="round", fc="white", ec="0.7"))
    ax.set_title(rf"Fig. 5(c): exit vs incident fan at $\varphi$ = {phi_deg:g}°" + "\n"
                 f"{n}×{n}, Δ = {SPACING_MRAD} mrad, angles in a plane normal to the centre beam", fontsize=11)
    fig.tight_layout()
    save_figure(fig, png)
    print(f"fig5c: φ = {phi_deg:g}°: largest beam shift {shift.max():.1f} µrad, "
          f"largest change of a beam-pair angle {change:.1f} µrad")
    return png, csv_path


# ---------------------------------------------------------------------------------------------
# Fig. 6(b): ground footprints round the scan circle


def ground_hits(origins: np.ndarray, directions: np.ndarray, ground_z: float) -> np.ndarray:
    """Points where rays (origins, directions [sensor frame]) meet the plane z = ground_z [m]."""
    t = (ground_z - origins[..., 2:3]) / directions[..., 2:3]
    return origins + t * directions


def fig6b(out_dir, altitude_m: float = 500.0) -> tuple[Path, Path]:
    """Fig. 6(b): the fan's ground footprint at 8 prism angles (0°, 45°, …, 315°) over flat ground.

    Level flight, no motion: the sensor frame is the body frame (x forward, y right, z down),
    the ground is the plane z = altitude_m. Exact rays start at their own exit points on Σ2;
    the nominal (rigid-array) rays start at the centre beam's exit point, as the georeferencing
    does. CSV columns: phi_deg, beam, i, j, exact_x_m, exact_y_m, nominal_x_m, nominal_y_m.
    """
    png, csv_path = figure_paths(out_dir, "fig6b_footprints")
    n = ARRAY
    centre = (n * n) // 2
    phi_deg = np.arange(0.0, 360.0, 45.0)
    fan = default_fan(np.radians(phi_deg))
    exact = ground_hits(fan.exit_points, fan.directions, altitude_m)
    nominal = ground_hits(fan.exit_points[:, centre : centre + 1], fan.nominal, altitude_m)
    rows = [[phi_deg[p], beam_name(k, n), k // n + 1, k % n + 1, *exact[p, k, :2], *nominal[p, k, :2]]
            for p in range(len(phi_deg)) for k in range(n * n)]
    write_csv(csv_path, ["phi_deg", "beam", "i", "j", "exact_x_m", "exact_y_m", "nominal_x_m", "nominal_y_m"], rows)

    fig = new_figure(11.0, 11.0)
    grid = fig.add_gridspec(3, 3)
    overview = fig.add_subplot(grid[1, 1])
    radius = (altitude_m - THICKNESS_M) * math.tan(CONE_RAD)
    overview.add_patch(Circle((0.0, 0.0), radius, fill=False, ls="--", color="0.5"))
    rel_exact = exact - exact[:, centre : centre + 1]
    rel_nominal = nominal - exact[:, centre : centre + 1]
    span = 1.15 * np.abs(np.concatenate([rel_exact, rel_nominal], axis=1)[..., :2]).max()
    gap = np.linalg.norm(exact - nominal, axis=-1)
    for p, phi in enumerate(phi_deg):
        # map view: y (right) across, x (forward) up; the beam leaves at azimuth φ + 180°
        overview.plot(exact[p, :, 1], exact[p, :, 0], ".", color="tab:red", ms=3)
        cx, cy = exact[p, centre, 1], exact[p, centre, 0]
        overview.annotate(rf"$\varphi$={phi:g}°", (0.75 * cx, 0.75 * cy), ha="center", va="center", fontsize=7)
        row, col = 1 + round(math.cos(math.radians(phi))), 1 - round(math.sin(math.radians(phi)))
        ax = fig.add_subplot(grid[row, col])
        _footprint_panel(ax, rel_exact[p], rel_nominal[p], n)
        ax.set_xlim(-span, span)
        ax.set_ylim(-span, span)
        ax.set_title(rf"$\varphi$ = {phi:g}°: exact−nominal ≤ {gap[p].max() * 100:.0f} cm", fontsize=9)
        if row == 2:
            ax.set_xlabel("Δy, right [m]", fontsize=8)
        if col == 0:
            ax.set_ylabel("Δx, forward [m]", fontsize=8)
    _scan_circle_axes(fig, overview, radius)
    fig.suptitle(f"Fig. 6(b): ground footprints of the {n}×{n} fan at h = {altitude_m / 1000:g} km, flat ground"
                 f"\nzoomed panels: positions relative to the exact centre beam $A_{{2-2}}$ [m] "
                 f"(y right across, x forward up)")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    save_figure(fig, png)
    size = np.ptp(rel_exact[..., :2], axis=1).max()
    print(f"fig6b: h = {altitude_m:g} m: scan radius {radius:.3f} m, footprint up to {size:.3f} m across, "
          f"exact vs nominal up to {gap.max():.3f} m apart")
    return png, csv_path


def _scan_circle_axes(fig, overview, radius: float) -> None:
    """The middle panel's axes round the scan circle of ``radius`` [m] (map view), and the figure's legend."""
    overview.set_xlim(-1.25 * radius, 1.25 * radius)
    overview.set_ylim(-1.25 * radius, 1.25 * radius)
    overview.set_aspect("equal")
    overview.set_xlabel("y, right [m]")
    overview.set_ylabel("x, forward [m]")
    overview.set_title(f"scan circle, radius {radius:.1f} m", fontsize=9)
    overview.tick_params(labelsize=7)
    handles = [overview.plot([], [], "o-", color="tab:red", ms=4, lw=1)[0],
               overview.plot([], [], "s--", mfc="none", color="tab:blue", ms=5, lw=1)[0]]
    fig.legend(handles, ["exact footprint", "nominal (rigid-array) footprint"], loc="lower center", ncol=2)


def _footprint_panel(ax, exact: np.ndarray, nominal: np.ndarray, n: int) -> None:
    """One footprint in map view (y across, x up), exact and nominal, with the fan's outline."""
    ring = [k for k in range(n)] + [i * n + n - 1 for i in range(1, n)] + \
           [(n - 1) * n + j for j in range(n - 2, -1, -1)] + [i * n for i in range(n - 2, -1, -1)]
    ring.append(ring[0])
    ax.plot(exact[ring, 1], exact[ring, 0], "-", color="tab:red", lw=0.8)
    ax.plot(nominal[ring, 1], nominal[ring, 0], "--", color="tab:blue", lw=0.8)
    ax.plot(exact[:, 1], exact[:, 0], "o", color="tab:red", ms=4)
    ax.plot(nominal[:, 1], nominal[:, 0], "s", mfc="none", color="tab:blue", ms=5)
    for k in (0, n * n - 1):
        ax.annotate(_tex(k, n), (exact[k, 1], exact[k, 0]), xytext=(4, 4), textcoords="offset points", fontsize=7)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=7)


def optics_figures(out_dir) -> list[Path]:
    """Write the three optics figures (5a, 5c, 6b) and their CSVs into ``out_dir``; returns all paths."""
    return [path for make in (fig5a, fig5c, fig6b) for path in make(out_dir)]
