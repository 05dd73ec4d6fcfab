"""The leaves' echo in photon counting: a continuous part of a pixel's arrival intensity (kernels/photon.py).

Along a beam (unit ``direction`` from ``start``, down to the surface it meets at ``t_end`` [m]) a voxel crossed
from s_a to s_b with extinction κ (kernels/canopy.py) holds the expected photo-electrons
    n_v = S · T(s_a) · (1 − e^{−κ(s_b − s_a)}) / r_v²
(S: a white Lambertian target's photo-electrons at unit range times the leaves' albedo ρ_l, :func:`leaf_ray`;
r_v the voxel's middle range; light returns through the same gaps), spread over its times of flight
τ = (2s/c)(1 + drift) + delay as A e^{−k(τ − a)}, τ in [a, b], with k = κ c / (2 (1 + drift)). Seen through the
pulse and the timing jitter (a Gaussian of σ, as the surface's echo), its rate and its integral up to t are
closed forms:
    R_v(t) = A J(t),   I_v(t) = (A/k) [Φ((t − a)/σ) − e^{−k(b − a)} Φ((t − b)/σ) − J(t)],
    J(t) = e^{−k(t − a) + k²σ²/2} [Φ((b − t + kσ²)/σ) − Φ((a − t + kσ²)/σ)],
so the sampler inverts Λ(t) = noise + surface + Σ_v I_v(t) exactly, as it does the surface's echo alone. A voxel
more than :data:`FAR_SIGMAS` σ away from t adds its whole n_v (before t) or nothing (after): J's exponential stays
finite.
"""
import warp as wp

from kernels.canopy import Canopy, g_of, walk_begin, walk_next
from kernels.normal import normal_cdf

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

LIGHT_SPEED = wp.constant(wp.float64(299792458.0))  # [m/s]
FAR_SIGMAS = wp.constant(wp.float64(12.0))
THIN = wp.constant(wp.float64(1.0e-12))  # optical depth of a voxel below which it holds no leaves


@wp.struct
class LeafRay:
    """A beam through the leaves, as the photon sampler reads it."""

    start: wp.vec3d  # [m, local]
    direction: wp.vec3d  # unit
    t_end: wp.float64  # where the beam meets the surface (or leaves the scene) [m]
    scale: wp.float64  # S: photo-electrons at unit range from leaves intercepting the whole beam [pe m²]
    drift: wp.float64  # the ranging chain's clock drift: times of flight read (1 + drift) long
    delay: wp.float64  # and the beam's fixed delay [s]
    at_open: wp.float64  # the leaves' expected photo-electrons before the gate opens (leaf_sum at its opening)
    present: wp.int32  # 0: no leaves on this beam (no canopy, or the beam never left the instrument)


@wp.func
def _voxel_part(sigma: wp.float64, t: wp.float64, a: wp.float64, b: wp.float64, k: wp.float64, density: wp.float64,
                rate: int):
    """One voxel's share of the leaves' rate (``rate`` = 1) or of its integral up to t (0); ``density`` = A/k, the
    voxel's photo-electrons n_v over 1 − e^{−k(b − a)}."""
    decay = wp.exp(-k * (b - a))
    if t < a - FAR_SIGMAS * sigma:
        return wp.float64(0.0)
    if t > b + FAR_SIGMAS * sigma:
        if rate == 1:
            return wp.float64(0.0)
        return density * (wp.float64(1.0) - decay)
    shift = k * sigma * sigma
    j = wp.exp(-k * (t - a) + wp.float64(0.5) * k * shift) * (normal_cdf((b - t + shift) / sigma)
                                                             - normal_cdf((a - t + shift) / sigma))
    if rate == 1:
        return density * k * j
    return density * (normal_cdf((t - a) / sigma) - decay * normal_cdf((t - b) / sigma) - j)


@wp.func
def leaf_sum(c: Canopy, leaf: LeafRay, sigma: wp.float64, t: wp.float64, rate: int):
    """Σ over the beam's voxels of the leaves' rate at time of flight t [1/s] (``rate`` = 1), or of their expected
    photo-electrons up to t (0); with t past every voxel (and ``rate`` = 0), all the leaves' photo-electrons."""
    if leaf.present == 0:
        return wp.float64(0.0)
    g = g_of(c, leaf.direction)
    stretch = wp.float64(2.0) * (wp.float64(1.0) + leaf.drift) / LIGHT_SPEED  # dτ/ds [s/m]
    transmission = wp.float64(1.0)
    total = wp.float64(0.0)
    w = walk_begin(c, leaf.start, leaf.direction, wp.float64(0.0), leaf.t_end)
    while w.done == 0:
        depth = g * wp.float64(w.lad) * (w.t_out - w.t_in)
        if depth > THIN:
            mid = wp.float64(0.5) * (w.t_in + w.t_out)
            a = w.t_in * stretch + leaf.delay
            b = w.t_out * stretch + leaf.delay
            total += _voxel_part(sigma, t, a, b, depth / (b - a), leaf.scale * transmission / (mid * mid), rate)
            transmission *= wp.exp(-depth)
        w = walk_next(c, w)
    return total


@wp.func
def transmission_to(c: Canopy, leaf: LeafRay):
    """exp(−optical depth) of the leaves between the beam's start and ``t_end``: what reaches the surface."""
    if leaf.present == 0:
        return wp.float64(1.0)
    g = g_of(c, leaf.direction)
    depth = wp.float64(0.0)
    w = walk_begin(c, leaf.start, leaf.direction, wp.float64(0.0), leaf.t_end)
    while w.done == 0:
        depth += g * wp.float64(w.lad) * (w.t_out - w.t_in)
        w = walk_next(c, w)
    return wp.exp(-depth)
