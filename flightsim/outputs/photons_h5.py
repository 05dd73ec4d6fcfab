"""Photon events to HDF5 (h5py): one row per detection, the way photon-counting products (e.g. ICESat-2
ATL03) keep them. ``photons.h5``:

/photons/line_id            int32    flight line
/photons/pulse              int64    pulse index within its line
/photons/pixel              int32    detector pixel (beam) index
/photons/delta_time         float64  adjusted standard GPS time of the pulse [s]
/photons/time_of_flight_s   float64  round-trip time of flight from the exit point [s]
/photons/range_m            float64  one-way range, c·t/2 [m]
/photons/signal             uint8    truth: 1 the surface's echo, 2 a retroreflector's, 0 background or dark count
/photons/x, y, z            float64  the photon on its believed beam at range_m, world E, N, H of the scene CRS [m]

The file's attributes hold the run's config (TOML) and the flightsim version. It is written under a
temporary name and renamed when complete.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from flightsim.outputs.h5_product import H5Product

C = 299_792_458.0
FIELDS = {"line_id": np.int32, "pulse": np.int64, "pixel": np.int32, "delta_time": np.float64,
          "time_of_flight_s": np.float64, "range_m": np.float64, "signal": np.uint8,
          "x": np.float64, "y": np.float64, "z": np.float64}


class PhotonWriter:
    """Appends PhotonChunks to ``directory/photons.h5``; ``close()`` renames it into place. The datasets are made at
    the first photons, so that their HDF5 chunks fit the run (up to 2^16 rows: a reader of a large file reads a few
    chunks per column rather than one per thousand photons); a run without photons gets them empty at close."""

    def __init__(self, directory: Path, cfg_text: str, prf_hz: float, origin: np.ndarray, crs_wkt: str):
        self.product = H5Product(directory / "photons.h5", config_toml=cfg_text, crs_wkt=crs_wkt)
        self.prf_hz = prf_hz
        self.origin = np.asarray(origin, dtype=np.float64)
        self.count = 0
        self.signal = 0

    def __call__(self, chunk) -> None:
        self.take(self.prepare(chunk))

    def prepare(self, chunk) -> tuple[dict[str, np.ndarray], int]:
        """The columns of a PhotonChunk and its signal photons (safe on several threads at once; :meth:`take`
        writes them)."""
        n = len(chunk)
        columns = {"line_id": np.full(n, chunk.line_id, dtype=FIELDS["line_id"]), "pulse": chunk.pulse,
                   "pixel": chunk.pixel, "delta_time": chunk.start_time + chunk.pulse / self.prf_hz,
                   "time_of_flight_s": chunk.time_of_flight_s, "range_m": chunk.time_of_flight_s * (C / 2.0),
                   "signal": chunk.kind}
        for axis, name in enumerate("xyz"):  # each world coordinate made contiguous as it is made [m]
            columns[name] = chunk.points[:, axis] + self.origin[axis]
        signal = int(np.count_nonzero(chunk.signal))
        return {name: np.asarray(v, dtype=FIELDS[name]) for name, v in columns.items()}, signal

    def take(self, prepared: tuple[dict[str, np.ndarray], int]) -> None:
        """Append the columns :meth:`prepare` made, in the order chunks came."""
        columns, signal = prepared
        n = len(columns["pulse"])
        if n == 0:
            return
        self.product.append("photons", columns)
        self.count += n
        self.signal += signal

    def close(self) -> str:
        if self.count == 0:
            self.product.append("photons", {name: np.zeros(0, dtype) for name, dtype in FIELDS.items()})
        return self.product.close()

    def abort(self) -> None:
        self.product.abort()
