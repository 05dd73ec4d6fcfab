"""Photon-counting detection: a single-photon avalanche diode (SPAD) pixel with its own TDC.

Per pixel and pulse the photo-electrons arrive as an inhomogeneous Poisson process over the range
gate [t_open, t_close] (times of flight [s]) of intensity
    λ(t) = r + n_s · φ((t − t₀)/σ)/σ,
r the noise rate (solar background plus dark counts) [Hz], n_s the expected signal photo-electrons
(the lidar equation, :func:`expected_signal`), t₀ the echo's time of flight and σ its spread (the
pulse's and the timing jitter, added in quadrature). The pixel is live at t_open; after each
detection it is dead for τ_d and does not extend it (non-paralyzable; arrivals while dead are lost).

Sampling is exact and costs one step per detection: with Λ the integrated intensity, the next
arrival after the pixel turns live at t is Λ⁻¹(Λ(t) + E), E ~ Exp(1) (time rescaling; the process
is memoryless, so the dead time only moves t). Each detection is signal with probability
n_s φ/σ ÷ λ at its time. Random numbers are Warp's counter-based PCG keyed by (seed, slot): the
same seed gives the same photons on the CPU and the GPU. The TDC reads each detection as the centre
of its bin (the dead time runs from the true time).
"""
import warp as wp

from kernels.frames import ROW_PULSE, ROW_SEED
from kernels.trace import STATUS_RETURN

wp.set_module_options({"enable_backward": False})

SQRT1_2 = wp.constant(wp.float64(0.7071067811865476))
INV_SQRT_2PI = wp.constant(wp.float64(0.3989422804014327))
LIGHT_SPEED = wp.constant(wp.float64(299792458.0))  # [m/s]
PHOTON_STREAM = wp.constant(0x68E31DA4)  # seed key of the photon streams of traced runs
BISECTIONS = wp.constant(64)  # halvings of the gate when inverting Λ: below 1e-15 of the gate


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


@wp.func
def expected_signal(det: PhotonDetector, distance: wp.float64, cos_incidence: wp.float64,
                    reflectance: wp.float64):
    """Expected signal photo-electrons of one pulse from a Lambertian surface filling the footprint:
    E·(λ/hc) · ρ cos θ / π · A / R² · η (no atmosphere) [photo-electrons]."""
    return (det.pulse_energy * det.photons_per_joule * reflectance * wp.max(cos_incidence, wp.float64(0.0))
            / wp.float64(3.141592653589793) * det.aperture_area / (distance * distance) * det.efficiency)


@wp.func
def _normal_cdf(x: wp.float64):
    return wp.float64(0.5) * wp.erfc(-x * SQRT1_2)


@wp.func
def integrated_intensity(det: PhotonDetector, t: wp.float64, t0: wp.float64, n_signal: wp.float64):
    """Λ(t): expected arrivals from the gate's opening to time of flight t [photo-electrons]."""
    noise = det.noise_rate * (t - det.gate_open)
    signal = n_signal * (_normal_cdf((t - t0) / det.sigma_t) - _normal_cdf((det.gate_open - t0) / det.sigma_t))
    return noise + signal


@wp.func
def _invert(det: PhotonDetector, target: wp.float64, lo: wp.float64, t0: wp.float64, n_signal: wp.float64):
    """The time of flight t ≥ lo at which Λ(t) = target (bisection; Λ is non-decreasing)."""
    hi = det.gate_close
    for _ in range(BISECTIONS):
        mid = wp.float64(0.5) * (lo + hi)
        if integrated_intensity(det, mid, t0, n_signal) < target:
            lo = mid
        else:
            hi = mid
    return wp.float64(0.5) * (lo + hi)


@wp.func
def _uniform64(state: wp.uint32):
    """(uniform deviate in (0, 1), advanced state): 32 random bits, never 0 or 1."""
    bits = wp.randu(state)
    return (wp.float64(bits) + wp.float64(0.5)) / wp.float64(4294967296.0), state


@wp.func
def detect(det: PhotonDetector, state: wp.uint32, n: wp.float64, echo: wp.float64, row: int,
           times: wp.array2d(dtype=wp.float64), signal: wp.array2d(dtype=wp.int8)):
    """Sample one pixel's detections of one pulse (expected signal ``n`` echoing at time of flight
    ``echo`` [s]) into row ``row`` of ``times`` [s] and ``signal``, in time order; return their count."""
    live = det.gate_open
    total = integrated_intensity(det, det.gate_close, echo, n)
    count = int(0)
    while count < det.max_events and live < det.gate_close:
        u, state = _uniform64(state)
        target = integrated_intensity(det, live, echo, n) - wp.log(u)
        if target >= total:
            break
        t = _invert(det, target, live, echo, n)
        z = (t - echo) / det.sigma_t
        signal_rate = n * INV_SQRT_2PI * wp.exp(wp.float64(-0.5) * z * z) / det.sigma_t
        v, state = _uniform64(state)
        if det.tdc_bin > wp.float64(0.0):
            times[row, count] = (wp.floor(t / det.tdc_bin) + wp.float64(0.5)) * det.tdc_bin
        else:
            times[row, count] = t
        flag = wp.int8(0)
        if v * (signal_rate + det.noise_rate) < signal_rate:
            flag = wp.int8(1)
        signal[row, count] = flag
        count += 1
        live = t + det.dead_time
    return count


@wp.kernel
def photon_events(det: PhotonDetector, seed: int, first_slot: wp.int64, n_signal: wp.array(dtype=wp.float64),
                  t0: wp.array(dtype=wp.float64), times: wp.array2d(dtype=wp.float64),
                  signal: wp.array2d(dtype=wp.int8), counts: wp.array(dtype=wp.int32)):
    """Detections of slots given their expected signal and echo time (slot i keyed by (seed, first_slot + i),
    so splitting a run into launches never changes a photon)."""
    i = wp.tid()
    state = wp.rand_init(seed, int((first_slot + wp.int64(i)) % wp.int64(2147483647)))
    counts[i] = detect(det, state, n_signal[i], t0[i], i, times, signal)


@wp.kernel
def photon_slots(det: PhotonDetector, reflectance: wp.float64, pulses: wp.array2d(dtype=wp.float64), per_pulse: int,
                 status: wp.array(dtype=wp.int32), ranges: wp.array(dtype=wp.float32),
                 cos_incidence: wp.array(dtype=wp.float32), times: wp.array2d(dtype=wp.float64),
                 signal: wp.array2d(dtype=wp.int8), counts: wp.array(dtype=wp.int32)):
    """The detections of each slot of a traced chunk: its return (if any) through the lidar equation,
    background and dark counts over the whole gate. Keyed by (line seed, pulse · beams + beam)."""
    slot = wp.tid()
    p = slot // per_pulse
    beam = slot % per_pulse
    n = wp.float64(0.0)
    echo = det.gate_open
    if status[slot] == STATUS_RETURN:
        r = wp.float64(ranges[slot])
        n = expected_signal(det, r, wp.float64(cos_incidence[slot]), reflectance)
        echo = wp.float64(2.0) * r / LIGHT_SPEED
    key = (wp.int64(pulses[ROW_PULSE, p]) * wp.int64(per_pulse) + wp.int64(beam)) % wp.int64(2147483647)
    state = wp.rand_init(int(pulses[ROW_SEED, p]) ^ PHOTON_STREAM, int(key))
    counts[slot] = detect(det, state, n, echo, slot, times, signal)


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
