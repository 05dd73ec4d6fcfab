"""Per-beam kernels: fire the fan, refract through the prism, ray-cast the scene, georeference.

One thread per (pulse, sub-beam) slot of a chunk. Kernels are specialised at build time for
the georeferencing models and features a run asks for (``wp.static``), so a feature that is off
costs nothing per beam.
"""
import functools
from typing import Any

import warp as wp

from kernels.frames import PulsePose
from kernels.optics import doe_direction, prism_exit, rigid_array_direction

wp.set_module_options({"enable_backward": False})

STATUS_MISS = wp.constant(0)
STATUS_RETURN = wp.constant(1)
STATUS_TIR = wp.constant(2)

COUNT_TIR = 0
COUNT_MISS = 1


@wp.struct
class Prism:
    """Wedge prism parameters as one side (truth or processing) believes them."""

    n_glass: wp.float32  # refractive index of the glass (air = 1)
    apex: wp.float32  # apex angle α [rad]
    thickness: wp.float32  # d1, centre thickness [m]


@wp.struct
class BeamArray:
    """The DOE fan: n×n sub-beams spaced by ``spacing`` [rad]."""

    n: wp.int32
    spacing: wp.float32


@wp.func
def signed_off_nadir(direction: wp.vec3f, right: wp.vec3f):
    """Signed off-nadir angle of a local-frame direction [deg]; positive towards the right wing."""
    off_nadir = wp.acos(wp.clamp(-direction[2], -1.0, 1.0))
    return wp.where(wp.dot(direction, right) < 0.0, -off_nadir, off_nadir) * 57.29577951308232


@wp.func
def _gaussian(state: wp.uint32):
    """Standard normal deviate by Box–Muller, the two uniforms drawn in separate statements."""
    u1 = wp.randf(state)
    u2 = wp.randf(state)
    return wp.sqrt(-2.0 * wp.log(wp.max(u1, 1.0e-12))) * wp.cos(6.283185307179586 * u2)


@functools.cache
def trace_kernel(exact: bool, nominal: bool, believed_is_truth: bool, with_truth: bool, noisy: bool):
    """Build the per-beam kernel for one combination of features.

    exact / nominal: which georeferencing models to evaluate (SPEC §5); believed_is_truth: the
    processing's prism equals the simulated one, so the exact model reuses the traced ray;
    with_truth: also write the true hit point; noisy: add Gaussian range noise.
    """

    @wp.kernel(module="unique")
    def trace(
        # In: scene
        mesh: wp.uint64,
        max_range: wp.float32,  # [m]
        # In: instrument
        poses: wp.array(dtype=PulsePose),
        beams: BeamArray,
        truth: Prism,
        believed: Prism,
        noise_sigma: wp.float32,  # range noise, 1σ [m]
        noise_seed: wp.int32,
        slot_base: wp.int32,  # offset of this chunk's slots in the run's noise stream
        # Out: per slot
        status: wp.array(dtype=wp.int32),
        ranges: wp.array(dtype=wp.float32),  # observed one-way range, exit point to hit [m]
        faces: wp.array(dtype=wp.int32),
        scan_angles: wp.array(dtype=wp.float32),  # [deg]
        cos_incidence: wp.array(dtype=wp.float32),
        true_points: wp.array(dtype=wp.vec3f),  # [m, local]
        exact_points: wp.array(dtype=wp.vec3f),
        nominal_points: wp.array(dtype=wp.vec3f),
        counters: wp.array(dtype=wp.int32),  # [TIR, misses]
    ):
        slot = wp.tid()
        per_pulse = beams.n * beams.n
        pose = poses[slot // per_pulse]
        beam = slot % per_pulse
        s1 = doe_direction(beam // beams.n, beam % beams.n, beams.n, beams.spacing)

        s3, exit_point, ok = prism_exit(s1, pose.phi, truth.n_glass, truth.apex, truth.thickness)
        if not ok:
            status[slot] = STATUS_TIR
            wp.atomic_add(counters, COUNT_TIR, 1)
            return
        start = pose.origin + pose.rot * exit_point
        direction = pose.rot * s3
        hit = wp.mesh_query_ray(mesh, start, direction, max_range)
        if not hit.result:
            status[slot] = STATUS_MISS
            wp.atomic_add(counters, COUNT_MISS, 1)
            return

        r = hit.t
        if wp.static(noisy):
            state = wp.rand_init(noise_seed, slot_base + slot)
            r = r + noise_sigma * _gaussian(state)
        # georeference from the observation (φ, i, j, r) with the prism the processing believes in
        ok_exact = True
        ok_nominal = True
        if wp.static(exact):
            if wp.static(believed_is_truth):
                exact_points[slot] = start + r * direction
            else:
                s3b, exit_b, ok_exact = prism_exit(s1, pose.phi, believed.n_glass, believed.apex, believed.thickness)
                exact_points[slot] = pose.origin + pose.rot * (exit_b + r * s3b)
        if wp.static(nominal):
            axis = wp.vec3f(0.0, 0.0, 1.0)
            s3c, exit_c, ok_nominal = prism_exit(axis, pose.phi, believed.n_glass, believed.apex, believed.thickness)
            nominal_points[slot] = pose.origin + pose.rot * (exit_c + r * rigid_array_direction(s1, s3c))
        if not (ok_exact and ok_nominal):
            # the believed prism reflects this beam internally: processing cannot place it
            status[slot] = STATUS_TIR
            wp.atomic_add(counters, COUNT_TIR, 1)
            return
        status[slot] = STATUS_RETURN
        ranges[slot] = r
        faces[slot] = hit.face
        scan_angles[slot] = signed_off_nadir(direction, pose.right)
        cos_incidence[slot] = wp.abs(wp.dot(direction, hit.normal))
        if wp.static(with_truth):
            true_points[slot] = start + hit.t * direction

    return trace


@wp.kernel
def flag_returns(status: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where slot i produced a return."""
    i = wp.tid()
    flags[i] = wp.where(status[i] == STATUS_RETURN, 1, 0)


@wp.kernel
def compact_slots(
    flags: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),  # exclusive prefix sum of flags
    src: wp.array(dtype=Any),
    dst: wp.array(dtype=Any),
):
    """Gather the returning slots of ``src`` into ``dst``, keeping their order."""
    i = wp.tid()
    if flags[i] != 0:
        dst[offsets[i]] = src[i]


@wp.kernel
def slot_indices(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), dst: wp.array(dtype=wp.int32)):
    """dst[k] = slot index of the k-th return of the chunk."""
    i = wp.tid()
    if flags[i] != 0:
        dst[offsets[i]] = i
