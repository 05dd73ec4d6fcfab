"""Scan patterns of the risley_n deflector: the on-axis beam traced exactly (float64 model) over one pattern period,
beside the thin-prism closed form, for BK7 prisms of the default 10° apex angle. Writes ``patterns.png`` and
``patterns.csv`` (the numbers it plots) into the output directory:

    python3 -m flightsim.studies.risley_patterns --out results/risley_n
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from flightsim.core.atomic import save_figure
from flightsim.instrument import risley_multi_model as model
from flightsim.instrument.risley_multi import RisleyNSettings, stack
from flightsim.studies.figure_files import figure_paths, new_figure, write_csv

SAMPLES = 1200  # per pattern period
PATTERNS = (  # title, rates [Hz], phases [deg]
    ("co-rotating in phase: circle 2δ", (20.0, 20.0), (0.0, 0.0)),
    ("counter-rotating 20/−20 Hz: line 4δ", (20.0, -20.0), (90.0, 90.0)),
    ("20/−10 Hz: rose of 3 petals", (20.0, -10.0), (0.0, 0.0)),
    ("20/−13 Hz: rose of 33 petals", (20.0, -13.0), (0.0, 0.0)),
    ("co-rotating 20/30 Hz: 1 radius maximum", (20.0, 30.0), (0.0, 0.0)),
    ("three prisms 20/−20/7.5 Hz", (20.0, -20.0, 7.5), (90.0, 90.0, 0.0)),
)


def trace_pattern(rates, phases_deg) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t [s], exact (x, y), first-order (x, y)) of the on-axis beam over one period, direction components [rad]."""
    s = RisleyNSettings(prisms=len(rates), rotation_hz=tuple(rates), phase0_deg=tuple(phases_deg))
    f_p, turns = model.pattern_turns(rates)
    t = np.linspace(0.0, 1.0 / f_p, SAMPLES + 1)
    phis = model.prism_angles(2.0 * np.pi * f_p * t, turns, np.radians(phases_deg))
    st = stack(s)
    exact = model.trace(st, np.array([0.0, 0.0, 1.0]), phis).directions[:, :2]
    deviations = [(n - 1.0) * a for n, a in zip(st.n_glass, st.apex)]
    return t, exact, model.first_order_pointing(phis, deviations)


def pattern_figure(out_dir) -> tuple[Path, Path]:
    """The six patterns of PATTERNS, exact (solid) over the closed form (dashed), in degrees; the CSV's panel is the
    index in PATTERNS, its numbers to 7 significant digits."""
    png, csv_path = figure_paths(out_dir, "patterns")
    fig = new_figure(12.0, 8.0)
    rows = []
    for k, (title, rates, phases) in enumerate(PATTERNS):
        t, exact, first = trace_pattern(rates, phases)
        ax = fig.add_subplot(2, 3, k + 1)
        ax.plot(*np.degrees(first).T, "--", color="0.6", lw=1.0, label="first order")
        ax.plot(*np.degrees(exact).T, lw=0.7, label="exact")
        reach = 1.1 * np.degrees(np.abs(exact).max())
        ax.set_xlim(-reach, reach)
        ax.set_ylim(-reach, reach)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x [deg]")
        ax.set_ylabel("y [deg]")
        rows += [[k] + [f"{v:.7g}" for v in (ti, *e, *f)] for ti, e, f in zip(t, exact, first)]
    fig.axes[0].legend(fontsize=8, loc="upper right")
    fig.suptitle("risley_n: the on-axis beam's pointing over one pattern period (BK7, 10° apex angles)")
    fig.tight_layout()
    save_figure(fig, png)
    write_csv(csv_path, ["panel", "t_s", "x_exact_rad", "y_exact_rad", "x_first_order_rad",
                         "y_first_order_rad"], rows)
    return png, csv_path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output directory, e.g. results/risley_n")
    args = parser.parse_args(argv)
    for path in pattern_figure(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
