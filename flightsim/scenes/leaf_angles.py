"""The leaf projection function G(μ) of the de Wit (1965) leaf inclination distributions.

G(μ) is the mean projection of unit leaf area onto the plane normal to a direction of zenith angle θ,
μ = |cos θ|, for leaves of random azimuth (Ross 1981, Myneni, Ross & Asrar 1989):

    G(μ) = ∫₀^{π/2} g(θ_L) ψ(μ, θ_L) dθ_L,

with g the density of the leaf inclination θ_L (∫₀^{π/2} g = 1) and ψ the azimuth-averaged
|cos| between the direction and a leaf normal of inclination θ_L, in closed form:

    ψ = μ cos θ_L                                              where θ + θ_L ≤ π/2 (|cot θ cot θ_L| ≥ 1),
    ψ = μ cos θ_L (1 − 2φ/π) + (2/π) sin θ sin θ_L sin φ      otherwise, φ = arccos(cot θ cot θ_L)

(the second form is Ross's μ cos θ_L [1 + (2/π)(tan φ − φ)] written without tan φ, so that it also holds at
μ = 0). The extinction of a turbid medium of leaf area density u along a ray is then G(μ) u per metre.

The de Wit densities (θ_L in [0, π/2]):

=============  ==========================
spherical      sin θ_L                    (G = ½ for every μ)
planophile     (2/π)(1 + cos 2θ_L)        (mostly horizontal leaves)
erectophile    (2/π)(1 − cos 2θ_L)        (mostly vertical)
plagiophile    (2/π)(1 − cos 4θ_L)        (mostly at 45°)
extremophile   (2/π)(1 + cos 4θ_L)        (mostly horizontal or vertical)
uniform        2/π
=============  ==========================

The integral is split at the kink of ψ (θ_L = π/2 − θ); on the far piece θ_L = κ + (π/2 − κ) w², which makes
the integrand smooth (ψ − μ cos θ_L grows like (θ_L − κ)^{3/2}), so Gauss–Legendre quadrature on both pieces
converges to machine precision.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from flightsim.core.errors import InputError

HALF_PI = 0.5 * np.pi

DENSITIES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "spherical": lambda t: np.sin(t),
    "planophile": lambda t: (2.0 / np.pi) * (1.0 + np.cos(2.0 * t)),
    "erectophile": lambda t: (2.0 / np.pi) * (1.0 - np.cos(2.0 * t)),
    "plagiophile": lambda t: (2.0 / np.pi) * (1.0 - np.cos(4.0 * t)),
    "extremophile": lambda t: (2.0 / np.pi) * (1.0 + np.cos(4.0 * t)),
    "uniform": lambda t: np.full_like(t, 2.0 / np.pi),
}
"""Leaf inclination density g(θ_L) [1/rad] of each de Wit distribution, θ_L in [0, π/2] rad."""

DISTRIBUTIONS = tuple(DENSITIES)

QUADRATURE_NODES = 48
"""Gauss–Legendre nodes on each of the two pieces of the projection integral."""


def check_distribution(distribution: str, field: str = "scene.canopy.leaf_angles") -> str:
    """``distribution`` if it names a de Wit distribution, else InputError naming ``field``."""
    if distribution not in DENSITIES:
        raise InputError(field, distribution, f"one of {', '.join(DISTRIBUTIONS)}")
    return distribution


def leaf_density(distribution: str, theta_l) -> np.ndarray:
    """g(θ_L) [1/rad] of a de Wit distribution at leaf inclinations ``theta_l`` [rad] in [0, π/2]."""
    return DENSITIES[check_distribution(distribution)](np.asarray(theta_l, dtype=np.float64))


def psi(mu, theta_l) -> np.ndarray:
    """ψ(μ, θ_L): the mean |cos| of the angle between a direction of |cos zenith| ``mu`` and the normals of
    leaves of inclination ``theta_l`` [rad] and random azimuth (Ross 1981), in closed form; broadcasts."""
    mu, theta_l = np.broadcast_arrays(np.asarray(mu, dtype=np.float64), np.asarray(theta_l, dtype=np.float64))
    theta = np.arccos(np.clip(mu, 0.0, 1.0))
    s, sl, cl = np.sin(theta), np.sin(theta_l), np.cos(theta_l)
    out = mu * cl
    far = theta + theta_l > HALF_PI
    if np.any(far):
        # 1 − cos φ = −cos(θ + θ_L) / (sin θ sin θ_L), accurate near the kink where cos φ → 1
        one_minus = np.sin(theta_l[far] - (HALF_PI - theta[far])) / (s[far] * sl[far])
        cos_phi = 1.0 - one_minus
        sin_phi = np.sqrt(np.clip(one_minus * (2.0 - one_minus), 0.0, None))
        phi = np.arctan2(sin_phi, cos_phi)
        out[far] = mu[far] * cl[far] * (1.0 - phi / HALF_PI) + s[far] * sl[far] * sin_phi / HALF_PI
    return out


def projection_integral(density: Callable[[np.ndarray], np.ndarray], mu, nodes: int = QUADRATURE_NODES) -> np.ndarray:
    """G(μ) = ∫₀^{π/2} density(θ_L) ψ(μ, θ_L) dθ_L for any leaf inclination density (normalised on
    [0, π/2]), at each |cos zenith| in ``mu`` (values in [0, 1]); float64, the shape of ``mu``."""
    mu = np.asarray(mu, dtype=np.float64)
    flat = mu.reshape(-1)
    if not np.all((flat >= 0.0) & (flat <= 1.0)):  # NaN fails too
        bad = flat[~((flat >= 0.0) & (flat <= 1.0))][0]
        raise InputError("mu", float(bad), "|cos zenith| values in [0, 1]")
    x, w = np.polynomial.legendre.leggauss(nodes)
    u, wu = 0.5 * (x + 1.0), 0.5 * w  # nodes and weights on [0, 1]
    kink = (HALF_PI - np.arccos(flat))[:, None]  # θ_L = π/2 − θ [rad]
    near = kink * u  # piece 1: θ_L in [0, κ], ψ = μ cos θ_L
    total = (kink * wu * density(near) * flat[:, None] * np.cos(near)).sum(axis=1)
    width = HALF_PI - kink  # piece 2: θ_L = κ + width · v², v in [0, 1]
    far = kink + width * u * u
    jacobian = 2.0 * width * u
    total += (wu * jacobian * density(far) * psi(flat[:, None], far)).sum(axis=1)
    return total.reshape(mu.shape)


def g_function(distribution: str, mu) -> np.ndarray:
    """G(μ) of a de Wit leaf inclination distribution at each |cos zenith| in ``mu`` ([0, 1]), float64,
    from the projection integral (``"spherical"`` gives ½ to rounding, as it must)."""
    return projection_integral(DENSITIES[check_distribution(distribution)], mu)


def g_table(distribution: str, n: int = 257) -> np.ndarray:
    """(n,) float64 G(μ) at μ = i / (n − 1), i = 0 … n − 1: the table the device interpolates
    (:func:`kernels.canopy.g_of`)."""
    if not (isinstance(n, (int, np.integer)) and n >= 2):
        raise InputError("n", n, "an integer ≥ 2 table entries")
    return g_function(distribution, np.linspace(0.0, 1.0, int(n)))
