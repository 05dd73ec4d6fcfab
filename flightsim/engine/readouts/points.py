"""The points readout of the discrete detector: one return per beam (over a canopy, up to the detector's
``max_returns``: ``max_returns`` slots per beam, :mod:`kernels.canopy_returns`), each chunk's returns compacted on
the device; only the returns cross to the host (or nothing, for consumers on the device: the LAS records, the plane
sums)."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.constants import MODELS
from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.warp_runtime import host_array, to_host
from flightsim.engine.chunks import POINT_SLOTS_PER_CHUNK, Segment
from kernels import compaction, trace
from kernels.looks import LOOKS

canopy_returns = lazy_module("kernels.canopy_returns")  # a run over a canopy only


@dataclass
class ReturnChunk:
    """The returns of one chunk of pulses of one flight line (host arrays, one row per return)."""

    line_id: int
    start_time: float  # adjusted standard GPS time of the line's pulse 0 [s]
    pulse: np.ndarray  # (m,) int64 pulse index within the line
    beam: np.ndarray  # (m,) int32 sub-beam index i·n + j
    range_m: np.ndarray  # (m,) float32 one-way range, exit point to hit [m]
    face: np.ndarray  # (m,) int32 triangle hit
    scan_angle_deg: np.ndarray  # (m,) float32 signed off-nadir angle [deg]
    cos_incidence: np.ndarray  # (m,) float32
    edge_distance_m: np.ndarray | None  # (m,) float32 true hit to its plane boundary, capped [m]
    points: dict[str, np.ndarray]  # georeferencing model -> (m, 3) float64 local [m]
    true_points: np.ndarray | None  # (m, 3) float64 local [m], when asked for
    return_number: np.ndarray | None = None  # (m,) uint8, 1 = first; None: one return per beam
    number_of_returns: np.ndarray | None = None  # (m,) uint8 returns of the beam

    def __len__(self) -> int:
        return len(self.pulse)


@dataclass
class DeviceReturns:
    """The returns of one chunk of pulses left on the device: the points kernel's per-slot outputs in ``buffers``
    (``buffers.pulses`` is the chunk's pulse table) and ``buffers.index[:count]``, the slot of each return in slot
    order. Valid until the consumer returns. ``count`` is read from the device when first asked for (a consumer that
    never asks costs the chunk no wait for the device)."""

    segments: list[Segment]  # the chunk's pieces of flight lines, in pulse order
    n_slots: int  # slots traced (pulses × beams per pulse)
    buffers: "PointBuffers"

    @functools.cached_property
    def count(self) -> int:
        """The chunk's returns."""
        return int(to_host(self.buffers.total)[0])


class PointBuffers:
    """Device arrays for one chunk of the points kernel, allocated once (a readout keeps them for its tracer's later
    runs, :meth:`Tracer.kept`) and reused chunk after chunk; ``per_beam`` slots per beam (the returns a beam may
    have)."""

    def __init__(self, tracer, pulses: int, per_beam: int = 1):
        device, slots = tracer.device, pulses * tracer.beams_per_pulse * per_beam
        self.device, self.per_beam = device, per_beam
        self.pulses = tracer.pulse_table(pulses)
        self.status = wp.empty(slots, dtype=wp.int32, device=device)
        self.ranges = wp.empty(slots, dtype=wp.float32, device=device)
        self.faces = wp.empty(slots, dtype=wp.int32, device=device)
        self.scan_angles = wp.empty(slots, dtype=wp.float32, device=device)
        self.cos_incidence = wp.empty(slots, dtype=wp.float32, device=device)
        self.edge_distance = wp.empty(slots, dtype=wp.float32, device=device)
        self.true_points = wp.empty(slots, dtype=wp.vec3f, device=device)
        self.model_points = {m: wp.empty(slots, dtype=wp.vec3f, device=device) for m in MODELS}
        self.counters = wp.zeros(canopy_returns.COUNTERS if per_beam > 1 else 3, dtype=wp.int32, device=device)
        self.returns = wp.empty(slots, dtype=wp.int32, device=device) if per_beam > 1 else None
        self.counts = wp.empty(slots // per_beam, dtype=wp.int32, device=device)  # per beam: its returns
        self.offsets = wp.empty(slots // per_beam, dtype=wp.int32, device=device)  # ... and the beams' before it
        self.index = wp.empty(slots, dtype=wp.int32, device=device)
        self.total = wp.zeros(1, dtype=wp.int32, device=device)  # the returns of the chunk last compacted
        self.line_returns = wp.zeros(len(tracer.trajectories), dtype=wp.int64, device=device)  # per line of the run
        self.compacted: dict[int, wp.array] = {}

    def slot_outputs(self) -> list[wp.array]:
        """The points kernel's outputs, in its argument order (the canopy kernel's: the return numbers too)."""
        returns = [] if self.returns is None else [self.returns]
        return [self.status, self.ranges, self.faces, self.scan_angles, self.cos_incidence, self.edge_distance,
                self.true_points, self.model_points["exact"], self.model_points["nominal"], *returns, self.counters]

    def compact_index(self, n_slots: int) -> None:
        """Count each beam's returns and prefix-sum them; fill ``index`` and ``total`` (on the device: no wait)."""
        n_beams = n_slots // self.per_beam
        counts, offsets = self.counts[:n_beams], self.offsets[:n_beams]
        wp.launch(compaction.beam_returns, n_beams, inputs=[self.status, self.per_beam], outputs=[counts],
                  device=self.device)
        wp.utils.array_scan(counts, offsets, inclusive=False)
        wp.launch(compaction.slot_indices, n_beams, inputs=[self.status, self.per_beam, offsets], outputs=[self.index],
                  device=self.device)
        wp.launch(compaction.count_returns, 1, inputs=[counts, offsets, n_beams], outputs=[self.total],
                  device=self.device)

    def add_line_returns(self, tracer, segments: list[Segment], n_slots: int) -> None:
        """Add the returns of each segment of the chunk last compacted (``n_slots`` slots) to ``line_returns``, by the
        tracer's segment table of the chunk (on the device already: no copy, so no wait for the device)."""
        wp.launch(compaction.add_segment_returns, len(segments),
                  inputs=[self.counts, self.offsets, n_slots // self.per_beam, tracer.segment_table,
                          tracer.beams_per_pulse], outputs=[self.line_returns], device=self.device)

    def gather(self, src: wp.array, n_returns: int) -> np.ndarray:
        """The returning slots of ``src`` (the chunk last compacted: ``n_returns`` of them), gathered on the device in
        slot order and copied to the host (an array of the caller's own)."""
        dst = self.compacted.get(id(src))
        if dst is None:
            dst = self.compacted[id(src)] = wp.empty(src.shape[0], dtype=src.dtype, device=self.device)
        wp.launch(compaction.gather_returns, n_returns, inputs=[self.index, src], outputs=[dst], device=self.device)
        return host_array(dst[:n_returns])


def trace_points(tracer, buffers: PointBuffers, n_slots: int, features: trace.Features | None = None) -> None:
    """Launch the points kernel (``features``, default the tracer's) over a traced chunk's slots, its two looks
    (:meth:`Tracer.launch_looks`); over a canopy the canopy kernels, one thread per beam: the beams' surface traces
    (two looks), then the leaf walks and the slots."""
    f = features or tracer.features
    if buffers.per_beam > 1:
        leaves = tracer.kept("canopy_returns", lambda: CanopyReturns(tracer, buffers))
        beams, scan = n_slots // buffers.per_beam, tracer.scan
        tracer.launch_looks(canopy_trace_kernels(tracer, f), beams, inputs=[buffers.pulses, scan],
                            outputs=[leaves.traces])
        wp.launch(points_kernels(tracer, f, buffers.per_beam)[0], beams,
                  inputs=[buffers.pulses, scan, leaves.traces, *leaves.inputs()], outputs=buffers.slot_outputs(),
                  device=tracer.device)
        return
    tracer.launch_looks(points_kernels(tracer, f, 1), n_slots, inputs=[buffers.pulses, tracer.scan],
                        outputs=buffers.slot_outputs())


def points_kernels(tracer, f: trace.Features, per_beam: int) -> tuple:
    """The points kernel of ``f`` on the tracer's instrument, its two looks; over a canopy (``per_beam`` > 1 slots
    per beam) the canopy kernel, one."""
    if per_beam > 1:
        return (canopy_returns.canopy_points_kernel(f, tracer.instrument.kernel, max_registers=tracer.max_registers),)
    return tuple(trace.points_kernel(f, tracer.instrument.kernel, tracer.max_registers, look) for look in LOOKS)


def canopy_trace_kernels(tracer, f: trace.Features) -> tuple:
    """The canopy kernels' first stage (each beam's surface trace) of ``f`` on the tracer's instrument, its two
    looks."""
    return tuple(canopy_returns.canopy_trace_kernel(f, tracer.instrument.kernel, tracer.max_registers, look)
                 for look in LOOKS)


class CanopyReturns:
    """The canopy kernels' inputs besides the scan: the canopy on the device, the detector's trigger, the surface's
    albedo per triangle (or none), a scratch row of leaf echoes per slot and one surface trace per beam."""

    def __init__(self, tracer, buffers: PointBuffers):
        s, scene = tracer.cfg.discrete, tracer.scene
        det = canopy_returns.EchoDetection()
        det.threshold, det.min_separation, det.max_returns = s.threshold, s.min_separation_m, s.max_returns
        det.leaf_reflectance, det.reflectance = scene.canopy.leaf_reflectance, s.reflectance
        det.triangles = len(scene.triangles)
        self.det = det
        self.canopy = scene.canopy.to_device(tracer.device)
        self.reflectance = (tracer.meshes.reflectance if tracer.meshes.per_face
                            else wp.zeros(0, dtype=wp.float32, device=tracer.device))
        self.echoes = wp.empty(buffers.status.shape[0], dtype=canopy_returns.Echo, device=tracer.device)
        self.traces = wp.empty(buffers.status.shape[0] // buffers.per_beam, dtype=trace.SlotTrace, device=tracer.device)

    def inputs(self) -> list:
        return [self.canopy, self.det, self.reflectance, self.echoes]


@register("readout", "points")
class Points:
    """One return per beam. ``consume`` gets each flight line's part of each chunk as a host :class:`ReturnChunk`,
    or with ``on_device`` each chunk's :class:`DeviceReturns`; ``RunCounts.returns`` counts the returns and
    ``per_line`` them by line (summed on the device, read once in ``end``: a chunk whose consumer stays on the device
    never waits for it)."""

    kind = "points"

    def __init__(self, on_device: bool = False):
        self.on_device = on_device

    def begin(self, tracer) -> wp.array:
        per_beam = tracer.returns_per_beam
        pulses = max(1, tracer.pulses_per_launch(POINT_SLOTS_PER_CHUNK) // per_beam)
        self.buffers = tracer.kept(f"points {per_beam}", lambda: PointBuffers(tracer, pulses, per_beam))
        self.buffers.counters.zero_()  # kept for the tracer's later runs: the run's sums start again
        self.buffers.line_returns.zero_()
        self.lines: dict[int, None] = {}  # indices of the lines the chunks held, in order
        return self.buffers.pulses

    def chunk(self, tracer, segments: list[Segment], n_slots: int, counts, consume) -> None:
        buffers = self.buffers
        n_slots *= buffers.per_beam  # the tracer counts beams
        trace_points(tracer, buffers, n_slots)
        buffers.compact_index(n_slots)
        buffers.add_line_returns(tracer, segments, n_slots)
        for segment in segments:  # the lines in the order they come (their counts are added in end)
            self.lines.setdefault(segment.line, None)
        returns = DeviceReturns(segments, n_slots, buffers)
        if self.on_device:
            consume(returns)
            return
        for part in host_returns(tracer, returns):
            consume(part)

    def kernels_needed(self, tracer) -> list:
        canopy = canopy_trace_kernels(tracer, tracer.features) if tracer.returns_per_beam > 1 else ()
        return [*points_kernels(tracer, tracer.features, tracer.returns_per_beam), *canopy, compaction.beam_returns]

    def end(self, tracer, counts) -> wp.array:
        per_line = to_host(self.buffers.line_returns)
        for line in self.lines:
            line_id, n = tracer.trajectories[line].line_id, int(per_line[line])
            counts.per_line[line_id] = counts.per_line.get(line_id, 0) + n
            counts.returns += n
        if self.buffers.per_beam > 1:
            c = to_host(self.buffers.counters)
            counts.dark, counts.beams_returned = int(c[canopy_returns.COUNT_DARK]), int(c[canopy_returns.COUNT_RETURNED])
            counts.leaf_returns = int(c[canopy_returns.COUNT_LEAF])
        return self.buffers.counters


def host_returns(tracer, returns: DeviceReturns) -> list[ReturnChunk]:
    """Compact a chunk's returning slots on the device, bring them to the host, split by line."""
    buffers, n_returns = returns.buffers, returns.count
    slots = host_array(buffers.index[:n_returns]).astype(np.int64)  # the chunk's returns only, not the buffer
    gather = functools.partial(buffers.gather, n_returns=n_returns)
    echo = None if buffers.returns is None else gather(buffers.returns)
    f = tracer.features
    fields = dict(
        range_m=gather(buffers.ranges),
        face=gather(buffers.faces),
        scan_angle_deg=gather(buffers.scan_angles),
        cos_incidence=gather(buffers.cos_incidence),
        edge_distance_m=gather(buffers.edge_distance) if f.edges else None,
        points={m: gather(buffers.model_points[m]).astype(np.float64) for m in tracer.models},
        true_points=gather(buffers.true_points).astype(np.float64) if f.with_truth else None,
        return_number=None if echo is None else (echo & 15).astype(np.uint8),
        number_of_returns=None if echo is None else (echo >> 4).astype(np.uint8),
    )
    return [ReturnChunk(line_id=trajectory.line_id, start_time=trajectory.start_time, pulse=pulse, beam=beam,
                        **_sliced(fields, a, b))
            for trajectory, pulse, beam, a, b in tracer.by_line(returns.segments, slots // buffers.per_beam)]


def _sliced(fields: dict, a: int, b: int) -> dict:
    """Rows a:b of every array in a dict of arrays, dicts of arrays and Nones."""
    def cut(v):
        if v is None:
            return None
        return {k: x[a:b] for k, x in v.items()} if isinstance(v, dict) else v[a:b]
    return {k: cut(v) for k, v in fields.items()}
