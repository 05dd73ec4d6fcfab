"""Bounded least-squares fit of k Gaussians to each of many waveforms, one thread per waveform (float64): the device
form of ``flightsim.instrument.waveform_model.decompose``'s ``curve_fit``, in the same units (x = (t − t0)/σ, y = the
echo over its maximum) and bounds (a ≥ 0, 0 ≤ μ ≤ x_last, Δt/σ ≤ s ≤ x_last).

Levenberg–Marquardt with Marquardt's scaling (JᵀJ + λ·diag JᵀJ) δ = −Jᵀr, projected on the bounds: a parameter at a
bound whose gradient points out of the box is held (its row and column left out of the step), and each step is
clipped into the box. A step is taken only when it lowers the sum of squared residuals (SSR); otherwise λ grows ×10.
The fit ends when LAMBDA_TRIES successive ×10 increases of λ find no lower SSR, or a step lowers it by less than
GAIN_TOLERANCE of it (float64 rounding), or after MAX_ITERATIONS steps.

Scratch arrays, parameter first and waveform last: ``jac`` (3·MAX_PEAKS, W), ``normal`` and ``chol``
(3·MAX_PEAKS, 3·MAX_PEAKS, W), ``grad``, ``trial``, ``delta`` (3·MAX_PEAKS, W), ``free`` (3·MAX_PEAKS, W).
"""
import warp as wp

from kernels.waveform_measures import GAIN_TOLERANCE, LAMBDA_TRIES, MAX_ITERATIONS, MAX_PEAKS, STATUS_CONVERGED, \
    STATUS_ITERATIONS, STATUS_SKIPPED, UNDERFLOW, _time

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})


@wp.func
def _residuals(echo: wp.array2d(dtype=wp.float64), w: int, t0: wp.float64, dt: wp.float64, sigma: wp.float64,
               scale: wp.float64, p: wp.array2d(dtype=wp.float64), k: int, jac: wp.array2d(dtype=wp.float64),
               normal: wp.array3d(dtype=wp.float64), grad: wp.array2d(dtype=wp.float64), build: int) -> wp.float64:
    """SSR of Σ a·exp(−(x − μ)²/2s²) − y over the waveform; with ``build`` also JᵀJ (upper triangle) and Jᵀr."""
    m = 3 * k
    if build != 0:
        for r in range(m):
            grad[r, w] = wp.float64(0.0)
            for c in range(r, m):
                normal[r, c, w] = wp.float64(0.0)
    ssr = wp.float64(0.0)
    for j in range(echo.shape[0]):
        x = (_time(t0, dt, j) - t0) / sigma
        model = wp.float64(0.0)
        for q in range(k):
            a = p[3 * q, w]
            s = p[3 * q + 2, w]
            z = (x - p[3 * q + 1, w]) / s
            h = wp.float64(0.5) * z * z
            e = wp.float64(0.0)
            if h < UNDERFLOW:
                e = wp.exp(-h)
            model += a * e
            if build != 0:
                jac[3 * q, w] = e
                jac[3 * q + 1, w] = a * e * z / s
                jac[3 * q + 2, w] = a * e * z * z / s
        res = model - echo[j, w] / scale
        ssr += res * res
        if build != 0:
            for q in range(k):
                if jac[3 * q, w] != wp.float64(0.0):
                    for r in range(3 * q, 3 * q + 3):
                        grad[r, w] = grad[r, w] + jac[r, w] * res
                        for c in range(r, m):
                            normal[r, c, w] = normal[r, c, w] + jac[r, w] * jac[c, w]
    return ssr


@wp.func
def _hold(p: wp.array2d(dtype=wp.float64), grad: wp.array2d(dtype=wp.float64), k: int, x_last: wp.float64,
          s_min: wp.float64, free: wp.array2d(dtype=wp.int32), w: int):
    """free[r] = 0 where parameter r sits on a bound and −∂SSR/∂p_r points out of the box."""
    for q in range(k):
        for i in range(3):
            r = 3 * q + i
            lo = wp.float64(0.0)
            hi = x_last
            if i == 2:
                lo = s_min
            v = p[r, w]
            g = grad[r, w]
            free[r, w] = 1
            if v <= lo and g > wp.float64(0.0):
                free[r, w] = 0
            if i > 0 and v >= hi and g < wp.float64(0.0):
                free[r, w] = 0


@wp.func
def _solve(normal: wp.array3d(dtype=wp.float64), grad: wp.array2d(dtype=wp.float64), free: wp.array2d(dtype=wp.int32),
           lam: wp.float64, m: int, chol: wp.array3d(dtype=wp.float64), delta: wp.array2d(dtype=wp.float64),
           w: int) -> int:
    """δ of (JᵀJ + λ diag JᵀJ) δ = −Jᵀr over the free parameters (held ones: δ = 0) by Cholesky; 0 if not positive."""
    biggest = wp.float64(0.0)
    for r in range(m):
        biggest = wp.max(biggest, normal[r, r, w])
    for r in range(m):
        for c in range(r, m):
            v = normal[r, c, w]
            if r == c:
                v = v + lam * wp.max(v, wp.float64(1.0e-15) * biggest)
            if free[r, w] == 0 or free[c, w] == 0:
                v = wp.float64(0.0)
                if r == c:
                    v = wp.float64(1.0)
            chol[r, c, w] = v
    for r in range(m):  # chol = Uᵀ U, U upper
        d = chol[r, r, w]
        for q in range(r):
            d = d - chol[q, r, w] * chol[q, r, w]
        if not (d > wp.float64(0.0)):
            return 0
        d = wp.sqrt(d)
        chol[r, r, w] = d
        for c in range(r + 1, m):
            v = chol[r, c, w]
            for q in range(r):
                v = v - chol[q, r, w] * chol[q, c, w]
            chol[r, c, w] = v / d
    for r in range(m):  # Uᵀ z = −Jᵀr
        v = wp.float64(0.0)
        if free[r, w] != 0:
            v = -grad[r, w]
        for q in range(r):
            v = v - chol[q, r, w] * delta[q, w]
        delta[r, w] = v / chol[r, r, w]
    for i in range(m):  # U δ = z
        r = m - 1 - i
        v = delta[r, w]
        for c in range(r + 1, m):
            v = v - chol[r, c, w] * delta[c, w]
        delta[r, w] = v / chol[r, r, w]
    return 1


@wp.func
def _clipped_step(p: wp.array2d(dtype=wp.float64), delta: wp.array2d(dtype=wp.float64), k: int, x_last: wp.float64,
                  s_min: wp.float64, trial: wp.array2d(dtype=wp.float64), w: int):
    """trial = p + δ clipped into the bounds."""
    for q in range(k):
        trial[3 * q, w] = wp.max(p[3 * q, w] + delta[3 * q, w], wp.float64(0.0))
        trial[3 * q + 1, w] = wp.clamp(p[3 * q + 1, w] + delta[3 * q + 1, w], wp.float64(0.0), x_last)
        trial[3 * q + 2, w] = wp.clamp(p[3 * q + 2, w] + delta[3 * q + 2, w], s_min, x_last)


@wp.kernel
def fit_gaussians(echo: wp.array2d(dtype=wp.float64), t0: wp.array(dtype=wp.float64), dt: wp.float64,
                  step: wp.array(dtype=wp.float64), sigma: wp.float64, maximum: wp.array2d(dtype=wp.float64),
                  count: wp.array(dtype=wp.int32), params: wp.array2d(dtype=wp.float64),
                  trial: wp.array2d(dtype=wp.float64), jac: wp.array2d(dtype=wp.float64),
                  normal: wp.array3d(dtype=wp.float64), chol: wp.array3d(dtype=wp.float64),
                  grad: wp.array2d(dtype=wp.float64), delta: wp.array2d(dtype=wp.float64),
                  free: wp.array2d(dtype=wp.int32), ssr: wp.array(dtype=wp.float64),
                  status: wp.array2d(dtype=wp.int32)):
    """Each waveform's ``count`` Gaussians fitted from their start ``params`` (find_echo_peaks), in place.

    # In:
    echo      (N, W) received power [W]; t0 (W,) time of sample 0 [s]; dt: sample interval [s]
    step      (W,) t_1 − t_0 of each waveform [s]: s ≥ step/σ; sigma: σ of the pulse [s]
    maximum   (7, W) echo_measures' output (row 5: each waveform's maximum, the unit of a)
    count     (W,) peaks per waveform (none, more than MAX_PEAKS, or a start outside the bounds: not fitted)
    # In/Out:
    params    (3·MAX_PEAKS, W) (a, μ, s) per Gaussian: a in units of the maximum, μ and s in σ from t0
    # Out:
    ssr       (W,) sum of squared residuals at the end, in units of the maximum squared
    status    (2, W) STATUS_* and the steps taken
    """
    w = wp.tid()
    k = count[w]
    outside = int(0)  # a start amplitude below 0 (a peak on a negative sample): curve_fit refuses it, so does this
    for q in range(wp.min(k, MAX_PEAKS)):
        if params[3 * q, w] < wp.float64(0.0):
            outside = 1
    if k == 0 or k > MAX_PEAKS or outside != 0:
        status[0, w] = STATUS_SKIPPED
        status[1, w] = 0
        return
    start = t0[w]
    scale = maximum[5, w]
    x_last = (_time(start, dt, echo.shape[0] - 1) - start) / sigma
    s_min = step[w] / sigma
    cost = _residuals(echo, w, start, dt, sigma, scale, params, k, jac, normal, grad, 1)
    lam = wp.float64(1.0e-3)
    state = STATUS_ITERATIONS
    steps = int(0)
    while steps < MAX_ITERATIONS:
        _hold(params, grad, k, x_last, s_min, free, w)
        better = int(0)
        tries = int(0)
        new_cost = cost
        while tries < LAMBDA_TRIES and better == 0:
            if _solve(normal, grad, free, lam, 3 * k, chol, delta, w) != 0:
                _clipped_step(params, delta, k, x_last, s_min, trial, w)
                new_cost = _residuals(echo, w, start, dt, sigma, scale, trial, k, jac, normal, grad, 0)
                if new_cost < cost:
                    better = 1
            if better == 0:
                lam = lam * wp.float64(10.0)
            tries = tries + 1
        if better == 0:
            state = STATUS_CONVERGED
            break
        steps = steps + 1
        for r in range(3 * k):
            params[r, w] = trial[r, w]
        gain = cost - new_cost
        lam = wp.max(lam * wp.float64(0.1), wp.float64(1.0e-12))
        cost = _residuals(echo, w, start, dt, sigma, scale, params, k, jac, normal, grad, 1)
        if gain <= GAIN_TOLERANCE * cost:
            state = STATUS_CONVERGED
            break
    ssr[w] = cost
    status[0, w] = state
    status[1, w] = steps
