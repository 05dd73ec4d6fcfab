"""A paper figure's files: a headless Matplotlib figure and the PNG and CSV written side by side (the CSV
holding the numbers the PNG plots, floats at full precision)."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

DPI = 150


def new_figure(width: float, height: float) -> Figure:
    """A figure of ``width`` × ``height`` [inches] at DPI, drawn by Agg (no display)."""
    fig = Figure(figsize=(width, height), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def figure_paths(out_dir, stem: str) -> tuple[Path, Path]:
    """(``out_dir/stem.png``, ``out_dir/stem.csv``), ``out_dir`` created if need be."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return out / f"{stem}.png", out / f"{stem}.csv"


def write_csv(path: Path, columns: list[str], rows) -> None:
    """A CSV of ``columns`` and ``rows``, floats as their repr (every digit)."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        writer.writerows([[repr(float(v)) if isinstance(v, (float, np.floating)) else v for v in row]
                          for row in rows])
