"""Accuracy of a run against the float64 reference of the same pipeline (kernels/reference.py).

Pointing error: the angle, seen from the pulse's sensor origin, between the run's true hit and
the reference hit [rad]. Point error: distance between the run's georeferenced point and the
reference's, per model [m]. Noise must be off (the reference has none).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from flightsim.engine.readouts.points import ReturnChunk
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from kernels import reference


@dataclass
class ErrorStats:
    """Largest errors seen over the checked returns."""

    returns: int = 0
    max_pointing_rad: float = 0.0
    max_point_error_m: dict[str, float] = field(default_factory=dict)

    def add(self, pointing: np.ndarray, errors: dict[str, np.ndarray]) -> None:
        self.returns += len(pointing)
        self.max_pointing_rad = max(self.max_pointing_rad, float(pointing.max(initial=0.0)))
        for model, e in errors.items():
            self.max_point_error_m[model] = max(self.max_point_error_m.get(model, 0.0), float(e.max(initial=0.0)))


class ReferenceCheck:
    """A consumer for :meth:`Tracer.run` that compares every return with the float64 reference.

    The simulator must have been built with ``with_truth=True``.
    """

    def __init__(self, simulator: Tracer):
        self.sim = simulator
        self.truth, self.believed = simulator.scan.truth, simulator.scan.believed
        self.stats = ErrorStats()

    def __call__(self, chunk: ReturnChunk) -> None:
        d = self.sim.device
        first = int(chunk.pulse.min())
        n_pulses = int(chunk.pulse.max()) - first + 1
        poses = self.sim.poses64(chunk.line_id, first, n_pulses)
        m = len(chunk)
        outputs = [wp.empty(m, dtype=wp.vec3d, device=d) for _ in range(4)]
        fan = self.sim.instrument.emitter
        wp.launch(reference.reference_returns, m, device=d, outputs=outputs, inputs=[
            poses, wp.array((chunk.pulse - first).astype(np.int32), dtype=wp.int32, device=d),
            wp.array(chunk.beam, dtype=wp.int32, device=d), wp.array(chunk.face, dtype=wp.int32, device=d),
            self.sim.meshes.vertices64, self.sim.meshes.indices, fan.n, fan.spacing_rad, self.truth, self.believed])
        true_ref, exact_ref, nominal_ref, origin = (a.numpy() for a in outputs)
        a = chunk.true_points - origin
        b = true_ref - origin
        pointing = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
        refs = {"exact": exact_ref, "nominal": nominal_ref}
        self.stats.add(pointing, {m: np.linalg.norm(chunk.points[m] - refs[m], axis=1) for m in chunk.points})


def measure_errors(simulator: Tracer) -> ErrorStats:
    """Run the simulator in points mode and return the largest errors against the float64 reference."""
    check = ReferenceCheck(simulator)
    simulator.run(Points(), check)
    return check.stats
