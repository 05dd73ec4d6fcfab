"""Photon events as an ATL03-style HDF5 product (h5py), for photon-counting runs: per beam a group
``gtN`` (N = beam + 1) the way ICESat-2's ATL03 lays out its ground tracks. ``atl03.h5``:

gtN/heights/delta_time        float64  adjusted standard GPS time of the photon's shot [s]
gtN/heights/lat_ph, lon_ph    float64  geodetic latitude, longitude of the photon [deg]
gtN/heights/h_ph              float64  its height [m]: above the WGS84 ellipsoid (or the Moon's sphere) for
                                       the orbit platform, else the scene's height
gtN/heights/signal_conf_ph    int8     ATL03's confidence 0 noise, 1 buffer, 2 low, 3 medium, 4 high, from
                                       the photons' height histograms in 20 m along-track segments against the
                                       background of the telemetry band (flightsim.scoring.signal_finder),
                                       not from the truth; one surface type
gtN/heights/truth_kind        int8     the simulator's truth: 0 background or dark count, 1 the surface's
                                       echo, 2 a corner cube's, 3 leaves' (a canopy)
gtN/heights/ph_id_pulse       int64    pulse index within its line
gtN/heights/dist_ph_along     float64  horizontal distance from the line's first photon [m]
gtN/geolocation/delta_time, reference_photon_lat, reference_photon_lon, reference_photon_h: per shot
                                       that has photons, the beam's footprint centre (its believed axis
                                       where it meets the scene's ground height)

Attributes: ``config_toml``, ``flightsim``. Geolocation is the processing's (the believed instrument), as
the product's is. Written under a temporary name and renamed when complete; signal_conf_ph is computed
at close, reading each beam's heights back block by block (memory bounded by the block, not the run).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from flightsim.outputs.h5_product import H5Product
from flightsim.platforms.orbit import local_to_geodetic
from flightsim.scoring.signal_finder import SignalFinder


class Atl03Writer:
    """Appends PhotonChunks to ``directory/atl03.h5``; ``close()`` renames it into place."""

    def __init__(self, directory: Path, body: str, cfg_text: str, prf_hz: float, scene):
        """body: the body orbited (earth, moon)."""
        self.product = H5Product(directory / "atl03.h5", config_toml=cfg_text)
        self.body, self.prf_hz, self.scene = body, prf_hz, scene
        self.first: dict[tuple, np.ndarray] = {}  # each (line, beam)'s first photon (local), for dist_ph_along
        self.count = 0

    def __call__(self, chunk) -> None:
        for beam in np.unique(chunk.pixel):
            rows = np.flatnonzero(chunk.pixel == beam)
            self._heights(f"gt{int(beam) + 1}", chunk, rows)
            self._geolocation(f"gt{int(beam) + 1}", chunk, rows)
        self.count += len(chunk)

    def _heights(self, group: str, chunk, rows: np.ndarray) -> None:
        lat, lon, h = local_to_geodetic(self.body, self.scene, chunk.points[rows])
        start = self.first.setdefault((chunk.line_id, group), chunk.points[rows[0]].copy())
        along = np.linalg.norm(chunk.points[rows, :2] - start[:2], axis=1)
        self.product.append(f"{group}/heights", {
            "delta_time": chunk.start_time + chunk.pulse[rows] / self.prf_hz, "lat_ph": lat, "lon_ph": lon, "h_ph": h,
            "truth_kind": chunk.kind[rows].astype(np.int8), "ph_id_pulse": chunk.pulse[rows],
            "dist_ph_along": along})

    def _geolocation(self, group: str, chunk, rows: np.ndarray) -> None:
        pulses, first = np.unique(chunk.pulse[rows], return_index=True)
        i = rows[first]
        d = chunk.directions[i].astype(np.float64)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        start = chunk.points[i] - (chunk.time_of_flight_s[i] * 149896229.0)[:, None] * d  # the beam's exit point
        t = (self.scene.ground_z - start[:, 2]) / d[:, 2]
        lat, lon, h = local_to_geodetic(self.body, self.scene, start + t[:, None] * d)
        self.product.append(f"{group}/geolocation", {
            "delta_time": chunk.start_time + pulses / self.prf_hz, "reference_photon_lat": lat,
            "reference_photon_lon": lon, "reference_photon_h": h})

    def close(self) -> str:
        for group in self.product.file:
            self._confidence(self.product.file[f"{group}/heights"])
        return self.product.close()

    @staticmethod
    def _confidence(heights) -> None:
        """signal_conf_ph of one beam's heights group, by the signal finder over its photons."""
        n = heights["h_ph"].shape[0]
        conf = heights.create_dataset("signal_conf_ph", shape=(n,), dtype=np.int8, chunks=True)

        def read(lo: int, hi: int) -> tuple:
            return heights["dist_ph_along"][lo:hi], heights["h_ph"][lo:hi], heights["ph_id_pulse"][lo:hi]

        def write(lo: int, values: np.ndarray) -> None:
            conf[lo:lo + len(values)] = values

        SignalFinder().classify_stream(n, read, write)

    def abort(self) -> None:
        self.product.abort()
