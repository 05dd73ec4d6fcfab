"""H5Product's appends: a compressed column (of numbers, or of rows of them) deflated on threads and stored chunk by
chunk reads back as HDF5's own filters would have stored it, with the filters declared, whatever the rows before it;
an uncompressed one's whole chunks stored as they are hold the bytes HDF5 would have stored."""
import zlib

import h5py
import numpy as np
import pytest

from flightsim.outputs import h5_product
from flightsim.outputs.h5_product import H5Product

ROWS = h5_product.ROWS_PER_CHUNK


def _appends(rng) -> list[np.ndarray]:
    """Appends to one column: a first one of 1.5 chunks (HDF5's filters), then ones that start mid-chunk and at a
    boundary, long enough for the threads, one of them float32 into the float64 column, one tiny."""
    return [rng.normal(size=ROWS * 3 // 2), rng.normal(size=ROWS * 5 + 17), rng.normal(size=ROWS * 4 - 17 + ROWS),
            rng.normal(size=ROWS * 6).astype(np.float32), rng.normal(size=3)]


def _chunk_writes(monkeypatch) -> list[tuple[int, bool]]:
    """The (first row, deflated) of every append that writes its whole chunks by hand, as the appends make them."""
    calls = []
    original = h5_product._write_chunks
    monkeypatch.setattr(h5_product, "_write_chunks", lambda d, n, v, deflate: calls.append((n, deflate))
                        or original(d, n, v, deflate))
    return calls


@pytest.mark.parametrize("dtype", [np.float64, np.int8, np.int32])
def test_compressed_appends_read_back_as_written(tmp_path, dtype, monkeypatch):
    rng = np.random.default_rng(7)
    parts = [(p * 40).clip(-100, 100).astype(dtype) if np.dtype(dtype).kind == "i" else p for p in _appends(rng)]
    by_hand = _chunk_writes(monkeypatch)
    product = H5Product(tmp_path / "a.h5")
    for part in parts:
        product.append("g", {"x": part}, compress=True)
    product.close()
    assert by_hand == [(ROWS * 3 // 2, True), (ROWS * 13 // 2 + 17, True), (ROWS * 23 // 2, True)]  # the three long
    with h5py.File(tmp_path / "a.h5") as f:
        x = f["g/x"]
        assert (x.compression, x.shuffle, x.chunks) == ("gzip", True, (ROWS,))
        expected = np.concatenate([p.astype(x.dtype) for p in parts])
        assert x.dtype == np.dtype(dtype) and x.shape == expected.shape
        np.testing.assert_array_equal(x[:], expected)
        np.testing.assert_array_equal(x[ROWS * 7 - 5:ROWS * 7 + 5], expected[ROWS * 7 - 5:ROWS * 7 + 5])


def test_hand_deflated_chunks_match_hdf5s_filters(tmp_path):
    """Every chunk stored by hand decompresses to the bytes HDF5's own shuffle and gzip filters stored."""
    values = np.random.default_rng(3).normal(size=ROWS * 4 + 100)
    product = H5Product(tmp_path / "b.h5")
    product.append("g", {"x": values}, compress=True)
    product.close()
    with h5py.File(tmp_path / "c.h5", "w") as f:
        f.create_dataset("x", data=values, chunks=(ROWS,), maxshape=(None,), compression="gzip", shuffle=True)
    with h5py.File(tmp_path / "b.h5") as ours, h5py.File(tmp_path / "c.h5") as hdf5:
        for k in range(5):
            mask_ours, chunk_ours = ours["g/x"].id.read_direct_chunk((k * ROWS,))
            mask_hdf5, chunk_hdf5 = hdf5["x"].id.read_direct_chunk((k * ROWS,))
            assert mask_ours == mask_hdf5 == 0
            assert zlib.decompress(chunk_ours) == zlib.decompress(chunk_hdf5)


@pytest.mark.parametrize("dtype", [np.float64, np.int8, np.uint16])
def test_uncompressed_appends_store_whole_chunks_as_hdf5_would(tmp_path, dtype, monkeypatch):
    """An uncompressed 1-D column's long appends store their whole chunks by hand (the rows up to a chunk boundary
    and the short appends through HDF5): it reads back as written, and every chunk holds HDF5's own bytes."""
    rng = np.random.default_rng(11)
    parts = [(p * 40).clip(0, 100).astype(dtype) for p in _appends(rng)]
    by_hand = _chunk_writes(monkeypatch)
    product = H5Product(tmp_path / "p.h5")
    for part in parts:
        product.append("g", {"x": part})
    product.close()
    assert by_hand == [(ROWS * 3 // 2, False), (ROWS * 13 // 2 + 17, False), (ROWS * 23 // 2, False)]
    expected = np.concatenate(parts).astype(dtype)
    with h5py.File(tmp_path / "q.h5", "w") as f:
        f.create_dataset("x", data=expected, chunks=(ROWS,), maxshape=(None,))
    with h5py.File(tmp_path / "p.h5") as ours, h5py.File(tmp_path / "q.h5") as hdf5:
        x = ours["g/x"]
        assert (x.compression, x.chunks, x.dtype) == (None, (ROWS,), np.dtype(dtype))
        np.testing.assert_array_equal(x[:], expected)
        for k in range(len(expected) // ROWS):  # the whole chunks (the last one's padding is no row)
            assert x.id.read_direct_chunk((k * ROWS,)) == hdf5["x"].id.read_direct_chunk((k * ROWS,))


def test_big_endian_string_and_column_chunked_appends_take_hdf5s_path(tmp_path, monkeypatch):
    monkeypatch.setattr(h5_product, "_write_chunks", lambda *a: pytest.fail("written by hand"))
    product = H5Product(tmp_path / "d.h5")
    rows = np.arange(ROWS * 8 * 2, dtype=np.float32).reshape(-1, 2)
    big = np.arange(ROWS * 8, dtype=">f8")
    names = np.array([b"ab", b"c"] * (ROWS * 4))
    product.file.create_dataset("h/wide", shape=(0, 2), maxshape=(None, 2), dtype=np.float32, chunks=(ROWS, 1),
                                compression="gzip", shuffle=True)  # a chunk holds a column's part, not whole rows
    product.append("g", {"big": big, "name": names}, compress=False)
    product.append("h", {"wide": rows}, compress=True)
    product.close()
    with h5py.File(tmp_path / "d.h5") as f:
        np.testing.assert_array_equal(f["h/wide"][:], rows)
        assert f["g/big"].dtype == np.dtype(">f8")
        np.testing.assert_array_equal(f["g/big"][:], big)
        np.testing.assert_array_equal(f["g/name"][:], names)


@pytest.mark.parametrize("compress", [True, False])
def test_rows_of_many_values_store_whole_chunks_of_rows_as_hdf5_would(tmp_path, monkeypatch, compress):
    """Rows of 101 float32 (l2a.h5's rh): chunks of whole rows holding as many values as a 1-D chunk; the long appends
    store their whole chunks by hand, and every chunk holds the bytes HDF5's own writes (and filters) store."""
    rng = np.random.default_rng(5)
    rows = ROWS // 101  # a chunk's rows
    parts = [rng.normal(size=(n, 101)).astype(np.float32) for n in (rows + 7, rows * 6 + 3, 5, rows * 5)]
    by_hand = _chunk_writes(monkeypatch)
    product = H5Product(tmp_path / "r.h5")
    for part in parts:
        product.append("g", {"rh": part}, compress=compress)
    product.close()
    assert by_hand == [(rows + 7, compress), (rows * 7 + 15, compress)]
    expected = np.concatenate(parts)
    with h5py.File(tmp_path / "s.h5", "w") as f:
        f.create_dataset("rh", data=expected, chunks=(rows, 101), maxshape=(None, 101),
                         **({"compression": "gzip", "shuffle": True} if compress else {}))
    with h5py.File(tmp_path / "r.h5") as ours, h5py.File(tmp_path / "s.h5") as hdf5:
        x = ours["g/rh"]
        assert x.chunks == (rows, 101) and (x.compression, x.shuffle) == (("gzip", True) if compress else (None, False))
        np.testing.assert_array_equal(x[:], expected)
        for k in range(len(expected) // rows):  # the whole chunks (the last one's padding is no row)
            (mask_ours, ours_bytes), (mask_hdf5, hdf5_bytes) = (d.id.read_direct_chunk((k * rows, 0))
                                                                for d in (x, hdf5["rh"]))
            assert mask_ours == mask_hdf5 == 0
            if compress:
                ours_bytes, hdf5_bytes = zlib.decompress(ours_bytes), zlib.decompress(hdf5_bytes)
            assert ours_bytes == hdf5_bytes


@pytest.mark.parametrize("compress", [True, False])
def test_a_dataset_with_another_fill_value_takes_hdf5s_path(tmp_path, monkeypatch, compress):
    """A chunk stored by hand pads with 0; a dataset whose fill value is not 0 is left to HDF5."""
    monkeypatch.setattr(h5_product, "_write_chunks", lambda *a: pytest.fail("written by hand"))
    product = H5Product(tmp_path / "e.h5")
    product.file.create_dataset("g/x", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(ROWS,),
                                fillvalue=-9.0, **({"compression": "gzip", "shuffle": True} if compress else {}))
    values = np.arange(ROWS * 5 + 3, dtype=np.float64)
    product.append("g", {"x": values}, compress=compress)
    product.close()
    with h5py.File(tmp_path / "e.h5") as f:
        np.testing.assert_array_equal(f["g/x"][:], values)


def test_appends_of_the_datasets_type_take_the_low_level_write_and_read_back_as_written(tmp_path, monkeypatch):
    """Values of a dataset's own dtype and row shape (booleans, small ints, floats, fixed strings, rows of two) are
    written through h5py's low-level write; others (another dtype) through h5py's own assignment: every append reads
    back as written, as h5py's own writes of the same values in another file."""
    calls = []
    original = h5_product._write_rows
    monkeypatch.setattr(h5_product, "_write_rows", lambda d, n, v: calls.append(d.name) or original(d, n, v))
    rng = np.random.default_rng(9)
    parts = [{"flag": rng.random(n) < 0.5, "small": rng.integers(-5, 5, n).astype(np.int8),
              "x": rng.normal(size=n).astype(np.float32), "name": np.array([b"ab", b"c"] * (n // 2)),
              "rows": rng.normal(size=(n, 2))} for n in (10, 4, 1000)]
    parts.append({**parts[-1], "x": rng.normal(size=1000)})  # float64 into the float32 column: h5py's assignment
    product = H5Product(tmp_path / "f.h5")
    for part in parts:
        product.append("g", part)
    product.close()
    assert len(calls) == 4 * 5 - 1  # every append but the float64 one
    with h5py.File(tmp_path / "f.h5") as ours, h5py.File(tmp_path / "h.h5", "w") as theirs:
        for name in parts[0]:
            expected = np.concatenate([part[name] for part in parts]).astype(ours[f"g/{name}"].dtype)
            theirs.create_dataset(name, data=expected)
            np.testing.assert_array_equal(ours[f"g/{name}"][:], expected)
            np.testing.assert_array_equal(ours[f"g/{name}"][:], theirs[name][:])
            assert ours[f"g/{name}"].dtype == theirs[name].dtype
