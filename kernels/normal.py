"""The standard normal distribution in float64 on the device, for the photon samplers (kernels/photon.py,
kernels/canopy_photons.py): Φ and the shape exp(−z²/2) of φ, their tails returned without erfc or exp where float64
makes them exactly 0 or 1 (the same values: detections far from an echo skip the calls)."""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

SQRT1_2 = wp.constant(wp.float64(0.7071067811865476))
INV_SQRT_2PI = wp.constant(wp.float64(0.3989422804014327))
NORMAL_TAIL = wp.constant(wp.float64(40.0))
"""|x| from which float64 gives Φ(x) = erfc(−x/√2)/2 exactly 0 (x ≤ −40: erfc(28.3) ≈ 1e-349 underflows to 0) or
exactly 1 (x ≥ 40: erfc(−28.3) = 2 − 1e-349 rounds to 2), and exp(−x²/2) exactly 0 (e^−800 underflows)."""


@wp.func
def normal_cdf(x: wp.float64):
    """Φ(x), the standard normal CDF: erfc(−x/√2)/2, its tails beyond ±NORMAL_TAIL without the erfc (the same
    values)."""
    if x <= -NORMAL_TAIL:
        return wp.float64(0.0)
    if x >= NORMAL_TAIL:
        return wp.float64(1.0)
    return wp.float64(0.5) * wp.erfc(-x * SQRT1_2)


@wp.func
def normal_shape(z: wp.float64):
    """exp(−z²/2) (√(2π) φ(z)), exactly 0 beyond ±NORMAL_TAIL without the exp."""
    if wp.abs(z) < NORMAL_TAIL:
        return wp.exp(wp.float64(-0.5) * z * z)
    return wp.float64(0.0)
