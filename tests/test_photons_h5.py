"""photons.h5's writer: its columns from the chunks handed to it, the datasets made at the first photons (their
HDF5 chunks as large as the first chunk allows, up to 2^16 rows), and the datasets of a run without photons."""
from __future__ import annotations

import h5py
import numpy as np

from flightsim.engine.readouts.photons import PhotonChunk
from flightsim.outputs.h5_product import ROWS_PER_CHUNK
from flightsim.outputs.photons_h5 import FIELDS, PhotonWriter

C_HALF = 299_792_458.0 / 2.0


def _chunk(first_pulse: int, n: int, rng) -> PhotonChunk:
    kind = rng.integers(0, 3, n).astype(np.int8)
    return PhotonChunk(3, 100.0, np.arange(first_pulse, first_pulse + n, dtype=np.int64),
                       rng.integers(0, 6, n).astype(np.int32), rng.uniform(1e-6, 4e-6, n), kind > 0, kind,
                       rng.normal(0.0, 50.0, (n, 3)), np.tile(np.float32([0.0, 0.0, -1.0]), (n, 1)))


def test_photon_columns_from_chunks_in_chunks_of_the_first_size(tmp_path):
    rng = np.random.default_rng(2)
    chunks = [_chunk(0, 70_000, rng), _chunk(70_000, 1_234, rng)]
    origin = np.array([500_000.0, 4_000_000.0, 10.0])
    writer = PhotonWriter(tmp_path, "", 10_000.0, origin, "")
    for chunk in chunks:
        writer(chunk)
    assert writer.close() == "photons.h5"
    with h5py.File(tmp_path / "photons.h5") as f:
        g = f["photons"]
        assert sorted(g) == sorted(FIELDS)
        assert all(g[name].chunks == (ROWS_PER_CHUNK,) and g[name].dtype == FIELDS[name] for name in FIELDS)
        pulse = np.concatenate([c.pulse for c in chunks])
        tof = np.concatenate([c.time_of_flight_s for c in chunks])
        points = np.concatenate([c.points for c in chunks])
        np.testing.assert_array_equal(g["pulse"][:], pulse)
        np.testing.assert_array_equal(g["line_id"][:], np.full(len(pulse), 3))
        np.testing.assert_array_equal(g["delta_time"][:], 100.0 + pulse / 10_000.0)
        np.testing.assert_array_equal(g["range_m"][:], tof * C_HALF)
        np.testing.assert_array_equal(g["signal"][:], np.concatenate([c.kind for c in chunks]))
        np.testing.assert_array_equal(np.column_stack([g["x"][:], g["y"][:], g["z"][:]]), points + origin)
    assert (writer.count, writer.signal) == (len(pulse), sum(int(c.signal.sum()) for c in chunks))


def test_a_small_first_chunk_keeps_small_chunks_and_no_photons_keep_empty_columns(tmp_path):
    rng = np.random.default_rng(3)
    (tmp_path / "small").mkdir()
    small = PhotonWriter(tmp_path / "small", "", 10_000.0, np.zeros(3), "")
    small(_chunk(0, 10, rng))
    small.close()
    with h5py.File(tmp_path / "small" / "photons.h5") as f:
        assert f["photons/x"].chunks == (1024,) and len(f["photons/x"]) == 10  # a short run's file stays small
    (tmp_path / "none").mkdir()
    none = PhotonWriter(tmp_path / "none", "", 10_000.0, np.zeros(3), "")
    none(_chunk(0, 0, rng))
    none.close()
    with h5py.File(tmp_path / "none" / "photons.h5") as f:
        assert {name: (f["photons"][name].shape, f["photons"][name].dtype) for name in f["photons"]} == {
            name: ((0,), np.dtype(dtype)) for name, dtype in FIELDS.items()}
