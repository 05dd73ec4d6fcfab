"""Photon-counting detection: a single-photon avalanche diode (SPAD) pixel with its own TDC.

Per pixel and pulse the photo-electrons arrive as an inhomogeneous Poisson process over the range
gate [t_open, t_close] (times of flight [s]) of intensity
    λ(t) = r + n_s · φ((t − t₀)/σ)/σ + n_c · φ((t − t_c)/σ)/σ,
r the noise rate (solar background plus dark counts) [Hz], n_s the expected signal photo-electrons
(the lidar equation, :func:`expected_signal`, with the Lambertian albedo of the triangle hit when the
scene has one per triangle, else the run's), t₀ the echo's time of flight and σ its spread (the
pulse's and the timing jitter, added in quadrature); n_c, t_c a corner-cube retroreflector's echo
when the footprint lights one (:func:`retro_echo`; the sampler is built without it for scenes that
have none). The pixel is live at t_open; after each
detection it is dead for τ_d and does not extend it (non-paralyzable; arrivals while dead are lost).

Sampling is exact and costs one step per detection: with Λ the integrated intensity, the next
arrival after the pixel turns live at t is Λ⁻¹(Λ(t) + E), E ~ Exp(1) (time rescaling; the process
is memoryless, so the dead time only moves t). Λ⁻¹ is Newton's method on Λ' = λ > 0, kept inside a
shrinking bracket (a step that leaves it bisects instead) until a step moves less than
INVERSION_TOL_S, started from the inverse of Λ's dominant part: the noise line before and after
the echo (beyond ECHO_SIGMAS σ), the echo's normal CDF within. Each detection is signal with probability
n_s φ/σ ÷ λ at its time. Random numbers are Warp's counter-based PCG keyed by (seed, slot): the
same seed gives the same photons on the CPU and the GPU. The TDC reads each detection as the centre
of its bin (the dead time runs from the true time).
"""
import functools
import math

import warp as wp

from kernels.canopy import Canopy
from kernels.canopy_photons import LeafRay, leaf_sum, transmission_to
from kernels.frames import ROW_PULSE, ROW_SEED
from kernels.normal import INV_SQRT_2PI, normal_cdf, normal_shape
from kernels.trace import STATUS_RETURN

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

LIGHT_SPEED = wp.constant(wp.float64(299792458.0))  # [m/s]
PHOTON_STREAM = wp.constant(0x68E31DA4)  # seed key of the photon streams of traced runs
INVERSION_TOL_S = wp.constant(wp.float64(1.0e-15))  # Λ⁻¹ to 1 fs (0.15 µm of range)
ECHO_SIGMAS = 6.0  # the echo's extent for the starting guess of Λ⁻¹ [σ]
ECHO_CDF_LOW = wp.constant(wp.float64(0.5 * math.erfc(ECHO_SIGMAS / math.sqrt(2.0))))  # Φ(−ECHO_SIGMAS)
INVERSION_STEPS = wp.constant(80)  # at most: the bracket alone would shrink below 1e-24 of the gate


@wp.struct
class PhotonDetector:
    """One pixel's photon budget and timing (every field in SI units)."""

    photons_per_joule: wp.float64  # λ / (h c) of the laser line [1/J]
    pulse_energy: wp.float64  # energy of the pulse in this pixel's sub-beam [J]
    aperture_area: wp.float64  # receiver aperture [m²]
    efficiency: wp.float64  # receiver optics transmission × photon detection efficiency
    sigma_t: wp.float64  # echo spread: pulse and timing jitter in quadrature, 1σ [s]
    gate_open: wp.float64  # time of flight at which the pixel is armed [s]
    gate_close: wp.float64  # end of the range gate [s]
    noise_rate: wp.float64  # background and dark counts [Hz]
    dead_time: wp.float64  # non-paralyzable dead time after a detection [s]
    max_events: wp.int32  # detections kept per pixel and pulse (the TDC's stop registers)
    tdc_bin: wp.float64  # TDC resolution: a detection reads the centre of its bin [s]; 0 = exact times


@wp.struct
class Echoes:
    """A pixel's echoes in one pulse: the surface's and, optionally, a retroreflector's (n1 = 0: none);
    expected photo-electrons n, time of flight t [s] and the echo's normal CDF at the gate's opening."""

    n0: wp.float64
    t0: wp.float64
    cdf0: wp.float64
    n1: wp.float64
    t1: wp.float64
    cdf1: wp.float64


@wp.func
def echoes(det: PhotonDetector, n0: wp.float64, t0: wp.float64, n1: wp.float64, t1: wp.float64):
    """The Echoes of a surface (n0 at t0) and a retroreflector (n1 at t1)."""
    e = Echoes()
    e.n0 = n0
    e.t0 = t0
    e.cdf0 = normal_cdf((det.gate_open - t0) / det.sigma_t)
    e.n1 = n1
    e.t1 = t1
    e.cdf1 = wp.float64(0.0)
    if n1 > wp.float64(0.0):
        e.cdf1 = normal_cdf((det.gate_open - t1) / det.sigma_t)
    return e


@wp.func
def expected_signal(det: PhotonDetector, distance: wp.float64, cos_incidence: wp.float64,
                    reflectance: wp.float64):
    """Expected signal photo-electrons of one pulse from a Lambertian surface filling the footprint:
    E·(λ/hc) · ρ cos θ / π · A / R² · η (no atmosphere) [photo-electrons]."""
    return (det.pulse_energy * det.photons_per_joule * reflectance * wp.max(cos_incidence, wp.float64(0.0))
            / wp.float64(3.141592653589793) * det.aperture_area / (distance * distance) * det.efficiency)


@wp.func
def echo_rate(det: PhotonDetector, t: wp.float64, t0: wp.float64, n_signal: wp.float64):
    """One echo's part of λ(t) = Λ'(t) at time of flight t [1/s] (λ = noise rate + the echoes' rates)."""
    z = (t - t0) / det.sigma_t
    return n_signal * INV_SQRT_2PI * normal_shape(z) / det.sigma_t


@wp.func
def _uniform64(state: wp.uint32):
    """(uniform deviate in (0, 1), advanced state): 32 random bits, never 0 or 1."""
    bits = wp.randu(state)
    return (wp.float64(bits) + wp.float64(0.5)) / wp.float64(4294967296.0), state


@wp.func
def _source(v: wp.float64, surface: wp.float64, lit: wp.float64, green: wp.float64, noise: wp.float64):
    """Which process a detection came from, drawn in proportion to the rates at its time (``v`` uniform in (0, 1)):
    1 the surface, 2 a retroreflector, 3 the leaves, 0 background or dark counts."""
    share = v * (surface + lit + green + noise)
    if share < surface:
        return wp.int8(1)
    if share < surface + lit:
        return wp.int8(2)
    if share < surface + lit + green:
        return wp.int8(3)
    return wp.int8(0)


@functools.cache
def sampler(retro: bool, leaves: bool = False):
    """The photon sampler's device functions, with the retroreflector's echo (``retro``) and the leaves' along the
    beam (``leaves``: :mod:`kernels.canopy_photons`, whose integral up to the gate's opening is ``leaf.at_open``)
    or without them (compiled out: the surface-only sampler of the SPAD frames pays nothing for them); returns
    detect."""

    @wp.func(module="unique")  # not in this file's module: each variant would replace the last there
    def integrated_intensity(det: PhotonDetector, t: wp.float64, e: Echoes, c: Canopy, leaf: LeafRay):
        """Λ(t): expected arrivals from the gate's opening to time of flight t [photo-electrons]."""
        value = det.noise_rate * (t - det.gate_open) + e.n0 * (normal_cdf((t - e.t0) / det.sigma_t) - e.cdf0)
        if wp.static(retro):
            value += e.n1 * (normal_cdf((t - e.t1) / det.sigma_t) - e.cdf1)
        if wp.static(leaves):
            value += leaf_sum(c, leaf, det.sigma_t, t, 0) - leaf.at_open
        return value

    @wp.func(module="unique")  # not in this file's module: each variant would replace the last there
    def _first_guess(det: PhotonDetector, target: wp.float64, lo: wp.float64, at_lo: wp.float64, e: Echoes):
        """Λ⁻¹(target) for Λ's dominant part (the surface echo's): the noise line where the target lies before
        or after the echo (beyond ECHO_SIGMAS σ), else the echo's normal CDF plus the noise up to its centre
        (``at_lo`` = Λ(lo), computed once by the caller)."""
        reach = wp.float64(ECHO_SIGMAS) * det.sigma_t
        start = wp.max(lo, e.t0 - reach)
        before = at_lo + det.noise_rate * (start - lo)
        if target <= before or e.n0 <= wp.float64(0.0):
            return lo + (target - at_lo) / det.noise_rate
        after = det.noise_rate * (e.t0 + reach - det.gate_open) + e.n0 * (wp.float64(1.0) - ECHO_CDF_LOW - e.cdf0)
        if target >= after:
            return e.t0 + reach + (target - after) / det.noise_rate
        p = (target - det.noise_rate * (e.t0 - det.gate_open)) / e.n0 + e.cdf0
        p = wp.min(wp.max(p, wp.float64(1.0e-15)), wp.float64(1.0 - 1.0e-15))
        return e.t0 + det.sigma_t * wp.float64(1.4142135623730951) * wp.erfinv(wp.float64(2.0) * p - wp.float64(1.0))

    @wp.func(module="unique")  # not in this file's module: each variant would replace the last there
    def _invert(det: PhotonDetector, target: wp.float64, lo: wp.float64, at_lo: wp.float64, e: Echoes, c: Canopy,
                leaf: LeafRay):
        """The time of flight t ≥ lo at which Λ(t) = target ≤ Λ(gate close), ``at_lo`` = Λ(lo) (safeguarded Newton)."""
        hi = det.gate_close
        t = _first_guess(det, target, lo, at_lo, e)
        if not (t > lo and t < hi):
            t = lo
        for _ in range(INVERSION_STEPS):
            f = integrated_intensity(det, t, e, c, leaf) - target
            if f == wp.float64(0.0):
                return t
            if f < wp.float64(0.0):
                lo = t
            else:
                hi = t
            rate = det.noise_rate + echo_rate(det, t, e.t0, e.n0)
            if wp.static(retro):
                rate += echo_rate(det, t, e.t1, e.n1)
            if wp.static(leaves):
                rate += leaf_sum(c, leaf, det.sigma_t, t, 1)
            step = wp.float64(0.5) * (lo + hi)
            if rate > wp.float64(0.0):
                newton = t - f / rate
                if newton > lo and newton < hi:
                    step = newton
            if wp.abs(step - t) <= INVERSION_TOL_S:
                return step
            t = step
        return t

    @wp.func(module="unique")  # not in this file's module: each variant would replace the last there
    def detect(det: PhotonDetector, state: wp.uint32, e: Echoes, c: Canopy, leaf: LeafRay, row: int,
               times: wp.array2d(dtype=wp.float64), signal: wp.array2d(dtype=wp.int8)):
        """Sample one pixel's detections of one pulse (its echoes ``e``) into row ``row`` of ``times`` [s] and
        ``signal`` (0 noise, 1 the surface's echo, 2 the retroreflector's, 3 the leaves'), in time order; return
        their count."""
        live = det.gate_open
        total = integrated_intensity(det, det.gate_close, e, c, leaf)
        at_live = wp.float64(0.0)  # Λ(gate open): each of its terms is a value less itself
        count = int(0)
        while count < det.max_events and live < det.gate_close:
            u, state = _uniform64(state)
            if count > 0:
                at_live = integrated_intensity(det, live, e, c, leaf)  # once per detection, not three times
            target = at_live - wp.log(u)
            if target >= total:
                break
            t = _invert(det, target, live, at_live, e, c, leaf)
            surface = echo_rate(det, t, e.t0, e.n0)
            lit = wp.float64(0.0)
            if wp.static(retro):
                lit = echo_rate(det, t, e.t1, e.n1)
            green = wp.float64(0.0)
            if wp.static(leaves):
                green = leaf_sum(c, leaf, det.sigma_t, t, 1)
            v, state = _uniform64(state)
            if det.tdc_bin > wp.float64(0.0):
                times[row, count] = (wp.floor(t / det.tdc_bin) + wp.float64(0.5)) * det.tdc_bin
            else:
                times[row, count] = t
            signal[row, count] = _source(v, surface, lit, green, det.noise_rate)
            count += 1
            live = t + det.dead_time
        return count

    return detect


@functools.cache
def photon_events_kernel():
    """The kernel sampling detections of slots given their expected signal and echo time (a surface, no
    retroreflector, no leaves). Made in a module of its own, like :func:`photon_slots_kernel`: a kernel of this file's
    module that called the sampler would make the module's identity (its hash) depend on whether another kernel had
    built the sampler's functions before, so a prebuilt module of it would not be found."""
    detect = sampler(False)

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
    def photon_events(det: PhotonDetector, seed: int, first_slot: wp.int64, n_signal: wp.array(dtype=wp.float64),
                      t0: wp.array(dtype=wp.float64), times: wp.array2d(dtype=wp.float64),
                      signal: wp.array2d(dtype=wp.int8), counts: wp.array(dtype=wp.int32)):
        """Detections of slots given their expected signal and echo time (slot i keyed by (seed, first_slot + i),
        so splitting a run into launches never changes a photon)."""
        i = wp.tid()
        state = wp.rand_init(seed, int((first_slot + wp.int64(i)) % wp.int64(2147483647)))
        counts[i] = detect(det, state, echoes(det, n_signal[i], t0[i], wp.float64(0.0), wp.float64(0.0)), Canopy(),
                           LeafRay(), i, times, signal)

    return photon_events


@wp.func
def retro_echo(position: wp.vec3d, photons: wp.float64, footprint: wp.float64, start: wp.vec3d, direction: wp.vec3d):
    """(expected photo-electrons, time of flight [s]) of a point retroreflector at ``position`` [m, local]
    in the Gaussian footprint of a beam (unit ``direction`` from ``start``): ``photons`` at the footprint's
    centre, times exp(−2 d²/w²) with d its distance from the beam axis and w = ``footprint`` × its
    distance along the axis (the e⁻² radius; ``footprint`` the e⁻² half angle [rad])."""
    v = position - start
    along = wp.dot(v, direction)
    if along <= wp.float64(0.0):
        return wp.float64(0.0), wp.float64(0.0)
    off2 = wp.max(wp.dot(v, v) - along * along, wp.float64(0.0))
    w = footprint * along
    return photons * wp.exp(wp.float64(-2.0) * off2 / (w * w)), wp.float64(2.0) * wp.length(v) / LIGHT_SPEED


@functools.cache
def photon_slots_kernel(retro: bool, per_face: bool, leaves: bool = False):
    """The kernel turning a traced chunk's slots into detections, with or without retroreflectors, with
    the scene's per-triangle reflectance (``per_face``) or the run's one value, and through the leaves of
    ``canopy`` (``leaves``) or not."""
    detect = sampler(retro, leaves)

    # 68 registers uncapped, 64 with 12 B spilled: four 256-thread blocks per multiprocessor instead of three
    # (an H100: the SPAD frame's photon_slots 7.58 -> 7.27 ms; profile-experiments.md section 20)
    @wp.kernel(module="unique", enable_backward=False, grid_stride=False, cuda_max_registers=64)
    def photon_slots(det: PhotonDetector, reflectance: wp.float64, face_reflectance: wp.array(dtype=wp.float32),
                     pulses: wp.array2d(dtype=wp.float64), per_pulse: int, energy: wp.array(dtype=wp.float64),
                     status: wp.array(dtype=wp.int32), ranges: wp.array(dtype=wp.float32),
                     faces: wp.array(dtype=wp.int32),
                     cos_incidence: wp.array(dtype=wp.float32), ccr_positions: wp.array(dtype=wp.vec3d),
                     ccr_photons: wp.float64, footprint: wp.float64, starts: wp.array(dtype=wp.vec3d),
                     directions: wp.array(dtype=wp.vec3d), delays: wp.array(dtype=wp.float32), drift: wp.float64,
                     canopy: Canopy, leaf_reflectance: wp.float64,
                     times: wp.array2d(dtype=wp.float64), signal: wp.array2d(dtype=wp.int8),
                     counts: wp.array(dtype=wp.int32)):
        """The detections of each slot of a traced chunk: its return (if any) through the lidar equation, with
        the Lambertian albedo of the triangle it hit (``face_reflectance[faces[slot]]``, with ``per_face``)
        or the run's ``reflectance`` (without; ``face_reflectance`` is then a placeholder), the
        retroreflector its footprint lights most (``ccr_positions``, with ``retro``: ``starts`` and
        ``directions`` the beams' true rays; its range read through the ranging chain's drift and the
        beam's delay, as the surface's), the leaves along the beam (``leaves``: ``starts``/``directions``
        again; the surface's echo dimmed by what they let through), background and dark counts over the whole
        gate. Every echo scales with the beam's share ``energy[beam]`` of the detector's pulse energy (1 but
        for the weak beams of ATLAS's pairs). Keyed by (line seed, pulse · beams + beam)."""
        slot = wp.tid()
        p = slot // per_pulse
        beam = slot % per_pulse
        n = wp.float64(0.0)
        echo = det.gate_open
        scale = energy[beam]
        if status[slot] == STATUS_RETURN:
            r = wp.float64(ranges[slot])
            rho = reflectance
            if wp.static(per_face):
                rho = wp.float64(face_reflectance[faces[slot]])
            n = scale * expected_signal(det, r, wp.float64(cos_incidence[slot]), rho)
            echo = wp.float64(2.0) * r / LIGHT_SPEED
        key = (wp.int64(pulses[ROW_PULSE, p]) * wp.int64(per_pulse) + wp.int64(beam)) % wp.int64(2147483647)
        state = wp.rand_init(int(pulses[ROW_SEED, p]) ^ PHOTON_STREAM, int(key))
        n1 = wp.float64(0.0)
        t1 = wp.float64(0.0)
        if wp.static(retro):
            for c in range(ccr_positions.shape[0]):  # the retroreflector lit most by the beam's footprint
                n_c, t_c = retro_echo(ccr_positions[c], scale * ccr_photons, footprint, starts[slot], directions[slot])
                if n_c > n1:
                    n1 = n_c
                    t1 = t_c * (wp.float64(1.0) + drift) + wp.float64(2.0) * wp.float64(delays[beam]) / LIGHT_SPEED
        leaf = LeafRay()
        if wp.static(leaves):
            if wp.length(directions[slot]) > wp.float64(0.5):  # the beam left the instrument
                leaf.start = starts[slot]
                leaf.direction = directions[slot]
                leaf.t_end = wp.float64(0.5) * LIGHT_SPEED * det.gate_close
                if status[slot] == STATUS_RETURN:
                    leaf.t_end = wp.float64(ranges[slot])
                leaf.scale = scale * expected_signal(det, wp.float64(1.0), wp.float64(1.0), leaf_reflectance)
                leaf.drift = drift
                leaf.delay = wp.float64(2.0) * wp.float64(delays[beam]) / LIGHT_SPEED
                leaf.present = canopy.present
                n = n * transmission_to(canopy, leaf)
                leaf.at_open = leaf_sum(canopy, leaf, det.sigma_t, det.gate_open, 0)
        counts[slot] = detect(det, state, echoes(det, n, echo, n1, t1), canopy, leaf, slot, times, signal)

    return photon_slots


@wp.kernel
def gather_events(counts: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                  times: wp.array2d(dtype=wp.float64), signal: wp.array2d(dtype=wp.int8),
                  out_slot: wp.array(dtype=wp.int32), out_time: wp.array(dtype=wp.float64),
                  out_signal: wp.array(dtype=wp.int8)):
    """Compact the detections of every slot into flat arrays at the slot's offset (exclusive scan of counts)."""
    slot = wp.tid()
    base = offsets[slot]
    for k in range(counts[slot]):
        out_slot[base + k] = slot
        out_time[base + k] = times[slot, k]
        out_signal[base + k] = signal[slot, k]
