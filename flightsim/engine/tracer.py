"""The tracer: per flight line, per chunk of pulses, the pulses' poses and the instrument's beams deflected and cast
against the scene; a readout turns each chunk's traced beams into what its detector makes of them.

Data flow on the device (ARCHITECTURE.md): trajectory samples → pulse poses → per-pulse optics → the readout's
kernels (per-beam trace and georeference, then its own work: compaction of the returns, per-plane moments, photon
events, waveforms). A readout (:mod:`flightsim.engine.readouts`) is registered like any part; a detector names the
readouts it provides (``Detector.readouts``), and :meth:`Tracer.run` runs one.
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Protocol

import numpy as np
import warp as wp

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.core.timeline import mark
from flightsim.core.warp_runtime import compile_ahead, resolve_device
from flightsim.engine.chunks import SLOTS_PER_CHUNK, Segment, line_table, pack, segment_tables
from flightsim.engine.coverage import pulse_windows
from flightsim.engine.instrument import Instrument
from flightsim.engine.meshes import SceneMeshes
from flightsim.scenes.scene import Scene
from flightsim.scoring.reduction import sum_replicas
from kernels import frames, looks, mesh_hits, trace
from trajectories import Trajectory, rotation

MAX_REGISTERS = 64  # registers per thread of the trace kernels on a GPU (measured best: results/profile-experiments.md
# section 19); the CPU's compiler ignores it, so a CPU run builds the very kernels a GPU run does (prebuilt kernels)


@dataclass
class RunCounts:
    """What happened to every beam of a run."""

    pulses: int = 0  # pulses launched
    pulses_culled: int = 0  # pulses skipped because their beams could not reach the scene
    beams_fired: int = 0
    returns: int = 0  # what the readout counts: returns, photons, sub-ray returns
    tir_dropped: int = 0
    misses: int = 0
    edge_excluded: int = 0  # statistics: returns left out for lying within the edge buffer
    beams_returned: int = 0  # through a canopy: beams with at least one return
    leaf_returns: int = 0  # ... returns from leaves
    dark: int = 0  # ... beams that hit a surface but whose every echo stayed below the detector's threshold
    wall_s: float = 0.0
    per_line: dict[int, int] = field(default_factory=dict)


class Readout(Protocol):
    """What a detector makes of the traced beams, chunk by chunk. ``kind``: its registered name."""

    kind: str

    def begin(self, tracer: "Tracer") -> wp.array:
        """Allocate (or take the kept) device buffers; return the pulse table the chunks are traced into."""

    def chunk(self, tracer: "Tracer", segments: list[Segment], n_slots: int, counts: RunCounts,
              consume: Callable[[Any], None] | None) -> None:
        """Run the readout's kernels on a traced chunk of ``n_slots`` slots and hand ``consume`` what it made."""

    def end(self, tracer: "Tracer", counts: RunCounts) -> wp.array:
        """Finish the run's device work; return the counters [TIR, misses, ...] of its beams."""

    def kernels_needed(self, tracer: "Tracer") -> list:
        """The kernels its chunks and end launch on ``tracer`` (compiled together before the first chunk)."""


class Tracer:
    """Fly a validated config's trajectories over a scene on one device.

    ``meshes`` (the scene's BVHs on the device) may be shared by many tracers, e.g. all the configurations of a
    sweep; ``edge_buffer_m`` > 0 turns on the per-return distance to the plane boundaries; ``pulse_limits``
    {line id: (k0, k1)} restricts a line to the pulses k0 ≤ k < k1 (a survey split into tasks gives each task its
    own pulses).
    """

    def __init__(self, cfg, scene: Scene, trajectories: list[Trajectory], with_truth: bool = False,
                 edge_buffer_m: float = 0.0, meshes: SceneMeshes | None = None,
                 pulse_limits: dict[int, tuple[int, int]] | None = None):
        self.cfg = cfg
        self.pulse_limits = pulse_limits or {}
        self.scene = scene
        self.trajectories = trajectories
        self.device = resolve_device(cfg.run.device)
        self.instrument = Instrument(cfg)
        self.timing = self.instrument.deflector.timing()
        self.models = tuple(cfg.output.models) if "models" in cfg.output.names() else ("exact",)
        self.edge_buffer_m = edge_buffer_m
        self.features = self._features(with_truth)
        self.rows = trace.pulse_rows(self.instrument.kernel, self.features.pose)
        self.boresight_quat = rotation.from_euler_zyx(cfg.instrument.boresight_deg[::-1], degrees=True)  # body←sensor
        self.boresight = wp.quatd(*self.boresight_quat)
        self.meshes = meshes or SceneMeshes(scene, self.device, cfg.run.bvh, cfg.run.bvh_leaf_size or None)
        self.scan = self._scan()
        self._cone_rad: float | None = None
        self._windows: dict[int, list[tuple[int, int]]] = {}
        self._pulse_counts: dict[int, int] = {}  # pulses of each line (line_id), worked out once
        self._kept: dict[str, Any] = {}
        self.segment_table: frames.Segments | None = None  # the device segment table of the chunk being traced

    def _features(self, with_truth: bool) -> trace.Features:
        instrument = self.instrument
        return trace.Features(
            exact="exact" in self.models, nominal="nominal" in self.models,
            believed_is_truth=instrument.deflector.believed_is_truth and not instrument.pose.active,
            with_truth=with_truth, noisy=instrument.ranging.sigmas().gaussian > 0.0,
            ranging=instrument.ranging.has_systematics, pose=instrument.pose.active,
            edges=self.edge_buffer_m > 0.0, optics=self.cfg.run.optics)

    def _scan(self):
        """The instrument's scan struct (kernels.trace.scan_struct) with its per-beam table filled."""
        instrument, d = self.instrument, self.device
        scan = trace.scan_struct(instrument.kernel)()
        scan.mesh = self.meshes.mesh.id
        scan.max_range = self.cfg.instrument.max_range_m
        scan.per_pulse = self.beams_per_pulse
        scan.emitter = instrument.emitter.params(d)
        scan.truth = instrument.deflector.params(believed=False)
        scan.believed = instrument.deflector.params(believed=True)
        scan.noise_sigma = instrument.ranging.sigmas().gaussian
        scan.ranging = instrument.ranging.struct(self.beams_per_pulse, d)
        scan.pose = instrument.pose.struct()
        if self.features.edges:
            scan.boundary_a, scan.boundary_b = self.meshes.boundary
            scan.edge_grid = self.meshes.edge_grid(self.edge_buffer_m)
        else:
            scan.boundary_a = scan.boundary_b = wp.zeros(1, dtype=wp.vec3f, device=d)
            scan.edge_grid = self.meshes.none_grid()
        scan.edge_cap = self.edge_buffer_m
        scan.lut_directions, scan.lut_exits = self._exit_table()
        scan.vertices64, scan.indices = self.meshes.vertices64, self.meshes.indices
        scan.padded = self.meshes.padded.id
        n_beams = self.beams_per_pulse
        scan.beam_truth, scan.beam_believed = (wp.empty(n_beams, dtype=wp.vec3d, device=d) for _ in range(2))
        scan.beam_rigid = wp.empty(n_beams, dtype=wp.quatd, device=d)
        wp.launch(trace.beam_table_kernel(instrument.kernel), n_beams, inputs=[scan], device=d)
        return scan

    def set_errors(self, cfg) -> None:
        """Swap in the true and believed deflectors and the pose errors of ``cfg`` (same parts, same
        compiled features: a Monte Carlo draw) and rebuild the per-beam tables."""
        instrument = Instrument(cfg)
        self.scan.truth = instrument.deflector.params(believed=False)
        self.scan.believed = instrument.deflector.params(believed=True)
        self.scan.pose = instrument.pose.struct()
        wp.launch(trace.beam_table_kernel(instrument.kernel), self.beams_per_pulse, inputs=[self.scan],
                  device=self.device)

    def _exit_table(self) -> tuple[wp.array, wp.array]:
        """Exit directions and points of every beam at M + 1 prism angles over a turn, for
        ``optics = "lut"`` (a deflector with an exit table); a 2×beams placeholder otherwise."""
        deflector = self.instrument.deflector
        if not hasattr(deflector, "exit_table"):
            placeholder = np.zeros((2, self.beams_per_pulse, 3), dtype=np.float32)
            return (wp.array(placeholder, dtype=wp.vec3f, device=self.device),
                    wp.array(placeholder, dtype=wp.vec3f, device=self.device))
        directions, exits = deflector.exit_table(self.cfg.run.lut_samples if self.features.optics == "lut" else 1)
        return (wp.array(directions, dtype=wp.vec3f, device=self.device),
                wp.array(exits, dtype=wp.vec3f, device=self.device))

    @property
    def max_registers(self) -> int | None:
        """Register cap of the trace kernels on a GPU: the config's, else the measured default."""
        return self.cfg.run.max_registers or MAX_REGISTERS

    @property
    def beams_per_pulse(self) -> int:
        return self.instrument.beams_per_pulse

    @property
    def returns_per_beam(self) -> int:
        """Slots per beam of the points readout: the discrete detector's ``max_returns`` over a scene with a
        canopy, else 1."""
        if self.scene.canopy is None or self.cfg.instrument.detector != "discrete":
            return 1
        return self.cfg.discrete.max_returns

    @property
    def device_kind(self) -> str:
        return "cpu" if self.device == "cpu" else "cuda"

    def chunk_pulses(self, budget: dict[str, int] = SLOTS_PER_CHUNK) -> int:
        """Pulses per launch: the config's, or enough to fill the readout's slot ``budget`` on this device kind."""
        if self.cfg.run.chunk_pulses:
            return self.cfg.run.chunk_pulses
        return max(1, budget[self.device_kind] // self.beams_per_pulse)

    def pulses_per_launch(self, budget: dict[str, int] = SLOTS_PER_CHUNK) -> int:
        """Pulses the device buffers hold: a chunk, or all the run's pulses where they are fewer."""
        return max(1, min(self.chunk_pulses(budget), self.planned_pulses()))

    def planned_pulses(self) -> int:
        """Pulses the run will launch (within the pulse limits, culled ones left out)."""
        return sum(k1 - k0 for t in self.trajectories for k0, k1 in self.windows(t))

    def pulse_count(self, trajectory: Trajectory) -> int:
        """Pulses fired along ``trajectory``, one of this tracer's lines (worked out once a line: a run of the shots
        platform asks for each of its many two-sample lines several times)."""
        count = self._pulse_counts.get(trajectory.line_id)
        if count is None:
            count = self._pulse_counts[trajectory.line_id] = self.timing.pulse_count(trajectory.start_time,
                                                                                   trajectory.end_time)
        return count

    def sum_replicas(self, groups: int | None = None) -> int:
        """Copies of the per-group sums (``groups`` of them, the scene's planes by default) of the statistics
        reduction (:func:`flightsim.scoring.reduction.sum_replicas`)."""
        groups = len(self.scene.planes) if groups is None else groups
        return sum_replicas(self.device_kind, groups, self.cfg.run.sum_replicas)

    def pulse_table(self, pulses: int) -> wp.array:
        """A chunk's per-pulse table: float64 rows (pose, then optics; trace.pulse_rows), one column per pulse."""
        return wp.empty((self.rows.total, pulses), dtype=wp.float64, device=self.device)

    def kept(self, key: str, make: Callable[[], Any]) -> Any:
        """What ``make`` builds, built on first use and kept for this tracer's later runs (a readout's device
        buffers: a sweep or a Monte Carlo budget runs one tracer many times)."""
        if key not in self._kept:
            self._kept[key] = make()
        return self._kept[key]

    # ------------------------------------------------------------------------------------------

    def run(self, readout: Readout, consume: Callable[[Any], None] | None = None,
            progress: Callable[[int, int], None] | None = None, share: tuple[int, int] = (0, 1)) -> RunCounts:
        """Trace every chunk of the run and hand it to ``readout``; return the counts.

        ``share`` = (k, n) runs only every n-th chunk from the k-th, so n processes can split a run.
        """
        self._check_readout(readout)
        self.compile_ahead(readout)
        started = time.perf_counter()
        counts = RunCounts()
        pulses = readout.begin(self)
        for segments in self._chunks(pulses, counts, progress, share):
            n_slots = sum(s.count for s in segments) * self.beams_per_pulse
            readout.chunk(self, segments, n_slots, counts, consume)
            mark("first_ray")  # the first chunk's kernels compiled (or loaded) and launched
        tir, misses = (int(v) for v in readout.end(self, counts).numpy()[:2])
        counts.beams_fired = counts.pulses * self.beams_per_pulse
        counts.tir_dropped, counts.misses = tir, misses
        counts.wall_s = time.perf_counter() - started
        if hasattr(readout, "finish"):
            readout.finish(counts)
        return counts

    def launch_looks(self, kernels: tuple, dim: int, inputs: list, outputs: list) -> None:
        """Launch a trace kernel's two looks over ``dim`` threads (``kernels``: the first look's and the second's,
        :mod:`kernels.looks`): the first casts every slot's ray with the float32 closest-hit cast (Warp's mesh
        query) and lists those it misses, the second casts only those through the padded triangle boxes. Their arguments: ``inputs``, the
        list of misses, ``outputs``."""
        misses = self._kept.get("misses")
        if misses is None or misses.slots.shape[0] < dim:
            misses = self._kept["misses"] = looks.Misses()
            misses.count = wp.zeros(1, dtype=wp.int32, device=self.device)
            misses.slots = wp.empty(max(dim, 1), dtype=wp.int32, device=self.device)
        else:
            misses.count.zero_()
        for kernel in kernels:
            wp.launch(kernel, dim, inputs=[*inputs, misses], outputs=outputs, device=self.device)

    @staticmethod
    def setup_kernels(instrument: Instrument) -> list:
        """The kernels a tracer of ``instrument`` launches while it is made (the scene's padded boxes, the per-beam
        tables), for :func:`flightsim.engine.run.compile_setup`: (kernel, None = the run's device) pairs."""
        return [(mesh_hits.corner_extent, None), (trace.beam_table_kernel(instrument.kernel), None)]

    def compile_ahead(self, *parts) -> None:
        """Compile the modules of :meth:`kernels_needed` in parallel, before the first chunk would compile them
        one by one."""
        compile_ahead(self.device, self.kernels_needed(*parts))

    def kernels_needed(self, *parts) -> list:
        """The tracer's chunk kernels and every part's ``kernels_needed`` (a readout, a product's consumers)."""
        kernels = [frames.pulse_poses, trace.pulse_optics_kernel(self.instrument.kernel, self.features.pose)]
        for part in parts:
            kernels += part.kernels_needed(self) if hasattr(part, "kernels_needed") else []
        return kernels

    def _check_readout(self, readout: Readout) -> None:
        detector = self.instrument.detector
        if readout.kind not in getattr(detector, "readouts", ()):
            owners = [k for k, part in registry.kinds("detector").items() if readout.kind in getattr(part, "readouts", ())]
            raise InputError("instrument.detector", self.cfg.instrument.detector,
                             f"{' or '.join(owners)} for the {readout.kind} readout")

    def windows(self, trajectory: Trajectory) -> list[tuple[int, int]]:
        """Pulse index ranges [k0, k1) of a trajectory to launch: within the line's pulse limits, and
        (with culling on) only those whose beams can reach the scene. Worked out once, for every line at once."""
        if not self._windows:
            self._windows = self._plan_windows(self.trajectories)
        return self._windows[trajectory.line_id]

    def _plan_windows(self, trajectories: list[Trajectory]) -> dict[int, list[tuple[int, int]]]:
        if not trajectories:
            return {}
        if not self.cfg.run.cull:
            reaching = [[(0, self.pulse_count(t))] for t in trajectories]
        else:
            sizes = np.cumsum([len(t.position) for t in trajectories])[:-1]
            local = np.split(self.scene.world_to_local(np.concatenate([t.position for t in trajectories])), sizes)
            reaching = pulse_windows(trajectories, local, self.scene.bounds(), self.timing, self.cone_rad,
                                     self.boresight_quat, [self.pulse_count(t) for t in trajectories])
        planned = {}
        for trajectory, windows in zip(trajectories, reaching):
            lo, hi = self.pulse_limits.get(trajectory.line_id, (0, self.pulse_count(trajectory)))
            hi = min(hi, self.pulse_count(trajectory))
            planned[trajectory.line_id] = [(max(k0, lo), min(k1, hi)) for k0, k1 in windows if min(k1, hi) > max(k0, lo)]
        return planned

    @property
    def cone_rad(self) -> float:
        """Largest angle of any beam from the sensor axis over the scan [rad] (worked out once)."""
        if self._cone_rad is None:
            self._cone_rad = self.instrument.max_off_axis_rad()
        return self._cone_rad

    def _chunks(self, pulses: wp.array, counts: RunCounts, progress: Callable[[int, int], None] | None,
                share: tuple[int, int] = (0, 1)) -> Iterator[list[Segment]]:
        """Compute each chunk's pulse poses and per-pulse optics into the pulse table ``pulses`` and
        yield the chunk's segments.

        ``share`` = (k, n) keeps every n-th chunk from the k-th. Range noise is keyed by (seed,
        line, pulse, beam), so culling, chunking and sharing never change it.
        """
        plans = [self.windows(t) for t in self.trajectories]
        mine, tables = self.kept(f"chunks of {pulses.shape[1]} pulses, share {share}",
                                 lambda: self._plan_chunks(plans, pulses.shape[1], share))
        total = sum(s.count for chunk in mine for s in chunk) if progress else 0
        optics = trace.pulse_optics_kernel(self.instrument.kernel, self.features.pose)
        for chunk, table in zip(mine, tables):
            self.segment_table = table  # the chunk's pieces of lines on the device, for the readouts
            n_pulses = sum(s.count for s in chunk)
            wp.launch(frames.pulse_poses, n_pulses, inputs=[self.lines, table, len(chunk)], outputs=[pulses],
                      device=self.device)
            wp.launch(optics, n_pulses, inputs=[self.scan, pulses], device=self.device)
            yield chunk
            counts.pulses += n_pulses
            if progress:
                progress(counts.pulses, total)
        if share[0] == 0:  # counted once the device has every chunk queued (a many-line run's host work)
            counts.pulses_culled = sum(self._limited_count(t) - sum(k1 - k0 for k0, k1 in w)
                                       for t, w in zip(self.trajectories, plans))

    def _plan_chunks(self, plans: list, pulses: int, share: tuple[int, int]) -> tuple[list, list]:
        """(the chunks of at most ``pulses`` pulses this ``share`` of the run traces, their segment tables on the
        device): worked out, and the tables copied up, once per tracer (both follow from the lines' windows, which
        are worked out once too)."""
        pieces = [(line, k0, k1) for line, windows in enumerate(plans) for k0, k1 in windows]
        mine = pack(pieces, pulses)[share[0]::share[1]]
        return mine, segment_tables(mine, self.device)

    @functools.cached_property
    def lines(self) -> frames.Lines:
        """Every line's samples on the device (built on first use, then kept)."""
        return line_table(self.trajectories, self.scene, self.timing, self.boresight, self.cfg.instrument.lever_arm_m,
                          self.cfg.run.seed, self.device)

    def poses64(self, line_id: int, first: int, count: int) -> wp.array:
        """Float64 poses of pulses first ≤ k < first + count of a line (the reference path)."""
        line = next(i for i, t in enumerate(self.trajectories) if t.line_id == line_id)
        (table,) = segment_tables([[Segment(line, first, count)]], self.device)
        poses = wp.empty(count, dtype=frames.PulsePose64, device=self.device)
        wp.launch(frames.pulse_poses64, count, inputs=[self.lines, table, 1], outputs=[poses], device=self.device)
        return poses

    def _limited_count(self, trajectory: Trajectory) -> int:
        """Pulses of a trajectory within its pulse limits."""
        lo, hi = self.pulse_limits.get(trajectory.line_id, (0, self.pulse_count(trajectory)))
        return max(0, min(hi, self.pulse_count(trajectory)) - lo)

    def first_chunk(self, pulses: int) -> tuple[wp.array, int]:
        """(pulse table, slots) of the run's first chunk of at most ``pulses`` pulses, traced to its optics."""
        table = self.pulse_table(max(1, pulses))
        chunk = next(self._chunks(table, RunCounts(), None))
        return table, sum(s.count for s in chunk) * self.beams_per_pulse

    def sample_rays(self, max_slots: int) -> tuple[wp.array, wp.array]:
        """The float32 rays of the run's first slots (up to ``max_slots``), on the device."""
        pulses, n = self.first_chunk(max_slots // self.beams_per_pulse)
        starts = wp.empty(n, dtype=wp.vec3f, device=self.device)
        directions = wp.empty(n, dtype=wp.vec3f, device=self.device)
        wp.launch(trace.emit_rays_kernel(self.instrument.kernel), n, inputs=[pulses, self.scan],
                  outputs=[starts, directions], device=self.device)
        return starts, directions

    def by_line(self, chunk: list[Segment], slots: np.ndarray):
        """Split a chunk's slot indices (ascending) by flight line: (trajectory, pulse within the line,
        beam, a, b) for each line holding any, the slots being ``slots[a:b]``."""
        pulse = slots // self.beams_per_pulse  # within the chunk
        starts = np.cumsum([0] + [s.count for s in chunk])
        bounds = np.searchsorted(pulse, starts)
        first = np.array([s.first for s in chunk], dtype=np.int64) - starts[:-1]  # a segment's pulse 0 in its line
        line_pulse = pulse + np.repeat(first, np.diff(bounds))  # the whole chunk's at once, each line's part a view
        beam = (slots % self.beams_per_pulse).astype(np.int32)
        for segment, a, b in zip(chunk, bounds[:-1].tolist(), bounds[1:].tolist()):
            if b > a:
                yield self.trajectories[segment.line], line_pulse[a:b], beam[a:b], a, b
