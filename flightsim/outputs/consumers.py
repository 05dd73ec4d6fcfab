"""Consumers of simulated returns: LAS tiles per georeferencing model, and per-plane statistics."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from flightsim import __version__
from flightsim.core.config import RunConfig
from flightsim.outputs.las_tiles import PointBatch, TileWriter, gps_week_date
from flightsim.scoring.planes import PlaneMoments, pooled_rms
from flightsim.scenes.scene import Scene
from flightsim.engine.simulate import ReturnChunk
from trajectories import PulseTiming


class LasOutput:
    """Writes each georeferencing model's points to its own tile set, ``DIR/<model>/<tile>.las``.

    Intensity is the Lambertian cos(incidence) scaled to 16 bits; gps_time is the pulse time.
    """

    def __init__(self, directory: Path, cfg: RunConfig, scene: Scene, timing: PulseTiming, edge_distance: bool,
                 plane_ids: np.ndarray | None = None):
        """plane_ids: the plane id written for each triangle (default: the scene's own)."""
        self.cfg = cfg
        self.plane_ids = scene.plane_id if plane_ids is None else plane_ids
        self.scene = scene
        self.timing = timing
        self.n = cfg.sensor.array if cfg.instrument.emitter == "fan" else 256  # channel c: beam_row 0, beam_col c
        date = gps_week_date(cfg.flight.start_gps_time)
        self.writers = {
            model: TileWriter(Path(directory) / model, scene.crs, tile_size_m=cfg.output.tile_size_m,
                              compress=cfg.output.laz,
                              extras=("position_error",) * cfg.output.position_error + ("edge_distance",) * edge_distance,
                              creation_date=date, software=f"flightsim {__version__}")
            for model in cfg.output.models
        }

    def __call__(self, chunk: ReturnChunk) -> None:
        shared = self._shared_fields(chunk)
        for model, writer in self.writers.items():
            world = self.scene.local_to_world(chunk.points[model])
            error = None
            if self.cfg.output.position_error:
                error = np.linalg.norm(chunk.points[model] - chunk.true_points, axis=1).astype(np.float32)
            writer.write(PointBatch(x=world[:, 0], y=world[:, 1], z=world[:, 2], position_error_m=error,
                                    edge_distance_m=chunk.edge_distance_m, **shared))

    def _shared_fields(self, chunk: ReturnChunk) -> dict:
        """The fields every model's points share: timing, beam, range, labels."""
        times = self.timing.pulse_times(chunk.start_time, chunk.pulse)
        angles = self.timing.prism_angles(chunk.start_time, chunk.pulse)
        return dict(
            gps_time=times,
            point_source_id=np.full(len(chunk), chunk.line_id, dtype=np.uint16),
            classification=self.scene.classification[chunk.face],
            scan_angle_deg=chunk.scan_angle_deg,
            intensity=np.round(np.clip(chunk.cos_incidence, 0.0, 1.0) * 65535.0).astype(np.uint16),
            beam_row=(chunk.beam // self.n).astype(np.uint8),
            beam_col=(chunk.beam % self.n).astype(np.uint8),
            prism_angle_deg=np.degrees(angles).astype(np.float32),
            range_m=chunk.range_m,
            plane_id=self.plane_ids[chunk.face],
        )

    def close(self) -> dict[str, dict[str, int]]:
        """Finish every tile (atomic renames); return {model: {tile: points}}."""
        return {model: writer.close() for model, writer in self.writers.items()}

    def abort(self) -> None:
        """Remove every unfinished tile."""
        for writer in self.writers.values():
            writer.abort()


class PlaneStatistics:
    """Per-plane float64 moments of each model's points, accumulated chunk by chunk on the host.

    Returns whose true hit lies within ``edge_buffer_m`` of a plane boundary are left out, the
    same rule the device statistics apply.
    """

    def __init__(self, scene: Scene, models: tuple[str, ...], edge_buffer_m: float = 0.0):
        self.scene = scene
        self.edge_buffer_m = edge_buffer_m
        references = np.array([plane.point for plane in scene.planes], dtype=np.float64)
        self.moments = {model: PlaneMoments(references) for model in models}

    def __call__(self, chunk: ReturnChunk) -> None:
        keep = slice(None)
        if chunk.edge_distance_m is not None:
            keep = chunk.edge_distance_m >= self.edge_buffer_m
        plane_id = self.scene.plane_id[chunk.face[keep]]
        for model, moments in self.moments.items():
            moments.add(chunk.points[model][keep], plane_id)

    def rms_m(self) -> dict[str, float]:
        """Pooled plane-fit RMS of each model over all planes [m]."""
        return {model: _finite_or_none(pooled_rms(m.fits())) for model, m in self.moments.items()}


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None
