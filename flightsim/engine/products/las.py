"""The LAS product of the points readout (discrete returns): each georeferencing model's LAS/LAZ tiles packed on
the device, the plane-fit (or, on curved ground, patch-fit) scores, the COPC files and patch raster when asked
for, and over a canopy the canopy height model ``chm.tif``."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from flightsim.core.constants import MODELS
from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.engine.readouts.points import Points
from flightsim.engine.world import edge_buffer_m
from flightsim.outputs.consumers import PatchStatistics, PlaneStatistics, patch_grid

PATCH_RASTER = "patch_rms.tif"
"""Per-patch fit RMS of a LAS run over curved ground (:class:`flightsim.outputs.consumers.PatchStatistics`)."""
CHM_RASTER = "chm.tif"
"""Canopy height model of a LAS run over a scene with a canopy (cells of ``output.chm_m``; :func:`write_chm`)."""
CHM_COLUMNS = ("x", "y", "z", "return_number", "classification")  # what the CHM reads of each tile


@register("product", "points")
class LasProduct:
    """Tiles per model (``<model>/<E>_<N>.las``), scores, COPC, the patch raster and the canopy height model."""

    kind = "points"
    files = (*MODELS, *(f"{m}.copc.laz" for m in MODELS), PATCH_RASTER, CHM_RASTER)

    @staticmethod
    def setup_kernels(cfg) -> list:
        """The kernels the tracer launches for this product while it is made: the plane boundaries' grid of an edge
        buffer (automatic or set), for :func:`flightsim.engine.run.compile_setup`."""
        if cfg.scoring.edge_buffer_m == 0.0:
            return []
        from kernels import edges

        return [(edges.near_cells, None)]

    def __init__(self, cfg, scene):
        self.cfg, self.scene = cfg, scene
        self.buffer = edge_buffer_m(cfg)
        if self.buffer > 0.0:
            scene.prefetch_boundary_segments()  # found while the flight is planned and the BVHs built
        self.patches = patch_grid(scene, cfg.scoring.patch_m)

    @property
    def tracer_options(self) -> dict:
        return {"with_truth": self.cfg.output.position_error, "edge_buffer_m": self.buffer}

    def open(self, tracer, directory: Path, cfg_text: str) -> None:
        from flightsim.outputs.device_las import DeviceLasOutput

        self.tracer, self.directory = tracer, directory
        self.las = DeviceLasOutput(directory, self.cfg.output, tracer, self.buffer > 0.0, self.cfg.flight.start_gps_time)
        self.planes = PlaneStatistics(tracer, self.buffer) if self.scene.planar else None  # curved: patches only
        self.fits = PatchStatistics(tracer, self.patches, self.buffer) if self.patches is not None else None
        self.consumers = [c for c in (self.planes, self.fits, self.las) if c is not None]

    def readout(self) -> Points:
        return Points(on_device=True)

    def kernels_needed(self, tracer) -> list:
        return [k for consumer in self.consumers for k in consumer.kernels_needed(tracer)]

    def __call__(self, returns) -> None:
        for consumer in self.consumers:
            consumer(returns)

    def close(self, counts) -> dict:
        """Finish the tiles, the COPC files, the patch raster and the CHM; the summary's fields."""
        from flightsim.outputs.copc import write_run_copc

        tiles = self.las.close()
        copc = write_run_copc(self.directory, tiles) if self.cfg.output.copc else None
        patches = self.fits.write(self.directory / PATCH_RASTER, self.scene) if self.fits is not None else None
        models = self.tracer.models
        first = self.cfg.output.models[0]
        chm = self.scene.canopy is not None and self.cfg.output.chm_m > 0.0
        chm = write_chm(self.directory, first, tiles[first], self.cfg.output.chm_m, self.scene.crs) if chm else None
        return {
            "points": {model: counts.returns for model in models},
            "tir_dropped": counts.tir_dropped,
            "misses": counts.misses,
            **(self._canopy(counts) if self.tracer.returns_per_beam > 1 else {}),
            "rms_m": self.planes.rms_m() if self.planes is not None else {model: None for model in models},
            **({"patches": patches} if patches is not None else {}),
            "edge_buffer_m": self.buffer,
            **({"apex_angle_deg": self.cfg.risley.apex_angle_deg} if self.cfg.instrument.deflector == "risley" else {}),
            "tiles": tiles,
            **({"copc": copc} if copc is not None else {}),
            **({"chm": chm} if chm is not None else {}),
        }

    @staticmethod
    def _canopy(counts) -> dict:
        """What a canopy did to the beams: beams_fired = beams_returned + dark + tir_dropped + misses, and the
        points are the beams' returns, leaves' and surfaces'."""
        return {"beams_returned": counts.beams_returned, "leaf_returns": counts.leaf_returns,
                "surface_returns": counts.returns - counts.leaf_returns, "dark": counts.dark}

    def empty(self, counts) -> bool:
        return counts.returns == 0

    def abort(self) -> None:
        self.las.abort()


def write_chm(directory: Path, model: str, tiles: dict[str, int], cell_m: float, crs) -> dict:
    """``directory/chm.tif``, the canopy height model (:func:`flightsim.outputs.chm.chm_from_points`: DTM from the
    ground points, class 2; DSM from the first returns) on cells of ``cell_m`` [m] of the finished ``tiles``
    ({name: points}) of ``model``, read back with laspy (only x, y, z, return number and class, chunk by chunk) and
    written in ``crs``. Summary fields: ``file`` (None, with the ``reason``, where the points give no CHM: none, none
    of class 2, or more cells than a CHM may hold), ``model``, ``cell_m``, ``points``."""
    import laspy

    from flightsim.outputs.chm import chm_from_points, write_chm_tif

    parts = {name: [] for name in CHM_COLUMNS}
    for name in sorted(tiles):
        with laspy.open(directory / model / name) as reader:
            for points in reader.chunk_iterator(1 << 20):
                for column in CHM_COLUMNS:
                    parts[column].append(np.asarray(points[column]))
    x, y, z, returns, classes = (np.concatenate(parts[c]) if parts[c] else np.zeros(0) for c in CHM_COLUMNS)
    fields = {"model": model, "cell_m": cell_m, "points": len(x)}
    if not len(x):
        return {"file": None, "reason": "no points", **fields}
    try:  # none of class 2, or too many cells: no CHM, the run's other products stand
        grids, transform = chm_from_points(x, y, z, returns.astype(np.uint8), classes.astype(np.uint8), cell_m)
    except InputError as error:
        return {"file": None, "reason": str(error), **fields}
    return {"file": write_chm_tif(directory / CHM_RASTER, grids.chm, transform, crs).name, **fields}
