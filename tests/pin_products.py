#!/usr/bin/env python3
"""Pins of every kind of product flightsim writes, recorded before the refactor of the config format.

The promise of the refactor is "nothing changes for users but the config": the same commands (with the
config keys renamed) must write the same products, bit for bit. This module runs a small, fast version
of every product-writing command through ``flightsim.cli.main`` (and, where a command is too slow, the
study's own function with its loop shortened) in temporary directories, and digests what they write:

- LAS / LAZ / COPC tiles and Markdown reports: SHA-256 of the bytes;
- HDF5 (``photons.h5``, ``atl03.h5``, ``waveforms.h5``): every dataset (dtype, shape, SHA-256 of the
  array's raw bytes; the values too when it holds at most ``SMALL`` of them) and every attribute (its
  value), recursively, by path: nothing depends on h5py's file-level bytes;
- GeoTIFF: the file's bytes (stable between runs) and, through rasterio, its CRS, transform, nodata,
  dtypes, tags and the SHA-256 of each band's values;
- the range-image PNG of gridded photons: its pixels and text metadata (not the bytes: matplotlib writes
  its own version into them);
- JSON summaries: the values, with the volatile keys (``VOLATILE_KEYS``: times, devices, versions, hosts)
  removed; CSV tables: the rows (or their count and SHA-256 when there are many), volatile columns removed.

A run may write more than its pins hold (a file, a dataset, an attribute, a key that a later feature adds: the
waveforms' beam attributes, ``atl08.h5``): that is no difference, while every pinned value must stay as it was.

Not pinned (listed in ``_files`` all the same, so a missing file is still seen): the config
files (``run.toml``, ``survey.toml``, ``sweep.json`` and the attribute ``config_toml`` of the HDF5 files,
which change with the refactor by design), the sweep's resume rows (``rows/<hash of the config>.json``,
counted only), matplotlib figures (their bytes and text rendering depend on the matplotlib and FreeType
build; the numbers they plot are pinned in the CSV / JSON beside them) and the reports that print run
times (``SKIP`` of each case).

Every command line and config key lives in ``CASES`` below: after the refactor, renaming a key there is
the only edit this file needs. ``TOLERANCES`` can loosen the comparison of JSON / CSV numbers of one
product on one device (none is needed on the CPU: every product is bit-stable between two runs there).

    python3 tests/pin_products.py --device cpu --out tests/data/product_pins_cpu.json   # record
    python3 tests/pin_products.py --device cpu --check tests/data/product_pins_cpu.json  # compare
    python3 tests/pin_products.py --compare A.json B.json                                # two records

``tests/test_product_pins.py`` runs each case on the CPU against ``data/product_pins_cpu.json``.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import fnmatch
import hashlib
import importlib
import io
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import same_bits  # noqa: F401  (before NumPy loads: the same bits on every x86-64 machine)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

PIN_DIR = Path(__file__).resolve().parent / "data"

# ---------------------------------------------------------------------------------------------------
# The cases: every command line and config key used. A step is a flightsim command line (``{work}``:
# the case's directory, ``{device}``: the device) or a dict calling ``module:function`` with args.
# ``patch`` sets module attributes while the case runs (a study's loop shortened; the attribute must
# exist). ``skip`` lists files of the case (fnmatch on the path relative to ``{work}``) left unpinned.

CASES: dict[str, dict] = {
    # the default airborne Risley instrument; its run directory scored by plane id and blind
    "las_default": {
        "steps": [
            ["simulate", "--duration", "0.2", "--device", "{device}", "--out", "{work}/run"],
            ["score", "{work}/run", "--out", "{work}/score_truth"],
            ["score", "{work}/run", "--mode", "blind", "--out", "{work}/score_blind"],
        ],
    },
    # LAZ tiles and each model's COPC file
    "las_laz_copc": {
        "steps": [
            ["simulate", "--duration", "0.2", "--array", "4", "--device", "{device}",
             "--set", "output.laz=true", "--set", "output.copc=true", "--out", "{work}/run"],
        ],
    },
    # curved ground: patch fits and patch_rms.tif
    "las_lunar": {
        "steps": [
            ["simulate", "--scene", "lunar", "--duration", "0.3", "--device", "{device}", "--out", "{work}/run"],
        ],
    },
    # terrain: the test DEM generator's products, and a run over the DEM with land cover and buildings
    "las_dem": {
        "steps": [
            {"call": "flightsim.scenes.testdem:main",
             "args": [["--out", "{work}/terrain", "--size-m", "600", "--cell-m", "2", "--seed", "0"]]},
            ["simulate", "--scene", "{work}/terrain/dem.tif", "--altitude", "300", "--duration", "0.3",
             "--device", "{device}", "--set", "scene.landcover={work}/terrain/landcover.tif",
             "--set", "scene.buildings={work}/terrain/buildings.obj", "--out", "{work}/run"],
        ],
    },
    # the procedural forest: leaf returns through the voxel walk (classes 3-5, return numbers), its chm.tif
    "las_forest": {
        "steps": [
            ["simulate", "--scene", "forest", "--duration", "0.3", "--device", "{device}", "--out", "{work}/run"],
        ],
    },
    # the Chang'e-3 galvo imager (channels emitter, galvo deflector, ranging chain) hovering over a plane
    "galvo_change3": {
        "steps": [
            ["simulate", "--instrument", "change3", "--device", "{device}", "--out", "{work}/run"],
        ],
    },
    # the waveform altimeter through `simulate` and through `waveform` (slope; bump with the receiver chain), ranged
    # by the host's reference (pinned before the device's ranging became the default) and by the device (the default)
    "waveform_change1": {
        "steps": [
            ["simulate", "--instrument", "change1", "--device", "{device}", "--set", "waveform.processing=host",
             "--out", "{work}/run"],
        ],
    },
    "waveform_change1_device": {
        "steps": [
            ["simulate", "--instrument", "change1", "--device", "{device}", "--out", "{work}/run"],
        ],
    },
    "waveform_slope": {
        "steps": [
            ["waveform", "--scene", "slope", "--device", "{device}", "--set", "waveform.processing=host",
             "--out", "{work}/run"],
        ],
    },
    "waveform_bump_receiver": {
        "steps": [
            ["waveform", "--scene", "bump", "--device", "{device}", "--set", "waveform.processing=host",
             "--set", "waveform.n_rings=30", "--set", "waveform.n_sectors=60", "--set", "waveform.samples=16384",
             "--set", "waveform.receiver_fwhm_s=2e-9", "--set", "waveform.shot_noise=true",
             "--set", "waveform.peak_power_w=1e5", "--set", "waveform.background_w=1e-8",
             "--set", "waveform.thermal_noise_w=1e-8", "--set", "waveform.bits=12",
             "--set", "waveform.full_scale_w=4e-6", "--out", "{work}/run"],
        ],
    },
    # the patent's Figs. 3-5: flat, slope and bump beside the float64 reference (REPORT.md has no timing)
    "waveform_patent": {
        "steps": [
            ["waveform", "--patent", "--device", "{device}", "--out", "{work}/patent"],
        ],
    },
    # the SPAD lidar: the first 100 pulses of a MODE-A frame (50 kHz) over the sandbox
    "photons_spad": {
        "steps": [
            ["simulate", "--instrument", "spad", "--duration", "0.00199", "--device", "{device}",
             "--out", "{work}/run"],
        ],
    },
    # the spaceborne altimeter from orbit: photons.h5, atl03.h5 and the photon LAS tiles
    "photons_atlas": {
        "steps": [
            ["simulate", "--instrument", "atlas", "--duration", "0.05", "--device", "{device}", "--out", "{work}/run"],
        ],
    },
    # error budgets (REPORT.md prints the Monte Carlo's run time: not pinned; deviation_maps.png: a figure)
    "budget_change3": {
        "steps": [
            ["budget", "--instrument", "change3", "--draws", "4", "--columns", "8", "--device", "{device}",
             "--out", "{work}/budget"],
        ],
        "skip": ["budget/REPORT.md"],
    },
    "budget_risley": {
        "steps": [
            ["budget", "--instrument", "risley", "--draws", "4", "--device", "{device}", "--out", "{work}/budget"],
        ],
        "skip": ["budget/REPORT.md"],
    },
    # `flightsim spad`: every experiment, 100 pulses a frame; the MODE-A frame's range PNG, heights
    # GeoTIFF and points LAS (REPORT.md prints run times: not pinned)
    "spad_study": {
        "steps": [
            ["spad", "--pulses", "100", "--device", "{device}", "--out", "{work}/spad"],
        ],
        "skip": ["spad/REPORT.md"],
    },
    # `flightsim calibrate` with its sweep cut to three passes of seed 0 (the full 30 passes take ~56 s
    # on the 2-core CPU): the default pass (figures), a small field under strong background, the orbit
    "calibrate": {
        "patch": {
            "flightsim.studies.spaceborne:SEEDS": (0,),
            "flightsim.studies.spaceborne:SETTINGS": [(16, 1.0e6, "lines"), (4, 2.0e7, "lines"),
                                                      (16, 1.0e6, "orbit")],
        },
        "steps": [
            ["calibrate", "--device", "{device}", "--out", "{work}/calibration"],
        ],
    },
    # sweeps in statistics mode, and the paper's accuracy figures' tables made from them
    "sweep": {
        "steps": [
            ["sweep", "--scene", "plane", "--altitudes", "500,1500", "--arrays", "2,3", "--spacings-mrad",
             "2.314,4.628", "--duration", "0.2", "--device", "{device}", "--out", "{work}/plane"],
            ["sweep", "--scene", "calibration", "--duration", "0.3", "--device", "{device}",
             "--out", "{work}/calibration"],
            {"call": "flightsim.studies.figures:fig8a", "args": ["{work}/calibration/planes.csv", "{work}/figures"]},
            {"call": "flightsim.studies.figures:fig8b", "args": ["{work}/plane/sweep.csv", "{work}/figures"]},
            {"call": "flightsim.studies.figures:fig9a", "args": ["{work}/plane/sweep.csv", "{work}/figures"]},
            {"call": "flightsim.studies.figures:fig10a", "args": ["{work}/plane/sweep.csv", "{work}/figures"]},
        ],
    },
    # the seed paper's optics figures (5a, 5c, 6b): their CSVs
    "figures_optics": {
        "steps": [
            {"call": "flightsim.studies.figures_optics:optics_figures", "args": ["{work}/figures"]},
        ],
    },
    # a survey of one scene tile, two segments per line (parts merged per LAS tile), LAS; and to LAZ
    "survey": {
        "steps": [
            ["survey", "--size-km", "0.5", "--tile-m", "500", "--segment-m", "250", "--device", "{device}",
             "--out", "{work}/survey"],
        ],
    },
    "survey_laz": {
        "steps": [
            ["survey", "--size-km", "0.4", "--tile-m", "400", "--segment-m", "200", "--altitude", "1000",
             "--array", "2", "--device", "{device}", "--set", "output.laz=true", "--out", "{work}/survey"],
        ],
    },
}

# Left out: `flightsim paper` (its sweeps fly 2 s and 12 s lines: minutes; its parts are the sweeps and
# the figure functions above), `flightsim bench` (timings only), the full `calibrate` sweep (see above).

SKIP = {  # files never pinned (relative paths, fnmatch; `*` crosses folders), with the reason
    "*run.toml": "the resolved config: changes with the refactor by design",
    "*survey.toml": "the survey's settings as TOML",
    "*sweep.json": "the sweep's base config and axes (config keys)",
    "*rows/*.json": "the sweep's resume state, named by a hash of the config TOML",
    "*.png": "a matplotlib figure (bytes and text rendering depend on the matplotlib build)",
}
COUNT_ONLY = ("*rows/*.json",)  # listed in _files by pattern and count, not by name
PIXEL_PNGS = ("*_range.png",)  # PNG images of values (grid_products.write_png): their pixels are pinned
VOLATILE_KEYS = frozenset({
    "wall_s", "stages_s", "writers_s", "score_s", "scan_s", "tls_scan_s", "deterministic_wall_s", "draws_per_s",
    "slot_draws_per_s", "points_per_s",
    "workers", "device", "host", "flightsim", "version", "versions", "commit", "date", "created", "python",
})
VOLATILE_COLUMNS = frozenset({"wall_s"})
H5_SKIP_ATTRS = {"config_toml": "the run's config TOML", "flightsim": "the flightsim version"}
PNG_SKIP_TEXT = ("Software",)  # matplotlib's version
SMALL = 8  # datasets and CSVs with at most this many values / rows keep them in the pins (readable diffs)
SMALL_CSV_ROWS = 40
TOLERANCES: dict[str, dict[tuple[str, str], dict]] = {
    # device -> {(case, product fnmatch): {"rel": r, "abs": a}} for the numbers of JSON / CSV / HDF5
    # attribute values; SHA-256 digests are always compared exactly. None needed on the CPU.
    "cpu": {},
}


def pin_path(device: str) -> Path:
    """The pin file of a device kind: data/product_pins_cpu.json, data/product_pins_cuda.json."""
    return PIN_DIR / f"product_pins_{device.split(':')[0]}.json"


# ---------------------------------------------------------------------------------------------------
# digests


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _jsonable(value):
    """A numpy / bytes value as plain JSON (exact: floats round-trip through repr)."""
    import numpy as np

    import h5py

    if isinstance(value, h5py.Reference):  # a dimension scale's DIMENSION_LIST / REFERENCE_LIST (atl03.h5)
        return "<HDF5 object reference>"
    if isinstance(value, bytes):
        return value.decode("utf-8", "backslashreplace")
    if isinstance(value, np.ndarray):
        return [_jsonable(v) for v in value.tolist()] if value.dtype.kind in "OSUV" else value.tolist()
    if isinstance(value, np.generic):
        return _jsonable(value.item()) if isinstance(value, np.void) else value.item()
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def _array(value) -> dict:
    """dtype, shape and SHA-256 of an array's raw bytes (strings: of their JSON), values if small."""
    import numpy as np

    a = np.asarray(value)
    if a.dtype.kind in "OSU":
        data = json.dumps(_jsonable(a), sort_keys=True).encode()
    else:
        data = np.ascontiguousarray(a).tobytes()
    out = {"dtype": a.dtype.str, "shape": list(a.shape), "sha256": _sha(data)}
    if a.size <= SMALL and a.dtype.names is None:
        out["values"] = _jsonable(a)
    return out


def _attribute(value):
    import numpy as np

    if isinstance(value, np.ndarray):
        return {"dtype": value.dtype.str, "shape": list(value.shape), "values": _jsonable(value)}
    if isinstance(value, np.generic):
        return {"dtype": value.dtype.str, "value": _jsonable(value)}
    return _jsonable(value)


def digest_h5(path: Path) -> dict:
    """Every dataset and attribute of an HDF5 file by path (``/group/name``, ``/group/name@attribute``)."""
    import h5py

    out = {}

    def attrs(name: str, obj) -> None:
        for key in sorted(obj.attrs):
            if key not in H5_SKIP_ATTRS:
                out[f"{name}@{key}"] = _attribute(obj.attrs[key])

    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            out["/" + name] = _array(obj[()])
        attrs("/" + name, obj)

    with h5py.File(path, "r") as f:
        attrs("/", f)
        f.visititems(visit)
    return dict(sorted(out.items()))


def digest_tif(path: Path) -> dict:
    """A GeoTIFF's bytes and, through rasterio, its georeferencing and each band's values."""
    import rasterio

    with rasterio.open(path) as ds:
        bands = ds.read()
        return {"sha256": _sha(path.read_bytes()), "driver": ds.driver,
                "crs": ds.crs.to_wkt() if ds.crs else None, "transform": list(ds.transform)[:6],
                "shape": list(bands.shape), "dtypes": list(ds.dtypes), "nodata": ds.nodata,
                "descriptions": list(ds.descriptions), "tags": ds.tags(),
                "bands": [_array(band) for band in bands]}


def digest_png_pixels(path: Path) -> dict:
    """A PNG image's mode, size, pixels and text metadata (less the writing software's version)."""
    from PIL import Image

    with Image.open(path) as im:
        text = {k: v for k, v in sorted(getattr(im, "text", {}).items()) if k not in PNG_SKIP_TEXT}
        return {"mode": im.mode, "size": list(im.size), "pixels_sha256": _sha(im.tobytes()), "text": text}


def strip_volatile(value):
    """A JSON value less the keys of VOLATILE_KEYS, at any depth."""
    if isinstance(value, dict):
        return {k: strip_volatile(v) for k, v in value.items() if k not in VOLATILE_KEYS}
    if isinstance(value, list):
        return [strip_volatile(v) for v in value]
    return value


def digest_csv(text: str) -> dict:
    rows = list(csv.reader(io.StringIO(text)))
    if not rows:
        return {"columns": [], "rows": []}
    keep = [i for i, name in enumerate(rows[0]) if name not in VOLATILE_COLUMNS]
    rows = [[row[i] for i in keep if i < len(row)] for row in rows]
    header, body = rows[0], rows[1:]
    if len(body) <= SMALL_CSV_ROWS:
        return {"columns": header, "rows": body}
    return {"columns": header, "n_rows": len(body), "sha256": _sha(json.dumps(body).encode())}


def _matches(rel: str, patterns) -> bool:
    return any(fnmatch.fnmatchcase(rel, p) for p in patterns)


def digest_file(path: Path, rel: str, work: Path):
    """The digest of one product file, by its kind."""
    name = path.name
    if name.endswith((".las", ".laz")):
        return _sha(path.read_bytes())
    if name.endswith(".h5"):
        return digest_h5(path)
    if name.endswith((".tif", ".tiff")):
        return digest_tif(path)
    if name.endswith(".png"):
        return digest_png_pixels(path)
    if name.endswith((".json", ".csv", ".md", ".txt")):
        text = path.read_text(encoding="utf-8").replace(str(work), "{work}")  # paths of this run's directory
        if name.endswith(".json"):
            return strip_volatile(json.loads(text))
        if name.endswith(".csv"):
            return digest_csv(text)
        return _sha(text.encode())
    return _sha(path.read_bytes())


def collect(work: Path, skip=()) -> dict:
    """``{"_files": [...], relpath: digest}`` of everything under ``work``."""
    files = sorted(str(p.relative_to(work)).replace(os.sep, "/") for p in work.rglob("*") if p.is_file())
    listing = [rel for rel in files if not _matches(rel, COUNT_ONLY)]
    listing += [f"{pattern} x{sum(fnmatch.fnmatchcase(rel, pattern) for rel in files)}" for pattern in COUNT_ONLY
                if any(fnmatch.fnmatchcase(rel, pattern) for rel in files)]
    products = {"_files": listing}
    for rel in files:
        if _matches(rel, skip) or (_matches(rel, SKIP) and not _matches(rel, PIXEL_PNGS)):
            continue
        products[rel] = digest_file(work / rel, rel, work)
    return products


# ---------------------------------------------------------------------------------------------------
# running the cases


@contextlib.contextmanager
def patched(patch: dict):
    """Module attributes set for the duration (each must exist: a renamed one fails loudly)."""
    saved = []
    try:
        for target, value in patch.items():
            module_name, attr = target.split(":")
            module = importlib.import_module(module_name)
            if not hasattr(module, attr):
                raise AttributeError(f"case patch: {module_name} has no attribute {attr}")
            saved.append((module, attr, getattr(module, attr)))
            setattr(module, attr, value)
        yield
    finally:
        for module, attr, value in reversed(saved):
            setattr(module, attr, value)


def _fill(value, work: Path, device: str):
    """``value`` with ``{work}`` and ``{device}`` filled in (in lists too)."""
    if isinstance(value, str):
        return value.replace("{work}", str(work)).replace("{device}", device)
    if isinstance(value, list):
        return [_fill(v, work, device) for v in value]
    return value


def run_case(name: str, device: str, root: Path) -> dict:
    """Run case ``name`` on ``device`` in ``root/name`` (created); return its products' digests."""
    from flightsim.cli import main

    case = CASES[name]
    work = Path(root) / name
    work.mkdir(parents=True, exist_ok=False)
    with patched(case.get("patch", {})):
        for step in case["steps"]:
            printed = io.StringIO()  # what the commands print: shown only when one fails
            if isinstance(step, dict):
                module_name, function = step["call"].split(":")
                fn = getattr(importlib.import_module(module_name), function)
                with contextlib.redirect_stdout(printed):
                    result = fn(*_fill(step.get("args", []), work, device),
                                **{k: _fill(v, work, device) for k, v in step.get("kwargs", {}).items()})
                if function == "main" and result not in (None, 0):
                    raise RuntimeError(f"case {name}: {step['call']} returned {result}:\n{printed.getvalue()}")
                continue
            argv = _fill(step, work, device)
            with contextlib.redirect_stdout(printed):
                status = main(argv)
            if status != 0:
                raise RuntimeError(f"case {name}: `flightsim {' '.join(argv)}` exited {status}:\n{printed.getvalue()}")
    return collect(work, case.get("skip", ()))


# ---------------------------------------------------------------------------------------------------
# comparing


def _tolerance(device: str, case: str, product: str):
    for (c, pattern), tol in TOLERANCES.get(device.split(":")[0], {}).items():
        if c == case and fnmatch.fnmatchcase(product, pattern):
            return tol
    return None


def differences(pinned, got, tol=None, path: str = "") -> list[str]:
    """Where ``got`` differs from ``pinned`` (JSON values), as ``path: pinned -> got`` lines. What ``got`` adds (a
    key, an attribute, a dataset; a name in a listing of names such as ``_files`` or a summary's ``files``) is no
    difference: products may gain what new features write, but every pinned value must stay."""
    if isinstance(pinned, dict) and isinstance(got, dict):
        out = []
        for key in sorted(pinned, key=str):
            where = f"{path}/{key}" if path else str(key)
            if key not in got:
                out.append(f"{where}: missing (pinned {_short(pinned[key])})")
            else:
                out += differences(pinned[key], got[key], tol, where)
        return out
    if path == "_files":
        return [f"{name}: pinned but not written" for name in pinned if name not in got]
    if _names(pinned) and _names(got) and [name for name in got if name in pinned] == pinned:
        return []  # a listing of names (files, models) that gained names
    if isinstance(pinned, list) and isinstance(got, list) and len(pinned) == len(got):
        return [d for i, (a, b) in enumerate(zip(pinned, got)) for d in differences(a, b, tol, f"{path}[{i}]")]
    if tol is not None and _number(pinned) and _number(got) and math.isclose(
            pinned, got, rel_tol=tol.get("rel", 0.0), abs_tol=tol.get("abs", 0.0)):
        return []
    if json.dumps(pinned, sort_keys=True) == json.dumps(got, sort_keys=True):  # NaN equals NaN here
        return []
    return [f"{path}: pinned {_short(pinned)} -> got {_short(got)}"]


def _names(v) -> bool:
    return isinstance(v, list) and all(isinstance(x, str) for x in v)


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _short(value, limit: int = 200) -> str:
    text = json.dumps(value, sort_keys=True)
    return text if len(text) <= limit else text[:limit] + "..."


def compare_case(case: str, pinned: dict, got: dict, device: str = "cpu") -> list[str]:
    """Lines naming each product of ``case`` that differs from its pin, and how."""
    out = []
    for product in sorted(set(pinned) | set(got)):
        if product not in got:
            out.append(f"{case}: {product}: pinned but not written")
        elif product in pinned:  # a product the pins do not know is a new feature's
            out += [f"{case}: {product}: {d}" for d in differences(pinned[product], got[product],
                                                                   _tolerance(device, case, product),
                                                                   "_files" if product == "_files" else "")]
    return out


def compare(pinned: dict, got: dict, device: str = "cpu") -> list[str]:
    out = []
    for case in sorted(k for k in set(pinned) | set(got) if not k.startswith("_")):
        if case not in got or case not in pinned:
            out.append(f"{case}: only in {'the pins' if case in pinned else 'this run'}")
            continue
        out += compare_case(case, pinned[case], got[case], device)
    return out


# ---------------------------------------------------------------------------------------------------
# command line


def _commit() -> str | None:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip() or None
    except (OSError, subprocess.CalledProcessError):
        return None


def run_all(device: str, names: list[str], keep: Path | None = None) -> tuple[dict, dict]:
    """(pins of the cases ``names``, seconds per case), each case in a fresh temporary directory."""
    root = Path(tempfile.mkdtemp(prefix="flightsim-pins-")) if keep is None else keep
    pins, seconds = {}, {}
    try:
        for name in names:
            started = time.perf_counter()
            pins[name] = run_case(name, device, root)
            seconds[name] = round(time.perf_counter() - started, 2)
            print(f"{name}: {len(pins[name]) - 1} products in {seconds[name]:.1f} s", file=sys.stderr)
    finally:
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)
    return pins, seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    parser.add_argument("--cases", help="comma-separated subset of the cases (default: all)")
    parser.add_argument("--out", help="write the pins of this run to this JSON file")
    parser.add_argument("--check", nargs="?", const="", metavar="PINS.json",
                        help="compare this run with a pin file (default: data/product_pins_<device>.json)")
    parser.add_argument("--compare", nargs=2, metavar=("A.json", "B.json"), help="compare two pin files; run nothing")
    parser.add_argument("--keep", help="run the cases in this (new) directory and keep their products")
    args = parser.parse_args(argv)
    if args.compare:
        a, b = (json.loads(Path(p).read_text()) for p in args.compare)
        lines = compare(a, b, args.device)
        print("\n".join(lines) if lines else "identical")
        return 1 if lines else 0
    names = args.cases.split(",") if args.cases else list(CASES)
    unknown = set(names) - set(CASES)
    if unknown:
        parser.error(f"unknown cases: {', '.join(sorted(unknown))}")
    os.environ.setdefault("WARP_CACHE_PATH", str(ROOT / ".warp-cache"))
    scene_cache = None
    if "FLIGHTSIM_CACHE" not in os.environ:  # never the user's ~/.cache/flightsim: a fresh one, removed
        scene_cache = tempfile.mkdtemp(prefix="flightsim-pins-scenes-")
        os.environ["FLIGHTSIM_CACHE"] = scene_cache
    keep = Path(args.keep) if args.keep else None
    try:
        started = time.perf_counter()
        pins, seconds = run_all(args.device, names, keep)
        total = time.perf_counter() - started
    finally:
        if scene_cache:
            shutil.rmtree(scene_cache, ignore_errors=True)
    print(f"{len(names)} cases in {total:.1f} s", file=sys.stderr)
    if args.out:
        record = {"_meta": {"commit": _commit(), "device": args.device, "cases_s": seconds,
                            "command": f"python3 tests/pin_products.py --device {args.device} --out {args.out}"},
                  **pins}
        Path(args.out).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    if args.check is not None:
        path = Path(args.check) if args.check else pin_path(args.device)
        pinned = json.loads(path.read_text())
        pinned = {k: v for k, v in pinned.items() if k in names}
        lines = compare(pinned, pins, args.device)
        print("\n".join(lines) if lines else f"every product of {len(names)} cases equals {path}")
        return 1 if lines else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
