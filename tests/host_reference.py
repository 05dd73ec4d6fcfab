"""Host-side references of the points path, kept for the tests: the LAS writer and per-plane moments as
flightsim computed them from host arrays before records were packed and moments summed on the device.

``HostLasOutput`` turns each host :class:`ReturnChunk` into a :class:`PointBatch` and streams it through
``TileWriter.write`` (laspy quantisation and packing in numpy); ``HostPlaneStatistics`` accumulates float64
moments with numpy. The device path must give the same LAS bytes and the same moments.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from flightsim.engine.config import RunConfig
from flightsim.engine.readouts.points import ReturnChunk
from flightsim.engine.instrument import Instrument
from flightsim.outputs.device_las import tile_writers
from flightsim.outputs.las_points import PointBatch
from flightsim.scenes.scene import Scene
from flightsim.scoring.planes import PlaneMoments
from trajectories import PulseTiming


class HostLasOutput:
    """Each georeferencing model's points to its own tile set, from host arrays.

    Intensity is the Lambertian cos(incidence) scaled to 16 bits; gps_time is the pulse time.
    """

    def __init__(self, directory: Path, cfg: RunConfig, scene: Scene, timing: PulseTiming, edge_distance: bool,
                 plane_ids: np.ndarray | None = None):
        self.cfg = cfg
        self.plane_ids = scene.plane_id if plane_ids is None else plane_ids
        self.scene = scene
        self.timing = timing
        self.n = Instrument(cfg).emitter.beam_columns
        self.writers = tile_writers(directory, cfg.output, scene, cfg.flight.start_gps_time, edge_distance)

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
        return {model: writer.close() for model, writer in self.writers.items()}


class HostPlaneStatistics:
    """Per-plane float64 moments of each model's points, accumulated chunk by chunk with numpy; returns
    within ``edge_buffer_m`` of a plane boundary are left out."""

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
