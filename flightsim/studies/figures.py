"""Figures of the seed paper's §4 (Figs. 5a, 5c, 6b, 8a, 8b, 9a, 10a), each a PNG beside the CSV it plots.

The optics figures (5a, 5c, 6b) are drawn by :mod:`flightsim.studies.figures_optics`
(:func:`optics_figures` writes all three). The accuracy figures here (8a, 8b, 9a, 10a) plot plane-fit RMS
tables written by the simulator's scoring and sweep commands. Every function returns ``(png_path, csv_path)``.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from flightsim.core.atomic import save_figure
from flightsim.core.errors import InputError
from flightsim.studies.figure_files import figure_paths, new_figure, write_csv
from flightsim.studies.figures_optics import ARRAY, SPACING_MRAD

MODEL_STYLE = {"nominal": dict(color="tab:red", marker="o", label="nominal (rigid array, uncorrected)"),
               "exact": dict(color="tab:blue", marker="s", label="exact (vector optics, corrected)")}
PLANE_COLUMNS = ("altitude_m", "array", "spacing_mrad", "model", "plane_id", "kind", "n", "rms_m",
                 "pitch_deg", "azimuth_deg")
SWEEP_COLUMNS = ("altitude_m", "array", "spacing_mrad", "model", "rms_m", "points")


# ---------------------------------------------------------------------------------------------
# helpers


def linear_fit(x, y) -> tuple[float, float, float]:
    """Least-squares line y = slope·x + intercept; returns (slope, intercept, R²).

    R² = 1 − SS_res / SS_tot; NaN when y is constant (SS_tot = 0), where it is undefined.
    Raises InputError unless x holds at least two distinct values.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1 or len(np.unique(x)) < 2:
        raise InputError("linear_fit.x", x.tolist(), "at least two distinct x values, one y per x")
    xc, yc = x - x.mean(), y - y.mean()
    slope = float(xc @ yc / (xc @ xc))
    intercept = float(y.mean() - slope * x.mean())
    ss_res = float(np.sum((y - (slope * x + intercept)) ** 2))
    ss_tot = float(yc @ yc)
    return slope, intercept, (1.0 - ss_res / ss_tot) if ss_tot > 0.0 else math.nan


def _read_table(path, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Columns of a CSV file as arrays (numbers where every value parses, else strings)."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(f"{path}: columns", reader.fieldnames, f"a header with {', '.join(columns)}")
        rows = list(reader)
    table = {}
    for c in columns:
        values = [r[c] for r in rows]
        try:
            table[c] = np.array([float(v) for v in values])
        except ValueError:
            table[c] = np.array(values)
    return table


def _select(table: dict[str, np.ndarray], path, **equal: float) -> dict[str, np.ndarray]:
    """Rows whose numeric columns equal the given values (to 1e-6 relative); InputError if none."""
    keep = np.ones(len(table["model"]), dtype=bool)
    for column, value in equal.items():
        keep &= np.isclose(table[column], value, rtol=1e-6, atol=1e-9)
    if not keep.any():
        wanted = ", ".join(f"{c} = {v:g}" for c, v in equal.items())
        raise InputError(f"{path}: rows", f"{len(keep)} rows", f"at least one row with {wanted}")
    return {c: v[keep] for c, v in table.items()}


# ---------------------------------------------------------------------------------------------
# Fig. 5: angular distortion of the exit fan


# ---------------------------------------------------------------------------------------------
# Figs. 8–10: plane-fit RMS from the simulator's tables


def fig8a(planes_csv, out_dir) -> tuple[Path, Path]:
    """Fig. 8(a): plane-fit RMS per roof and road plane, nominal vs exact, and their difference.

    Uses the rows of the first (altitude, array, spacing) in ``planes_csv`` (columns
    PLANE_COLUMNS, one row per plane and model), planes present for both models, by plane id.
    CSV columns: plane_id, kind, rms_nominal_m, rms_exact_m, difference_m.
    """
    png, csv_path = figure_paths(out_dir, "fig8a_plane_rms")
    table = _read_table(planes_csv, PLANE_COLUMNS)
    if len(table["model"]) == 0:
        raise InputError(f"{planes_csv}: rows", "0 rows", "one row per plane and model")
    first = {c: table[c][0] for c in ("altitude_m", "array", "spacing_mrad")}
    table = _select(table, planes_csv, **first)
    wanted = np.isin(table["kind"], ["roof", "road"])
    rms = {m: {int(p): r for p, r, k, mm in zip(table["plane_id"], table["rms_m"], wanted, table["model"])
               if k and mm == m} for m in ("nominal", "exact")}
    kinds = {int(p): k for p, k in zip(table["plane_id"], table["kind"])}
    ids = sorted(set(rms["nominal"]) & set(rms["exact"]))
    if not ids:
        raise InputError(f"{planes_csv}: rows", "no roof or road plane with both models",
                         "roof/road rows for model nominal and model exact")
    nominal = np.array([rms["nominal"][i] for i in ids])
    exact = np.array([rms["exact"][i] for i in ids])
    difference = nominal - exact
    write_csv(csv_path, ["plane_id", "kind", "rms_nominal_m", "rms_exact_m", "difference_m"],
               [[i, kinds[i], a, b, d] for i, a, b, d in zip(ids, nominal, exact, difference)])

    fig = new_figure(11.0, 5.5)
    ax = fig.subplots()
    x = np.arange(len(ids))
    ax.plot(x, nominal, "o-", color="tab:red", ms=4, label="nominal model (uncorrected)")
    ax.plot(x, exact, "s-", color="tab:blue", ms=4, label="exact model (corrected)")
    ax.plot(x, difference, "^-", color="0.5", ms=4,
            label=f"difference nominal − exact, mean {difference.mean():.4f} m (paper: 0.0498 m at 0.5 km)")
    ax.set_xticks(x, [f"{i}\n{kinds[i]}" if len(ids) <= 20 else str(i) for i in ids], fontsize=7,
                  rotation=0 if len(ids) <= 20 else 90)
    ax.set_xlabel("plane id (roofs and roads)")
    ax.set_ylabel("plane-fit RMS [m]")
    ax.set_ylim(bottom=min(0.0, difference.min() * 1.1))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9)
    ax.set_title(f"Fig. 8(a): plane-fit RMS per plane, h = {first['altitude_m'] / 1000:g} km, "
                 f"{int(first['array'])}×{int(first['array'])} fan, Δ = {first['spacing_mrad']:g} mrad")
    fig.tight_layout()
    save_figure(fig, png)
    print(f"fig8a: {len(ids)} planes, mean RMS difference nominal − exact = {difference.mean():.4f} m")
    return png, csv_path


def fig8b(sweep_csv, out_dir, array: int = ARRAY, spacing_mrad: float = SPACING_MRAD) -> tuple[Path, Path]:
    """Fig. 8(b): plane-fit RMS vs altitude with a least-squares line per model.

    CSV columns: model, altitude_km, rms_m, fit_rms_m, slope_m_per_km, intercept_m, r2.
    """
    png, csv_path = figure_paths(out_dir, "fig8b_rms_vs_altitude")
    table = _select(_read_table(sweep_csv, SWEEP_COLUMNS), sweep_csv, array=array, spacing_mrad=spacing_mrad)
    fig = new_figure(8.0, 5.5)
    ax = fig.subplots()
    rows, fits = [], []
    for model in _models(table):
        keep = table["model"] == model
        order = np.argsort(table["altitude_m"][keep])
        km, rms = table["altitude_m"][keep][order] / 1000.0, table["rms_m"][keep][order]
        style = MODEL_STYLE.get(model, dict(color="k", marker="x", label=model))
        ax.plot(km, rms, style["marker"], color=style["color"], label=style["label"])
        if len(np.unique(km)) < 2:
            rows += [[model, k, r, "", "", "", ""] for k, r in zip(km, rms)]
            continue
        slope, intercept, r2 = linear_fit(km, rms)
        line = np.array([0.0, km.max() * 1.05])
        ax.plot(line, slope * line + intercept, "-", color=style["color"], lw=1,
                label=f"{model} fit: {slope:.4g} m/km × h {intercept:+.3g} m, R² = {r2:.4f}")
        if model == "exact":
            _exact_inset(ax, km, rms, "h [km]", (line, slope * line + intercept))
        rows += [[model, k, r, slope * k + intercept, slope, intercept, r2] for k, r in zip(km, rms)]
        fits.append(f"{model}: slope {slope:.5f} m/km, intercept {intercept:.5f} m, R² {r2:.5f}")
    write_csv(csv_path, ["model", "altitude_km", "rms_m", "fit_rms_m", "slope_m_per_km", "intercept_m", "r2"], rows)
    ax.set_xlim(left=0.0)
    ax.set_ylim(bottom=-0.02 * ax.get_ylim()[1])
    ax.set_xlabel("altitude above ground h [km]")
    ax.set_ylabel("plane-fit RMS [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(f"Fig. 8(b): plane-fit RMS vs altitude ({array}×{array}, Δ = {spacing_mrad:g} mrad)"
                 "\npaper: linear, slope ≈ 0.1 m/km")
    fig.tight_layout()
    save_figure(fig, png)
    print("fig8b: " + "; ".join(fits))
    return png, csv_path


def _models(table: dict[str, np.ndarray]) -> list[str]:
    """Models present, nominal first."""
    present = set(table["model"].tolist())
    return [m for m in ("nominal", "exact") if m in present] + sorted(present - {"nominal", "exact"})


def _exact_inset(ax, x, rms, xlabel: str, fit=None, ticks=None) -> None:
    """The exact model's RMS in mm, too small to read on the main axes, in an inset at the lower right."""
    inset = ax.inset_axes([0.62, 0.15, 0.35, 0.28])
    inset.plot(x, rms * 1e3, **{**MODEL_STYLE["exact"], "label": None, "ms": 4})
    if fit is not None:
        inset.plot(fit[0], fit[1] * 1e3, "-", color=MODEL_STYLE["exact"]["color"], lw=0.8)
    inset.set_ylim(0.0, 1.25 * max(rms.max() * 1e3, 1e-6))
    inset.set_title("exact model", fontsize=7)
    inset.set_ylabel("RMS [mm]", fontsize=7)
    inset.set_xlabel(xlabel, fontsize=7)
    inset.tick_params(labelsize=6)
    if ticks is not None:
        inset.set_xticks(ticks[0], [label.split("\n")[0] for label in ticks[1]])
    inset.grid(alpha=0.3)


def _rms_versus(table, x: np.ndarray, ax, xlabel: str, ticks: tuple[np.ndarray, list[str]]) -> list[list]:
    """Plot RMS against x for each model (ticks: positions and labels); returns rows (model, x, rms, points)."""
    ax.set_xticks(*ticks)
    rows = []
    for model in _models(table):
        keep = table["model"] == model
        order = np.argsort(x[keep])
        xs, rms, points = x[keep][order], table["rms_m"][keep][order], table["points"][keep][order]
        style = MODEL_STYLE.get(model, dict(color="k", marker="x", label=model))
        ax.plot(xs, rms, "-", **style)
        rows += [[model, a, r, int(p)] for a, r, p in zip(xs, rms, points)]
        if model == "exact":
            _exact_inset(ax, xs, rms, xlabel, ticks=ticks)
        else:
            for a, r in zip(xs, rms):
                ax.annotate(f"{r:.3f}", (a, r), xytext=(0, 6), textcoords="offset points", ha="center",
                            fontsize=7, color=style["color"])
    ax.set_ylim(-0.02 * ax.get_ylim()[1], 1.08 * ax.get_ylim()[1])
    ax.set_ylabel("plane-fit RMS [m]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=9, loc="upper left")
    return rows


def fig9a(sweep_csv, out_dir, altitude_m: float = 500.0, spacing_mrad: float = SPACING_MRAD) -> tuple[Path, Path]:
    """Fig. 9(a): plane-fit RMS vs array size N×N (both models). CSV columns: model, array, rms_m, points."""
    png, csv_path = figure_paths(out_dir, "fig9a_rms_vs_array")
    table = _select(_read_table(sweep_csv, SWEEP_COLUMNS), sweep_csv, altitude_m=altitude_m, spacing_mrad=spacing_mrad)
    fig = new_figure(8.0, 5.5)
    ax = fig.subplots()
    sizes = np.unique(table["array"]).astype(int)
    rows = _rms_versus(table, table["array"], ax, "N×N", (sizes, [f"{s}×{s}" for s in sizes]))
    ax.set_xlabel("beam array size N×N")
    ax.set_title(f"Fig. 9(a): plane-fit RMS vs array size (h = {altitude_m:g} m, Δ = {spacing_mrad:g} mrad)")
    fig.tight_layout()
    save_figure(fig, png)
    write_csv(csv_path, ["model", "array", "rms_m", "points"], [[m, int(a), r, p] for m, a, r, p in rows])
    return png, csv_path


def fig10a(sweep_csv, out_dir, altitude_m: float = 500.0, array: int = ARRAY) -> tuple[Path, Path]:
    """Fig. 10(a): plane-fit RMS vs sub-beam spacing in multiples of Δ = 2.314 mrad (both models).

    CSV columns: model, spacing_mrad, spacing_multiple, rms_m, points.
    """
    png, csv_path = figure_paths(out_dir, "fig10a_rms_vs_spacing")
    table = _select(_read_table(sweep_csv, SWEEP_COLUMNS), sweep_csv, altitude_m=altitude_m, array=array)
    fig = new_figure(8.0, 5.5)
    ax = fig.subplots()
    multiple = table["spacing_mrad"] / SPACING_MRAD
    ticks = np.unique(multiple)
    labels = [f"{t:g}Δ\n{t * SPACING_MRAD:.3f}" if t != 1 else f"Δ\n{SPACING_MRAD:.3f}" for t in ticks]
    rows = _rms_versus(table, multiple, ax, "spacing", (ticks, labels))
    ax.set_xlabel(f"sub-beam spacing (Δ = {SPACING_MRAD} mrad) [mrad]")
    ax.set_title(f"Fig. 10(a): plane-fit RMS vs sub-beam spacing (h = {altitude_m:g} m, {array}×{array})")
    fig.tight_layout()
    save_figure(fig, png)
    write_csv(csv_path, ["model", "spacing_mrad", "spacing_multiple", "rms_m", "points"],
               [[m, x * SPACING_MRAD, x, r, p] for m, x, r, p in rows])
    return png, csv_path
