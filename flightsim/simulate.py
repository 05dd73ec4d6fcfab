"""The simulation driver: per flight line, per chunk of pulses, launch the kernels and hand back returns.

Data flow on the device (ARCHITECTURE.md): trajectory samples → pulse poses → per-beam trace and
georeference → compaction of the slots that returned. Only the compacted returns cross to the
host, where they go to the consumers the run asked for (LAS tiles, plane statistics).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from flightsim.config import RunConfig
from flightsim.scene import Scene
from flightsim.warp_runtime import resolve_device
from kernels import frames, trace
from trajectories import PulseTiming, Trajectory

SLOTS_PER_CHUNK = {"cpu": 1 << 19, "cuda": 1 << 24}  # automatic chunk size, in beam slots


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
    points: dict[str, np.ndarray]  # georeferencing model -> (m, 3) float64 local [m]
    true_points: np.ndarray | None  # (m, 3) float64 local [m], when asked for

    def __len__(self) -> int:
        return len(self.pulse)


@dataclass
class RunCounts:
    """What happened to every beam of a run."""

    pulses: int = 0
    beams_fired: int = 0
    returns: int = 0
    tir_dropped: int = 0
    misses: int = 0
    wall_s: float = 0.0
    per_line: dict[int, int] = field(default_factory=dict)


def _prism(n_glass: float, apex_deg: float, thickness_mm: float) -> trace.Prism:
    prism = trace.Prism()
    prism.n_glass = n_glass
    prism.apex = math.radians(apex_deg)
    prism.thickness = thickness_mm * 1e-3
    return prism


class Simulator:
    """Fly a validated config's trajectories over a scene on one device.

    The scene's BVH and the kernels are built once here and reused by every :meth:`run`.
    """

    def __init__(self, cfg: RunConfig, scene: Scene, trajectories: list[Trajectory], with_truth: bool = False):
        self.cfg = cfg
        self.scene = scene
        self.trajectories = trajectories
        self.device = resolve_device(cfg.run.device)
        s, p = cfg.sensor, cfg.processing
        self.timing = PulseTiming(prf_hz=s.prf_hz, rotation_hz=s.rotation_hz, phase0_rad=math.radians(s.phase0_deg),
                                  field_prefix="sensor")
        self.beams = trace.BeamArray()
        self.beams.n = s.array
        self.beams.spacing = s.spacing_mrad * 1e-3
        self.truth = _prism(s.refractive_index, s.apex_angle_deg, s.thickness_mm)
        self.believed = _prism(p.refractive_index, p.apex_angle_deg, p.thickness_mm)
        believed_is_truth = (p.refractive_index, p.apex_angle_deg, p.thickness_mm) == (
            s.refractive_index, s.apex_angle_deg, s.thickness_mm)
        self.models = tuple(cfg.output.models)
        self.with_truth = with_truth
        self.kernel = trace.trace_kernel("exact" in self.models, "nominal" in self.models, believed_is_truth,
                                         with_truth, s.range_noise_m > 0.0)
        self.boresight = wp.quatd(*Rotation.from_euler("ZYX", s.boresight_deg[::-1], degrees=True).as_quat())
        self.mesh = wp.Mesh(
            points=wp.array(scene.vertices.astype(np.float32), dtype=wp.vec3f, device=self.device),
            indices=wp.array(scene.triangles.astype(np.int32).ravel(), dtype=wp.int32, device=self.device),
            bvh_constructor="sah",
        )

    @property
    def beams_per_pulse(self) -> int:
        return self.cfg.sensor.array ** 2

    def chunk_pulses(self) -> int:
        """Pulses per launch: the config's, or enough to fill the device's slot budget."""
        if self.cfg.run.chunk_pulses:
            return self.cfg.run.chunk_pulses
        slots = SLOTS_PER_CHUNK["cpu" if self.device == "cpu" else "cuda"]
        return max(1, slots // self.beams_per_pulse)

    def pulse_count(self, trajectory: Trajectory) -> int:
        return self.timing.pulse_count(trajectory.start_time, trajectory.end_time)

    def run(self, consume: Callable[[ReturnChunk], None],
            progress: Callable[[int, int], None] | None = None) -> RunCounts:
        """Fly every trajectory; call ``consume`` with each chunk's returns; return the counts."""
        started = time.perf_counter()
        counts = RunCounts()
        buffers = _Buffers(self.chunk_pulses(), self.beams_per_pulse, self.device)
        total = sum(self.pulse_count(t) for t in self.trajectories)
        slot_base = 0
        for trajectory in self.trajectories:
            line = self._line_inputs(trajectory)
            n_pulses = self.pulse_count(trajectory)
            returns_before = counts.returns
            for first in range(0, n_pulses, buffers.pulses):
                chunk_pulses = min(buffers.pulses, n_pulses - first)
                chunk = self._trace_chunk(trajectory, line, first, chunk_pulses, slot_base, buffers)
                slot_base = (slot_base + chunk_pulses * self.beams_per_pulse) % (1 << 31)
                counts.pulses += chunk_pulses
                counts.returns += len(chunk)
                if len(chunk):
                    consume(chunk)
                if progress:
                    progress(counts.pulses, total)
            counts.per_line[trajectory.line_id] = counts.returns - returns_before
        tir, misses = (int(v) for v in buffers.counters.numpy())
        counts.beams_fired = counts.pulses * self.beams_per_pulse
        counts.tir_dropped, counts.misses = tir, misses
        counts.wall_s = time.perf_counter() - started
        return counts

    def _line_inputs(self, trajectory: Trajectory) -> list:
        """Device-side inputs of ``pulse_poses`` that are fixed for a line."""
        t0 = trajectory.start_time
        d = self.device
        return [
            wp.array(trajectory.gps_time - t0, dtype=wp.float64, device=d),
            wp.array(self.scene.world_to_local(trajectory.position), dtype=wp.vec3d, device=d),
            wp.array(trajectory.quaternions(), dtype=wp.quatd, device=d),
            self.boresight,
            wp.vec3d(*self.cfg.sensor.lever_arm_m),
            self.timing.pulse_period_s,
            self.timing.phase_cycles_at(t0),
            self.timing.cycles_per_pulse,
        ]

    def _trace_chunk(self, trajectory: Trajectory, line: list, first: int, n_pulses: int, slot_base: int,
                     buffers: "_Buffers") -> ReturnChunk:
        d = self.device
        n_slots = n_pulses * self.beams_per_pulse
        wp.launch(frames.pulse_poses, n_pulses, inputs=[*line, first], outputs=[buffers.poses], device=d)
        s = self.cfg.sensor
        wp.launch(
            self.kernel, n_slots,
            inputs=[self.mesh.id, s.max_range_m, buffers.poses, self.beams, self.truth, self.believed,
                    s.range_noise_m, self.cfg.run.seed, slot_base],
            outputs=[buffers.status, buffers.ranges, buffers.faces, buffers.scan_angles, buffers.cos_incidence,
                     buffers.true_points, buffers.model_points["exact"], buffers.model_points["nominal"],
                     buffers.counters],
            device=d,
        )
        n_returns = buffers.compact_index(n_slots)
        slots = buffers.index.numpy()[:n_returns].astype(np.int64)
        gather = buffers.gather
        return ReturnChunk(
            line_id=trajectory.line_id,
            start_time=trajectory.start_time,
            pulse=first + slots // self.beams_per_pulse,
            beam=(slots % self.beams_per_pulse).astype(np.int32),
            range_m=gather(buffers.ranges, n_slots, n_returns),
            face=gather(buffers.faces, n_slots, n_returns),
            scan_angle_deg=gather(buffers.scan_angles, n_slots, n_returns),
            cos_incidence=gather(buffers.cos_incidence, n_slots, n_returns),
            points={m: gather(buffers.model_points[m], n_slots, n_returns).astype(np.float64) for m in self.models},
            true_points=gather(buffers.true_points, n_slots, n_returns).astype(np.float64) if self.with_truth else None,
        )


class _Buffers:
    """Device arrays for one chunk, allocated once per run and reused chunk after chunk."""

    def __init__(self, pulses: int, beams_per_pulse: int, device: str):
        self.pulses = pulses
        self.device = device
        slots = pulses * beams_per_pulse
        self.poses = wp.empty(pulses, dtype=frames.PulsePose, device=device)
        self.status = wp.empty(slots, dtype=wp.int32, device=device)
        self.ranges = wp.empty(slots, dtype=wp.float32, device=device)
        self.faces = wp.empty(slots, dtype=wp.int32, device=device)
        self.scan_angles = wp.empty(slots, dtype=wp.float32, device=device)
        self.cos_incidence = wp.empty(slots, dtype=wp.float32, device=device)
        self.true_points = wp.empty(slots, dtype=wp.vec3f, device=device)
        self.model_points = {m: wp.empty(slots, dtype=wp.vec3f, device=device) for m in ("exact", "nominal")}
        self.counters = wp.zeros(2, dtype=wp.int32, device=device)
        self.flags = wp.empty(slots, dtype=wp.int32, device=device)
        self.offsets = wp.empty(slots, dtype=wp.int32, device=device)
        self.index = wp.empty(slots, dtype=wp.int32, device=device)
        self.compacted: dict[object, wp.array] = {}

    def compact_index(self, n_slots: int) -> int:
        """Flag and prefix-sum the returning slots; fill ``index``; return the number of returns."""
        flags, offsets = self.flags[:n_slots], self.offsets[:n_slots]
        wp.launch(trace.flag_returns, n_slots, inputs=[self.status[:n_slots]], outputs=[flags], device=self.device)
        wp.utils.array_scan(flags, offsets, inclusive=False)
        last = np.concatenate([flags[n_slots - 1:].numpy(), offsets[n_slots - 1:].numpy()])
        wp.launch(trace.slot_indices, n_slots, inputs=[flags, offsets], outputs=[self.index], device=self.device)
        return int(last.sum())

    def gather(self, src: wp.array, n_slots: int, n_returns: int) -> np.ndarray:
        """Compact ``src`` on the device and copy only the returns to the host."""
        dst = self.compacted.get(id(src))
        if dst is None:
            dst = self.compacted[id(src)] = wp.empty(src.shape[0], dtype=src.dtype, device=self.device)
        wp.launch(trace.compact_slots, n_slots, inputs=[self.flags[:n_slots], self.offsets[:n_slots],
                                                        src[:n_slots]], outputs=[dst], device=self.device)
        return dst[:n_returns].numpy()
