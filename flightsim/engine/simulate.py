"""The simulation driver: per flight line, per chunk of pulses, launch the kernels.

Data flow on the device (ARCHITECTURE.md): trajectory samples → pulse poses → per-beam trace and
georeference → either compaction of the slots that returned (points mode: only the returns
cross to the host) or per-plane float64 moments (statistics mode: only the sums cross).
"""
from __future__ import annotations

import dataclasses

import functools
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from flightsim.engine.chunks import Segment, line_table, pack, segment_tables
from flightsim.core.constants import MODELS
from flightsim.core.errors import InputError
from flightsim.engine.coverage import pulse_windows
from flightsim.engine.instrument import Instrument
from flightsim.scoring.reduction import SLOTS_PER_THREAD, replica_totals, sum_replicas, symmetric
from flightsim.scoring.planes import PlaneMoments
from flightsim.scenes.scene import Scene
from flightsim.core.warp_runtime import resolve_device, to_host
from kernels import frames, trace
from trajectories import Trajectory

SLOTS_PER_CHUNK = {"cpu": 1 << 18, "cuda": 1 << 24}  # automatic chunk size, in beam slots
POINT_SLOTS_PER_CHUNK = {"cpu": 1 << 18, "cuda": 1 << 22}  # points mode: host memory grows with it
WAVEFORM_SAMPLES_PER_CHUNK = {"cpu": 1 << 22, "cuda": 1 << 28}  # waveform mode: waveform samples per launch
MAX_REGISTERS = {"cpu": None, "cuda": 64}  # registers per thread of the trace kernels (None: the compiler's choice)
EDGE_GRID_CELLS = 4096  # the edge grid has at most this many cells along a side
EDGE_GRIDS_KEPT = 4  # edge grids (one per edge cap) a SceneMeshes keeps


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

    def __len__(self) -> int:
        return len(self.pulse)


@dataclass
class DeviceReturns:
    """The returns of one chunk of pulses left on the device (points mode): the points kernel's per-slot
    outputs in ``buffers`` (``buffers.pulses`` is the chunk's pulse table) and ``buffers.index[:count]``,
    the slot of each return in slot order. Valid until the consumer returns."""

    segments: list[Segment]  # the chunk's pieces of flight lines, in pulse order
    n_slots: int  # slots traced (pulses × beams per pulse)
    count: int  # returns
    buffers: "_PointBuffers"


@dataclass
class PhotonChunk:
    """The photon detections of one chunk of pulses of one flight line (host arrays, one row per photon)."""

    line_id: int
    start_time: float  # adjusted standard GPS time of the line's pulse 0 [s]
    pulse: np.ndarray  # (m,) int64 pulse index within the line
    pixel: np.ndarray  # (m,) int32 beam (pixel) index
    time_of_flight_s: np.ndarray  # (m,) float64 [s]
    signal: np.ndarray  # (m,) bool: the photon came from the pulse (truth), else background or dark count
    kind: np.ndarray  # (m,) int8 truth: 0 background or dark count, 1 the surface's echo, 2 a retroreflector's
    points: np.ndarray  # (m, 3) float64 local [m]: the photon placed on its believed beam at c·t/2
    directions: np.ndarray  # (m, 3) float32 local unit direction of the photon's believed beam

    def __len__(self) -> int:
        return len(self.pulse)


@dataclass
class DevicePhotons:
    """The photon detections of one chunk on the device, ordered by slot (valid until the next chunk)."""

    count: int
    slot: wp.array  # int32 slot within the chunk (pulse of the chunk · beams per pulse + beam)
    time_of_flight_s: wp.array  # float64 [s]
    signal: wp.array  # int8 truth: 0 background or dark count, 1 the surface's echo, 2 a retroreflector's
    points: wp.array  # vec3d local [m]: placed on its believed beam at c·t/2
    directions: wp.array  # vec3f local unit direction of the photon's believed beam


@dataclass
class WaveformChunk:
    """The waveforms of one chunk of pulses of one flight line (host arrays, one row per beam whose
    central ray reached the scene)."""

    line_id: int
    start_time: float  # adjusted standard GPS time of the line's pulse 0 [s]
    pulse: np.ndarray  # (m,) int64 pulse index within the line
    beam: np.ndarray  # (m,) int32
    window_start_s: np.ndarray  # (m,) float64 two-way time of flight of sample 0 [s]
    power_w: np.ndarray  # (m, samples) float32 received power at window start + i·dt [W]
    received: np.ndarray  # (m, 4) float64 Σ power shares inside, outside the window; Σ w·z [m], Σ w of the hits (kernels.waveform)
    start: np.ndarray  # (m, 3) float64 local beam start [m]
    direction: np.ndarray  # (m, 3) float64 local unit beam direction

    def __len__(self) -> int:
        return len(self.pulse)


@dataclass
class DeviceWaveforms:
    """A chunk's waveforms on the device, one row per slot (valid until the next chunk)."""

    count: int  # slots of the chunk (rows beyond are stale)
    window_start_s: wp.array  # float64 [s]; −1 where the central ray missed
    power_w: wp.array  # (slots, samples) float32 [W]
    received: wp.array  # (slots, 4) float64 (WaveformChunk.received)
    starts: wp.array  # vec3d local beam starts [m]
    directions: wp.array  # vec3d local unit beam directions


@dataclass
class RunCounts:
    """What happened to every beam of a run."""

    pulses: int = 0  # pulses launched
    pulses_culled: int = 0  # pulses skipped because their beams could not reach the scene
    beams_fired: int = 0
    returns: int = 0
    tir_dropped: int = 0
    misses: int = 0
    edge_excluded: int = 0  # statistics mode: returns left out for lying within the edge buffer
    wall_s: float = 0.0
    per_line: dict[int, int] = field(default_factory=dict)


class SceneMeshes:
    """A scene's acceleration structures on one device, built once: the triangle BVH, a BVH of the
    plane-boundary segments for edge-buffer queries and the per-triangle reflectance (both on first use)."""

    def __init__(self, scene: Scene, device: str, bvh_constructor: str = "auto", leaf_size: int | None = None):
        self.scene = scene
        self.device = device
        if bvh_constructor == "auto":  # measured fastest per device kind (README, run.bvh)
            bvh_constructor = "sah" if wp.get_device(device).is_cpu else "cubql"
        points = scene.vertices.astype(np.float32)
        self.mesh = wp.Mesh(points=wp.array(points, dtype=wp.vec3f, device=device),
                            indices=wp.array(scene.triangles.astype(np.int32).ravel(), dtype=wp.int32, device=device),
                            bvh_constructor=bvh_constructor, bvh_leaf_size=leaf_size)
        self.vertices64 = wp.array(scene.vertices, dtype=wp.vec3d, device=device)
        self.indices = self.mesh.indices
        self.padded = self._padded_bvh(scene, device)
        self._boundary: tuple[wp.Bvh, wp.array, wp.array] | None = None
        self._reflectance: wp.array | None = None
        self._grids: dict[float, trace.EdgeGrid] = {}

    def _padded_bvh(self, scene: Scene, device: str) -> wp.Bvh:
        """BVH of the triangles' boxes padded by 1e-6·(1 + the largest |coordinate| of a triangle corner)
        [m], for the fallback cast (:func:`kernels.trace._fallback_hit`); the boxes are made on the device."""
        n = len(scene.triangles)
        extent = wp.zeros(1, dtype=wp.float32, device=device)
        wp.launch(trace.corner_extent, n, inputs=[self.mesh.points, self.mesh.indices], outputs=[extent], device=device)
        pad = np.float32(1e-6 * (1.0 + to_host(extent)[0]))
        self._padded_boxes = (wp.empty(n, dtype=wp.vec3f, device=device), wp.empty(n, dtype=wp.vec3f, device=device))
        wp.launch(trace.padded_boxes, n, inputs=[self.mesh.points, self.mesh.indices, pad],
                  outputs=list(self._padded_boxes), device=device)
        return wp.Bvh(*self._padded_boxes)

    @property
    def per_face(self) -> bool:
        """Whether the scene carries a Lambertian albedo per triangle (else the detectors take the run's value)."""
        return self.scene.reflectance is not None

    @property
    def reflectance(self) -> wp.array:
        """float32 Lambertian albedo of each triangle on the device (uploaded on first use); a one-element
        placeholder when the scene has none."""
        if self._reflectance is None:
            rho = self.scene.reflectance if self.per_face else np.ones(1, dtype=np.float32)
            self._reflectance = wp.array(rho, dtype=wp.float32, device=self.device)
        return self._reflectance

    @property
    def boundary(self) -> tuple[wp.Bvh, wp.array, wp.array]:
        """(BVH of segment boxes, segment starts, segment ends)."""
        if self._boundary is None:
            segments = self.scene.boundary_segments().astype(np.float32)
            if len(segments) == 0:  # a closed surface has no boundary: one far-away dummy segment
                segments = np.full((1, 2, 3), 1e9, dtype=np.float32)
            a = wp.array(segments[:, 0], dtype=wp.vec3f, device=self.device)
            b = wp.array(segments[:, 1], dtype=wp.vec3f, device=self.device)
            lowers = wp.array(segments.min(axis=1), dtype=wp.vec3f, device=self.device)
            uppers = wp.array(segments.max(axis=1), dtype=wp.vec3f, device=self.device)
            self._boundary = (wp.Bvh(lowers, uppers), a, b)
        return self._boundary

    def edge_grid(self, cap_m: float) -> trace.EdgeGrid:
        """The grid of cells a plane boundary may come within ``cap_m`` of (built on first use per cap;
        the last few are kept, as a sweep's configurations share few caps)."""
        if cap_m not in self._grids:
            if len(self._grids) >= EDGE_GRIDS_KEPT:
                self._grids.pop(next(iter(self._grids)))
            self._grids[cap_m] = self._build_edge_grid(cap_m)
        return self._grids[cap_m]

    def _build_edge_grid(self, cap_m: float) -> trace.EdgeGrid:
        lower, upper = self.scene.bounds()
        extent = float(max(upper[0] - lower[0], upper[1] - lower[1])) + 2.0 * cap_m
        cell = max(cap_m, extent / EDGE_GRID_CELLS, 1e-6)
        shape = tuple(int(math.ceil((upper[k] - lower[k] + 2.0 * cap_m) / cell)) + 1 for k in (0, 1))
        grid = trace.EdgeGrid()
        grid.near = wp.zeros(shape, dtype=wp.uint8, device=self.device)
        grid.origin = wp.vec2f(float(lower[0]) - cap_m, float(lower[1]) - cap_m)
        grid.inv_cell = 1.0 / cell
        _, a, b = self.boundary
        wp.launch(trace.mark_near_cells, a.shape[0], inputs=[a, b, cap_m], outputs=[grid], device=self.device)
        return grid


class Simulator:
    """Fly a validated config's trajectories over a scene on one device.

    ``meshes`` (the scene's BVHs on the device) may be shared by many simulators, e.g. all the
    configurations of a sweep; ``edge_buffer_m`` > 0 turns on the per-return distance to the
    plane boundaries; ``pulse_limits`` {line id: (k0, k1)} restricts a line to the pulses
    k0 ≤ k < k1 (a survey split into tasks gives each task its own pulses).
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
        self.features = trace.Features(
            exact="exact" in self.models, nominal="nominal" in self.models,
            believed_is_truth=self.instrument.deflector.believed_is_truth and not self.instrument.pose.active,
            with_truth=with_truth, noisy=self.instrument.ranging.sigmas().gaussian > 0.0,
            ranging=self.instrument.ranging.has_systematics, pose=self.instrument.pose.active,
            edges=edge_buffer_m > 0.0, optics=cfg.run.optics,
        )
        self.rows = trace.pulse_rows(self.instrument.kernel, self.features.pose)
        self.boresight_rotation = Rotation.from_euler("ZYX", cfg.instrument.boresight_deg[::-1], degrees=True)  # body←sensor
        self.boresight = wp.quatd(*self.boresight_rotation.as_quat())
        self.meshes = meshes or SceneMeshes(scene, self.device, cfg.run.bvh, cfg.run.bvh_leaf_size or None)
        self.scan = self._scan()
        self._cone_rad: float | None = None
        self._windows: dict[int, list[tuple[int, int]]] = {}
        self._statistics: _StatisticsBuffers | None = None  # statistics-mode device buffers, kept between runs
        self._points: _PointBuffers | None = None  # budget-mode device buffers, kept between draws

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
            bvh, scan.boundary_a, scan.boundary_b = self.meshes.boundary
            scan.boundary = bvh.id
            scan.edge_grid = self.meshes.edge_grid(self.edge_buffer_m)
        else:
            scan.boundary = 0
            scan.boundary_a = scan.boundary_b = wp.zeros(1, dtype=wp.vec3f, device=self.device)
            scan.edge_grid = trace.EdgeGrid()
            scan.edge_grid.near = wp.zeros((1, 1), dtype=wp.uint8, device=self.device)
        scan.edge_cap = self.edge_buffer_m
        scan.lut_directions, scan.lut_exits = self._exit_table()
        scan.vertices64, scan.indices = self.meshes.vertices64, self.meshes.indices
        scan.padded = self.meshes.padded.id
        n_beams = self.beams_per_pulse
        scan.beam_truth, scan.beam_believed = (wp.empty(n_beams, dtype=wp.vec3d, device=self.device) for _ in range(2))
        scan.beam_rigid = wp.empty(n_beams, dtype=wp.quatd, device=self.device)
        wp.launch(trace.beam_table_kernel(instrument.kernel), n_beams, inputs=[scan], device=self.device)
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
        return self.cfg.run.max_registers or MAX_REGISTERS[self.device_kind]

    @property
    def beams_per_pulse(self) -> int:
        return self.instrument.beams_per_pulse

    @property
    def device_kind(self) -> str:
        return "cpu" if self.device == "cpu" else "cuda"

    def chunk_pulses(self, budget: dict[str, int] = SLOTS_PER_CHUNK) -> int:
        """Pulses per launch: the config's, or enough to fill the mode's slot ``budget`` on this device kind."""
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
        return self.timing.pulse_count(trajectory.start_time, trajectory.end_time)

    # ------------------------------------------------------------------------------------------

    def run(self, consume: Callable[[ReturnChunk], None],
            progress: Callable[[int, int], None] | None = None) -> RunCounts:
        """Points mode: call ``consume`` with the returns of each line's part of each chunk, on the host;
        return the counts."""
        return self.run_device(lambda returns: [consume(part) for part in self._returns(returns)], progress)

    def run_device(self, consume: Callable[[DeviceReturns], None],
                   progress: Callable[[int, int], None] | None = None) -> RunCounts:
        """Points mode with the returns left on the device: call ``consume`` with each chunk's
        :class:`DeviceReturns` (the points kernel's slot outputs and the slot of each return); return
        the counts (returns per flight line counted on the device)."""
        self._require_discrete("points")
        started = time.perf_counter()
        counts = RunCounts()
        buffers = _PointBuffers(self.pulses_per_launch(POINT_SLOTS_PER_CHUNK), self.beams_per_pulse, self.rows.total,
                                self.device)
        kernel = trace.points_kernel(self.features, self.instrument.kernel, max_registers=self.max_registers)
        for chunk in self._chunks(buffers.pulses, counts, progress):
            n_slots = sum(s.count for s in chunk) * self.beams_per_pulse
            wp.launch(kernel, n_slots, inputs=[buffers.pulses, self.scan], outputs=buffers.slot_outputs(),
                      device=self.device)
            returns = DeviceReturns(chunk, n_slots, buffers.compact_index(n_slots), buffers)
            for segment, n in zip(chunk, buffers.returns_per_segment(chunk, self.beams_per_pulse)):
                line_id = self.trajectories[segment.line].line_id
                counts.per_line[line_id] = counts.per_line.get(line_id, 0) + n
                counts.returns += n
            consume(returns)
        return self._finish(counts, buffers.counters, started)

    def _require_discrete(self, mode: str) -> None:
        if self.cfg.instrument.detector != "discrete":
            raise InputError("instrument.detector", self.cfg.instrument.detector,
                             f"discrete for {mode} mode (sweeps, surveys, studies); photon runs go through "
                             "flightsim simulate")

    def run_photons(self, consume: Callable[[PhotonChunk], None],
                    progress: Callable[[int, int], None] | None = None, on_device: bool = False) -> RunCounts:
        """Photon mode (``instrument.detector = "photon"``): trace every beam, turn its return into the
        detections of its SPAD pixel on the device, and call ``consume`` with each line's part of each
        chunk's detections; ``RunCounts.returns`` counts the photons. ``on_device``: ``consume`` gets
        each chunk's detections as a :class:`DevicePhotons` instead, and nothing leaves the device."""
        from kernels import photon

        started = time.perf_counter()
        counts = RunCounts()
        budget = SLOTS_PER_CHUNK if on_device else POINT_SLOTS_PER_CHUNK  # on the host, photons fill memory
        buffers = _PointBuffers(self.pulses_per_launch(budget), self.beams_per_pulse, self.rows.total, self.device)
        events = _PhotonBuffers(len(buffers.status), self.cfg.photon.max_events, self.device)
        det = self.instrument.detector.struct()
        ranges_only = dataclasses.replace(self.features, exact=False, nominal=False, edges=False)  # no georeferencing
        kernel = trace.points_kernel(ranges_only, self.instrument.kernel, max_registers=self.max_registers)
        retro = _Retroreflectors(self.cfg.scene, self.instrument.emitter.divergence_mrad, len(buffers.status),
                                 self.device)
        for chunk in self._chunks(buffers.pulses, counts, progress):
            n_slots = sum(s.count for s in chunk) * self.beams_per_pulse
            wp.launch(kernel, n_slots, inputs=[buffers.pulses, self.scan], outputs=buffers.slot_outputs(),
                      device=self.device)
            if retro.count:
                wp.launch(trace.emit_rays_kernel(self.instrument.kernel, precise=True, pose=self.features.pose),
                          n_slots, inputs=[buffers.pulses, self.scan], outputs=[retro.starts, retro.directions],
                          device=self.device)
            wp.launch(photon.photon_slots_kernel(retro.count > 0, self.meshes.per_face), n_slots,
                      inputs=[det, self.cfg.photon.reflectance, self.meshes.reflectance, buffers.pulses,
                              self.beams_per_pulse, buffers.status, buffers.ranges, buffers.faces,
                              buffers.cos_incidence, retro.positions, retro.photons, retro.footprint,
                              retro.starts, retro.directions, self.scan.ranging.delays, self.scan.ranging.drift],
                      outputs=[events.times, events.signal, events.counts], device=self.device)
            found = events.gather(n_slots, buffers.pulses, self.scan, self.instrument.kernel)
            counts.returns += found.count
            if on_device:
                consume(found)
                continue
            for part in self._photon_parts(chunk, found):
                counts.per_line[part.line_id] = counts.per_line.get(part.line_id, 0) + len(part)
                consume(part)
        return self._finish(counts, buffers.counters, started)

    def run_waveforms(self, consume: Callable[[WaveformChunk], None],
                      progress: Callable[[int, int], None] | None = None, on_device: bool = False) -> RunCounts:
        """Waveform mode (``instrument.detector = "waveform"``): per beam, every sub-ray of its footprint
        traced and its echo summed into the beam's waveform on the device (kernels/waveform.py); ``consume``
        gets each line's part of each chunk's waveforms. ``RunCounts.returns`` counts sub-rays cast by
        beams whose central ray reached the scene (on the device: all sub-rays launched). ``on_device``:
        ``consume`` gets each chunk's :class:`DeviceWaveforms` instead, and nothing leaves the device."""
        from kernels import waveform as kw

        started = time.perf_counter()
        counts = RunCounts()
        det = self.instrument.detector
        params, subrays = det.struct(self.meshes.per_face), det.subrays(self.device)
        taps, first_lag = det.pulse_taps(self.device)
        refs = self._mesh_refs()
        budget = max(1, WAVEFORM_SAMPLES_PER_CHUNK[self.device_kind] // params.samples)
        pulses_per_launch = max(1, min(self.pulses_per_launch(), budget // self.beams_per_pulse))
        pulses = _pulse_table(pulses_per_launch, self.rows.total, self.device)
        slots = pulses_per_launch * self.beams_per_pulse
        starts, directions = (wp.empty(slots, dtype=wp.vec3d, device=self.device) for _ in range(2))
        window = wp.empty(slots, dtype=wp.float64, device=self.device)
        impulses = wp.empty((slots, params.samples), dtype=wp.float64, device=self.device)
        power = wp.empty((slots, params.samples), dtype=wp.float32, device=self.device)
        received = wp.empty((slots, 4), dtype=wp.float64, device=self.device)
        span = wp.empty((slots, 2), dtype=wp.int32, device=self.device)
        receiver, keys = det.receiver(), wp.empty(slots, dtype=wp.int64, device=self.device)
        for chunk in self._chunks(pulses, counts, progress):
            n = sum(s.count for s in chunk) * self.beams_per_pulse
            wp.launch(trace.emit_rays_kernel(self.instrument.kernel, precise=True, pose=self.features.pose), n,
                      inputs=[pulses, self.scan], outputs=[starts, directions], device=self.device)
            wp.launch(kw.pilot, n, inputs=[refs, params, starts, directions], outputs=[window], device=self.device)
            impulses.zero_()
            received.zero_()
            wp.launch(kw.start_span, n, inputs=[params.samples], outputs=[span], device=self.device)
            groups = -(-len(subrays) // kw.SUBRAYS_PER_THREAD)
            wp.launch(kw.deposit_kernel(self.meshes.per_face), (n, groups),
                      inputs=[refs, params, starts, directions, window, subrays.offsets, subrays.weights,
                              kw.SUBRAYS_PER_THREAD],
                      outputs=[impulses, received, span], device=self.device)
            wp.launch(kw.convolve, (n, params.samples), inputs=[impulses, span, taps, first_lag], outputs=[power],
                      device=self.device)
            if receiver is not None:
                wp.launch(kw.beam_keys, n, inputs=[pulses, self.beams_per_pulse], outputs=[keys], device=self.device)
                wp.launch(kw.receive, (n, params.samples), inputs=[receiver, params.dt, params.samples, keys],
                          outputs=[power], device=self.device)
            if on_device:
                counts.returns += n * len(subrays)
                consume(DeviceWaveforms(n, window, power, received, starts, directions))
                continue
            found = window.numpy()[:n]
            slot = np.flatnonzero(found >= 0.0)
            counts.returns += len(slot) * len(subrays)
            for part in self._waveform_parts(chunk, slot, found, power, received, starts, directions):
                counts.per_line[part.line_id] = counts.per_line.get(part.line_id, 0) + len(part)
                consume(part)
        return self._finish(counts, wp.zeros(3, dtype=wp.int32, device=self.device), started)

    def _mesh_refs(self):
        from kernels import waveform as kw

        refs = kw.MeshRefs()
        refs.mesh, refs.padded = self.meshes.mesh.id, self.meshes.padded.id
        refs.vertices64, refs.indices = self.meshes.vertices64, self.meshes.indices
        refs.max_range = self.cfg.instrument.max_range_m
        refs.reflectance = self.meshes.reflectance
        return refs

    def _waveform_parts(self, chunk: list[Segment], slot: np.ndarray, window: np.ndarray, power: wp.array,
                        received: wp.array, starts: wp.array, directions: wp.array) -> list[WaveformChunk]:
        """Bring a chunk's waveforms (beams whose pilot reached the scene) to the host, split by line."""
        rows = {name: a.numpy()[slot] for name, a in (("power", power), ("received", received), ("start", starts),
                                                       ("direction", directions))}
        return [WaveformChunk(trajectory.line_id, trajectory.start_time, pulse, beam, window[slot[a:b]],
                              rows["power"][a:b], rows["received"][a:b], rows["start"][a:b], rows["direction"][a:b])
                for trajectory, pulse, beam, a, b in self._by_line(chunk, slot)]

    def _photon_parts(self, chunk: list[Segment], found: DevicePhotons) -> list[PhotonChunk]:
        """Bring a chunk's detections (ordered by slot) to the host, split by flight line."""
        slot = found.slot[:found.count].numpy().astype(np.int64)
        tof, kind = found.time_of_flight_s.numpy(), found.signal.numpy()
        points, directions = found.points.numpy(), found.directions.numpy()
        return [PhotonChunk(trajectory.line_id, trajectory.start_time, pulse, beam, tof[a:b], kind[a:b] > 0, kind[a:b],
                            points[a:b], directions[a:b])
                for trajectory, pulse, beam, a, b in self._by_line(chunk, slot)]

    def _by_line(self, chunk: list[Segment], slots: np.ndarray):
        """Split a chunk's slot indices (ascending) by flight line: (trajectory, pulse within the line,
        beam, a, b) for each line holding any, the slots being ``slots[a:b]``."""
        pulse = slots // self.beams_per_pulse  # within the chunk
        starts = np.cumsum([0] + [s.count for s in chunk])
        bounds = np.searchsorted(pulse, starts)
        for segment, a, b, offset in zip(chunk, bounds[:-1], bounds[1:], starts[:-1]):
            if b > a:
                yield (self.trajectories[segment.line], segment.first + pulse[a:b] - offset,
                       (slots[a:b] % self.beams_per_pulse).astype(np.int32), a, b)

    def accumulate_deviations(self, sums: wp.array, squares: wp.array, hits: wp.array) -> RunCounts:
        """Budget mode: add each slot's believed − true point [m, local] and its square to float64 sums on
        the device, indexed by run slot (pulse of the run · beams per pulse + beam). Nothing else leaves
        the device; needs ``with_truth`` and the exact model."""
        from kernels.budget import accumulate_deviations

        if not (self.features.with_truth and self.features.exact):
            raise ValueError("accumulate_deviations needs with_truth=True and the exact model")
        started = time.perf_counter()
        counts = RunCounts()
        if self._points is None:
            self._points = _PointBuffers(self.pulses_per_launch(POINT_SLOTS_PER_CHUNK), self.beams_per_pulse, self.rows.total,
                                         self.device)
        buffers = self._points
        buffers.counters.zero_()
        kernel = trace.points_kernel(self.features, self.instrument.kernel, max_registers=self.max_registers)
        for chunk in self._chunks(buffers.pulses, counts, None):
            base = counts.pulses * self.beams_per_pulse
            n_slots = sum(s.count for s in chunk) * self.beams_per_pulse
            wp.launch(kernel, n_slots, inputs=[buffers.pulses, self.scan], outputs=buffers.slot_outputs(),
                      device=self.device)
            wp.launch(accumulate_deviations, n_slots, inputs=[buffers.status, buffers.model_points["exact"],
                                                               buffers.true_points, base],
                      outputs=[sums, squares, hits], device=self.device)
        return self._finish(counts, buffers.counters, started)

    def run_statistics(self, progress: Callable[[int, int], None] | None = None,
                       slots_per_thread: int | None = None,
                       share: tuple[int, int] = (0, 1)) -> tuple[dict[str, PlaneMoments], RunCounts]:
        """Statistics mode: per-plane float64 moments of each model, accumulated on the device.

        No point leaves the device: one kernel writes each slot's plane and points to a record
        buffer on the device (a second settles the returns near plane boundaries), a third reduces
        the records, ``slots_per_thread`` consecutive ones per thread.
        Returns within the edge buffer of a plane boundary are left out (``RunCounts.edge_excluded``).
        ``share`` = (k, n) runs only every n-th chunk from the k-th, so n processes can split a run
        and add their sums.
        """
        self._require_discrete("statistics")
        started = time.perf_counter()
        counts = RunCounts()
        spt = slots_per_thread or self.cfg.run.slots_per_thread or SLOTS_PER_THREAD[self.device_kind]
        if self._statistics is None:
            self._statistics = _StatisticsBuffers(self, self.pulses_per_launch())
        b = self._statistics
        sums = b.zeroed_sums()
        trace_records = trace.records_kernel(self.features, self.instrument.kernel, max_registers=self.max_registers)
        reduce_records = trace.reduce_kernel(self.features)
        d = self.device
        for chunk in self._chunks(b.pulses, counts, progress, share):
            n_slots = sum(s.count for s in chunk) * self.beams_per_pulse
            wp.launch(trace_records, n_slots, inputs=[b.pulses, self.scan, b.face_plane],
                      outputs=[*b.records, *b.near], device=d)
            if self.features.edges:
                wp.launch(trace.check_edges_kernel(self.instrument.kernel), n_slots, inputs=[self.scan, self.edge_buffer_m, *b.near],
                          outputs=[b.records[0]], device=d)
                b.near[0].zero_()
            wp.launch(reduce_records, (n_slots + spt - 1) // spt,
                      inputs=[*b.records, n_slots, spt, b.references], outputs=sums, device=d)
        count, first, second = replica_totals(sums[:3])
        counters = sums[3].numpy()
        moments = {}
        for k, model in enumerate(MODELS):
            if model in self.models:
                m = PlaneMoments(b.reference_points)
                m.add_sums(count[k], first[k], symmetric(second[k]))
                moments[model] = m
        counts.edge_excluded = int(counters[2])
        self._finish(counts, sums[3], started)
        counts.returns = counts.beams_fired - counts.tir_dropped - counts.misses
        return moments, counts

    def sum_replicas(self, groups: int | None = None) -> int:
        """Copies of the per-group sums (``groups`` of them, the scene's planes by default) of the statistics
        reduction (:func:`flightsim.scoring.reduction.sum_replicas`)."""
        groups = len(self.scene.planes) if groups is None else groups
        return sum_replicas(self.device_kind, groups, self.cfg.run.sum_replicas)

    # ------------------------------------------------------------------------------------------

    def windows(self, trajectory: Trajectory) -> list[tuple[int, int]]:
        """Pulse index ranges [k0, k1) of a trajectory to launch: within the line's pulse limits, and
        (with culling on) only those whose beams can reach the scene. Worked out once per line."""
        if trajectory.line_id not in self._windows:
            self._windows[trajectory.line_id] = self._plan_windows(trajectory)
        return self._windows[trajectory.line_id]

    def _plan_windows(self, trajectory: Trajectory) -> list[tuple[int, int]]:
        lo, hi = self.pulse_limits.get(trajectory.line_id, (0, self.pulse_count(trajectory)))
        hi = min(hi, self.pulse_count(trajectory))
        if not self.cfg.run.cull:
            windows = [(0, hi)]
        else:
            if self._cone_rad is None:
                self._cone_rad = self.instrument.max_off_axis_rad()
            windows = pulse_windows(trajectory, self.scene.world_to_local(trajectory.position), self.scene.bounds(),
                                    self.timing, self._cone_rad, self.boresight_rotation)
        return [(max(k0, lo), min(k1, hi)) for k0, k1 in windows if min(k1, hi) > max(k0, lo)]

    def _chunks(self, pulses: wp.array, counts: RunCounts, progress: Callable[[int, int], None] | None,
                share: tuple[int, int] = (0, 1)) -> Iterator[list[Segment]]:
        """Compute each chunk's pulse poses and per-pulse optics into the pulse table ``pulses`` and
        yield the chunk's segments.

        ``share`` = (k, n) keeps every n-th chunk from the k-th. Range noise is keyed by (seed,
        line, pulse, beam), so culling, chunking and sharing never change it.
        """
        plans = [self.windows(t) for t in self.trajectories]
        pieces = [(line, k0, k1) for line, windows in enumerate(plans) for k0, k1 in windows]
        mine = pack(pieces, pulses.shape[1])[share[0]::share[1]]
        if share[0] == 0:
            counts.pulses_culled = sum(self._limited_count(t) - sum(k1 - k0 for k0, k1 in w)
                                       for t, w in zip(self.trajectories, plans))
        total = sum(s.count for chunk in mine for s in chunk)
        for chunk, table in zip(mine, segment_tables(mine, self.device)):
            n_pulses = sum(s.count for s in chunk)
            wp.launch(frames.pulse_poses, n_pulses, inputs=[self.lines, table, len(chunk)], outputs=[pulses],
                      device=self.device)
            wp.launch(trace.pulse_optics_kernel(self.instrument.kernel, self.features.pose), n_pulses, inputs=[self.scan, pulses],
                      device=self.device)
            yield chunk
            counts.pulses += n_pulses
            if progress:
                progress(counts.pulses, total)

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

    def sample_rays(self, max_slots: int) -> tuple[wp.array, wp.array]:
        """The float32 rays of the run's first slots (up to ``max_slots``), on the device."""
        pulses = _pulse_table(max(1, max_slots // self.beams_per_pulse), self.rows.total, self.device)
        chunk = next(self._chunks(pulses, RunCounts(), None))
        n = sum(s.count for s in chunk) * self.beams_per_pulse
        starts = wp.empty(n, dtype=wp.vec3f, device=self.device)
        directions = wp.empty(n, dtype=wp.vec3f, device=self.device)
        wp.launch(trace.emit_rays_kernel(self.instrument.kernel), n, inputs=[pulses, self.scan], outputs=[starts, directions], device=self.device)
        return starts, directions

    def sample_subrays(self, max_rays: int) -> tuple[wp.array, wp.array]:
        """The float32 sub-rays of the waveform detector for the run's first beams (up to ``max_rays``
        rays), on the device: what the deposit kernel casts."""
        from kernels import waveform as kw

        subrays = self.instrument.detector.subrays(self.device)
        pulses = _pulse_table(max(1, max_rays // (len(subrays) * self.beams_per_pulse)), self.rows.total, self.device)
        chunk = next(self._chunks(pulses, RunCounts(), None))
        n = sum(s.count for s in chunk) * self.beams_per_pulse
        starts, directions = (wp.empty(n, dtype=wp.vec3d, device=self.device) for _ in range(2))
        wp.launch(trace.emit_rays_kernel(self.instrument.kernel, precise=True), n, inputs=[pulses, self.scan],
                  outputs=[starts, directions], device=self.device)
        ray_starts, ray_directions = (wp.empty(n * len(subrays), dtype=wp.vec3f, device=self.device) for _ in range(2))
        wp.launch(kw.emit_subrays, (n, len(subrays)), inputs=[starts, directions, subrays.offsets],
                  outputs=[ray_starts, ray_directions], device=self.device)
        return ray_starts, ray_directions

    def _finish(self, counts: RunCounts, counters: wp.array, started: float) -> RunCounts:
        tir, misses = (int(v) for v in counters.numpy()[:2])
        counts.beams_fired = counts.pulses * self.beams_per_pulse
        counts.tir_dropped, counts.misses = tir, misses
        counts.wall_s = time.perf_counter() - started
        return counts

    def _returns(self, returns: DeviceReturns) -> list[ReturnChunk]:
        """Compact a chunk's returning slots on the device, bring them to the host, split by line."""
        buffers, n_slots, n_returns = returns.buffers, returns.n_slots, returns.count
        slots = buffers.index.numpy()[:n_returns].astype(np.int64)
        gather = buffers.gather
        f = self.features
        fields = dict(
            range_m=gather(buffers.ranges, n_slots, n_returns),
            face=gather(buffers.faces, n_slots, n_returns),
            scan_angle_deg=gather(buffers.scan_angles, n_slots, n_returns),
            cos_incidence=gather(buffers.cos_incidence, n_slots, n_returns),
            edge_distance_m=gather(buffers.edge_distance, n_slots, n_returns) if f.edges else None,
            points={m: gather(buffers.model_points[m], n_slots, n_returns).astype(np.float64) for m in self.models},
            true_points=gather(buffers.true_points, n_slots, n_returns).astype(np.float64) if f.with_truth else None,
        )
        return [ReturnChunk(line_id=trajectory.line_id, start_time=trajectory.start_time, pulse=pulse, beam=beam,
                            **_sliced(fields, a, b))
                for trajectory, pulse, beam, a, b in self._by_line(returns.segments, slots)]


class _Retroreflectors:
    """The scene's corner-cube retroreflectors as the photon kernel reads them, and the chunk's true beam
    rays they need (one-element placeholders when the scene has none)."""

    def __init__(self, scene, divergence_mrad: float, slots: int, device: str):
        """scene: the [scene] settings (ccrs, ccr_photons); divergence_mrad: the beams' full divergence [mrad]."""
        positions = np.asarray(scene.ccrs, dtype=np.float64).reshape(-1, 3)
        self.count = len(positions)
        self.positions = wp.array(positions, dtype=wp.vec3d, device=device)
        self.photons = scene.ccr_photons
        self.footprint = divergence_mrad * 0.5e-3  # the e⁻² half angle [rad]
        size = slots if self.count else 1
        self.starts, self.directions = (wp.empty(size, dtype=wp.vec3d, device=device) for _ in range(2))


class _PhotonBuffers:
    """Device arrays of photon mode: each slot's detections, and the flat compacted events (sized for
    FLAT_EVENTS_PER_SLOT detections per slot at first, grown when a chunk holds more)."""

    FLAT = {"slot": wp.int32, "tof": wp.float64, "flag": wp.int8, "points": wp.vec3d, "directions": wp.vec3f}
    FLAT_EVENTS_PER_SLOT = 2

    def __init__(self, slots: int, max_events: int, device: str):
        self.device = device
        self.times = wp.empty((slots, max_events), dtype=wp.float64, device=device)
        self.signal = wp.empty((slots, max_events), dtype=wp.int8, device=device)
        self.counts = wp.empty(slots, dtype=wp.int32, device=device)
        self.offsets = wp.empty(slots, dtype=wp.int32, device=device)
        self.capacity = 0
        self._reserve(slots * min(max_events, self.FLAT_EVENTS_PER_SLOT))

    def _reserve(self, n: int) -> None:
        """Flat arrays for at least ``n`` detections (their contents are not kept)."""
        if n <= self.capacity:
            return
        self.capacity = max(n, self.capacity + self.capacity // 2)
        for name, dtype in self.FLAT.items():
            setattr(self, name, wp.empty(self.capacity, dtype=dtype, device=self.device))

    def gather(self, n_slots: int, pulses: wp.array, scan, instrument) -> DevicePhotons:
        """Compact every slot's detections (ordered by slot) and place each on its believed beam, on the device."""
        from kernels import photon

        counts, offsets = self.counts[:n_slots], self.offsets[:n_slots]
        wp.utils.array_scan(counts, offsets, inclusive=False)
        n = int(to_host(offsets[n_slots - 1:])[0] + to_host(counts[n_slots - 1:])[0])
        self._reserve(n)
        wp.launch(photon.gather_events, n_slots, inputs=[counts, offsets, self.times, self.signal],
                  outputs=[self.slot, self.tof, self.flag], device=self.device)
        if n:
            wp.launch(trace.photon_points_kernel(instrument), n, inputs=[pulses, scan, self.slot[:n], self.tof[:n]],
                      outputs=[self.points, self.directions], device=self.device)
        return DevicePhotons(n, self.slot[:n], self.tof[:n], self.flag[:n], self.points[:n], self.directions[:n])


def _pulse_table(pulses: int, rows: int, device: str) -> wp.array:
    """A chunk's per-pulse table: ``rows`` float64 rows (pose, then optics; trace.pulse_rows), one column per pulse."""
    return wp.empty((rows, pulses), dtype=wp.float64, device=device)


def _sliced(fields: dict, a: int, b: int) -> dict:
    """Rows a:b of every array in a dict of arrays, dicts of arrays and Nones."""
    def cut(v):
        if v is None:
            return None
        return {k: x[a:b] for k, x in v.items()} if isinstance(v, dict) else v[a:b]
    return {k: cut(v) for k, v in fields.items()}


class _StatisticsBuffers:
    """Device arrays of statistics mode for one simulator, allocated once and reused by its runs."""

    def __init__(self, sim: Simulator, pulses: int):
        d, slots, f = sim.device, pulses * sim.beams_per_pulse, sim.features
        self.device = d
        self.pulses = _pulse_table(pulses, sim.rows.total, d)
        self.records = [wp.empty(slots, dtype=wp.int32, device=d)] + [
            wp.empty(slots if model in sim.models else 1, dtype=wp.vec3f, device=d) for model in MODELS]
        listed = slots if f.edges else 1  # returns the edge grid leaves to the boundary query
        self.near = [wp.zeros(1, dtype=wp.int32, device=d), wp.empty(listed, dtype=wp.int32, device=d),
                     wp.empty(listed, dtype=wp.vec3f, device=d)]
        self.face_plane = wp.array(sim.scene.plane_id.astype(np.int32), dtype=wp.int32, device=d)
        self.reference_points = np.array([plane.point for plane in sim.scene.planes], dtype=np.float64)  # [m, local]
        self.references = wp.array(self.reference_points, dtype=wp.vec3d, device=d)
        self.sum_shape = (sim.sum_replicas(), 2, len(sim.scene.planes))

    def zeroed_sums(self) -> list[wp.array]:
        """Fresh per-plane sums (count, Σd, Σddᵀ per replica, model and plane) and counters."""
        d, shape = self.device, self.sum_shape
        return [wp.zeros(shape, dtype=wp.int64, device=d), wp.zeros(shape, dtype=wp.vec3d, device=d),
                wp.zeros(shape, dtype=trace.vec6d, device=d), wp.zeros(3, dtype=wp.int32, device=d)]


class _PointBuffers:
    """Device arrays for one chunk in points mode, allocated once per run and reused."""

    def __init__(self, pulses: int, beams_per_pulse: int, rows: int, device: str):
        self.device = device
        slots = pulses * beams_per_pulse
        self.pulses = _pulse_table(pulses, rows, device)
        self.status = wp.empty(slots, dtype=wp.int32, device=device)
        self.ranges = wp.empty(slots, dtype=wp.float32, device=device)
        self.faces = wp.empty(slots, dtype=wp.int32, device=device)
        self.scan_angles = wp.empty(slots, dtype=wp.float32, device=device)
        self.cos_incidence = wp.empty(slots, dtype=wp.float32, device=device)
        self.edge_distance = wp.empty(slots, dtype=wp.float32, device=device)
        self.true_points = wp.empty(slots, dtype=wp.vec3f, device=device)
        self.model_points = {m: wp.empty(slots, dtype=wp.vec3f, device=device) for m in MODELS}
        self.counters = wp.zeros(3, dtype=wp.int32, device=device)
        self.flags = wp.empty(slots, dtype=wp.int32, device=device)
        self.offsets = wp.empty(slots, dtype=wp.int32, device=device)
        self.index = wp.empty(slots, dtype=wp.int32, device=device)
        self.compacted: dict[int, wp.array] = {}

    def slot_outputs(self) -> list[wp.array]:
        """The points kernel's outputs, in its argument order."""
        return [self.status, self.ranges, self.faces, self.scan_angles, self.cos_incidence, self.edge_distance,
                self.true_points, self.model_points["exact"], self.model_points["nominal"], self.counters]

    def compact_index(self, n_slots: int) -> int:
        """Flag and prefix-sum the returning slots; fill ``index``; return the number of returns."""
        flags, offsets = self.flags[:n_slots], self.offsets[:n_slots]
        wp.launch(trace.flag_returns, n_slots, inputs=[self.status[:n_slots]], outputs=[flags], device=self.device)
        wp.utils.array_scan(flags, offsets, inclusive=False)
        last = np.concatenate([flags[n_slots - 1:n_slots].numpy(), offsets[n_slots - 1:n_slots].numpy()])
        wp.launch(trace.slot_indices, n_slots, inputs=[flags, offsets], outputs=[self.index], device=self.device)
        return int(last.sum())

    def returns_per_segment(self, segments: list[Segment], beams_per_pulse: int) -> list[int]:
        """Returns of each segment of the chunk last compacted (from the prefix sums, a few ints back)."""
        bounds = np.cumsum([0] + [s.count for s in segments]) * beams_per_pulse
        before = wp.array(bounds.astype(np.int32), dtype=wp.int32, device=self.device)
        wp.launch(trace.returns_before, len(bounds), inputs=[self.flags, self.offsets, int(bounds[-1]), before],
                  device=self.device)
        return np.diff(to_host(before)).tolist()

    def gather(self, src: wp.array, n_slots: int, n_returns: int) -> np.ndarray:
        """Compact ``src`` on the device and copy only the returns to the host."""
        dst = self.compacted.get(id(src))
        if dst is None:
            dst = self.compacted[id(src)] = wp.empty(src.shape[0], dtype=src.dtype, device=self.device)
        wp.launch(trace.compact_slots, n_slots, inputs=[self.flags[:n_slots], self.offsets[:n_slots],
                                                        src[:n_slots]], outputs=[dst], device=self.device)
        return dst[:n_returns].numpy()
