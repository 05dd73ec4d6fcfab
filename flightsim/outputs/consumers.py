"""Consumers of simulated returns left on the device: per-plane statistics (LAS tiles: ``device_las``)."""
from __future__ import annotations

import math

import numpy as np
import warp as wp

from flightsim.core.config import MODELS
from flightsim.engine.simulate import SLOTS_PER_THREAD, symmetric
from flightsim.scoring.planes import PlaneMoments, pooled_rms
from kernels import trace


class PlaneStatistics:
    """Per-plane float64 moments of each model's points, accumulated on the device chunk by chunk from the
    points kernel's slots (the statistics-mode reduction, :func:`kernels.trace.reduce_kernel`).

    Returns whose true hit lies within ``edge_buffer_m`` of a plane boundary are left out, the same rule
    statistics mode applies.
    """

    def __init__(self, simulator, edge_buffer_m: float = 0.0):
        scene, d = simulator.scene, simulator.device
        self.device, self.models = d, simulator.models
        self.edge_buffer_m = edge_buffer_m if simulator.features.edges else 0.0
        self.slots_per_thread = SLOTS_PER_THREAD[simulator.device_kind]
        self.face_plane = wp.array(scene.plane_id.astype(np.int32), dtype=wp.int32, device=d)
        self.reference_points = np.array([plane.point for plane in scene.planes], dtype=np.float64)
        self.references = wp.array(self.reference_points, dtype=wp.vec3d, device=d)
        shape = (simulator.sum_replicas(), 2, len(scene.planes))
        self.sums = [wp.zeros(shape, dtype=wp.int64, device=d), wp.zeros(shape, dtype=wp.vec3d, device=d),
                     wp.zeros(shape, dtype=trace.vec6d, device=d), wp.zeros(3, dtype=wp.int32, device=d)]
        self.reduce = trace.reduce_kernel(simulator.features)
        self.codes: wp.array | None = None

    def __call__(self, returns) -> None:
        b, n, d = returns.buffers, returns.n_slots, self.device
        if self.codes is None or self.codes.shape[0] < n:
            self.codes = wp.empty(n, dtype=wp.int32, device=d)
        wp.launch(trace.plane_codes, n, inputs=[b.status, b.faces, b.edge_distance, self.face_plane,
                                                self.edge_buffer_m], outputs=[self.codes], device=d)
        spt = self.slots_per_thread
        wp.launch(self.reduce, (n + spt - 1) // spt, inputs=[self.codes, b.model_points["exact"],
                                                            b.model_points["nominal"], n, spt, self.references],
                  outputs=self.sums, device=d)

    def rms_m(self) -> dict[str, float]:
        """Pooled plane-fit RMS of each model over all planes [m]."""
        count, first, second = (a.numpy().sum(axis=0) for a in self.sums[:3])
        rms = {}
        for k, model in enumerate(MODELS):
            if model in self.models:
                moments = PlaneMoments(self.reference_points)
                moments.add_sums(count[k], first[k], symmetric(second[k]))
                rms[model] = _finite_or_none(pooled_rms(moments.fits()))
        return rms


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None
