"""tests/compare_products.py, the check that two runs' products are the same bit for bit, finds each kind of
difference and nothing else."""
from __future__ import annotations

import shutil

import h5py
import numpy as np

from compare_products import differences


def _run(folder, rx=(1.0, np.nan, 3.0), attr=1.5, created="2026-12-07"):
    folder.mkdir()
    with h5py.File(folder / "waveforms.h5", "w") as f:
        f["BEAM0000/rxwaveform"] = np.array(rx)
        f["BEAM0000"].attrs["pulse_sigma_s"] = attr
        f.attrs["date_created"] = created
    (folder / "returns.las").write_bytes(b"LASF" + bytes(range(40)))
    (folder / "summary.json").write_text(f'{{"wall_s": {attr}}}')
    return folder


def test_the_same_products_are_found_the_same_and_each_difference_named(tmp_path):
    a = _run(tmp_path / "a")
    assert differences(a, _run(tmp_path / "b", created="2027-01-01")) == []  # NaN = NaN; times and summary aside
    assert differences(a, _run(tmp_path / "c", rx=(1.0, np.nan, 3.0000000000000004))) == [
        "waveforms.h5: BEAM0000/rxwaveform: values differ"]  # one ulp
    assert differences(a, _run(tmp_path / "d", attr=1.25)) == ["waveforms.h5: BEAM0000@pulse_sigma_s: differs"]
    e = _run(tmp_path / "e")
    (e / "returns.las").write_bytes(b"LASF" + bytes(range(39)) + b"\x00")
    (e / "l2a.h5").write_bytes(b"")
    assert differences(a, e) == ["l2a.h5: in one run only", "returns.las: bytes differ"]
    f = tmp_path / "f"
    shutil.copytree(a, f)
    with h5py.File(f / "waveforms.h5", "a") as h5:
        h5["BEAM0000/extra"] = np.zeros(2)
    assert differences(a, f) == ["waveforms.h5: BEAM0000/extra: in one file only"]
