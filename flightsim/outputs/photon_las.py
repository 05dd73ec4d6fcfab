"""Photon events of a photon-counting run as LAS 1.4 tiles (``photons/``), in the CRS the user picks.

Every detection is written, signal and noise alike: classification 1 (unclassified) for the pulse's
photons (the surface's or a corner cube's echo), 5 (high vegetation) for the leaves' of a canopy and 7 (low
noise) for background and dark counts — the
simulator's truth, as the discrete-return tiles take their classes from the scene; the ATL03-style
confidence of a classifier is in atl03.h5. Each point is the photon on its believed beam at c·t/2 (the
processing's geolocation, as photons.h5 and atl03.h5 have it).

CRS (``output.crs``): "" writes the scene's CRS; otherwise any projected CRS in metres that pyproj knows
and that has a WKT1 form (e.g. a UTM zone), as the tiles (flightsim.outputs.las_tiles.TileWriter) need.
Geographic CRSs are refused for LAS (config validation): latitude, longitude and height are in atl03.h5.
Coordinates: from the orbit platform around the Earth the local points go through their geodetic
latitude, longitude and WGS84 ellipsoidal height (flightsim.platforms.orbit.local_to_geodetic) into the
CRS — the true projection, not the tangent plane; elsewhere world = scene origin + local, re-projected
through latitude and longitude when output.crs differs from the scene's (heights as the scene's). Around
the Moon only "" is allowed and the points are the scene frame's.

Fields: gps_time the pulse's adjusted standard GPS time, point_source_id the flight line, scan_angle the
beam's angle from the local vertical (signed by its east component), intensity 0, beam_row/beam_col the
pixel as the discrete tiles number beams, range the one-way range c·t/2 [m], plane_id −1.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.transform import transform
from flightsim.core.settings import Settings, setting
from flightsim.outputs.las_format import gps_week_date
from flightsim.outputs.las_points import PointBatch
from flightsim.outputs.las_tiles import TileWriter
from flightsim.platforms.orbit import local_to_geodetic
from flightsim.scenes.scene import parse_crs

C_HALF = 299_792_458.0 / 2.0  # [m/s]
SIGNAL_CLASS, NOISE_CLASS, LEAF_CLASS = 1, 7, 5  # ASPRS: unclassified, low noise, high vegetation
LEAF_KIND = 3  # the photon kernel's truth flag of the leaves' photons (kernels/photon.py)
FOLDER = "photons"


@dataclass
class PhotonOutputSettings(Settings):
    """The photon events' LAS tiles and, from orbit, whether atl08.h5 is written (photons.h5 and atl03.h5 have no
    settings)."""

    table = "output"

    crs: str = setting("", "CRS of the photon LAS points: \"\" = the scene's, or any projected CRS in metres "
                       "(from the Earth only)")
    tile_size_m: int = setting(500, "side of a LAS tile", "m", range=(1, 100000))
    laz: bool = setting(False, "compress the tiles to LAZ")
    atl08: bool = setting(True, "from orbit, also atl08.h5: ATL08-like ground and canopy heights per 100 m segment "
                          "from atl03.h5's photons")

    def check(self, context) -> None:
        if not self.crs:
            return
        flight = context.settings("flight") if context is not None else None
        if flight is not None and flight.platform == "orbit" and flight.body != "earth":
            raise InputError("output.crs", self.crs, "\"\" (the scene's CRS) around the Moon")
        parse_crs(self.crs, field="output.crs")


def output_crs(crs: str, scene) -> pyproj.CRS:
    """The CRS the photon points are written in: ``crs`` (output.crs), or the scene's when it is ""."""
    return parse_crs(crs, field="output.crs") if crs else scene.crs


def photon_world(body: str | None, scene, chunk, crs: pyproj.CRS) -> np.ndarray:
    """(n, 3) coordinates [m] in ``crs`` of a PhotonChunk's photons, from orbit around ``body`` (None: not from orbit;
    see the module docstring)."""
    if body != "earth" and crs == scene.crs:
        return scene.local_to_world(chunk.points)
    lat, lon, h = photon_geodetic(chunk, body, scene)
    x, y = transform("EPSG:4326", crs, lon, lat)
    return np.column_stack([x, y, h])


def photon_geodetic(chunk, body: str | None, scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(latitude, longitude [deg], height [m]) of a PhotonChunk's photons (:func:`flightsim.platforms.orbit.
    local_to_geodetic`), worked out once and kept in the chunk: from orbit atl03.h5 and the LAS tiles both want them
    (each photon's values are those of a transform of it alone)."""
    if chunk.geodetic is None:
        chunk.geodetic = local_to_geodetic(body, scene, chunk.points)
    return chunk.geodetic


@register("output", "photons")
class PhotonLas:
    """Appends PhotonChunks to LAS tiles in ``directory/photons``; ``close()`` renames them into place."""

    settings = PhotonOutputSettings

    def __init__(self, directory: Path, output, scene, timing, beam_columns: int, body: str | None,
                 start_gps_time: float):
        """output: the [output] settings; beam_columns: as the discrete tiles number beams (the emitter's); body: the
        body orbited, None when not from orbit; start_gps_time: the flight's [s] (dates the tiles)."""
        self.scene, self.timing, self.body = scene, timing, body
        self.crs = output_crs(output.crs, scene)
        self.n = beam_columns
        self.writer = TileWriter(Path(directory) / FOLDER, self.crs, tile_size_m=output.tile_size_m,
                                 compress=output.laz, creation_date=gps_week_date(start_gps_time))
        self.tiles: dict[str, int] = {}

    def __call__(self, chunk) -> None:
        self.take(self.prepare(chunk))

    def prepare(self, chunk) -> list:
        """The tiles' records of a PhotonChunk (safe on several threads at once; :meth:`take` writes them)."""
        world = photon_world(self.body, self.scene, chunk, self.crs)
        d = chunk.directions.astype(np.float64)
        return self.writer.pack(PointBatch(
            x=world[:, 0], y=world[:, 1], z=world[:, 2],
            gps_time=self.timing.pulse_times(chunk.start_time, chunk.pulse),
            point_source_id=np.full(len(chunk), chunk.line_id, dtype=np.uint16),
            classification=np.select([chunk.kind == LEAF_KIND, chunk.signal], [LEAF_CLASS, SIGNAL_CLASS],
                                     NOISE_CLASS).astype(np.uint8),
            scan_angle_deg=np.degrees(np.arctan2(d[:, 0], -d[:, 2])).astype(np.float32),
            intensity=np.zeros(len(chunk), dtype=np.uint16),
            beam_row=(chunk.pixel // self.n).astype(np.uint8), beam_col=(chunk.pixel % self.n).astype(np.uint8),
            prism_angle_deg=np.degrees(self.timing.prism_angles(chunk.start_time, chunk.pulse)).astype(np.float32),
            range_m=(chunk.time_of_flight_s * C_HALF).astype(np.float32),
            plane_id=np.full(len(chunk), -1, dtype=np.int32)))

    def take(self, packed: list) -> None:
        """Write the records :meth:`prepare` made, in the order chunks came."""
        self.writer.write_packed(packed)

    def close(self) -> str:
        self.tiles = self.writer.close()
        return FOLDER

    def abort(self) -> None:
        self.writer.abort()
