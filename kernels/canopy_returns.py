"""Discrete returns through a turbid canopy: each beam's surface hit and the echoes of the leaves above it.

A beam of unit energy crossing voxels of leaf area density u (extinction κ = G(μ) u per metre, G the leaf
angle distribution's projection, :mod:`kernels.canopy`) keeps exp(−τ) of its energy after an optical depth
τ; a voxel the beam crosses for a length ℓ intercepts exp(−τ_before)·(1 − exp(−κℓ)) of it, and the leaves
send back ``leaf_reflectance`` times what they intercept; the surface under them returns exp(−τ_total)·ρ·cos θ
(ρ the triangle's albedo, or the detector's ``reflectance``). Returning light comes back through the same gaps
(the hot spot of a monostatic lidar), so it is not dimmed twice.

The detector (:class:`EchoDetection`) triggers on the leading edge: walking down the beam, the leaf echo
gathered since the detector was last armed reaches ``threshold`` (in units of a white Lambertian target filling
the footprint at normal incidence) at the range where the return is placed (exactly, within the voxel: the
intercepted energy grows as 1 − exp(−κs)); the detector is then blind for ``min_separation`` metres, and what
the leaves send back meanwhile is lost. The surface returns if its echo reaches the threshold and it lies
beyond the blind stretch of the last leaf return. At most ``max_returns`` are kept, the first ones.

A return lies on the beam at its range: the true point p_true − Δ·direction, and each model's point
p − Δ·d (:class:`kernels.trace.SlotTrace`), Δ its distance above the surface hit along the beam, so a leaf
return shares the beam's ranging errors. Its class is 3, 4 or 5 (low, medium, high vegetation: below
:data:`LOW_VEGETATION_M`, below :data:`MEDIUM_VEGETATION_M` or higher above the surface hit, vertically),
written as the face index ``triangles + class − 3`` (:func:`leaf_face`), so per-face tables extended by three
rows label it.
"""
import functools

import warp as wp

from kernels.canopy import NO_INTERACTION, Canopy, g_of, leaf_span, walk_begin, walk_next
from kernels.parts import Instrument
from kernels.looks import FIRST_LOOK, SECOND_LOOK, Misses, list_miss
from kernels.trace import (COUNT_MISS, COUNT_TIR, STATUS_LEAF, STATUS_MISS, STATUS_RETRY, STATUS_RETURN, STATUS_TIR,
                           Features, SlotTrace, scan_struct, signed_off_nadir, slot_function)
from kernels.edges import boundary_distance, near_boundary
from kernels.frames import ROW_RIGHT, get3

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

COUNT_DARK = 2  # counters: beams that hit the surface but whose every echo stayed below the threshold
COUNT_RETURNED = 3  # beams with at least one return
COUNT_LEAF = 4  # leaf returns
COUNTERS = 5
LOW_VEGETATION_M = wp.constant(wp.float64(0.5))
MEDIUM_VEGETATION_M = wp.constant(wp.float64(2.0))


@wp.struct
class EchoDetection:
    """The discrete detector's trigger, in units of a white Lambertian target filling the footprint."""

    threshold: wp.float64  # echo a return needs (> 0)
    min_separation: wp.float64  # the detector's blind stretch after a return [m]
    max_returns: wp.int32  # returns kept per beam (the slots per beam)
    leaf_reflectance: wp.float64  # what leaves send back of what they intercept
    reflectance: wp.float64  # the surface's albedo where the scene has none per triangle
    triangles: wp.int32  # the mesh's triangles: leaf returns' faces follow them


@wp.struct
class Echo:
    """A leaf return found on the way down: its distance above the surface along the beam [m] and its echo."""

    above: wp.float64
    strength: wp.float64


@wp.func
def leaf_face(triangles: wp.int32, height: wp.float64) -> wp.int32:
    """The face index of a leaf return ``height`` [m] above the surface, vertically (classes 3, 4, 5)."""
    if height < LOW_VEGETATION_M:
        return triangles
    if height < MEDIUM_VEGETATION_M:
        return triangles + 1
    return triangles + 2


@wp.func
def box_depth(c: Canopy, point: wp.vec3d, up: wp.vec3d) -> wp.float64:
    """How far the ray ``point + s · up`` (unit ``up``, s ≥ 0) runs before it leaves the canopy's box (0 when it
    starts outside and never enters, or the canopy is absent)."""
    if c.present == 0:
        return wp.float64(0.0)
    far = wp.float64(1.0e30)
    near = wp.float64(0.0)
    for a in range(3):
        lo = c.lower[a]
        hi = c.lower[a] + wp.float64(c.dims[a]) * c.cell[a]
        if wp.abs(up[a]) < wp.float64(1.0e-300):
            if point[a] < lo or point[a] > hi:
                return wp.float64(0.0)
        else:
            t0 = (lo - point[a]) / up[a]
            t1 = (hi - point[a]) / up[a]
            near = wp.max(near, wp.min(t0, t1))
            far = wp.min(far, wp.max(t0, t1))
    if far <= near:
        return wp.float64(0.0)
    return far


@wp.func
def depth_at(transmission: wp.float64) -> wp.float64:
    """The optical depth τ at which the beam keeps ``transmission`` = exp(−τ) of its energy; +inf where it is 0 or
    less (the light that is left can never be reached)."""
    if transmission <= wp.float64(0.0):
        return NO_INTERACTION
    return -wp.log(transmission)


@wp.struct
class Trigger:
    """The detector's state on the way down a beam (:func:`leaf_returns`)."""

    count: wp.int32  # returns so far (also those past max_returns, which are not kept)
    armed: wp.float64  # distance down from the walk's top at which the detector listens again [m]
    blind: wp.int32  # 1: the last return's blind stretch has not ended: its echo is still gathering
    at_return: wp.float64  # the beam's transmission where the last return was placed
    above: wp.float64  # the last return's distance above the surface along the beam [m]
    next_left: wp.float64  # the transmission at which the next return triggers
    target: wp.float64  # the optical depth at which it does (depth_at(next_left))


@wp.func
def arm(det: EchoDetection, t: Trigger, transmission: wp.float64) -> Trigger:
    """``t`` listening again where the beam's transmission is ``transmission``: the leaves' echo gathered from there,
    ρ_l (transmission − exp(−τ)), reaches the threshold where exp(−τ) = transmission − threshold / ρ_l. Once
    ``max_returns`` are kept it listens no more: a later return would change nothing kept (with them kept, the
    surface's return is not), and without a blind stretch a tiny threshold would otherwise make ρ_l / threshold
    returns."""
    r = t
    r.next_left = transmission - det.threshold / det.leaf_reflectance
    r.target = depth_at(r.next_left)
    if t.count >= det.max_returns:
        r.target = NO_INTERACTION
    return r


@wp.func
def end_blind(det: EchoDetection, t: Trigger, transmission: wp.float64, echoes: wp.array(dtype=Echo),
              base: int) -> Trigger:
    """The last return's blind stretch over where the beam's transmission is ``transmission``: its echo is the
    threshold plus what the leaves sent back meanwhile, ρ_l (transmission at the return − ``transmission``); the
    detector listens again."""
    if t.count <= det.max_returns:
        e = Echo()
        e.above = t.above
        e.strength = det.threshold + det.leaf_reflectance * (t.at_return - transmission)
        echoes[base + t.count - 1] = e
    r = arm(det, t, transmission)
    r.blind = 0
    return r


@wp.func
def trigger_in(t: Trigger, kappa: wp.float64, tau_out: wp.float64, t_in: wp.float64, t_out: wp.float64) -> bool:
    """Whether the detector ``t`` changes state in a voxel of extinction ``kappa`` [1/m] spanning t_in … t_out [m], at
    whose end the optical depth is ``tau_out``: its blind stretch ends there (or ended in voxels without leaves before
    it), or, listening, it triggers there. Only a voxel with leaves and a length can hold either."""
    if not (kappa > wp.float64(0.0) and t_in < t_out):
        return False
    if t.blind != 0:
        return t.armed <= t_out
    return tau_out >= t.target


@wp.func
def leaf_returns(c: Canopy, det: EchoDetection, top: wp.vec3d, direction: wp.vec3d, depth: wp.float64,
                 echoes: wp.array(dtype=Echo), base: int):
    """Walk the beam down from ``top`` (``depth`` [m] above the surface hit) and write its leaf returns into
    ``echoes[base:]`` (each one's echo: the threshold it reached and what the leaves sent back while the detector
    was blind after it); returns (their count, the transmission left at the surface, the end of the last blind
    stretch as a distance down from ``top`` [m]).

    The echo the leaves send back between two points of the beam is ρ_l times the energy they intercept there, the
    difference of the beam's transmissions exp(−τ) at the two, so the walk carries the optical depth τ alone: a
    return lies where τ reaches the trigger's target (linear within a voxel), and an exp is taken only where a
    blind stretch ends and at the surface, not in every voxel the beam crosses."""
    g = g_of(c, direction)
    tau = wp.float64(0.0)  # the optical depth from top to the current voxel's entry
    t = Trigger()
    t.count = 0
    t.armed = wp.float64(0.0)
    t.blind = 0
    t.at_return = wp.float64(1.0)
    t.above = wp.float64(0.0)
    t = arm(det, t, wp.float64(1.0))
    span = leaf_span(c, top, direction, depth)  # the walk crosses no leaves outside it: the same numbers
    w = walk_begin(c, top, direction, span[0], span[1])
    while w.done == 0:
        kappa = g * wp.float64(w.lad)
        tau_out = tau + kappa * (w.t_out - w.t_in)  # tau itself in a voxel without leaves
        if trigger_in(t, kappa, tau_out, w.t_in, w.t_out):  # the rare voxel where the detector's state changes
            s = w.t_in
            while s < w.t_out:
                if t.blind != 0:
                    if t.armed > w.t_out:
                        break
                    s = wp.max(s, t.armed)  # the blind stretch ends in this voxel (or ended in empty ones before it)
                    t = end_blind(det, t, wp.exp(-(tau + kappa * (s - w.t_in))), echoes, base)
                elif tau_out < t.target:
                    break
                else:
                    s = wp.min(wp.max(s, w.t_in + (t.target - tau) / kappa), w.t_out)
                    t.count += 1
                    t.at_return = t.next_left
                    t.above = depth - s
                    t.armed = s + det.min_separation
                    t.blind = 1
                    if det.min_separation == wp.float64(0.0):  # no blind stretch: listening again at once
                        t = end_blind(det, t, t.at_return, echoes, base)
        tau = tau_out
        w = walk_next(c, w)
    transmission = wp.exp(-tau)
    if t.blind != 0:  # the walk ended blind: the echo gathered to its end
        t = end_blind(det, t, transmission, echoes, base)
    return wp.min(t.count, det.max_returns), transmission, t.armed


SMEM_SPILLING = True  # the walk kernel's register spills go to shared memory first (False: all to local memory)
BLOCK_THREADS = 256  # threads per block of Warp's launches (wp.launch's default block_dim)
SM_REGISTERS = 65536  # 32-bit registers per multiprocessor (every CUDA architecture since Kepler)


def walk_register_options(max_registers: int | None) -> dict:
    """Kernel options capping the walk kernel's registers at ``max_registers`` (None: the compiler's choice). With
    :data:`SMEM_SPILLING`, the cap is given as launch bounds (blocks of :data:`BLOCK_THREADS` threads, enough of them
    per multiprocessor that no thread has more than ``max_registers``: 64 for caps 64 to 85, 80 for 86 to 127, 128
    for 128 to 255) so that the CUDA compiler (13.0 and later) may spill to shared memory, which the walk kernel
    does not use otherwise."""
    if max_registers is None:
        return {}
    if not SMEM_SPILLING:
        return {"cuda_max_registers": max_registers}
    blocks = min(8, -(-SM_REGISTERS // (BLOCK_THREADS * max_registers)))
    return {"launch_bounds": (BLOCK_THREADS, blocks), "enable_cuda_smem_spilling": True}


@functools.cache
def canopy_trace_kernel(f: Features, instrument: Instrument, max_registers: int | None = None, look: int = FIRST_LOOK):
    """The first stage of the points kernel of a scene with a canopy: one thread per beam (per listed beam in the
    second look), its surface trace (:class:`kernels.trace.SlotTrace`) into a per-beam scratch row that
    :func:`canopy_points_kernel` reads."""
    trace_slot = slot_function(f, instrument, look)
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique", enable_backward=False, cuda_max_registers=max_registers, grid_stride=False)
    def trace_canopy_beams(
        pulses: wp.array2d(dtype=wp.float64),  # In: the chunk's pulse table
        scan: Scan,
        misses: Misses,  # the first look's misses: listed by the first look, traced by the second
        traces: wp.array(dtype=SlotTrace),  # Out: per beam, its surface trace [m, local]
    ):
        beam_slot = wp.tid()
        if wp.static(look == SECOND_LOOK):
            if beam_slot >= misses.count[0]:
                return
            beam_slot = misses.slots[beam_slot]
        per_pulse = scan.per_pulse
        s = trace_slot(pulses, beam_slot // per_pulse, beam_slot % per_pulse, scan)
        if s.status == STATUS_RETRY:
            list_miss(misses, beam_slot)
        else:
            traces[beam_slot] = s

    return trace_canopy_beams


@functools.cache
def canopy_points_kernel(f: Features, instrument: Instrument, max_registers: int | None = None):
    """The second stage of the points kernel of a scene with a canopy: one thread per beam, ``max_returns`` slots
    per beam. It walks the leaves from what the walk needs of the beam's trace (:func:`canopy_trace_kernel`) and
    reads the rest of the trace only after the walk, so none of it is held in registers across the walk."""
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique", enable_backward=False, **walk_register_options(max_registers), grid_stride=False)
    def trace_canopy_points(
        pulses: wp.array2d(dtype=wp.float64),
        scan: Scan,
        traces: wp.array(dtype=SlotTrace),  # per beam, its surface trace (trace_canopy_beams)
        canopy: Canopy,
        det: EchoDetection,
        face_reflectance: wp.array(dtype=wp.float32),  # the surface's albedo per triangle (empty: none)
        echoes: wp.array(dtype=Echo),  # scratch: max_returns per beam
        # Out: per slot (beam · max_returns + k), as the points kernel's
        status: wp.array(dtype=wp.int32),
        ranges: wp.array(dtype=wp.float32),
        faces: wp.array(dtype=wp.int32),
        scan_angles: wp.array(dtype=wp.float32),
        intensity: wp.array(dtype=wp.float32),  # the echo [white Lambertian target], written as cos_incidence
        edge_distance: wp.array(dtype=wp.float32),
        true_points: wp.array(dtype=wp.vec3f),
        exact_points: wp.array(dtype=wp.vec3f),
        nominal_points: wp.array(dtype=wp.vec3f),
        returns: wp.array(dtype=wp.int32),  # per slot: return number | number of returns << 4
        counters: wp.array(dtype=wp.int32),  # [TIR, misses, dark beams, beams with returns, leaf returns]
    ):
        beam_slot = wp.tid()
        k_max = det.max_returns
        base = beam_slot * k_max
        for k in range(k_max):
            status[base + k] = STATUS_MISS
        traced = traces[beam_slot].status
        if traced == STATUS_TIR:
            status[base] = STATUS_TIR
            wp.atomic_add(counters, COUNT_TIR, 1)
            return
        if traced == STATUS_MISS:
            wp.atomic_add(counters, COUNT_MISS, 1)
            return
        direction = wp.vec3d(traces[beam_slot].direction)
        hit = wp.vec3d(traces[beam_slot].p_true)
        depth = wp.min(box_depth(canopy, hit, -direction), wp.float64(traces[beam_slot].r))
        n, transmission, armed = leaf_returns(canopy, det, hit - depth * direction, direction, depth, echoes, base)
        s = traces[beam_slot]  # the rest of the trace, read after the walk
        direction = wp.vec3d(s.direction)
        rho = det.reflectance
        if face_reflectance.shape[0] > 0:
            rho = wp.float64(face_reflectance[s.face])
        normal = wp.vec3d(wp.mesh_eval_face_normal(scan.mesh, s.face))
        surface = transmission * rho * wp.abs(wp.dot(direction, normal))
        ground = int(0)
        if surface >= det.threshold and armed <= depth and n < k_max:
            ground = 1
        total = n + ground
        if total == 0:
            wp.atomic_add(counters, COUNT_DARK, 1)
            return
        wp.atomic_add(counters, COUNT_RETURNED, 1)
        if n > 0:
            wp.atomic_add(counters, COUNT_LEAF, n)
        angle = signed_off_nadir(s.direction, wp.vec3f(get3(pulses, ROW_RIGHT, beam_slot // scan.per_pulse)))
        surface_edge = scan.edge_cap
        if wp.static(f.edges):
            if near_boundary(scan.edge_grid, s.p_true):
                surface_edge = boundary_distance(scan.edge_grid, scan.boundary_a, scan.boundary_b, s.p_true,
                                                 scan.edge_cap)
        for k in range(total):
            slot = base + k
            above = wp.float64(0.0)
            strength = surface
            code = STATUS_RETURN
            face = s.face
            edge = surface_edge
            if k < n:
                e = echoes[base + k]
                above = e.above
                strength = e.strength
                code = STATUS_LEAF
                face = leaf_face(det.triangles, above * wp.abs(direction[2]))
            status[slot] = code
            ranges[slot] = s.r - wp.float32(above)
            faces[slot] = face
            scan_angles[slot] = angle
            intensity[slot] = wp.float32(wp.min(strength, wp.float64(1.0)))
            edge_distance[slot] = edge
            returns[slot] = (k + 1) | (total << 4)
            lift = wp.float32(above)
            if wp.static(f.with_truth):
                true_points[slot] = s.p_true - lift * s.direction
            if wp.static(f.exact):
                exact_points[slot] = s.p_exact - lift * s.d_exact
            if wp.static(f.nominal):
                nominal_points[slot] = s.p_nominal - lift * s.d_nominal

    return trace_canopy_points
