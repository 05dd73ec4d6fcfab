"""The photons readout of the photon-counting detector: every beam traced to its range, its return turned into the
detections of its SPAD pixel on the device (kernels/photon.py: the lidar equation, the echo's spread, background,
dark counts and dead time over the range gate; corner-cube retroreflectors of the scene), each detection placed on
its believed beam."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.lazy import lazy_module
from flightsim.core.registry import register
from flightsim.core.warp_runtime import host_array, to_host
from flightsim.engine.chunks import POINT_SLOTS_PER_CHUNK, SLOTS_PER_CHUNK, Segment
from flightsim.engine.readouts.points import PointBuffers, points_kernels, trace_points
from flightsim.scenes.canopy import no_canopy
from kernels import trace

photon = lazy_module("kernels.photon")
photon_frame = lazy_module("kernels.photon_frame")

FRAME_SLOTS_PER_CHUNK = {"cpu": 1 << 18, "cuda": 1 << 26}  # into a frame: a whole SPAD frame (44M beams) one chunk


@dataclass
class PhotonChunk:
    """The photon detections of one chunk of pulses of one flight line (host arrays, one row per photon)."""

    line_id: int
    start_time: float  # adjusted standard GPS time of the line's pulse 0 [s]
    pulse: np.ndarray  # (m,) int64 pulse index within the line
    pixel: np.ndarray  # (m,) int32 beam (pixel) index
    time_of_flight_s: np.ndarray  # (m,) float64 [s]
    signal: np.ndarray  # (m,) bool: the photon came from the pulse (truth), else background or dark count
    kind: np.ndarray  # (m,) int8 truth: 0 background or dark count, 1 the surface's echo, 2 a retroreflector's, 3 leaves'
    points: np.ndarray  # (m, 3) float64 local [m]: the photon placed on its believed beam at c·t/2
    directions: np.ndarray  # (m, 3) float32 local unit direction of the photon's believed beam
    geodetic: tuple | None = None  # from orbit: (latitude, longitude [deg], height [m]) of every photon, worked out
    # once by the first writer that needs them (flightsim.outputs.photon_las.photon_geodetic)

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


class Retroreflectors:
    """The scene's corner-cube retroreflectors as the photon kernel reads them, and the chunk's true beam
    rays they (or a canopy's leaves: ``rays``) need (one-element placeholders when neither needs them)."""

    def __init__(self, scene, divergence_mrad: float, slots: int, device: str, rays: bool = False):
        """scene: the [scene] settings (ccrs, ccr_photons); divergence_mrad: the beams' full divergence [mrad]."""
        positions = np.asarray(scene.ccrs, dtype=np.float64).reshape(-1, 3)
        self.count = len(positions)
        self.positions = wp.array(positions, dtype=wp.vec3d, device=device)
        self.photons = scene.ccr_photons
        self.footprint = divergence_mrad * 0.5e-3  # the e⁻² half angle [rad]
        size = slots if self.count or rays else 1
        self.starts, self.directions = (wp.empty(size, dtype=wp.vec3d, device=device) for _ in range(2))


class PhotonBuffers:
    """Device arrays of the photons readout: each slot's detections, and the flat compacted events (allocated at
    the first ``gather``, sized for FLAT_EVENTS_PER_SLOT detections per slot at first, grown when a chunk holds
    more; a readout writing into a frame never needs them)."""

    FLAT = {"slot": wp.int32, "tof": wp.float64, "flag": wp.int8, "points": wp.vec3d, "directions": wp.vec3f}
    FLAT_EVENTS_PER_SLOT = 2

    def __init__(self, slots: int, max_events: int, device: str):
        self.device = device
        self.times = wp.empty((slots, max_events), dtype=wp.float64, device=device)
        self.signal = wp.empty((slots, max_events), dtype=wp.int8, device=device)
        self.counts = wp.empty(slots, dtype=wp.int32, device=device)
        self.offsets = wp.empty(slots, dtype=wp.int32, device=device)
        self.capacity = 0
        self.first = slots * min(max_events, self.FLAT_EVENTS_PER_SLOT)

    def _reserve(self, n: int) -> None:
        """Flat arrays for at least ``n`` detections (their contents are not kept)."""
        if self.capacity and n <= self.capacity:
            return
        self.capacity = max(n, self.first, self.capacity + self.capacity // 2)
        for name, dtype in self.FLAT.items():
            setattr(self, name, wp.empty(self.capacity, dtype=dtype, device=self.device))

    def gather(self, n_slots: int, pulses: wp.array, scan, instrument) -> DevicePhotons:
        """Compact every slot's detections (ordered by slot) and place each on its believed beam, on the device."""
        counts, offsets = self.counts[:n_slots], self.offsets[:n_slots]
        wp.utils.array_scan(counts, offsets, inclusive=False)
        n = int(to_host(offsets[n_slots - 1:])[0] + to_host(counts[n_slots - 1:])[0])
        self._reserve(n)
        wp.launch(photon.gather_events, n_slots, inputs=[counts, offsets, self.times, self.signal],
                  outputs=[self.slot, self.tof, self.flag], device=self.device)
        if n == 0:  # Warp arrays cannot be sliced to nothing
            return DevicePhotons(0, *(wp.empty(0, dtype=dtype, device=self.device) for dtype in self.FLAT.values()))
        wp.launch(trace.photon_points_kernel(instrument), n, inputs=[pulses, scan, self.slot[:n], self.tof[:n]],
                  outputs=[self.points, self.directions], device=self.device)
        return DevicePhotons(n, self.slot[:n], self.tof[:n], self.flag[:n], self.points[:n], self.directions[:n])

    def into_frame(self, frame, n_slots: int, pulses: wp.array, scan, instrument, found: wp.array) -> None:
        """Place every slot's detections into ``frame`` after its photons so far, and add their count to the
        frame's and to ``found[0]``, all on the device (no host sync)."""
        counts, offsets = self.counts[:n_slots], self.offsets[:n_slots]
        wp.utils.array_scan(counts, offsets, inclusive=False)
        xyz, cell, total, signal_count = frame.device_arrays()
        wp.launch(photon_frame.frame_photons_kernel(instrument), n_slots,
                  inputs=[pulses, scan, counts, offsets, self.times, self.signal, total, len(xyz), frame.half_field,
                          frame.cells], outputs=[xyz, cell, signal_count], device=self.device)
        wp.launch(photon_frame.advance_total, 1, inputs=[counts, offsets, n_slots - 1], outputs=[total, found],
                  device=self.device)


@register("readout", "photons")
class Photons:
    """The detections of every SPAD pixel. ``consume`` gets each flight line's part of each chunk as a host
    :class:`PhotonChunk`, or with ``on_device`` each chunk's :class:`DevicePhotons`; with ``frame`` (a
    :class:`~flightsim.scoring.photon_grid.PhotonFrame`) every chunk's detections go straight into the frame
    (placed and given their angle cells in one kernel, no count brought to the host between chunks; ``consume``
    is not called). ``RunCounts.returns`` counts the photons.

    Per chunk of n slots (CUDA; the frame path): the points kernel (ranges only), the photon kernel (n threads),
    a scan of the slot counts, the frame kernel (n threads) and a one-thread count: 5 launches, no host sync;
    the run's one sync is its end (the counters and the photon count, 16 bytes). Memory per slot: the points
    kernel writes ~72 bytes, the photon kernel reads ~20 and writes 9 per detection (8 stop registers), the frame
    kernel reads 8 + 9 per detection and writes 32 per detection."""

    kind = "photons"

    def __init__(self, on_device: bool = False, frame=None):
        self.on_device, self.frame = on_device or frame is not None, frame

    def begin(self, tracer) -> wp.array:
        budget = POINT_SLOTS_PER_CHUNK  # on the host, photons fill memory
        if self.frame is not None:
            budget = FRAME_SLOTS_PER_CHUNK
        elif self.on_device:
            budget = SLOTS_PER_CHUNK
        pulses = tracer.pulses_per_launch(budget)
        self.buffers, self.events, self.retro, self.leaves, self.energy, self.found = tracer.kept(
            f"photons:{pulses}", lambda: _buffers(tracer, pulses))  # allocated once per tracer: frame after frame
        settings = tracer.instrument.detector.s
        self.detector, self.reflectance = tracer.instrument.detector.struct(), settings.reflectance
        self.ranges_only = _ranges_only(tracer)
        canopy = tracer.scene.canopy
        self.leaf_reflectance = 0.0 if canopy is None else canopy.leaf_reflectance
        self.found.zero_()
        self.buffers.counters.zero_()
        return self.buffers.pulses

    def chunk(self, tracer, segments: list[Segment], n_slots: int, counts, consume) -> None:
        b, retro, d = self.buffers, self.retro, tracer.device
        trace_points(tracer, b, n_slots, self.ranges_only)  # ranges only: no georeferencing
        leaves = tracer.scene.canopy is not None
        if retro.count or leaves:  # the beams' true rays
            wp.launch(_rays_kernel(tracer), n_slots, inputs=[b.pulses, tracer.scan],
                      outputs=[retro.starts, retro.directions], device=d)
        meshes = tracer.meshes
        wp.launch(photon.photon_slots_kernel(retro.count > 0, meshes.per_face, leaves), n_slots,
                  inputs=[self.detector, self.reflectance, meshes.reflectance, b.pulses, tracer.beams_per_pulse,
                          self.energy, b.status, b.ranges, b.faces, b.cos_incidence, retro.positions, retro.photons, retro.footprint,
                          retro.starts, retro.directions, tracer.scan.ranging.delays, tracer.scan.ranging.drift,
                          self.leaves, self.leaf_reflectance],
                  outputs=[self.events.times, self.events.signal, self.events.counts], device=d)
        if self.frame is not None:
            self.events.into_frame(self.frame, n_slots, b.pulses, tracer.scan, tracer.instrument.kernel, self.found)
            return
        found = self.events.gather(n_slots, b.pulses, tracer.scan, tracer.instrument.kernel)
        counts.returns += found.count
        if self.on_device:
            consume(found)
            return
        for part in _host_photons(tracer, segments, found):
            counts.per_line[part.line_id] = counts.per_line.get(part.line_id, 0) + len(part)
            consume(part)

    def kernels_needed(self, tracer) -> list:
        retro, leaves = len(tracer.cfg.scene.ccrs) > 0, tracer.scene.canopy is not None
        frame = [photon_frame.frame_photons_kernel(tracer.instrument.kernel), photon_frame.advance_total]
        return [*points_kernels(tracer, _ranges_only(tracer), 1),
                photon.photon_slots_kernel(retro, tracer.meshes.per_face, leaves), photon.gather_events,
                trace.photon_points_kernel(tracer.instrument.kernel), *([_rays_kernel(tracer)] if retro or leaves else []),
                *(frame if self.frame is not None else [])]

    def end(self, tracer, counts) -> wp.array:
        if self.frame is None:
            return self.buffers.counters
        counters = to_host(self.buffers.counters)  # the run's one sync
        counts.returns += int(to_host(self.found)[0])
        return wp.array(counters, dtype=wp.int32, device="cpu")  # read by the tracer without another device copy


def _buffers(tracer, pulses: int) -> tuple:
    """The photons readout's device memory for chunks of ``pulses`` pulses: (point buffers, photon buffers,
    retroreflectors, leaves, beam energies, the run's photon count)."""
    buffers = PointBuffers(tracer, pulses)
    slots, d = len(buffers.status), tracer.device
    events = PhotonBuffers(slots, tracer.instrument.detector.s.max_events, d)
    retro = Retroreflectors(tracer.cfg.scene, tracer.instrument.emitter.divergence_mrad, slots, d,
                            rays=tracer.scene.canopy is not None)
    canopy = tracer.scene.canopy
    leaves = no_canopy(d) if canopy is None else canopy.to_device(d)
    energy = wp.array(beam_energy(tracer.instrument.emitter), dtype=wp.float64, device=d)
    return buffers, events, retro, leaves, energy, wp.zeros(1, dtype=wp.int32, device=d)


def _ranges_only(tracer) -> trace.Features:
    """The tracer's features without georeferencing: the photon readout's points kernel makes ranges only."""
    return dataclasses.replace(tracer.features, exact=False, nominal=False, edges=False)


def _rays_kernel(tracer):
    """The kernel of the beams' true float64 rays (for the retroreflectors' footprints and the leaves)."""
    return trace.emit_rays_kernel(tracer.instrument.kernel, precise=True, pose=tracer.features.pose)


def beam_energy(emitter) -> np.ndarray:
    """Each beam's pulse energy over ``photon.pulse_energy_j``: the emitter's ``energy_scale()`` (ATLAS's pairs:
    1 strong, 1/ratio weak), else 1 for every beam."""
    scale = getattr(emitter, "energy_scale", None)
    return np.ones(emitter.beams_per_pulse) if scale is None else np.asarray(scale(), dtype=np.float64)


def _host_photons(tracer, segments: list[Segment], found: DevicePhotons):
    """A chunk's detections (ordered by slot) on the host, split by flight line and then into parts of at most
    ``run.host_photons`` photons of whole pulses (a pulse holding more is a part of its own), each part copied from the
    device as it is asked for: while the consumer holds a few parts, the host holds no more of a long chunk (arrays of
    the caller's own: a consumer may keep them while later chunks reuse the device buffers)."""
    slot = host_array(found.slot).astype(np.int64)
    for trajectory, pulse, beam, a, b in tracer.by_line(segments, slot):
        for lo, hi in pulse_parts(pulse, tracer.cfg.run.host_photons):
            rows = slice(int(a) + lo, int(a) + hi)  # Warp's slices take Python integers
            tof, kind = host_array(found.time_of_flight_s[rows]), host_array(found.signal[rows])
            yield PhotonChunk(trajectory.line_id, trajectory.start_time, pulse[lo:hi].copy(), beam[lo:hi].copy(), tof,
                              kind > 0, kind, host_array(found.points[rows]), host_array(found.directions[rows]))


def pulse_parts(pulse: np.ndarray, most: int) -> list[tuple[int, int]]:
    """[lo, hi) parts of the ascending ``pulse`` indices covering them all, each of at most ``most`` rows and of
    whole pulses (a pulse of more rows is a part of its own)."""
    parts, lo = [], 0
    while lo < len(pulse):
        hi = len(pulse)
        if lo + most < hi:
            hi = int(np.searchsorted(pulse, pulse[lo + most], side="left"))
            if hi == lo:  # one pulse of more than ``most`` rows
                hi = int(np.searchsorted(pulse, pulse[lo], side="right"))
        parts.append((lo, hi))
        lo = hi
    return parts
