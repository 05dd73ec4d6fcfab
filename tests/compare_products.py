"""Two runs' products compared: every HDF5 file dataset by dataset (values with their NaNs, dtype, shape) and
attribute by attribute, every other product file byte for byte; run.toml and summary.json (times, commit) left out.

    python3 tests/compare_products.py RUN_A RUN_B

Prints one line per difference (or ``same``) and exits 1 when any is found; what a speed-up that must leave every
number as it was is checked with (results/profile-experiments.md).
"""
from __future__ import annotations

import filecmp
import sys
from pathlib import Path

import h5py
import numpy as np

SKIPPED = {"run.toml", "summary.json"}  # the run's own record: its times and commit differ from run to run
TIMESTAMPS = {"date_created", "created", "software_version", "flightsim_version", "commit"}  # attributes as well


def differences(a: Path, b: Path) -> list[str]:
    """Each difference between the products of the run directories ``a`` and ``b`` (empty: the same)."""
    names = {p.relative_to(a) for p in a.rglob("*") if p.is_file()} | {p.relative_to(b) for p in b.rglob("*")
                                                                        if p.is_file()}
    found = []
    for name in sorted(n for n in names if n.name not in SKIPPED):
        if not (a / name).is_file() or not (b / name).is_file():
            found.append(f"{name}: in one run only")
        elif name.suffix == ".h5":
            found += [f"{name}: {d}" for d in _h5_differences(a / name, b / name)]
        elif not filecmp.cmp(a / name, b / name, shallow=False):
            found.append(f"{name}: bytes differ")
    return found


def _h5_differences(a: Path, b: Path) -> list[str]:
    found = []
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        def visit(name: str, obj) -> None:
            other = fb.get(name)
            if other is None or isinstance(obj, h5py.Dataset) != isinstance(other, h5py.Dataset):
                found.append(f"{name}: in one file only")
                return
            if isinstance(obj, h5py.Dataset) and not _same(obj[()], other[()]):
                found.append(f"{name}: values differ")
            for key in set(obj.attrs) | set(other.attrs):
                if key not in TIMESTAMPS and not _same(obj.attrs.get(key), other.attrs.get(key)):
                    found.append(f"{name}@{key}: differs")
        fa.visititems(visit)
        fb.visititems(lambda name, obj: None if name in fa else found.append(f"{name}: in one file only"))
    return found


def _same(x, y) -> bool:
    x, y = np.asarray(x), np.asarray(y)
    if x.dtype != y.dtype or x.shape != y.shape:
        return False
    return bool(np.array_equal(x, y, equal_nan=x.dtype.kind in "fc"))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    found = differences(Path(sys.argv[1]), Path(sys.argv[2]))
    print("\n".join(found) if found else "same")
    sys.exit(1 if found else 0)
