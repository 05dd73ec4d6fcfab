"""Beam optics on the device: the DOE fan, vector Snell refraction, the wedge prism, the rigid-array model.

Every function is generic in the float type (``float32`` in production, ``float64`` for the
reference path), so one source of each formula serves both precisions (SPEC §3–§5).

Sensor frame: +z is the prism axis, x and y span the prism faces. The front face Σ1 is the plane
z = 0; all sub-beams of the fan cross Σ1 at the origin. The back face Σ2 passes through
(0, 0, thickness) with normal N2(φ) = (sin α cos φ, sin α sin φ, cos α).
"""
import functools
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def doe_direction(i: int, j: int, n: int, spacing: Any):
    """Incident unit direction S1 of sub-beam (i, j) of an n×n fan [sensor frame].

    spacing: angular spacing Δ between neighbouring sub-beams [rad]. The offsets are
    a_i = (i − (n−1)/2)·Δ and b_j = (j − (n−1)/2)·Δ; S1 = normalize(tan a_i, tan b_j, 1).
    """
    half = type(spacing)(n - 1) * type(spacing)(0.5)
    a = (type(spacing)(i) - half) * spacing
    b = (type(spacing)(j) - half) * spacing
    return wp.normalize(wp.vector(wp.tan(a), wp.tan(b), type(spacing)(1.0)))


@wp.func
def refract(s: Any, normal: Any, mu: Any):
    """Vector Snell law: direction after crossing a surface.

    s: unit incident direction; normal: unit surface normal oriented along propagation
    (normal·s > 0); mu = n_in / n_out. Returns (t, ok): t is the unit refracted direction,
    ok is False on total internal reflection (then t is not meaningful, never NaN).
    """
    zero = type(mu)(0.0)
    one = type(mu)(1.0)
    c = wp.dot(normal, s)
    radicand = one - mu * mu * (one - c * c)
    t = mu * s + (wp.sqrt(wp.max(radicand, zero)) - mu * c) * normal
    return t, radicand >= zero


@wp.func
def back_face_normal(phi: Any, apex: Any):
    """Unit normal N2(φ) of the prism's back face Σ2; phi: prism angle [rad], apex: α [rad]."""
    sa = wp.sin(apex)
    return wp.vector(sa * wp.cos(phi), sa * wp.sin(phi), wp.cos(apex))


@wp.func
def enter_prism(s1: Any, n_glass: Any):
    """Direction S2 inside the glass after the front face Σ1 (z = 0); never reflects (n_glass > 1)."""
    zero = type(n_glass)(0.0)
    one = type(n_glass)(1.0)
    s2, ok = refract(s1, wp.vector(zero, zero, one), one / n_glass)
    return s2


@wp.func
def leave_prism(s2: Any, n2: Any, n_glass: Any, thickness: Any):
    """Leave the glass through Σ2 of normal n2: (exit direction S3, exit point [m], ok).

    The ray runs from the origin of Σ1 along s2 to Σ2, the plane through (0, 0, thickness) of
    normal n2: N2·(t·s2 − (0, 0, d1)) = 0 (seed paper eqs. 1–4); ok is False on total internal
    reflection.
    """
    t = thickness * n2[2] / wp.dot(n2, s2)
    s3, ok = refract(s2, n2, n_glass)
    return s3, t * s2, ok


@wp.func
def prism_exit(s1: Any, phi: Any, n_glass: Any, apex: Any, thickness: Any):
    """Trace an incident direction through the wedge prism (SPEC §4, seed paper eqs. 1–7).

    s1: unit incident direction [sensor frame]; phi: prism angle [rad]; n_glass: refractive
    index of the glass (air = 1); apex: wedge apex angle α [rad]; thickness: d1 [m].
    Returns (s3, exit_point, ok): exit direction, the point where the ray leaves Σ2 [m],
    and False on total internal reflection at Σ2.
    """
    return leave_prism(enter_prism(s1, n_glass), back_face_normal(phi, apex), n_glass, thickness)


@wp.func
def rigid_array_rotation(s1: Any):
    """Q, the smallest rotation taking ẑ to the unit vector s1 (quaternion (ẑ × s1, 1 + ẑ·s1), normalised)."""
    one = type(s1[0])(1.0)
    return wp.normalize(wp.quaternion(-s1[1], s1[0], type(s1[0])(0.0), one + s1[2]))


@wp.func
def rigid_array_direction(s1: Any, s3_center: Any):
    """Exit direction of sub-beam S1 under the nominal rigid-array model (SPEC §5): Q·S3_center.

    The processing assumes the fan leaves the prism with its incident shape.
    """
    return wp.quat_rotate(rigid_array_rotation(s1), s3_center)


PORTABLE_CPU_FLAGS = wp.config.cpu_compiler_flags.replace("-march=native", "").strip()  # Warp's, less the host's ISA


@functools.cache
def exit_fan_kernel(dtype: type):
    """Kernel tracing a whole fan at many prism angles, in ``dtype`` (wp.float32 or wp.float64).

    Used for the optics figures, to check the device optics against float64 references, and (on the CPU, float64)
    by every Risley run for its reach and distortion, a GPU run too. On the CPU it is compiled for any x86-64 host
    rather than for this one's instructions, so its prebuilt object serves every machine (a GPU run then compiles
    nothing) and its numbers do not depend on the host (no fused multiply-adds where a host lacks them).
    """
    vec3 = wp.types.vector(3, dtype)

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False,
               module_options={"cpu_compiler_flags": PORTABLE_CPU_FLAGS})
    def exit_fan(
        # In:
        phis: wp.array(dtype=dtype),  # prism angles [rad]
        n: int,  # beams per side
        spacing: dtype,  # [rad]
        n_glass: dtype,
        apex: dtype,  # [rad]
        thickness: dtype,  # [m]
        # Out: [angle, beam i·n + j]
        directions: wp.array2d(dtype=vec3),  # exit direction S3
        exit_points: wp.array2d(dtype=vec3),  # [m]
        nominal: wp.array2d(dtype=vec3),  # rigid-array direction
        ok: wp.array2d(dtype=wp.int32),  # 0 on total internal reflection
    ):
        k, beam = wp.tid()
        s1 = doe_direction(beam // n, beam % n, n, spacing)
        s3, point, passed = prism_exit(s1, phis[k], n_glass, apex, thickness)
        z = vec3(dtype(0.0), dtype(0.0), dtype(1.0))
        s3c, point_c, passed_c = prism_exit(z, phis[k], n_glass, apex, thickness)
        directions[k, beam] = s3
        exit_points[k, beam] = point
        nominal[k, beam] = rigid_array_direction(s1, s3c)
        ok[k, beam] = wp.where(passed, 1, 0)

    return exit_fan
