"""Full-waveform detection: every beam's footprint sampled by sub-rays, their echoes summed on the device.

Per beam (slot) with float64 start and unit direction d: its window opens ``samples``/2 samples before
the two-way delay of the central ray (the pilot; a beam whose pilot misses gets no waveform). Each
sub-ray k leaves along normalize(d + a_k u + b_k v), (a_k, b_k) = tan φ_k (cos θ_k, sin θ_k), u the
local east made normal to d and v = u × d (north for a nadir beam); it is cast against the mesh, its
range refined on the hit triangle in float64, and its share of the received power
    g_k = w_k · link · cos θ_i / r²,   link = π f T_A² D² η_t η_r / 4     (the patent's eq. 1)
(f the backscatter of eq. 1, ``waveform.reflectance``; over a scene with a Lambertian albedo ρ per
triangle, f = ρ/π of the triangle the sub-ray hits, so π f = ρ and g_k = w_k · ρ T_A² D² η_t η_r / 4 ·
cos θ_i / r²) added to the two samples around its delay 2r/c, split linearly (so each sub-ray's delay
is kept to first order: its error is below dt²/(8σ²) of the echo). The waveform is then that impulse train
convolved with the transmitted pulse P(t) = P_max exp(−(t − τ/2)²/2σ²) sampled at multiples of dt
over ±PULSE_SIGMAS σ: the received power [W] at t = window start + i·dt.
"""
import functools

import warp as wp

from kernels.canopy import Canopy, g_of, walk_begin, walk_next
from kernels.frames import ROW_PULSE, ROW_SEED
from kernels.mesh_cast import closest_hit
from kernels.mesh_hits import fallback_hit, refine_hit

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

SUBRAYS_PER_THREAD = 64  # sub-rays one deposit thread casts in turn (an H100, the flat waveform bench: the deposit
# 8.70 ms at 64, 9.45 at 32, 11.95 at 16; profile-experiments.md section 23)
PULSE_SIGMAS = 8.0  # the pulse kernel's half length [σ]: its tails hold 1e-15 of the energy
LIGHT_SPEED = wp.constant(wp.float64(299792458.0))  # [m/s]


@wp.struct
class WaveformParams:
    """The waveform detector's constants (SI units)."""

    link: wp.float64  # π f T_A² D² η_t η_r / 4: received / transmitted power times r² / cos θ_i [m²]
    # (per-triangle albedo, deposit_kernel(per_face=True): T_A² D² η_t η_r / 4, times the hit triangle's ρ = π f)
    dt: wp.float64  # sample interval [s]
    samples: wp.int32  # samples per waveform
    sigma: wp.float64  # the pulse's σ [s]
    centre: wp.float64  # the pulse's centre after its start, τ/2 [s]
    peak_power: wp.float64  # P_max [W]
    leaf_link: wp.float64  # through a canopy: T_A² D² η_t η_r / 4 times the leaves' reflectance ρ_l [m²]


@wp.struct
class Receiver:
    """Noise and digitiser after the optics (SI units; all zero: the noiseless power)."""

    shot_noise: wp.int32  # 1: Poisson photo-electrons of signal and background per sample
    joules_per_electron: wp.float64  # h c / (λ η): received energy per photo-electron [J]
    background: wp.float64  # optical background power [W]
    thermal: wp.float64  # receiver noise, rms per sample [W]
    lsb: wp.float64  # the digitiser's step [W]; 0: no digitiser
    top: wp.float64  # the digitiser's highest code (2^bits − 1)
    stream: wp.int32  # seed of the run's noise


@wp.struct
class MeshRefs:
    """The scene as the casts need it."""

    mesh: wp.uint64
    padded: wp.uint64  # BVH of padded triangle boxes for the fallback cast
    vertices64: wp.array(dtype=wp.vec3d)
    indices: wp.array(dtype=wp.int32)
    max_range: wp.float32
    reflectance: wp.array(dtype=wp.float32)  # Lambertian albedo ρ of each triangle; a placeholder without per_face


@wp.func
def face_of(m: MeshRefs, start: wp.vec3d, direction: wp.vec3d):
    """The face a float64 ray hits (float32 cast, the padded boxes where it slips through), or −1."""
    face, t = closest_hit(m.mesh, wp.vec3f(start), wp.vec3f(direction), m.max_range)
    if face < 0:
        face, t_second = fallback_hit(m.padded, m.vertices64, m.indices, start, direction, m.max_range)
    return face


@wp.func
def face_normal(m: MeshRefs, face: int):
    """The unit normal of ``face`` (float64)."""
    v0 = m.vertices64[m.indices[3 * face]]
    return wp.normalize(wp.cross(m.vertices64[m.indices[3 * face + 1]] - v0, m.vertices64[m.indices[3 * face + 2]] - v0))


@wp.func
def face_plane(m: MeshRefs, face: int, start: wp.vec3d):
    """(n, n·(v0 − start)) of ``face`` (float64 vertices v0, v1, v2 [m]): n = (v1 − v0) × (v2 − v0) its normal [m²] and
    the numerator [m³] of the distance n·(v0 − start) / n·d along any ray from ``start``: refine_hit's operations on
    the same values (the deposit's pinned waveforms hold the two to the same bits)."""
    v0 = m.vertices64[m.indices[3 * face]]
    normal = wp.cross(m.vertices64[m.indices[3 * face + 1]] - v0, m.vertices64[m.indices[3 * face + 2]] - v0)
    return normal, wp.dot(normal, v0 - start)


@wp.func
def cast64(m: MeshRefs, start: wp.vec3d, direction: wp.vec3d):
    """(face or −1, range [m], unit face normal) of a float64 ray: float32 cast, float64 range on the face."""
    face = face_of(m, start, direction)
    if face < 0:
        return -1, wp.float64(0.0), wp.vec3d()
    return face, refine_hit(m.vertices64, m.indices, face, start, direction), face_normal(m, face)


@wp.func
def beam_frame(d: wp.vec3d):
    """(u, v) across the unit beam axis d: u the local east made normal to d (north for a beam along east),
    v = u × d."""
    east = wp.vec3d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0))
    u = east - wp.dot(east, d) * d
    if wp.length(u) < wp.float64(1.0e-6):  # a beam along east: measure θ from north instead
        north = wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
        u = north - wp.dot(north, d) * d
    u = wp.normalize(u)
    return u, wp.cross(u, d)


@wp.func
def subray_direction(d: wp.vec3d, u: wp.vec3d, v: wp.vec3d, offset: wp.vec2d):
    """The unit direction of a sub-ray at offset tan φ (cos θ, sin θ) from the beam axis d (frame
    :func:`beam_frame`)."""
    return wp.normalize(d + offset[0] * u + offset[1] * v)


@wp.kernel
def pilot(m: MeshRefs, p: WaveformParams, starts: wp.array(dtype=wp.vec3d), directions: wp.array(dtype=wp.vec3d),
          window_start: wp.array(dtype=wp.float64)):
    """Each beam's window start [s, two-way time]: samples/2 samples before its central ray's delay; −1 when
    the central ray misses (or the beam does not leave the instrument)."""
    slot = wp.tid()
    window_start[slot] = wp.float64(-1.0)
    d = directions[slot]
    if wp.length(d) < wp.float64(0.5):
        return
    face, r, normal = cast64(m, starts[slot], d)
    if face >= 0:
        window_start[slot] = wp.float64(2.0) * r / LIGHT_SPEED - wp.float64(p.samples / 2) * p.dt


@wp.func
def _flush(impulses: wp.array2d(dtype=wp.float64), slot: int, i: int, low: wp.float64, high: wp.float64):
    """Add a run of deposits into samples i and i + 1 (nothing for i < 0)."""
    if i >= 0:
        wp.atomic_add(impulses, slot, i, low)
        wp.atomic_add(impulses, slot, i + 1, high)


@wp.func
def leaf_echo(c: Canopy, p: WaveformParams, start: wp.vec3d, direction: wp.vec3d, t_end: wp.float64,
              weight: wp.float64, t0: wp.float64, impulses: wp.array2d(dtype=wp.float64), slot: int):
    """A sub-ray's echo from the leaves between its start and ``t_end`` [m]: in a voxel of extinction κ entered
    with transmission T at t_a, the stretch [u, v] sends back w ρ_l T (e^{−κ(u − t_a)} − e^{−κ(v − t_a)}) · link/r²
    (leaves scatter as a Lambertian surface of albedo ρ_l facing the beam; light returns through the same gaps),
    cut at the sample boundaries and each piece split linearly between the two samples around its middle.
    Returns (the transmission left at t_end, the echo inside the window, outside it, first and last sample)."""
    g = g_of(c, direction)
    transmission = wp.float64(1.0)
    inside = wp.float64(0.0)
    outside = wp.float64(0.0)
    first = int(p.samples)
    last = int(-1)
    metres_per_sample = wp.float64(0.5) * LIGHT_SPEED * p.dt
    w = walk_begin(c, start, direction, wp.float64(0.0), t_end)
    while w.done == 0:
        kappa = g * wp.float64(w.lad)
        if kappa > wp.float64(0.0):
            u = w.t_in
            while u < w.t_out:
                x = (wp.float64(2.0) * u / LIGHT_SPEED - t0) / p.dt
                v = wp.min(w.t_out, u + (wp.floor(x) + wp.float64(1.0) - x) * metres_per_sample)
                v = wp.max(v, u + wp.float64(1.0e-9))  # a boundary met by rounding: step on
                mid = wp.float64(0.5) * (u + v)
                e = weight * p.leaf_link * transmission * (wp.exp(-kappa * (u - w.t_in)) - wp.exp(-kappa * (v - w.t_in)))
                e = e / (mid * mid)
                xm = (wp.float64(2.0) * mid / LIGHT_SPEED - t0) / p.dt
                i = int(wp.floor(xm))
                if i < 0 or i + 1 >= p.samples:
                    outside += e
                else:
                    f = xm - wp.float64(i)
                    _flush(impulses, slot, i, e * (wp.float64(1.0) - f), e * f)
                    inside += e
                    first = wp.min(first, i)
                    last = wp.max(last, i + 1)
                u = v
            transmission *= wp.exp(-kappa * (w.t_out - w.t_in))
        w = walk_next(c, w)
    return transmission, inside, outside, first, last


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return false;
#else
    return true;
#endif
""")
def keeps_plane() -> bool:
    """Whether the deposit keeps a triangle's plane across a thread's sub-rays: on the CPU (the deposit 1.25× over flat
    ground, the same bits), not on a GPU, where the 15 values it carries cost the registers it saves (section 84 of
    results/profile-experiments.md): there the plane is worked out for every sub-ray and the kept one is dead code
    (ptxas: the registers, spills and stack of the deposit without it)."""
    ...


@wp.func
def no_plane():
    """:func:`plane_hit`'s kept plane before a thread's first sub-ray: no face."""
    return int(-1), wp.vec3d(), wp.float64(0.0), wp.vec3d()


@wp.func
def plane_hit(m: MeshRefs, face: int, start: wp.vec3d, direction: wp.vec3d, kept: int, normal: wp.vec3d,
              top: wp.float64, unit: wp.vec3d):
    """(range [m], cos of incidence, and the plane kept for the next sub-ray: its face, n, n·(v0 − start), unit n) of a
    sub-ray from ``start`` along ``direction`` that hits ``face`` (≥ 0): refine_hit's range and face_normal's
    incidence, the plane worked out afresh unless it is kept (:func:`keeps_plane`) for the face hit."""
    if face != kept or not keeps_plane():
        normal, top = face_plane(m, face, start)
        unit = wp.normalize(normal)
        kept = face
    return top / wp.dot(normal, direction), wp.abs(wp.dot(unit, direction)), kept, normal, top, unit


DEPOSIT_MAX_REGISTERS = 128  # on a GPU: two 256-thread blocks per SM; 137 uncapped (one block), measured fastest of
# 64/96/128/uncapped on an H100 (results/profile-experiments.md, section 13)


@functools.cache
def deposit_kernel(per_face: bool, canopy: bool = False, max_registers: int | None = DEPOSIT_MAX_REGISTERS):
    """The deposit kernel, each sub-ray's link times its triangle's albedo (``per_face``: ``m.reflectance``) or the run's
    one link; through the leaves (``canopy``: :func:`leaf_echo`, the surface's echo dimmed by what they let through) or
    not (compiled out); ``max_registers`` caps its registers on a GPU (None: the compiler's; no result changes)."""

    @wp.kernel(module="unique", enable_backward=False, cuda_max_registers=max_registers, grid_stride=False)
    def deposit(m: MeshRefs, p: WaveformParams, leaves: Canopy, starts: wp.array(dtype=wp.vec3d),
                directions: wp.array(dtype=wp.vec3d), window_start: wp.array(dtype=wp.float64),
                offsets: wp.array2d(dtype=wp.vec2d), weights: wp.array2d(dtype=wp.float64), subrays: int,
                impulses: wp.array2d(dtype=wp.float64), received: wp.array2d(dtype=wp.float64),
                span: wp.array2d(dtype=wp.int32)):
        """Sub-rays k = group·P + step (of ``subrays``; P per thread) of beam ``slot`` in turn, their offsets and weights
        at [step, group] (``readouts.waveforms.by_lane``): each cast, its power share g_k [1] added to the impulse
        train at its delay (linear split; consecutive sub-rays in one sample summed first, the sums below once per
        thread). ``received[slot]``: Σ g_k inside (0) and outside (1) the window, Σ w_k z_k [m] (2) and Σ w_k (3) over
        the hits (local z); ``span[slot]``: the lowest and highest sample touched (start it at (samples, −1))."""
        slot, group = wp.tid()
        t0 = window_start[slot]
        if t0 < wp.float64(0.0):
            return
        inside = wp.float64(0.0)
        outside = wp.float64(0.0)
        wz = wp.float64(0.0)
        w = wp.float64(0.0)
        run = int(-1)
        low = wp.float64(0.0)
        high = wp.float64(0.0)
        first = int(p.samples)
        last = int(-1)
        start = starts[slot]
        d = directions[slot]
        u, v = beam_frame(d)
        kept, normal, top, unit = no_plane()  # (on the CPU) the plane of the face the last sub-ray hit
        for step in range(wp.min(offsets.shape[0], subrays - group * offsets.shape[0])):
            weight = weights[step, group]
            direction = subray_direction(d, u, v, offsets[step, group])
            face = face_of(m, start, direction)
            r, cos_incidence = wp.float64(0.0), wp.float64(0.0)
            if face >= 0:
                r, cos_incidence, kept, normal, top, unit = plane_hit(m, face, start, direction,
                                                                      kept, normal, top, unit)
            transmission = wp.float64(1.0)
            if wp.static(canopy):
                t_end = wp.where(face >= 0, r, wp.float64(m.max_range))
                transmission, e_in, e_out, e_first, e_last = leaf_echo(leaves, p, start, direction, t_end,
                                                                       weight, t0, impulses, slot)
                inside, outside = inside + e_in, outside + e_out
                first, last = wp.min(first, e_first), wp.max(last, e_last)
            if face >= 0:
                link = p.link * transmission
                if wp.static(per_face):
                    link = link * wp.float64(m.reflectance[face])
                g = weight * link * cos_incidence / (r * r)
                wz += weight * (start[2] + r * direction[2])
                w += weight
                x = (wp.float64(2.0) * r / LIGHT_SPEED - t0) / p.dt
                i = int(wp.floor(x))
                f = x - wp.float64(i)
                if i < 0 or i + 1 >= p.samples:
                    outside += g
                else:
                    inside += g
                    first = wp.min(first, i)
                    last = wp.max(last, i + 1)
                    if i != run:
                        _flush(impulses, slot, run, low, high)
                        run = i
                        low = wp.float64(0.0)
                        high = wp.float64(0.0)
                    low += g * (wp.float64(1.0) - f)
                    high += g * f
        _flush(impulses, slot, run, low, high)
        wp.atomic_add(received, slot, 0, inside)
        wp.atomic_add(received, slot, 1, outside)
        wp.atomic_add(received, slot, 2, wz)
        wp.atomic_add(received, slot, 3, w)
        wp.atomic_min(span, slot, 0, first)
        wp.atomic_max(span, slot, 1, last)

    return deposit


CONVOLVE_OUTPUTS = 8  # consecutive samples per convolve thread (one impulse load per tap feeds all of them)


@wp.func
def _impulse(impulses: wp.array2d(dtype=wp.float64), slot: int, j: int, lo: int, hi: int):
    """impulses[slot, j] within the touched span [lo, hi], else 0 (the rest of the row is 0)."""
    value = wp.float64(0.0)
    if j >= lo and j <= hi:
        value = impulses[slot, j]
    return value


@wp.kernel
def convolve(impulses: wp.array2d(dtype=wp.float64), span: wp.array2d(dtype=wp.int32), taps: wp.array(dtype=wp.float64),
             first_lag: int, from_reach: int, out: wp.array2d(dtype=wp.float32)):
    """out[slot, i] = Σ_j impulses[slot, j] · P((i − j)·dt): the received power [W] (taps: P at lags
    first_lag, first_lag + 1, … samples); only the impulses within ``span[slot]`` are visited.

    Each thread makes CONVOLVE_OUTPUTS consecutive samples i0 … i0 + 7 from a window of eight impulses held
    in registers and slid by one per tap (r_j = impulse i0 + j − first_lag − k): one load and one tap per
    eight products. Each sample adds the same products in the same order (taps ascending) as a sample on
    its own would; the products outside its own tap range are exact zeros (so the samples' grouping by eight
    changes no bit). ``out`` must be zeroed: a thread with no impulse within reach writes nothing.

    Thread (slot, block) makes the samples from block·8, or with ``from_reach`` = 1 from block·8 after the group
    of eight holding the row's first output in reach, max(lo + first_lag, 0): launched over as many blocks as
    the widest reach needs rather than the whole row."""
    slot, block = wp.tid()
    lo = span[slot, 0]
    hi = span[slot, 1]
    i0 = block * CONVOLVE_OUTPUTS
    if from_reach != 0:
        i0 += wp.max(lo + first_lag, 0) // CONVOLVE_OUTPUTS * CONVOLVE_OUTPUTS
    k0 = wp.max(0, i0 - first_lag - hi)
    k1 = wp.min(taps.shape[0] - 1, i0 + CONVOLVE_OUTPUTS - 1 - first_lag - lo)
    if k1 < k0:
        return  # no impulse within reach: the samples stay 0 (``out`` is zeroed beforehand)
    base = i0 - first_lag - k0
    r0, r1, r2, r3 = (_impulse(impulses, slot, base, lo, hi), _impulse(impulses, slot, base + 1, lo, hi),
                      _impulse(impulses, slot, base + 2, lo, hi), _impulse(impulses, slot, base + 3, lo, hi))
    r4, r5, r6, r7 = (_impulse(impulses, slot, base + 4, lo, hi), _impulse(impulses, slot, base + 5, lo, hi),
                      _impulse(impulses, slot, base + 6, lo, hi), _impulse(impulses, slot, base + 7, lo, hi))
    t0, t1, t2, t3 = wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0)
    t4, t5, t6, t7 = wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0)
    for k in range(k0, k1 + 1):
        c = taps[k]
        t0 += r0 * c
        t1 += r1 * c
        t2 += r2 * c
        t3 += r3 * c
        t4 += r4 * c
        t5 += r5 * c
        t6 += r6 * c
        t7 += r7 * c
        r7 = r6
        r6 = r5
        r5 = r4
        r4 = r3
        r3 = r2
        r2 = r1
        r1 = r0
        r0 = _impulse(impulses, slot, base - (k - k0) - 1, lo, hi)
    _put(out, slot, i0, t0)
    _put(out, slot, i0 + 1, t1)
    _put(out, slot, i0 + 2, t2)
    _put(out, slot, i0 + 3, t3)
    _put(out, slot, i0 + 4, t4)
    _put(out, slot, i0 + 5, t5)
    _put(out, slot, i0 + 6, t6)
    _put(out, slot, i0 + 7, t7)


@wp.func
def _put(out: wp.array2d(dtype=wp.float32), slot: int, i: int, value: wp.float64):
    if i < out.shape[1]:
        out[slot, i] = wp.float32(value)


CLEAR_THREADS = 128  # threads per row clearing a chunk's rows (each takes every CLEAR_THREADS-th sample)


@wp.kernel
def clear_impulses(span: wp.array2d(dtype=wp.int32), narrower: int, impulses: wp.array2d(dtype=wp.float64)):
    """A chunk's impulse trains zeroed for the next, launched over (rows, CLEAR_THREADS), thread k taking samples k,
    k + CLEAR_THREADS, … of the range (a warp's stores side by side): impulses[slot, j] = 0 over the touched span
    [lo, hi] of ``span[slot]`` (the deposits touch nothing outside it) of the rows narrower than ``narrower``
    samples; the wider ones the FFT convolution zeroed as it read them (kernels/waveform_fft.py)."""
    slot, k = wp.tid()
    lo = span[slot, 0]
    hi = span[slot, 1]
    if hi - lo + 1 < narrower:
        for j in range(lo + k, hi + 1, CLEAR_THREADS):
            impulses[slot, j] = wp.float64(0.0)


@wp.func
def reach_of(span: wp.array2d(dtype=wp.int32), slot: int, first_lag: int, taps: int, samples: int):
    """The samples [begin, end] of row ``slot`` whose power its touched span [lo, hi] reaches, [lo + first_lag,
    hi + first_lag + taps − 1] within the row (begin > end: none)."""
    lo = span[slot, 0]
    hi = span[slot, 1]
    if hi < lo:
        return samples, -1
    return wp.max(lo + first_lag, 0), wp.min(hi + first_lag + taps - 1, samples - 1)


@wp.kernel
def clear_power(last: wp.array2d(dtype=wp.int32), span: wp.array2d(dtype=wp.int32), rows: int, first_lag: int,
                taps: int, power: wp.array2d(dtype=wp.float32)):
    """power[slot, i] = 0 over the reach of the last chunk's span ``last[slot]`` where it is outside the reach of this
    chunk's ``span[slot]`` (none for the slots from ``rows`` on), which the convolution writes whole (its outputs
    there are 0 or the new waveform): launched over (the last chunk's rows, CLEAR_THREADS) as ``clear_impulses``."""
    slot, k = wp.tid()
    samples = power.shape[1]
    begin, end = reach_of(last, slot, first_lag, taps, samples)
    keep_begin, keep_end = int(samples), int(-1)
    if slot < rows:
        keep_begin, keep_end = reach_of(span, slot, first_lag, taps, samples)
    if keep_end < keep_begin:  # no new reach: the whole old one
        keep_begin, keep_end = end + 1, end
    for i in range(begin + k, wp.min(end, keep_begin - 1) + 1, CLEAR_THREADS):
        power[slot, i] = wp.float32(0.0)
    for i in range(wp.max(begin, keep_end + 1) + k, end + 1, CLEAR_THREADS):
        power[slot, i] = wp.float32(0.0)


@wp.kernel
def start_span(samples: int, span: wp.array2d(dtype=wp.int32)):
    """(samples, −1): no sample touched yet."""
    slot = wp.tid()
    span[slot, 0] = samples
    span[slot, 1] = -1


@wp.kernel
def emit_subrays(starts: wp.array(dtype=wp.vec3d), directions: wp.array(dtype=wp.vec3d),
                 offsets: wp.array(dtype=wp.vec2d), ray_starts: wp.array(dtype=wp.vec3f),
                 ray_directions: wp.array(dtype=wp.vec3f)):
    """The float32 sub-rays the deposit casts (for timing the bare ray cast of the same rays)."""
    slot, k = wp.tid()
    n = offsets.shape[0]
    ray_starts[slot * n + k] = wp.vec3f(starts[slot])
    u, v = beam_frame(directions[slot])
    ray_directions[slot * n + k] = wp.vec3f(subray_direction(directions[slot], u, v, offsets[k]))


@wp.kernel
def receive(r: Receiver, dt: wp.float64, samples: int, keys: wp.array(dtype=wp.int64), power: wp.array2d(dtype=wp.float32)):
    """The detector's reading of every sample: background added, photo-electrons drawn Poisson from the
    mean (power + background)·dt / (energy per electron), Gaussian receiver noise, then the digitiser's
    code (rounded, clipped to [0, top]) times its step [W]. Keyed by the beam (``keys[slot]``: line
    seed · 2³² + pulse · beams + beam) and the sample, so the same seed reads the same on any device and
    chunking."""
    slot, i = wp.tid()
    key = keys[slot]
    state = wp.rand_init(int((key * wp.int64(1000003) + wp.int64(r.stream)) % wp.int64(2147483647)), i)
    value = wp.float64(power[slot, i]) + r.background
    if r.shot_noise != 0:
        mean = value * dt / r.joules_per_electron
        value = wp.float64(wp.poisson(state, wp.float32(mean))) * r.joules_per_electron / dt
    if r.thermal > wp.float64(0.0):
        value += r.thermal * wp.float64(wp.randn(state))
    if r.lsb > wp.float64(0.0):
        value = wp.clamp(wp.round(value / r.lsb), wp.float64(0.0), r.top) * r.lsb
    power[slot, i] = wp.float32(value)


@wp.kernel
def beam_keys(pulses: wp.array2d(dtype=wp.float64), per_pulse: int, keys: wp.array(dtype=wp.int64)):
    """Each slot's noise key: its line's seed · 2³² + pulse · beams + beam."""
    slot = wp.tid()
    p = slot // per_pulse
    keys[slot] = (wp.int64(pulses[ROW_SEED, p]) << wp.int64(32)) + wp.int64(pulses[ROW_PULSE, p]) * wp.int64(per_pulse) \
        + wp.int64(slot % per_pulse)
