"""The statistics readout of the discrete detector: per-plane float64 moments of each georeferencing model,
accumulated on the device (sweeps, surveys' plane scores, benchmarks). No point leaves the device: one kernel
writes each slot's plane and points to a record buffer, a second settles the returns near plane boundaries, a
third reduces the records, ``slots_per_thread`` consecutive ones per thread, into copies of the sums that are
added on the device at the end."""
from __future__ import annotations

import numpy as np
import warp as wp

from flightsim.core.constants import MODELS
from flightsim.core.registry import register
from flightsim.scoring.planes import PlaneMoments
from flightsim.scoring.reduction import SLOTS_PER_THREAD, reduce_models, replica_totals, symmetric
from kernels import statistics
from kernels.looks import LOOKS


class StatisticsBuffers:
    """Device arrays of the statistics readout for one tracer, allocated once and reused by its runs."""

    def __init__(self, tracer, pulses: int):
        d, slots, f = tracer.device, pulses * tracer.beams_per_pulse, tracer.features
        self.device = d
        self.pulses = tracer.pulse_table(pulses)
        self.records = [wp.empty(slots, dtype=wp.int32, device=d)] + [
            wp.empty(slots if model in tracer.models else 1, dtype=wp.vec3f, device=d) for model in MODELS]
        listed = slots if f.edges else 1  # returns the edge grid leaves to the boundary query
        self.near = [wp.zeros(1, dtype=wp.int32, device=d), wp.empty(listed, dtype=wp.int32, device=d),
                     wp.empty(listed, dtype=wp.vec3f, device=d)]
        self.face_plane = wp.array(tracer.scene.plane_id.astype(np.int32), dtype=wp.int32, device=d)
        self.reference_points = np.array([plane.point for plane in tracer.scene.planes], dtype=np.float64)  # [m]
        self.references = wp.array(self.reference_points, dtype=wp.vec3d, device=d)
        self.sum_shape = (tracer.sum_replicas(), 2, len(tracer.scene.planes))

    def zeroed_sums(self) -> list[wp.array]:
        """Fresh per-plane sums (count, Σd, Σddᵀ per replica, model and plane) and counters."""
        d, shape = self.device, self.sum_shape
        return [wp.zeros(shape, dtype=wp.int64, device=d), wp.zeros(shape, dtype=wp.vec3d, device=d),
                wp.zeros(shape, dtype=statistics.vec6d, device=d), wp.zeros(3, dtype=wp.int32, device=d)]


@register("readout", "statistics")
class Statistics:
    """Per-plane float64 moments of each model (``moments`` after the run). Returns within the edge buffer of a
    plane boundary are left out (``RunCounts.edge_excluded``); ``RunCounts.returns`` counts every return."""

    kind = "statistics"

    def __init__(self, slots_per_thread: int | None = None):
        self.slots_per_thread = slots_per_thread
        self.moments: dict[str, PlaneMoments] = {}

    def begin(self, tracer) -> wp.array:
        self.buffers = tracer.kept("statistics", lambda: StatisticsBuffers(tracer, tracer.pulses_per_launch()))
        self.spt = (self.slots_per_thread or tracer.cfg.run.slots_per_thread
                    or SLOTS_PER_THREAD[tracer.device_kind])
        self.sums = self.buffers.zeroed_sums()
        self.kernels = self.kernels_needed(tracer)
        return self.buffers.pulses

    def kernels_needed(self, tracer) -> list:
        return [*records_kernels(tracer), statistics.check_edges_kernel(tracer.instrument.kernel),
                statistics.reduce_records]

    def chunk(self, tracer, segments, n_slots: int, counts, consume) -> None:
        b, d, spt = self.buffers, tracer.device, self.spt
        tracer.launch_looks(self.kernels[:2], n_slots, inputs=[b.pulses, tracer.scan, b.face_plane],
                            outputs=[*b.records, *b.near])
        check_edges = self.kernels[2]
        if tracer.features.edges:
            wp.launch(check_edges, n_slots, inputs=[tracer.scan, tracer.edge_buffer_m, *b.near],
                      outputs=[b.records[0]], device=d)
            b.near[0].zero_()
        reduce_models(b.records[0], b.records[1:], tracer.models, n_slots, spt, b.references, self.sums, d)

    def end(self, tracer, counts) -> wp.array:
        count, first, second = replica_totals(self.sums[:3])
        for k, model in enumerate(MODELS):
            if model in tracer.models:
                m = PlaneMoments(self.buffers.reference_points)
                m.add_sums(count[k], first[k], symmetric(second[k]))
                self.moments[model] = m
        counts.edge_excluded = int(self.sums[3].numpy()[2])
        return self.sums[3]

    def finish(self, counts) -> None:
        counts.returns = counts.beams_fired - counts.tir_dropped - counts.misses


def records_kernels(tracer) -> tuple:
    """The statistics trace kernel's two looks (:meth:`Tracer.launch_looks`) on the tracer's instrument."""
    return tuple(statistics.records_kernel(tracer.features, tracer.instrument.kernel, tracer.max_registers, look)
                 for look in LOOKS)


def run_statistics(tracer, progress=None, slots_per_thread: int | None = None,
                   share: tuple[int, int] = (0, 1)) -> tuple[dict[str, PlaneMoments], "object"]:
    """Run the statistics readout on ``tracer``: (each model's per-plane moments, the run's counts)."""
    readout = Statistics(slots_per_thread)
    counts = tracer.run(readout, progress=progress, share=share)
    return readout.moments, counts
