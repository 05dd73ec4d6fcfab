"""The readouts of the full-waveform detector. ``waveforms``: per beam, every sub-ray of its footprint traced and its
echo summed into the beam's waveform on the device (kernels/waveform.py: pilot ray, deposit, convolution with the
pulse, the receiver's noise and digitiser). ``cloud_waveforms``: over a point-cloud scene, per beam the ALS points
around its axis summed by the GEDI simulator's method (:mod:`flightsim.engine.cloud_waveforms`), in the same window
and through the same receiver."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.lazy import lazy_module
from flightsim.core.process_map import by_pieces
from flightsim.core.registry import register
from flightsim.core.warp_runtime import host_array
from flightsim.engine.chunks import Segment
from flightsim.engine.readouts.convolution import PulseConvolution
from flightsim.scenes.canopy import no_canopy
from kernels import trace

kw = lazy_module("kernels.waveform")
kc = lazy_module("kernels.cloud_waveform")

WAVEFORM_SAMPLES_PER_CHUNK = {"cpu": 1 << 22, "cuda": 1 << 28}  # waveform samples per launch
C = 299_792_458.0  # [m/s]
POWER_ROWS = 256  # the fewest cloud waveforms of a piece of _to_power's host work


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
    clean_w: np.ndarray | None = None  # (m, samples) float32 power before the receiver's noise and digitiser [W]

    def __len__(self) -> int:
        return len(self.pulse)


@dataclass
class DeviceWaveforms:
    """A chunk's waveforms on the device, one row per slot (valid until the next chunk; read only: the next chunk
    clears only what this one wrote)."""

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
    """Device arrays of one launch of waveforms (``traced``: with the sub-rays' impulse trains)."""

    def __init__(self, tracer, params: kw.WaveformParams, traced: bool = True, keep_clean: bool = False):
        budget = max(1, WAVEFORM_SAMPLES_PER_CHUNK[tracer.device_kind] // params.samples)
        pulses = max(1, min(tracer.pulses_per_launch(), budget // tracer.beams_per_pulse))
        slots, d = pulses * tracer.beams_per_pulse, tracer.device
        self.pulses = tracer.pulse_table(pulses)
        self.starts, self.directions = (wp.empty(slots, dtype=wp.vec3d, device=d) for _ in range(2))
        self.window = wp.empty(slots, dtype=wp.float64, device=d)
        self.power = wp.zeros((slots, params.samples), dtype=wp.float32, device=d)  # without a receiver: 0 beyond
        # the last chunk's reach (Waveforms.chunk)
        self.clean = wp.empty((slots, params.samples), dtype=wp.float32, device=d) if keep_clean else None
        self.keys = wp.empty(slots, dtype=wp.int64, device=d)
        if traced:
            self.impulses = wp.zeros((slots, params.samples), dtype=wp.float64, device=d)  # 0 beyond ``touched``
            self.touched = 0  # the last chunk's rows: their power and narrow rows' impulses, within ``span``, to clear
            self.received = wp.empty((slots, 4), dtype=wp.float64, device=d)
            self.span = wp.empty((slots, 2), dtype=wp.int32, device=d)
            self.last_span = wp.empty((slots, 2), dtype=wp.int32, device=d)  # the last chunk's (rows < touched)


def pilot_kernels(tracer) -> list:
    """The kernels of :func:`pilot_windows` and :func:`receive` (the beams' rays; the waveform module)."""
    return [trace.emit_rays_kernel(tracer.instrument.kernel, precise=True, pose=tracer.features.pose), kw.pilot]


def pilot_windows(tracer, b: _Buffers, refs: kw.MeshRefs, params: kw.WaveformParams, n: int) -> None:
    """Each slot's beam (start, direction) and window start (−1 where its central ray misses the scene)."""
    d = tracer.device
    wp.launch(pilot_kernels(tracer)[0], n, inputs=[b.pulses, tracer.scan], outputs=[b.starts, b.directions], device=d)
    wp.launch(kw.pilot, n, inputs=[refs, params, b.starts, b.directions], outputs=[b.window], device=d)


def by_lane(subrays, per_thread: int) -> tuple[wp.array, wp.array]:
    """The sub-rays' offsets and weights as the deposit kernel reads them: (per_thread, groups) arrays holding
    sub-ray group·per_thread + i at [i, group] (0 past the last), so that the threads of a warp, which take
    neighbouring groups, read neighbouring entries at each step (rather than each its own line, per_thread entries
    from its neighbour's)."""
    count, device = len(subrays), subrays.weights.device
    groups = -(-count // per_thread)
    tables = []
    for values in (subrays.offsets.numpy(), subrays.weights.numpy()):
        padded = np.zeros((groups * per_thread, *values.shape[1:]), dtype=values.dtype)
        padded[:count] = values
        tables.append(np.ascontiguousarray(np.swapaxes(padded.reshape(groups, per_thread, *values.shape[1:]), 0, 1)))
    return (wp.array(tables[0], dtype=wp.vec2d, device=device), wp.array(tables[1], dtype=wp.float64, device=device))


def receive(tracer, receiver: kw.Receiver | None, params: kw.WaveformParams, b: _Buffers, n: int) -> None:
    """The receiver's reading of the first ``n`` rows of ``b.power`` (kept first in ``b.clean`` when it is kept)."""
    if receiver is None:
        return
    d = tracer.device
    if b.clean is not None:
        wp.copy(b.clean, b.power, count=n * params.samples)
    wp.launch(kw.beam_keys, n, inputs=[b.pulses, tracer.beams_per_pulse], outputs=[b.keys], device=d)
    wp.launch(kw.receive, (n, params.samples), inputs=[receiver, params.dt, params.samples, b.keys],
              outputs=[b.power], device=d)


def hand_over(tracer, segments: list[Segment], slot: np.ndarray, rows: dict[str, np.ndarray], counts,
              consume) -> None:
    """Each flight line's part of a chunk's waveforms to ``consume`` as a :class:`WaveformChunk`: the slots ``slot``
    (ascending) that made one, ``rows`` their window starts, power, received, start, direction and (or None) clean
    power."""
    for trajectory, pulse, beam, lo, hi in tracer.by_line(segments, slot):
        clean = rows["clean"]
        part = WaveformChunk(trajectory.line_id, trajectory.start_time, pulse, beam, rows["window"][lo:hi],
                             rows["power"][lo:hi], rows["received"][lo:hi], rows["start"][lo:hi],
                             rows["direction"][lo:hi], None if clean is None else clean[lo:hi])
        counts.per_line[part.line_id] = counts.per_line.get(part.line_id, 0) + len(part)
        consume(part)


@register("readout", "waveforms")
class Waveforms:
    """A full waveform per beam. ``consume`` gets each flight line's part of each chunk as a host
    :class:`WaveformChunk` (beams whose central ray reached the scene), or with ``on_device`` each chunk's
    :class:`DeviceWaveforms`; ``RunCounts.returns`` counts the sub-rays cast by beams whose central ray reached
    the scene (on the device: every sub-ray launched), ``RunCounts.misses`` the beams whose central ray missed it
    (on the host only). ``keep_clean``: each WaveformChunk also holds the power before the receiver's noise and
    digitiser (``clean_w``; None when the detector has no receiver chain, the power being clean)."""

    kind = "waveforms"

    def __init__(self, on_device: bool = False, keep_clean: bool = False, **fft):
        self.on_device, self.keep_clean = on_device, keep_clean
        self.fft = fft  # with waveform.convolution = "fft": fft_least, block_dim, direct_below (PulseConvolution)

    def begin(self, tracer) -> wp.array:
        det = tracer.instrument.detector
        canopy = tracer.scene.canopy
        self.params = det.struct(tracer.meshes.per_face, 0.0 if canopy is None else canopy.leaf_reflectance)
        self.subrays = tracer.kept("waveform subrays", lambda: det.subrays(tracer.device))
        self.by_lane = tracer.kept("waveform subrays by lane", lambda: by_lane(self.subrays, kw.SUBRAYS_PER_THREAD))
        self.leaves = no_canopy(tracer.device) if canopy is None else canopy.to_device(tracer.device)
        self.canopy = canopy is not None
        self.convolution = self._convolution(tracer)
        self.receiver, self.refs = det.receiver(), mesh_refs(tracer)
        keep_clean = self.keep_clean and self.receiver is not None  # the device buffers are kept for the tracer's
        # next run (a study runs one tracer many times): their allocation and first zeroing are paid once
        self.buffers = tracer.kept(f"waveforms keep_clean={keep_clean}",
                                   lambda: _Buffers(tracer, self.params, keep_clean=keep_clean))
        self.misses = 0
        return self.buffers.pulses

    def chunk(self, tracer, segments: list[Segment], n: int, counts, consume) -> None:
        b, d, params = self.buffers, tracer.device, self.params
        pilot_windows(tracer, b, self.refs, params, n)
        conv, clean = self.convolution, self.receiver is None  # clean: no receiver writes whole rows of power
        last = b.touched  # the last chunk's rows: their impulse trains and power are cleared within their spans only
        if last:  # the trains the convolution did not zero as it read them
            wp.launch(kw.clear_impulses, (last, kw.CLEAR_THREADS), inputs=[b.span, conv.zeroes_narrower],
                      outputs=[b.impulses], device=d)
        b.span, b.last_span, b.touched = b.last_span, b.span, n
        b.received.zero_()
        wp.launch(kw.start_span, n, inputs=[params.samples], outputs=[b.span], device=d)
        offsets, weights = self.by_lane
        wp.launch(kw.deposit_kernel(tracer.meshes.per_face, self.canopy), (n, offsets.shape[1]),
                  inputs=[self.refs, params, self.leaves, b.starts, b.directions, b.window, offsets, weights,
                          len(self.subrays)],
                  outputs=[b.impulses, b.received, b.span], device=d)
        if clean and last:  # the last chunk's power beyond this one's reach (which the convolution writes whole)
            wp.launch(kw.clear_power, (last, kw.CLEAR_THREADS),
                      inputs=[b.last_span, b.span, n, conv.first_lag, len(conv.taps)], outputs=[b.power], device=d)
        conv.launch(b.impulses, b.span, b.power, n, zeroed=clean)
        receive(tracer, self.receiver, params, b, n)
        self._hand_over(tracer, segments, n, counts, consume)

    def kernels_needed(self, tracer) -> list:
        return [*pilot_kernels(tracer), kw.deposit_kernel(tracer.meshes.per_face, tracer.scene.canopy is not None),
                kw.clear_impulses, kw.clear_power, *self._convolution(tracer).kernels()]

    def _convolution(self, tracer) -> PulseConvolution:
        """The run's pulse convolution (its taps and spectrum on the device), made once per tracer: every run asks
        for it twice (the kernels it compiles ahead, then ``begin``), and making it is host work the device waits
        for at the run's start."""
        det = tracer.instrument.detector
        return tracer.kept(f"pulse convolution {sorted(self.fft.items())}", lambda: PulseConvolution(
            det.s.convolution, *det.pulse_taps(tracer.device), det.s.samples, tracer.device, **self.fft))

    def _hand_over(self, tracer, segments: list[Segment], n: int, counts, consume) -> None:
        b = self.buffers
        if self.on_device:
            counts.returns += n * len(self.subrays)
            consume(DeviceWaveforms(n, b.window, b.power, b.received, b.starts, b.directions))
            return
        found = host_array(b.window[:n])
        slot = np.flatnonzero(found >= 0.0)
        counts.returns += len(slot) * len(self.subrays)
        self.misses += n - len(slot)
        rows = {name: None if a is None else host_array(a[:n])[slot]  # the chunk's rows only, not the buffers'
                for name, a in (("power", b.power), ("received", b.received), ("start", b.starts),
                                ("direction", b.directions), ("clean", b.clean))}
        hand_over(tracer, segments, slot, {**rows, "window": found[slot]}, counts, consume)

    def end(self, tracer, counts) -> wp.array:
        return wp.array([0, self.misses, 0], dtype=wp.int32, device=tracer.device)


@register("readout", "cloud_waveforms")
class CloudWaveforms:
    """A full waveform per beam from the scene's point cloud (``Scene.cloud``) by the GEDI simulator's method.

    Each beam's window is the ray-traced readout's (its central ray cast against the scene's mesh, the cloud's
    ground: the window opens samples/2 samples before that ray's delay); its footprint is centred where that ray
    meets the ground. :func:`~flightsim.engine.cloud_waveforms.cloud_waveforms` sums the points within the cut
    around the axis, each a Gaussian pulse of the detector's σ (widened by the receiver's response) weighed by
    its class's reflectance (``scene.rho_ground``, ``scene.rho_canopy``) and exp(−ρ²/2σ_f²), σ_f = r α / 2 at the
    beam's range r; beams launch together in groups of one direction and footprint (see :func:`_groups`). The
    normalised waveform w [1/m] (∫ w dr = 1) becomes received power as the lidar equation gives it for a
    Lambertian surface facing the beam: P = E_t ρ̄ T_A² D² η_t η_r / (4 r²) · w · c/2, ρ̄ the footprint's
    reflectance (the harmonic mean of the class reflectances weighed by their shares of the echo: the
    Gaussian-weighted mean over the points). The receiver's noise and digitiser follow as in ``waveforms``.
    Beams whose central ray misses the scene, or with no point within 3 σ_f of their axis, make no waveform
    (``RunCounts.misses``); ``RunCounts.returns`` counts the waveforms made.
    """

    kind = "cloud_waveforms"

    def __init__(self, keep_clean: bool = False):
        self.keep_clean = keep_clean

    def begin(self, tracer) -> wp.array:
        from flightsim.engine.cloud_waveforms import prepare_cloud

        det, scene = tracer.instrument.detector, tracer.cfg.scene
        self.params = det.struct(tracer.meshes.per_face, 0.0)
        self.receiver, self.refs = det.receiver(), mesh_refs(tracer)
        self.weights = (scene.rho_ground, scene.rho_canopy, scene.cloud_normalise)
        cell = 0.5 * det.footprint_sigma_m(tracer.cfg.flight.altitude_m)
        self.prepared = prepare_cloud(tracer.scene.cloud, *self.weights, device=tracer.device, cell_m=cell)
        self.buffers = _Buffers(tracer, self.params, traced=False,
                                keep_clean=self.keep_clean and self.receiver is not None)
        self.misses = 0
        return self.buffers.pulses

    def chunk(self, tracer, segments: list[Segment], n: int, counts, consume) -> None:
        b, params = self.buffers, self.params
        pilot_windows(tracer, b, self.refs, params, n)
        window = host_array(b.window[:n])
        slot = np.flatnonzero(window >= 0.0)
        start, direction = host_array(b.starts[:n])[slot], host_array(b.directions[:n])[slot]
        power = np.zeros((n, params.samples), dtype=np.float32)
        power[slot], received = self._waveforms(tracer, window[slot], start, direction)
        wp.copy(b.power, wp.array(power, dtype=wp.float32, device=tracer.device), count=power.size)
        receive(tracer, self.receiver, params, b, n)
        made = received[:, 3] > 0.0  # footprints holding points
        kept = slot[made]
        counts.returns += len(kept)
        self.misses += n - len(kept)
        rows = {"power": host_array(b.power[:n])[kept], "received": received[made], "start": start[made],
                "direction": direction[made], "window": window[kept],
                "clean": None if b.clean is None else host_array(b.clean[:n])[kept]}
        hand_over(tracer, segments, kept, rows, counts, consume)

    def kernels_needed(self, tracer) -> list:
        from flightsim.engine.cloud_waveforms import waveform_kernels

        det = tracer.instrument.detector  # the cloud's cells and points (prepare_cloud), and its waveforms' kernel
        return [*pilot_kernels(tracer), kc.cloud_cells,
                *waveform_kernels(det.pulse_sigma_s(), det.s.sample_interval_s, det.s.samples)]

    def _waveforms(self, tracer, t0: np.ndarray, start: np.ndarray, direction: np.ndarray):
        """((m, samples) float32 received power [W], (m, 4) received columns as the deposit kernel's: share of the
        echo inside the window, outside it, mean height [local m] × 1, 1; all 0 for a footprint without a point
        within 3 σ_f) of the beams from ``start`` along ``direction`` whose windows start at ``t0`` [s]."""
        from flightsim.engine.cloud_waveforms import cloud_waveforms

        det, params = tracer.instrument.detector, self.params
        power = np.zeros((len(t0), params.samples), dtype=np.float32)
        received = np.zeros((len(t0), 4))
        r = 0.5 * C * (t0 + 0.5 * params.samples * params.dt)  # each central ray's range to the ground [m]
        first = 0.5 * C * (t0 - 0.5 * det.s.pulse_fwhm_s)  # range of sample 0 (waveforms.h5's geolocation) [m]
        for rows, beam in _groups(det, start, direction, r):
            d = beam.direction()
            to_axis = (beam.centre_z_m - start[rows, 2]) / d[2]  # sensor to the axis point at centre_z [m]
            centres = start[rows, :2] + to_axis[:, None] * d[None, :2]
            w = cloud_waveforms(tracer.scene.cloud, centres, beam.centre_z_m, first[rows] - to_axis, params.dt,
                                params.samples, beam, *self.weights, device=tracer.device, prepared=self.prepared)
            power[rows], received[rows] = _to_power(det, w, r[rows], (start[rows, 2], first[rows], d[2]),
                                                    self.weights[:2], params.dt)
        return power, received

    def end(self, tracer, counts) -> wp.array:
        return wp.array([0, self.misses, 0], dtype=wp.int32, device=tracer.device)


DIRECTION_STEP = 1e-6  # beams whose directions differ by less than this share a launch (≤ 1e-4 m over 100 m) [rad]
SIGMA_STEP = 1e-4  # ... and whose footprints' σ_f differ by less than this fraction


def _groups(det, start: np.ndarray, direction: np.ndarray, r: np.ndarray):
    """(rows, CloudBeam) of the beams that launch together: directions within DIRECTION_STEP, footprints σ_f = r α/2
    within SIGMA_STEP of each other; each group's beam has their mean direction and σ_f, the detector's pulse
    (widened by the receiver) and its axis points at the mean height where the central rays meet the ground."""
    from flightsim.instrument.cloud_waveform_model import CloudBeam

    sigma_f = det.footprint_sigma_m(r)
    keys = np.column_stack([np.round(direction[:, :2] / DIRECTION_STEP), np.round(np.log(sigma_f) / SIGMA_STEP)])
    _, group = np.unique(keys, axis=0, return_inverse=True)
    group = group.ravel()
    for g in range(int(group.max()) + 1 if len(group) else 0):
        rows = np.flatnonzero(group == g)
        d = direction[rows].mean(axis=0)
        d /= np.linalg.norm(d)
        yield rows, CloudBeam(footprint_sigma_m=float(sigma_f[rows].mean()), pulse_sigma_s=det.pulse_sigma_s(),
                              zenith_deg=math.degrees(math.acos(min(1.0, -d[2]))),
                              azimuth_deg=math.degrees(math.atan2(d[0], d[1])),
                              centre_z_m=float(np.mean(start[rows, 2] + r[rows] * direction[rows, 2])))


def _to_power(det, w: dict, r: np.ndarray, axis: tuple, rho: tuple[float, float], dt: float):
    """(received power [W] (k, samples) float32, received columns (k, 4)) of normalised cloud waveforms ``w``
    (rx, ground, canopy [1/m]; outside) at ranges ``r`` [m]: P = E_t ρ̄ T_A² D² η_t η_r / (4 r²) · w · c/2 with
    ρ̄ = 1 / (s_g/ρ_g + s_c/ρ_c), s_g, s_c the ground's and the rest's shares of the echo in the window (the
    Gaussian-weighted mean reflectance of the footprint's points). ``axis``: (the beams' local start z [m], the range
    of their sample 0 [m], the direction's z) placing each sample's height. Worked out in pieces of the waveforms on
    threads (each row its own: the same numbers)."""
    power, received = np.empty(w["rx"].shape, dtype=np.float32), np.empty((len(r), 4))

    def piece(rows: slice) -> None:
        rx = w["rx"][rows].astype(np.float64)
        e_g = w["ground"][rows].sum(axis=1, dtype=np.float64)
        e_c = w["canopy"][rows].sum(axis=1, dtype=np.float64)
        total = e_g + e_c
        made = (total > 0.0) & ~w["outside"][rows]
        safe = np.where(made, total, 1.0)
        rho_mean = np.divide(1.0, e_g / safe / rho[0] + e_c / safe / rho[1], out=np.zeros(len(made)),
                             where=made)  # 0 without an echo (not 1/0)
        scale = det.pulse_energy_j() * det.link_m2() * rho_mean / r[rows] ** 2 * 0.5 * C
        echo = rx.sum(axis=1)
        inside = np.where(made, echo * 0.5 * C * dt, 0.0)
        heights = axis[0][rows, None] + (axis[1][rows, None] + 0.5 * C * dt * np.arange(rx.shape[1])) * axis[2]
        mean_z = np.where(made, (rx * heights).sum(axis=1) / np.where(made, echo, 1.0), 0.0)
        received[rows] = np.column_stack([inside, np.where(made, np.maximum(1.0 - inside, 0.0), 0.0), mean_z,
                                          made * 1.0])
        power[rows] = rx * scale[:, None]

    by_pieces(len(r), piece, least=POWER_ROWS)
    return power, received


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
