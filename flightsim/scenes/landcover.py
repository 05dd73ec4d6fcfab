"""Land cover: a raster of ASPRS class codes classifying the triangles of a terrain scene, and the
reflectance of each class.

The raster (``scene.landcover``, a GeoTIFF in the DEM's CRS, on any grid) is sampled at each triangle's
centroid, nearest neighbour (the pixel holding it). Its codes are ASPRS classes, each with a Lambertian
reflectance at near-infrared wavelengths:

| code | class | reflectance |
| --- | --- | --- |
| 1 | unclassified | 0.25 |
| 2 | ground | 0.25 |
| 3, 4, 5 | low, medium, high vegetation | 0.45 |
| 6 | building | 0.35 |
| 9 | water | 0.05 |
| 11 | road surface | 0.15 |

Triangles whose centroid falls outside the raster or on a nodata pixel keep their class (the DEM's
ground, 2). The classes reach the LAS classification of every return, and their reflectance
(:func:`triangle_reflectance`) becomes the scene's per-triangle ``Scene.reflectance``, which the
photon and waveform detectors read at each hit in place of the run's ``photon.reflectance`` and
``waveform.reflectance`` (the photon detector's lidar equation takes ρ itself; the waveform's eq. 1
takes its backscatter f = ρ/π).
"""
from __future__ import annotations

import numpy as np

from flightsim.core.errors import InputError
from flightsim.scenes.scene import Scene

REFLECTANCE = {1: 0.25, 2: 0.25, 3: 0.45, 4: 0.45, 5: 0.45, 6: 0.35, 9: 0.05, 11: 0.15}
"""Lambertian reflectance of each ASPRS class a land-cover raster may hold."""

MAX_PIXELS = 1 << 30
CHUNK = 1 << 22  # triangles sampled at a time


def landcover_classes(scene: Scene, path: str) -> np.ndarray:
    """(T,) uint8 ASPRS class of each triangle of ``scene``: the land-cover raster's code at its centroid,
    else its present class."""
    from flightsim.scenes.raster import read_raster

    cover = read_raster(path, "scene.landcover", "a GeoTIFF of ASPRS class codes", MAX_PIXELS)
    if not cover.crs.equals(scene.crs, ignore_axis_order=True):
        raise InputError("scene.landcover", path, f"a raster in the DEM's CRS ({scene.crs.name}), not {cover.crs.name}")
    codes = np.unique(cover.values[cover.valid])
    unknown = codes[~np.isin(codes, list(REFLECTANCE))]
    if len(unknown):
        raise InputError("scene.landcover", path, f"class codes in {sorted(REFLECTANCE)} or nodata "
                                                  f"(this raster holds {unknown[0]})")
    classes = scene.classification.copy()
    for start in range(0, len(scene.triangles), CHUNK):
        corners = scene.triangles[start:start + CHUNK]
        east, north = (sum(scene.vertices[corners[:, k], axis] for k in range(3)) / 3.0 + scene.origin[axis]
                       for axis in (0, 1))  # the centroids, world [m]
        row, col, inside = cover.pixel_of(east, north)
        known = inside & cover.valid[row, col]
        part = classes[start:start + CHUNK]
        part[known] = cover.values[row[known], col[known]]
    return classes


def triangle_reflectance(scene: Scene) -> np.ndarray:
    """(T,) float32 Lambertian reflectance of each triangle, from its class (unlisted classes: 0.25)."""
    table = np.full(256, REFLECTANCE[1], dtype=np.float32)
    table[list(REFLECTANCE)] = list(REFLECTANCE.values())
    return table[scene.classification]
