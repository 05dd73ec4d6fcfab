"""The LAS product of the points readout (discrete returns): each georeferencing model's LAS/LAZ tiles packed on
the device, the plane-fit (or, on curved ground, patch-fit) scores, and the COPC files and patch raster when asked
for."""
from __future__ import annotations

from pathlib import Path

from flightsim.core.constants import MODELS
from flightsim.core.registry import register
from flightsim.engine.readouts.points import Points
from flightsim.engine.world import edge_buffer_m
from flightsim.outputs.consumers import PatchStatistics, PlaneStatistics, patch_grid

PATCH_RASTER = "patch_rms.tif"
"""Per-patch fit RMS of a LAS run over curved ground (:class:`flightsim.outputs.consumers.PatchStatistics`)."""


@register("product", "points")
class LasProduct:
    """Tiles per model (``<model>/<E>_<N>.las``), scores, COPC and the patch raster."""

    kind = "points"
    files = (*MODELS, *(f"{m}.copc.laz" for m in MODELS), PATCH_RASTER)

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

    def __call__(self, returns) -> None:
        for consumer in self.consumers:
            consumer(returns)

    def close(self, counts) -> dict:
        """Finish the tiles, the COPC files and the patch raster; the summary's fields."""
        from flightsim.outputs.copc import write_run_copc

        tiles = self.las.close()
        copc = write_run_copc(self.directory, tiles) if self.cfg.output.copc else None
        patches = self.fits.write(self.directory / PATCH_RASTER, self.scene) if self.fits is not None else None
        models = self.tracer.models
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
