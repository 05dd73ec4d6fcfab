"""The waveforms readout of the full-waveform detector: per beam, every sub-ray of its footprint traced and its echo
summed into the beam's waveform on the device (kernels/waveform.py: pilot ray, deposit, convolution with the pulse,
the receiver's noise and digitiser)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.registry import register
from flightsim.engine.chunks import Segment
from flightsim.scenes.canopy import no_canopy
from kernels import trace
from kernels import waveform as kw

WAVEFORM_SAMPLES_PER_CHUNK = {"cpu": 1 << 22, "cuda": 1 << 28}  # waveform samples per launch


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


def mesh_refs(tracer) -> kw.MeshRefs:
    """The scene as the waveform kernels read it."""
    meshes, refs = tracer.meshes, kw.MeshRefs()
    refs.mesh, refs.padded = meshes.mesh.id, meshes.padded.id
    refs.vertices64, refs.indices = meshes.vertices64, meshes.indices
    refs.max_range = tracer.cfg.instrument.max_range_m
    refs.reflectance = meshes.reflectance
    return refs


class _Buffers:
    """Device arrays of one launch of waveforms."""

    def __init__(self, tracer, params: kw.WaveformParams):
        budget = max(1, WAVEFORM_SAMPLES_PER_CHUNK[tracer.device_kind] // params.samples)
        pulses = max(1, min(tracer.pulses_per_launch(), budget // tracer.beams_per_pulse))
        slots, d = pulses * tracer.beams_per_pulse, tracer.device
        self.pulses = tracer.pulse_table(pulses)
        self.starts, self.directions = (wp.empty(slots, dtype=wp.vec3d, device=d) for _ in range(2))
        self.window = wp.empty(slots, dtype=wp.float64, device=d)
        self.impulses = wp.empty((slots, params.samples), dtype=wp.float64, device=d)
        self.power = wp.empty((slots, params.samples), dtype=wp.float32, device=d)
        self.received = wp.empty((slots, 4), dtype=wp.float64, device=d)
        self.span = wp.empty((slots, 2), dtype=wp.int32, device=d)
        self.keys = wp.empty(slots, dtype=wp.int64, device=d)


@register("readout", "waveforms")
class Waveforms:
    """A full waveform per beam. ``consume`` gets each flight line's part of each chunk as a host
    :class:`WaveformChunk` (beams whose central ray reached the scene), or with ``on_device`` each chunk's
    :class:`DeviceWaveforms`; ``RunCounts.returns`` counts the sub-rays cast by beams whose central ray reached
    the scene (on the device: every sub-ray launched), ``RunCounts.misses`` the beams whose central ray missed it
    (on the host only)."""

    kind = "waveforms"

    def __init__(self, on_device: bool = False):
        self.on_device = on_device

    def begin(self, tracer) -> wp.array:
        det = tracer.instrument.detector
        canopy = tracer.scene.canopy
        self.params = det.struct(tracer.meshes.per_face, 0.0 if canopy is None else canopy.leaf_reflectance)
        self.subrays = det.subrays(tracer.device)
        self.leaves = no_canopy(tracer.device) if canopy is None else canopy.to_device(tracer.device)
        self.canopy = canopy is not None
        self.taps, self.first_lag = det.pulse_taps(tracer.device)
        self.receiver, self.refs = det.receiver(), mesh_refs(tracer)
        self.buffers = _Buffers(tracer, self.params)
        self.misses = 0
        return self.buffers.pulses

    def chunk(self, tracer, segments: list[Segment], n: int, counts, consume) -> None:
        b, d, params = self.buffers, tracer.device, self.params
        wp.launch(trace.emit_rays_kernel(tracer.instrument.kernel, precise=True, pose=tracer.features.pose), n,
                  inputs=[b.pulses, tracer.scan], outputs=[b.starts, b.directions], device=d)
        wp.launch(kw.pilot, n, inputs=[self.refs, params, b.starts, b.directions], outputs=[b.window], device=d)
        b.impulses.zero_()
        b.received.zero_()
        wp.launch(kw.start_span, n, inputs=[params.samples], outputs=[b.span], device=d)
        groups = -(-len(self.subrays) // kw.SUBRAYS_PER_THREAD)
        wp.launch(kw.deposit_kernel(tracer.meshes.per_face, self.canopy), (n, groups),
                  inputs=[self.refs, params, self.leaves, b.starts, b.directions, b.window, self.subrays.offsets,
                          self.subrays.weights, kw.SUBRAYS_PER_THREAD],
                  outputs=[b.impulses, b.received, b.span], device=d)
        wp.launch(kw.convolve, (n, params.samples), inputs=[b.impulses, b.span, self.taps, self.first_lag],
                  outputs=[b.power], device=d)
        if self.receiver is not None:
            wp.launch(kw.beam_keys, n, inputs=[b.pulses, tracer.beams_per_pulse], outputs=[b.keys], device=d)
            wp.launch(kw.receive, (n, params.samples), inputs=[self.receiver, params.dt, params.samples, b.keys],
                      outputs=[b.power], device=d)
        self._hand_over(tracer, segments, n, counts, consume)

    def _hand_over(self, tracer, segments: list[Segment], n: int, counts, consume) -> None:
        b = self.buffers
        if self.on_device:
            counts.returns += n * len(self.subrays)
            consume(DeviceWaveforms(n, b.window, b.power, b.received, b.starts, b.directions))
            return
        found = b.window.numpy()[:n]
        slot = np.flatnonzero(found >= 0.0)
        counts.returns += len(slot) * len(self.subrays)
        self.misses += n - len(slot)
        rows = {name: a.numpy()[slot] for name, a in (("power", b.power), ("received", b.received),
                                                       ("start", b.starts), ("direction", b.directions))}
        for trajectory, pulse, beam, lo, hi in tracer.by_line(segments, slot):
            part = WaveformChunk(trajectory.line_id, trajectory.start_time, pulse, beam, found[slot[lo:hi]],
                                 rows["power"][lo:hi], rows["received"][lo:hi], rows["start"][lo:hi],
                                 rows["direction"][lo:hi])
            counts.per_line[part.line_id] = counts.per_line.get(part.line_id, 0) + len(part)
            consume(part)

    def end(self, tracer, counts) -> wp.array:
        return wp.array([0, self.misses, 0], dtype=wp.int32, device=tracer.device)


def sample_subrays(tracer, max_rays: int) -> tuple[wp.array, wp.array]:
    """The float32 sub-rays of the waveform detector for the run's first beams (up to ``max_rays`` rays), on the
    device: what the deposit kernel casts."""
    subrays = tracer.instrument.detector.subrays(tracer.device)
    pulses, n = tracer.first_chunk(max_rays // (len(subrays) * tracer.beams_per_pulse))
    starts, directions = (wp.empty(n, dtype=wp.vec3d, device=tracer.device) for _ in range(2))
    wp.launch(trace.emit_rays_kernel(tracer.instrument.kernel, precise=True), n, inputs=[pulses, tracer.scan],
              outputs=[starts, directions], device=tracer.device)
    ray_starts, ray_directions = (wp.empty(n * len(subrays), dtype=wp.vec3f, device=tracer.device) for _ in range(2))
    wp.launch(kw.emit_subrays, (n, len(subrays)), inputs=[starts, directions, subrays.offsets],
              outputs=[ray_starts, ray_directions], device=tracer.device)
    return ray_starts, ray_directions
