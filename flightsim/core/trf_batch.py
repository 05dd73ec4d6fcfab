"""Many small bounded nonlinear least-squares problems solved together: SciPy's Trust Region Reflective
algorithm, ``scipy.optimize.least_squares(method="trf", x_scale="jac", tr_solver="exact")`` with its default
tolerances (``trf_bounds`` and its helpers in ``scipy/optimize/_lsq``, SciPy 1.17), run on a batch of problems of
one size in NumPy array operations instead of one Python loop per problem.

Each problem takes the steps SciPy takes for it: the same Coleman-Li scaling, trust-region subproblem (the
regularised Gauss-Newton step from one SVD of the scaled Jacobian, its Levenberg-Marquardt parameter by up to ten
Newton steps), reflective step selection, radius update and stopping tests, and at most 100 · n residual
evaluations. The arithmetic is the same but not in the same order (batched matrix products, NumPy's LAPACK for the
SVD), so iterates agree with SciPy's to round-off, and a problem may stop one step sooner or later than SciPy's,
within the tolerances (``tests/test_trf_batch.py`` holds solutions to SciPy's).

A round takes one trial step of every problem still running: problems are at different points of their
iterations, and a problem whose step was accepted starts its next iteration in the same round.

Padding: problems of different residual counts share one array of L residuals; a problem's rows beyond its count
must have zero residual and zero Jacobian (they change no sum), and the count is passed to keep SciPy's rank test.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Protocol

import numpy as np

EPS = np.finfo(np.float64).eps
_NEWTON_STEPS, _NEWTON_RTOL = 10, 0.01  # the trust-region subproblem's root finding (SciPy's defaults)


class BatchModel(Protocol):
    """Residuals of a batch of problems: ``rows`` (k,) picks which problems, ``p`` (k, n) their parameters."""

    def residual(self, p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(k, L) residuals; zero beyond each problem's count."""

    def jacobian(self, p: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(k, n, L) derivatives of the residuals by the parameters (the Jacobian transposed); zero beyond each
        problem's count. Asked at the points of the last ``residual`` call or some of them."""


def least_squares_batch(model: BatchModel, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                        counts: np.ndarray, ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8) -> np.ndarray:
    """(G, n) solutions of G problems: minimise ½‖model.residual(x)‖² with lower ≤ x ≤ upper from x0.

    Args:
        model: the residuals and their Jacobian (:class:`BatchModel`), L rows per problem.
        x0, lower, upper: (G, n) starts and bounds (``lower`` < ``upper``, ±inf allowed, x0 within them).
        counts: (G,) residuals each problem has (its rows 0 … count−1 of L).
        ftol, xtol, gtol: SciPy's tolerances.
    """
    lb, ub = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    x = _strictly_feasible(np.asarray(x0, dtype=np.float64), lb, ub, rstep=1e-10)
    out = x.copy()
    if not len(x):
        return out
    rows = np.arange(len(x))
    f, jac = model.residual(x, rows), model.jacobian(x, rows)
    scale_inv = np.sqrt(np.einsum("knl,knl->kn", jac, jac))
    scale_inv[scale_inv == 0.0] = 1.0
    g = np.einsum("knl,kl->kn", jac, f)
    v, dv = _coleman_li(x, g, lb, ub)
    v = np.where(dv != 0, v * scale_inv, v)
    delta = np.linalg.norm(x * scale_inv / v ** 0.5, axis=1)
    n = x.shape[1]
    state = _State(rows=rows, x=x, lb=lb, ub=ub, m=np.asarray(counts, dtype=np.int64), cost=0.5 * np.sum(f * f, axis=1),
                   scale_inv=scale_inv, delta=np.where(delta == 0.0, 1.0, delta), alpha=np.zeros(len(x)),
                   nfev=np.ones(len(x), dtype=np.int64), theta=np.zeros(len(x)), d=np.zeros_like(x),
                   diag_h=np.zeros_like(x), g_h=np.zeros_like(x), j_h=np.zeros_like(jac), s=np.zeros_like(x),
                   v=np.zeros((len(x), n, n)), uf=np.zeros_like(x))
    done = _start(state, rows, f, jac, g, gtol, 100 * n)
    while True:
        if done.any():  # the finished leave the batch (a round in which none did copies nothing)
            out[state.rows[done]] = state.x[done]
            state = state.take(~done)
        if not len(state.rows):
            return out
        done = _trial(state, model, ftol, xtol, gtol, 100 * n)


@dataclass
class _State:
    """The running problems: their original index, point, bounds, residual count, cost, Jacobian scale, trust
    radius, LM parameter, evaluations, and what their current iteration worked out at its start (scaling d,
    diag_h, the scaled gradient g_h and transposed Jacobian j_h (k, n, L), the SVD s, v and Uᵀf, the step-back
    factor theta)."""

    rows: np.ndarray
    x: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    m: np.ndarray
    cost: np.ndarray
    scale_inv: np.ndarray
    delta: np.ndarray
    alpha: np.ndarray
    nfev: np.ndarray
    theta: np.ndarray
    d: np.ndarray
    diag_h: np.ndarray
    g_h: np.ndarray
    j_h: np.ndarray
    s: np.ndarray
    v: np.ndarray
    uf: np.ndarray

    def take(self, keep: np.ndarray) -> "_State":
        return _State(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})


def _start(state: _State, sel: np.ndarray, f: np.ndarray, jac: np.ndarray, g: np.ndarray, gtol: float,
           max_nfev: int) -> np.ndarray:
    """Begin an iteration of the problems ``sel`` at their point (residuals f, Jacobian jac, gradient g): the
    gradient test, then the scaled trust-region problem and its SVD; (len(state.rows),) bool, the problems done."""
    done = np.zeros(len(state.rows), dtype=bool)
    v, dv = _coleman_li(state.x[sel], g, state.lb[sel], state.ub[sel])
    g_norm = np.max(np.abs(g * v), axis=1)
    stop = (g_norm < gtol) | (state.nfev[sel] >= max_nfev)
    done[sel[stop]] = True
    go = ~stop
    sel, v, dv, g, f, jac, g_norm = sel[go], v[go], dv[go], g[go], f[go], jac[go], g_norm[go]
    scale_inv = state.scale_inv[sel]
    scale = 1.0 / scale_inv
    v = np.where(dv != 0, v * scale_inv, v)
    d = v ** 0.5 * scale
    diag_h = g * dv * scale
    k, n, length = jac.shape
    augmented = np.zeros((k, n, length + n))  # [J_h; diag(√diag_h)], transposed
    j_h = np.multiply(jac, d[:, :, None], out=augmented[:, :, :length])
    augmented[:, np.arange(n), length + np.arange(n)] = np.sqrt(diag_h)
    u, s, vt = np.linalg.svd(np.swapaxes(augmented, 1, 2), full_matrices=False)
    state.d[sel], state.diag_h[sel], state.g_h[sel], state.j_h[sel] = d, diag_h, d * g, j_h
    state.s[sel], state.v[sel] = s, np.swapaxes(vt, 1, 2)
    state.uf[sel] = np.einsum("kln,kl->kn", u[:, :length], f)
    state.theta[sel] = np.maximum(0.995, 1.0 - g_norm)
    return done


def _trial(state: _State, model: BatchModel, ftol: float, xtol: float, gtol: float, max_nfev: int) -> np.ndarray:
    """One trial step of every running problem: accepted where the cost falls (the next iteration begun), the
    radius updated; (k,) bool, the problems done."""
    p_h, state.alpha = _trust_region_step(state)
    step, step_h, predicted = _select_step(state, state.d * p_h, p_h)
    x_new = _strictly_feasible(state.x + step, state.lb, state.ub, rstep=0.0)
    f_new = model.residual(x_new, state.rows)
    state.nfev += 1
    step_h_norm = np.linalg.norm(step_h, axis=1)
    finite = np.isfinite(f_new).all(axis=1)
    cost_new = 0.5 * np.sum(np.where(finite[:, None], f_new, 0.0) ** 2, axis=1)
    reduction = np.where(finite, state.cost - cost_new, -1.0)
    delta_new, ratio = _radius(state.delta, reduction, predicted, step_h_norm, step_h_norm > 0.95 * state.delta)
    stop = finite & _converged(reduction, state.cost, np.linalg.norm(step, axis=1),
                               np.linalg.norm(state.x, axis=1), ratio, ftol, xtol)
    go = finite & ~stop
    with np.errstate(divide="ignore", invalid="ignore"):
        state.alpha = np.where(go, state.alpha * (state.delta / delta_new), state.alpha)
    state.delta = np.where(go, delta_new, np.where(finite, state.delta, 0.25 * step_h_norm))
    accept = np.flatnonzero(reduction > 0.0)
    state.x[accept], state.cost[accept] = x_new[accept], cost_new[accept]
    done = stop | (state.nfev >= max_nfev)
    if len(accept):
        jac = model.jacobian(x_new[accept], state.rows[accept])
        state.scale_inv[accept] = np.maximum(np.sqrt(np.einsum("knl,knl->kn", jac, jac)), state.scale_inv[accept])
        g = np.einsum("knl,kl->kn", jac, f_new[accept])
        go = ~done[accept]
        done |= _start(state, accept[go], f_new[accept[go]], jac[go], g[go], gtol, max_nfev)
    return done


# --- the trust-region subproblem and the step (SciPy's solve_lsq_trust_region and select_step) -----------------


def _trust_region_step(state: _State) -> tuple[np.ndarray, np.ndarray]:
    """(k, n) steps p_h in the scaled variables, ‖p_h‖ ≤ Δ, and the LM parameters α (More's method, one SVD)."""
    s, uf, delta, m = state.s, state.uf, state.delta, state.m
    n = s.shape[1]
    suf = s * uf
    full = (m >= n) & (s[:, -1] > EPS * m * s[:, 0])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        newton = -np.einsum("kij,kj->ki", state.v, np.where(full[:, None], uf / s, 0.0))
        gauss = full & (np.linalg.norm(newton, axis=1) <= delta)
        upper = np.linalg.norm(suf, axis=1) / delta
        phi, slope = _phi(np.zeros_like(delta), suf, s, delta)
        lower = np.where(full, -phi / slope, 0.0)
        alpha = np.where(~full & (state.alpha == 0.0), _alpha_guess(lower, upper), state.alpha)
        running = ~gauss
        for _ in range(_NEWTON_STEPS):
            if not running.any():
                break
            a = np.where((alpha < lower) | (alpha > upper), _alpha_guess(lower, upper), alpha)
            phi, slope = _phi(a, suf, s, delta)
            upper = np.where(running & (phi < 0.0), a, upper)
            ratio = phi / slope
            lower = np.where(running, np.maximum(lower, a - ratio), lower)
            alpha = np.where(running, a - (phi + delta) * ratio / delta, alpha)
            running &= ~(np.abs(phi) < _NEWTON_RTOL * delta)
        p = -np.einsum("kij,kj->ki", state.v, suf / (s * s + alpha[:, None]))
        p *= (delta / np.linalg.norm(p, axis=1))[:, None]
    return np.where(gauss[:, None], newton, p), np.where(gauss, 0.0, alpha)


def _phi(alpha, suf, s, delta) -> tuple[np.ndarray, np.ndarray]:
    """‖p(α)‖ − Δ and its derivative by α."""
    denom = s * s + alpha[:, None]
    p_norm = np.linalg.norm(suf / denom, axis=1)
    return p_norm - delta, -np.sum(suf ** 2 / denom ** 3, axis=1) / p_norm


def _alpha_guess(lower, upper):
    return np.maximum(0.001 * upper, np.sqrt(lower * upper))


def _select_step(state: _State, p: np.ndarray, p_h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trust-region step where it stays within the bounds; else the best of it stepped back from the bound,
    its reflection and the scaled gradient: (step, step_h, predicted reduction)."""
    inside = np.all((state.x + p >= state.lb) & (state.x + p <= state.ub), axis=1)
    step, step_h = p.copy(), p_h.copy()
    value = _quadratic(state.j_h, state.g_h, p_h, state.diag_h)
    out = np.flatnonzero(~inside)
    if len(out):
        step[out], step_h[out], value[out] = _reflective_step(state.take(out), p[out], p_h[out])
    return step, step_h, -value


def _reflective_step(st: _State, p: np.ndarray, p_h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SciPy's choice among the step to the bound (stepped back by theta), the reflected step and the gradient
    step, for problems whose trust-region step leaves the bounds: (step, step_h, quadratic value)."""
    theta = st.theta[:, None]
    p_stride, hits = _to_bound(st.x, p, st.lb, st.ub)
    r_h = np.where(hits != 0, -p_h, p_h)
    r = st.d * r_h
    p, p_h = p * p_stride[:, None], p_h * p_stride[:, None]
    to_tr = _to_sphere(p_h, r_h, st.delta)
    to_bound, _ = _to_bound(st.x + p, r, st.lb, st.ub)
    r_stride = np.minimum(to_bound, to_tr)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_lo = np.where(r_stride > 0.0, (1.0 - st.theta) * p_stride / r_stride, 0.0)
    r_hi = np.where(r_stride > 0.0, np.where(r_stride == to_bound, st.theta * to_bound, to_tr), -1.0)
    reflect = r_lo <= r_hi
    a, b, c = _line(st.j_h, st.g_h, r_h, st.diag_h, p_h)
    t, r_value = _min_on_segment(a, b, c, r_lo, r_hi)
    r_h = r_h * t[:, None] + p_h
    r_value = np.where(reflect, r_value, np.inf)
    p, p_h = p * theta, p_h * theta
    p_value = _quadratic(st.j_h, st.g_h, p_h, st.diag_h)
    ag_h = -st.g_h
    ag = st.d * ag_h
    to_tr = st.delta / np.linalg.norm(ag_h, axis=1)
    to_bound, _ = _to_bound(st.x, ag, st.lb, st.ub)
    ag_stride = np.where(to_bound < to_tr, st.theta * to_bound, to_tr)
    a, b, _ = _line(st.j_h, st.g_h, ag_h, st.diag_h)
    t, ag_value = _min_on_segment(a, b, 0.0, np.zeros_like(ag_stride), ag_stride)
    ag_h, ag = ag_h * t[:, None], ag * t[:, None]
    take_p = (p_value < r_value) & (p_value < ag_value)
    take_r = ~take_p & (r_value < p_value) & (r_value < ag_value)
    step = np.where(take_p[:, None], p, np.where(take_r[:, None], r_h * st.d, ag))
    step_h = np.where(take_p[:, None], p_h, np.where(take_r[:, None], r_h, ag_h))
    return step, step_h, np.where(take_p, p_value, np.where(take_r, r_value, ag_value))


def _quadratic(j_h, g_h, s, diag_h) -> np.ndarray:
    """½ sᵀ(JᵀJ + diag)s + gᵀs per problem."""
    js = np.einsum("knl,kn->kl", j_h, s)
    return 0.5 * (np.sum(js * js, axis=1) + np.sum(s * diag_h * s, axis=1)) + np.sum(s * g_h, axis=1)


def _line(j_h, g_h, s, diag_h, s0=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, c) of the quadratic along s0 + t·s: a t² + b t + c."""
    v = np.einsum("knl,kn->kl", j_h, s)
    a = 0.5 * (np.sum(v * v, axis=1) + np.sum(s * diag_h * s, axis=1))
    b = np.sum(g_h * s, axis=1)
    if s0 is None:
        return a, b, np.zeros_like(a)
    u = np.einsum("knl,kn->kl", j_h, s0)
    b = b + np.sum(u * v, axis=1) + np.sum(s0 * diag_h * s, axis=1)
    c = 0.5 * np.sum(u * u, axis=1) + np.sum(g_h * s0, axis=1) + 0.5 * np.sum(s0 * diag_h * s0, axis=1)
    return a, b, c


def _min_on_segment(a, b, c, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """The t in [lo, hi] minimising a t² + b t + c, and that minimum (the first of lo, hi, the vertex on ties)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.where(a != 0.0, -0.5 * b / np.where(a != 0.0, a, 1.0), np.nan)
    inner = (a != 0.0) & (lo < vertex) & (vertex < hi)
    t = np.stack([lo * np.ones_like(a), hi * np.ones_like(a), np.where(inner, vertex, 0.0)], axis=1)
    y = t * (a[:, None] * t + b[:, None]) + np.asarray(c)[..., None]
    y[:, 2] = np.where(inner, y[:, 2], np.inf)
    best = np.argmin(y, axis=1)[:, None]
    return np.take_along_axis(t, best, axis=1)[:, 0], np.take_along_axis(y, best, axis=1)[:, 0]


def _to_bound(x, s, lb, ub) -> tuple[np.ndarray, np.ndarray]:
    """The least t ≥ 0 at which x + t·s meets a bound, and which components meet it (−1 / +1 by the step's
    sign, 0 not)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        steps = np.where(s != 0.0, np.maximum((lb - x) / s, (ub - x) / s), np.inf)
    least = steps.min(axis=1)
    return least, (steps == least[:, None]) * np.sign(s).astype(np.int64)


def _to_sphere(x, s, delta) -> np.ndarray:
    """The positive t at which ‖x + t·s‖ = Δ (Numerical Recipes' stable root)."""
    a, b = np.sum(s * s, axis=1), np.sum(x * s, axis=1)
    c = np.sum(x * x, axis=1) - delta ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -(b + np.copysign(np.sqrt(b * b - a * c), b))
        return np.maximum(q / a, c / q)


# --- scaling, feasibility, radius and stopping (SciPy's common.py) -----------------------------------------------


def _coleman_li(x, g, lb, ub) -> tuple[np.ndarray, np.ndarray]:
    """The Coleman-Li scaling v (the distance to the bound the gradient points to, else 1) and dv/dx."""
    to_upper, to_lower = (g < 0.0) & np.isfinite(ub), (g > 0.0) & np.isfinite(lb)
    v = np.where(to_lower, x - lb, np.where(to_upper, ub - x, 1.0))
    dv = np.where(to_lower, 1.0, np.where(to_upper, -1.0, 0.0))
    return v, dv


def _strictly_feasible(x, lb, ub, rstep: float) -> np.ndarray:
    """x moved off the bounds it touches: by rstep · max(1, |bound|), or by one ulp when rstep is 0."""
    if rstep == 0.0:
        low, high = x <= lb, x >= ub
        moved = np.where(high, np.nextafter(ub, lb), np.where(low, np.nextafter(lb, ub), x))
    else:
        with np.errstate(invalid="ignore"):
            room_lo, room_hi = rstep * np.maximum(1.0, np.abs(lb)), rstep * np.maximum(1.0, np.abs(ub))
            low = np.isfinite(lb) & (x - lb <= np.minimum(ub - x, room_lo))
            high = np.isfinite(ub) & (ub - x <= np.minimum(x - lb, room_hi))
            moved = np.where(high, ub - room_hi, np.where(low, lb + room_lo, x))
    tight = (moved < lb) | (moved > ub)
    return np.where(tight, 0.5 * (lb + ub), moved)


def _radius(delta, reduction, predicted, step_norm, bound_hit) -> tuple[np.ndarray, np.ndarray]:
    """The next trust radius and the ratio of actual to predicted reduction."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(predicted > 0.0, reduction / predicted,
                         np.where((predicted == 0.0) & (reduction == 0.0), 1.0, 0.0))
    grown = np.where((ratio > 0.75) & bound_hit, 2.0 * delta, delta)
    return np.where(ratio < 0.25, 0.25 * step_norm, grown), ratio


def _converged(reduction, cost, step_norm, x_norm, ratio, ftol: float, xtol: float) -> np.ndarray:
    """SciPy's stopping tests: the cost's relative fall below ftol (on a good step) or the step below xtol."""
    return ((reduction < ftol * cost) & (ratio > 0.25)) | (step_norm < xtol * (xtol + x_norm))
