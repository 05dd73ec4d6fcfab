"""The deviations readout of the discrete detector (error budgets): each slot's believed − true point and its square
added to float64 sums on the device, indexed by run slot; nothing else leaves the device."""
from __future__ import annotations

import warp as wp

from flightsim.core.registry import register
from flightsim.engine.chunks import POINT_SLOTS_PER_CHUNK
from flightsim.engine.readouts.points import PointBuffers, points_kernels, trace_points
from kernels.budget import accumulate_deviations


@register("readout", "deviations")
class Deviations:
    """Add each returning slot's exact-model point − true point [m, local] to ``sums``, its square to ``squares``
    and 1 to ``hits`` (device arrays indexed by run slot: pulse of the run · beams per pulse + beam). Needs a tracer
    built ``with_truth`` and the exact model; its buffers are kept for the tracer's later runs (Monte Carlo draws)."""

    kind = "deviations"

    def __init__(self, sums: wp.array, squares: wp.array, hits: wp.array):
        self.outputs = [sums, squares, hits]

    def begin(self, tracer) -> wp.array:
        if not (tracer.features.with_truth and tracer.features.exact):
            raise ValueError("the deviations readout needs with_truth=True and the exact model")
        self.buffers = tracer.kept("deviations", lambda: PointBuffers(tracer, tracer.pulses_per_launch(
            POINT_SLOTS_PER_CHUNK)))
        self.buffers.counters.zero_()
        return self.buffers.pulses

    def chunk(self, tracer, segments, n_slots: int, counts, consume) -> None:
        b = self.buffers
        trace_points(tracer, b, n_slots)
        base = counts.pulses * tracer.beams_per_pulse  # the chunk's first run slot (counts.pulses: chunks before)
        wp.launch(accumulate_deviations, n_slots, inputs=[b.status, b.model_points["exact"], b.true_points, base],
                  outputs=self.outputs, device=tracer.device)

    def kernels_needed(self, tracer) -> list:
        return [*points_kernels(tracer, tracer.features, 1), accumulate_deviations]

    def end(self, tracer, counts) -> wp.array:
        return self.buffers.counters
