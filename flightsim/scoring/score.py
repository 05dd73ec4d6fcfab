"""`flightsim score`: plane-fit RMS of LAS files or a run directory (SPEC §9, §10).

Two modes:

- **truth**: points are grouped by the ``plane_id`` extra bytes the simulator writes, which
  isolates the measurement error. Points whose true hit lies within the edge buffer of its
  plane's boundary (the ``edge_distance`` extra, when written) are left out; without that extra
  the boundary is estimated from the points, as in blind mode.
- **blind**: planes are extracted from the points alone (:mod:`flightsim.scoring.blind`), as a user
  with real data would do; this works on any LAS 1.2–1.4 file. When the file carries
  ``plane_id``, each extracted plane is matched to the plane most of its points come from.

Every plane is a two-pass float64 total-least-squares fit; the RMS is that of the orthogonal
residuals. The edge buffer is, in order: ``--edge-buffer``; a run directory's summary.json
``edge_buffer_m``; the buffer the files' ``edge_distance`` values are capped at (truth mode);
half the median point spacing.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scoring.planes import PlaneFit, fit_groups, pooled_rms

if TYPE_CHECKING:
    from flightsim.outputs.las_points import PointBatch

# laspy, pyproj and scipy are imported where used, so that registering the command costs nothing

MODES = ("truth", "blind")
MODELS = ("exact", "nominal")  # georeferencing-model subfolders of a run directory
LAS_SUFFIXES = (".las", ".laz")
_EDGE_TOLERANCE = 1e-6  # relative: edge distances are float32, capped at the run's float64 buffer
_NEIGHBOURS = 24  # neighbours for the boundary estimate of truth mode without edge distances

TABLE_COLUMNS = ("source", "plane_id", "classification", "n", "nx", "ny", "nz", "pitch_deg", "azimuth_deg",
                 "rms_m", "x", "y", "z", "truth_plane_id", "truth_fraction")


@dataclass
class ScoreResult:
    """Plane fits of one set of points and what was left out.

    ``fits`` are in the input (world) frame; ``truth_plane_id`` / ``truth_fraction`` (blind mode,
    points with plane ids only) name the scene plane most of a fit's points come from and
    their share, -1 / NaN when unknown.
    """

    source: str
    mode: str
    edge_buffer_m: float
    fits: list[PlaneFit]
    classification: list[int]
    truth_plane_id: list[int]
    truth_fraction: list[float]
    points: int  #: points scored
    points_used: int  #: points in some plane's fit
    points_excluded: int  #: points of a plane left out by the edge buffer
    points_unassigned: int  #: points in no plane (no plane id, no blind segment, or too small a plane)

    @property
    def summary(self) -> dict:
        """Counts and RMS over all planes: pooled (by points) and median (by plane) [m]."""
        rms = [f.rms_m for f in self.fits]
        pooled = pooled_rms(self.fits)
        return {
            "source": self.source,
            "mode": self.mode,
            "planes": len(self.fits),
            "points": self.points,
            "points_used": self.points_used,
            "points_excluded": self.points_excluded,
            "points_unassigned": self.points_unassigned,
            "edge_buffer_m": self.edge_buffer_m,
            "rms_m": pooled if math.isfinite(pooled) else None,
            "median_rms_m": float(np.median(rms)) if rms else None,
        }

    def rows(self) -> list[dict]:
        """The per-plane table, one dict per plane with the keys of ``TABLE_COLUMNS``."""
        return [{
            "source": self.source,
            "plane_id": f.plane_id,
            "classification": cls,
            "n": f.n,
            "nx": float(f.normal[0]), "ny": float(f.normal[1]), "nz": float(f.normal[2]),
            "pitch_deg": f.pitch_deg,
            "azimuth_deg": f.azimuth_deg,
            "rms_m": f.rms_m,
            "x": float(f.centroid[0]), "y": float(f.centroid[1]), "z": float(f.centroid[2]),
            "truth_plane_id": truth,
            "truth_fraction": fraction,
        } for f, cls, truth, fraction in zip(self.fits, self.classification, self.truth_plane_id,
                                              self.truth_fraction)]


def score_points(batch: PointBatch, mode: str = "truth", edge_buffer_m: float | None = None,
                 source: str = "points") -> ScoreResult:
    """Plane fits of a batch of points in ``mode`` "truth" or "blind" (see the module docstring).

    ``edge_buffer_m`` None chooses it automatically; ``source`` names the points in messages and
    tables. Truth mode needs plane ids (``batch.plane_id`` ≥ 0 somewhere).
    """
    if mode not in MODES:
        raise InputError("--mode", mode, " or ".join(MODES))
    if edge_buffer_m is not None and not (math.isfinite(edge_buffer_m) and edge_buffer_m >= 0.0):
        raise InputError("--edge-buffer", edge_buffer_m, "a finite distance ≥ 0 m")
    if len(batch) == 0:
        raise InputError("path", source, "LAS files holding at least one point")
    xyz = np.column_stack([batch.x, batch.y, batch.z])
    if mode == "blind":
        return _score_blind(batch, xyz, edge_buffer_m, source)
    return _score_truth(batch, xyz, edge_buffer_m, source)


def _score_truth(batch: PointBatch, xyz: np.ndarray, buffer: float | None, source: str) -> ScoreResult:
    from flightsim.scoring.blind_edges import auto_edge_buffer_m, boundary_distance_m
    from flightsim.scoring.blind_neighbours import neighbourhoods

    labels = batch.plane_id.astype(np.int64)
    member = labels >= 0
    if not member.any():
        raise InputError("plane_id", source, "points with the plane_id extra bytes that flightsim simulate writes "
                         "(score other LAS files with --mode blind)")
    origin = xyz.mean(axis=0)
    local = xyz - origin
    if batch.edge_distance_m is not None:
        cap = float(np.max(batch.edge_distance_m))
        if buffer is None:
            buffer = cap
        elif buffer > cap * (1.0 + _EDGE_TOLERANCE):
            raise InputError("--edge-buffer", buffer, f"at most {cap:.6g} m: the files record edge distances only up "
                             "to the buffer of the run that wrote them")
        beyond = batch.edge_distance_m >= np.float32(buffer) * (1.0 - _EDGE_TOLERANCE)
    else:
        near = neighbourhoods(local, _NEIGHBOURS)
        if buffer is None:
            buffer = auto_edge_buffer_m(float(np.median(near.nearest_m)))
        beyond = boundary_distance_m(local, labels, near) > buffer
    used = member & beyond
    fits = fit_groups(local, np.where(used, labels, -1))
    for fit in fits:
        fit.centroid = fit.centroid + origin
    fitted = np.zeros(int(labels.max()) + 1, dtype=bool)
    fitted[[f.plane_id for f in fits]] = True
    in_fit = used & fitted[np.maximum(labels, 0)]
    classes = [_majority(batch.classification[labels == f.plane_id])[0] for f in fits]
    return ScoreResult(source, "truth", float(buffer), fits, classes, [-1] * len(fits), [math.nan] * len(fits),
                       len(batch), int(in_fit.sum()), int((member & ~beyond).sum()),
                       int((~member).sum() + (member & beyond & ~in_fit).sum()))


def _score_blind(batch: PointBatch, xyz: np.ndarray, buffer: float | None, source: str) -> ScoreResult:
    from flightsim.scoring.blind import extract_planes

    result = extract_planes(xyz, batch.classification, edge_buffer_m=buffer)
    fits = [s.fit for s in result.segments]
    known = bool((batch.plane_id >= 0).any())
    truth, fraction = [], []
    for segment in result.segments:
        plane, share = _majority(batch.plane_id[segment.indices]) if known else (-1, math.nan)
        truth.append(plane)
        fraction.append(share)
    member = result.labels >= 0
    return ScoreResult(source, "blind", result.edge_buffer_m, fits, [s.classification for s in result.segments],
                       truth, fraction, len(batch), int(result.used.sum()), int((member & ~result.used).sum()),
                       int((~member).sum()))


def _majority(values: np.ndarray) -> tuple[int, float]:
    """Most frequent value and its share (-1, NaN for no values)."""
    if len(values) == 0:
        return -1, math.nan
    unique, counts = np.unique(values, return_counts=True)
    best = int(np.argmax(counts))
    return int(unique[best]), float(counts[best] / len(values))


@dataclass
class _Source:
    """A set of LAS files scored together, and the edge buffer of the run that wrote them."""

    name: str
    files: list[Path]
    edge_buffer_m: float | None


def find_sources(paths: Sequence[str | os.PathLike]) -> list[_Source]:
    """LAS/LAZ files (all together one source) and run directories (one source per georeferencing
    model subfolder; a directory of LAS files is one source)."""
    if not paths:
        raise InputError("PATH", [], "at least one LAS/LAZ file or run directory")
    files, sources = [], []
    for raw in paths:
        path = Path(raw)
        if path.is_file():
            if path.suffix.lower() not in LAS_SUFFIXES:
                raise InputError("PATH", str(path), "a .las or .laz file, or a run directory")
            files.append(path)
        elif path.is_dir():
            sources.extend(_directory_sources(path))
        else:
            raise InputError("PATH", str(path), "an existing LAS/LAZ file or run directory")
    if files:
        sources.insert(0, _Source(", ".join(str(f) for f in files) if len(files) <= 3 else
                                  f"{files[0]} and {len(files) - 1} more", files, None))
    return sources


def _directory_sources(directory: Path) -> list[_Source]:
    buffer = _summary_edge_buffer(directory)
    sources = [_Source(str(directory / m), _las_files(directory / m), buffer) for m in MODELS
               if (directory / m).is_dir() and _las_files(directory / m)]
    if not sources and _las_files(directory):
        sources = [_Source(str(directory), _las_files(directory), buffer)]
    if not sources:
        raise InputError("PATH", str(directory), "a run directory with LAS tiles in exact/ or nominal/, or a "
                         "directory of LAS/LAZ files")
    return sources


def _las_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.is_file() and p.suffix.lower() in LAS_SUFFIXES)


def _summary_edge_buffer(directory: Path) -> float | None:
    """The run's ``edge_buffer_m`` from DIR/summary.json, or None."""
    summary = directory / "summary.json"
    if not summary.is_file():
        return None
    try:
        value = json.loads(summary.read_text(encoding="utf-8")).get("edge_buffer_m")
    except (OSError, ValueError, AttributeError):
        raise InputError("PATH", str(summary), "a readable summary.json (JSON object)") from None
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) and value >= 0 else None


def _has_dimension(path: Path, name: str) -> bool:
    import laspy

    try:
        with laspy.open(path) as reader:
            return name in reader.header.point_format.dimension_names
    except (OSError, laspy.LaspyException) as err:
        raise InputError("PATH", str(path), f"a readable LAS/LAZ file ({err})") from err


def score_paths(paths: Sequence[str | os.PathLike], mode: str = "truth", out: str | os.PathLike | None = None,
                edge_buffer_m: float | None = None) -> list[ScoreResult]:
    """Score LAS files and run directories (see :func:`find_sources`); write DIR/planes.csv and
    DIR/score.json when ``out`` is given."""
    from flightsim.outputs.las_points import read_points

    if mode not in MODES:
        raise InputError("--mode", mode, " or ".join(MODES))
    if edge_buffer_m is not None and not (math.isfinite(edge_buffer_m) and edge_buffer_m >= 0.0):
        raise InputError("--edge-buffer", edge_buffer_m, "a finite distance ≥ 0 m")
    if out is not None and Path(out).exists() and not Path(out).is_dir():
        raise InputError("--out", str(out), "a directory (this path is a file)")
    results = []
    for source in find_sources(paths):
        if mode == "truth":
            for path in source.files:
                if not _has_dimension(path, "plane_id"):
                    raise InputError("plane_id", str(path), "a LAS file with the plane_id extra bytes that flightsim "
                                     "simulate writes (score other LAS files with --mode blind)")
        batch, _crs = read_points(source.files)
        buffer = edge_buffer_m if edge_buffer_m is not None else source.edge_buffer_m
        results.append(score_points(batch, mode, buffer, source.name))
    if out is not None:
        write_results(results, Path(out))
    return results


def write_results(results: list[ScoreResult], directory: Path) -> None:
    """DIR/planes.csv (the per-plane table of every source) and DIR/score.json (the summaries)."""
    directory.mkdir(parents=True, exist_ok=True)
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=TABLE_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for result in results:
        writer.writerows(_csv_row(row) for row in result.rows())
    _write_atomic(directory / "planes.csv", table.getvalue())
    document = {"mode": results[0].mode if results else None, "sources": [r.summary for r in results]}
    _write_atomic(directory / "score.json", json.dumps(document, indent=2) + "\n")


def _csv_row(row: dict) -> dict:
    """Floats with enough digits, NaN as an empty cell."""
    return {k: ("" if isinstance(v, float) and not math.isfinite(v) else f"{v:.9g}" if isinstance(v, float) else v)
            for k, v in row.items()}


def _write_atomic(path: Path, text: str) -> None:
    """Write a text file under a temporary name, then rename it into place."""
    tmp = path.with_name(f".{path.name}.part")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def format_result(result: ScoreResult) -> str:
    """A compact text table of one source: summary line, then one line per plane."""
    s = result.summary
    rms = "n/a" if s["rms_m"] is None else f"{s['rms_m'] * 1000:.2f} mm"
    median = "n/a" if s["median_rms_m"] is None else f"{s['median_rms_m'] * 1000:.2f} mm"
    lines = [f"{result.source} [{result.mode}]: {s['planes']} planes, {s['points_used']} of {s['points']} points used "
             f"({s['points_excluded']} within the {result.edge_buffer_m:.3f} m edge buffer, {s['points_unassigned']} "
             f"in no plane); RMS pooled {rms}, median {median}"]
    blind = result.mode == "blind" and any(t >= 0 for t in result.truth_plane_id)
    header = f"{'plane':>6} {'class':>5} {'n':>8} {'pitch°':>7} {'azim°':>7} {'rms mm':>9}"
    lines.append(header + ("  truth (share)" if blind else ""))
    for row in result.rows():
        azimuth = "-" if not math.isfinite(row["azimuth_deg"]) else f"{row['azimuth_deg']:.2f}"
        line = (f"{row['plane_id']:>6} {row['classification']:>5} {row['n']:>8} {row['pitch_deg']:>7.2f} "
                f"{azimuth:>7} {row['rms_m'] * 1000:>9.3f}")
        if blind:
            line += f"  {row['truth_plane_id']} ({row['truth_fraction']:.2f})"
        lines.append(line)
    return "\n".join(lines)


def cmd_score(args: argparse.Namespace) -> int:
    """Run `flightsim score` from parsed arguments."""
    results = score_paths(args.paths, args.mode, args.out, args.edge_buffer)
    if args.out:
        for result in results:
            s = result.summary
            rms = "n/a" if s["rms_m"] is None else f"{s['rms_m'] * 1000:.2f} mm"
            print(f"{result.source} [{result.mode}]: {s['planes']} planes, {s['points_used']} points, RMS {rms}")
        print(f"written to {args.out}")
    else:
        print("\n\n".join(format_result(r) for r in results))
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``score`` subcommand to the flightsim command line."""
    parser = subparsers.add_parser("score", help="plane-fit RMS of LAS files or a run directory (truth or blind)")
    parser.add_argument("paths", nargs="+", metavar="PATH", help="LAS/LAZ files (scored together) or run directories")
    parser.add_argument("--mode", choices=MODES, default="truth",
                        help="truth: group by the simulator's plane ids (default); blind: extract planes from "
                             "the points alone (any LAS file)")
    parser.add_argument("--out", help="directory for planes.csv and score.json (default: print a table)")
    parser.add_argument("--edge-buffer", dest="edge_buffer", type=float, metavar="M",
                        help="leave out points within M metres of a plane's boundary (default: the run's buffer, "
                             "else half the point spacing)")
    parser.set_defaults(func=cmd_score)
    return parser
