"""Float64 NumPy model of two or three wedge prisms in a row (the geometry of kernels/wedges.py), the scan phase
that turns them, and the first-order (thin-prism) scan pattern; for the deflector's checks and reach, and as a
reference beside the device optics."""
from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

MAX_TURNS = 100_000  # most turns of a prism per turn of the scan phase


def pattern_turns(rates_hz) -> tuple[float, tuple[int, ...]] | None:
    """(f_p [Hz], m): the largest frequency of which every rate is a whole multiple, and each rate over it.

    The rates are taken as the decimals they are written as (20.001 is 20001/1000); the scan pattern repeats
    every 1/f_p seconds. None where no prism turns, or where some |m| exceeds MAX_TURNS.
    """
    fractions = [Fraction(repr(float(r))) for r in rates_hz]
    if not any(fractions):
        return None
    denominator = math.lcm(*(f.denominator for f in fractions))
    whole = [int(f * denominator) for f in fractions]
    step = math.gcd(*whole)
    turns = tuple(w // step for w in whole)
    if max(abs(m) for m in turns) > MAX_TURNS:
        return None
    return float(Fraction(step, denominator)), turns


def refract(s: np.ndarray, normal: np.ndarray, mu: float) -> tuple[np.ndarray, np.ndarray]:
    """Vector Snell law (SPEC §4) on arrays (..., 3): (t, ok), normal oriented along propagation, mu = n_in/n_out."""
    c = np.sum(normal * s, axis=-1, keepdims=True)
    radicand = 1.0 - mu * mu * (1.0 - c * c)
    t = mu * s + (np.sqrt(np.maximum(radicand, 0.0)) - mu * c) * normal
    return t, radicand[..., 0] >= 0.0


def back_face_normal(phi: np.ndarray, apex: float) -> np.ndarray:
    """N2(φ) = (sin α cos φ, sin α sin φ, cos α) on arrays of φ [rad]."""
    phi = np.asarray(phi, dtype=np.float64)
    return np.stack([math.sin(apex) * np.cos(phi), math.sin(apex) * np.sin(phi),
                     np.full_like(phi, math.cos(apex))], axis=-1)


@dataclass(frozen=True)
class Stack:
    """The prisms as one side believes them: per prism index, apex [rad], centre thickness [m]; gaps [m]."""

    n_glass: tuple[float, ...]
    apex: tuple[float, ...]
    thickness: tuple[float, ...]
    gaps: tuple[float, ...]

    @property
    def fronts(self) -> tuple[float, ...]:
        """z of each prism's front face on the axis [m]."""
        z = [0.0]
        for d, g in zip(self.thickness[:-1], self.gaps):
            z.append(z[-1] + d + g)
        return tuple(z)


@dataclass
class StackTrace:
    """Rays leaving a stack; arrays broadcast over the shapes of the beams and prism angles given."""

    directions: np.ndarray  # (..., 3) unit exit directions [sensor frame]
    exit_points: np.ndarray  # (..., 3) on the last back face [m]
    ok: np.ndarray  # (...) False on total internal reflection or a beam crossing a too small gap
    reflected: np.ndarray  # (...) True where a face reflects the beam totally
    overshoot: np.ndarray  # (..., prisms − 1) how far past the next front face each exit point lies [m] (≤ 0 fine)


def trace(stack: Stack, s1: np.ndarray, phis: np.ndarray) -> StackTrace:
    """Trace unit directions ``s1`` (..., 3) through the stack at prism angles ``phis`` (..., prisms) [rad]."""
    s1 = np.asarray(s1, dtype=np.float64)
    phis = np.asarray(phis, dtype=np.float64)
    z_axis = np.array([0.0, 0.0, 1.0])
    fronts = stack.fronts
    s, _ = refract(s1, z_axis, 1.0 / stack.n_glass[0])
    entry = np.zeros_like(s)
    reflected = np.zeros(np.broadcast_shapes(s.shape[:-1], phis.shape[:-1]), dtype=bool)
    overshoot = []
    for i, n_glass in enumerate(stack.n_glass):
        n2 = back_face_normal(phis[..., i], stack.apex[i])
        travel = (np.sum(n2 * (np.array([0.0, 0.0, fronts[i] + stack.thickness[i]]) - entry), axis=-1, keepdims=True)
                  / np.sum(n2 * s, axis=-1, keepdims=True))
        entry = entry + travel * s
        s, passed = refract(s, n2, n_glass)
        reflected = reflected | ~passed
        if i + 1 < len(stack.n_glass):
            overshoot.append(entry[..., 2] - fronts[i + 1])
            entry = entry + (fronts[i + 1] - entry[..., 2:3]) / s[..., 2:3] * s
            s, _ = refract(s, z_axis, 1.0 / stack.n_glass[i + 1])
    over = np.stack(overshoot, axis=-1)
    return StackTrace(s, entry, ~reflected & np.all(over <= 0.0, axis=-1), reflected, over)


def prism_angles(phase: np.ndarray, turns, phase0_rad) -> np.ndarray:
    """Each prism's angle (..., prisms) [rad] at scan phases ψ (...) [rad]: φ0_i + m_i·ψ."""
    return np.asarray(phase0_rad, dtype=np.float64) + np.multiply.outer(np.asarray(phase, dtype=np.float64),
                                                                         np.asarray(turns, dtype=np.float64))


def relative_angle_grid(prisms: int, samples: int) -> np.ndarray:
    """Every combination of ``samples`` angles per prism over a turn, (samples^prisms, prisms) [rad]."""
    axis = np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False)
    return np.stack(np.meshgrid(*([axis] * prisms), indexing="ij"), axis=-1).reshape(-1, prisms)


def first_order_pointing(phis: np.ndarray, deviations) -> np.ndarray:
    """Thin-prism pointing (..., 2): the (x, y) direction cosines −Σ δ_i (cos φ_i, sin φ_i) [rad],
    δ_i = (n_i − 1)·α_i.

    Each thin prism turns the beam by δ_i towards its thin edge, which lies opposite its back-face normal's tilt.
    """
    deviations = np.asarray(deviations, dtype=np.float64)
    return -np.stack([np.sum(deviations * np.cos(phis), axis=-1), np.sum(deviations * np.sin(phis), axis=-1)],
                     axis=-1)


def rigid_directions(s1: np.ndarray, center: np.ndarray) -> np.ndarray:
    """The rigid-array (nominal) directions Q(s1)·center: the smallest rotation taking ẑ to s1, applied to the
    on-axis ray's exit direction (SPEC §5), by Rodrigues' formula; s1 (..., 3), center (..., 3)."""
    s1 = np.asarray(s1, dtype=np.float64)
    axis = np.stack([-s1[..., 1], s1[..., 0], np.zeros_like(s1[..., 0])], axis=-1)  # ẑ × s1
    sin = np.linalg.norm(axis, axis=-1, keepdims=True)
    k = np.divide(axis, sin, out=np.zeros_like(axis), where=sin > 0.0)
    cos = s1[..., 2:3]
    return center * cos + np.cross(k, center) * sin + k * np.sum(k * center, axis=-1, keepdims=True) * (1.0 - cos)
