"""Bounded least-squares fit of k Gaussians to each of many waveforms (float64): the device form of
``flightsim.instrument.waveform_model.decompose``'s ``curve_fit``, in the same units (x = (t − t0)/σ, y = the echo over
its maximum) and bounds (a ≥ 0, 0 ≤ μ ≤ x_last, Δt/σ ≤ s ≤ x_last).

Levenberg–Marquardt with Marquardt's scaling (JᵀJ + λ·diag JᵀJ) δ = −Jᵀr, projected on the bounds: a parameter at a
bound whose gradient points out of the box is held (its row and column left out of the step), and each step is
clipped into the box. A step is taken only when it lowers the sum of squared residuals (SSR); otherwise λ grows ×10.
The fit ends when LAMBDA_TRIES successive ×10 increases of λ find no lower SSR, or a step lowers it by less than
GAIN_TOLERANCE of it (float64 rounding), or after MAX_ITERATIONS steps.

Each waveform's fit advances one evaluation of the SSR (with JᵀJ and Jᵀr, or without at a trial point) per round of
two launches: ``evaluate_chunks`` (:func:`evaluate_kernel`), one thread per FIT_CHUNK samples of a waveform (a long
waveform's sums are spread over many threads), then :data:`advance_fits`, one thread per waveform, adding the chunks'
sums in chunk order (so a fit is the same on every run) and taking the Levenberg–Marquardt decision the sums call
for. Rounds go on until no fit is left, checked every few rounds by :data:`clear_going` and :data:`mark_going`
(:func:`flightsim.instrument.waveform_batch.process`: on a GPU inside one CUDA graph).

Scratch arrays, parameter first and waveform last: ``normal`` and ``chol`` (3·MAX_PEAKS, 3·MAX_PEAKS, W), ``grad``,
``trial``, ``delta`` (3·MAX_PEAKS, W), ``free`` (3·MAX_PEAKS, W); the chunks' sums (:class:`ChunkSums`).
"""
import functools

import warp as wp

from kernels.waveform_measures import GAIN_TOLERANCE, LAMBDA_TRIES, MAX_ITERATIONS, MAX_PEAKS, STATUS_CONVERGED, \
    STATUS_ITERATIONS, STATUS_SKIPPED, UNDERFLOW, _time

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

FIT_CHUNK = 64  # samples whose SSR, JᵀJ and Jᵀr one thread of evaluate_chunks sums in turn: a round takes as long as
# its slowest fit's chunk, so fewer samples a thread shorten the rounds a few fits still go through (an H100, 8,389
# GEDI waveforms of 1000 samples: the batch 0.454 s at 256, 0.298 at 64, 0.292 at 32, 0.340 at 16; the CPU alike at
# 64 and 256; profile-experiments.md 29 and 98)
FEW_GAUSSIANS = 4  # batches fitting at most this many Gaussians per waveform take evaluate_kernel(4): its thread's
# sums of JᵀJ (78 entries, not MAX_PEAKS' 300) take a quarter of the local memory

PHASE_DONE = wp.constant(0)  # the fit has ended (or was never started)
PHASE_BUILD = wp.constant(1)  # the next evaluation: SSR, JᵀJ and Jᵀr at ``params``
PHASE_TRIAL = wp.constant(2)  # the next evaluation: the SSR at ``trial``


@wp.struct
class FitState:
    """Each waveform's Levenberg–Marquardt state between rounds (arrays of W)."""

    phase: wp.array(dtype=wp.int32)  # PHASE_*
    accepted: wp.array(dtype=wp.int32)  # 1: the pending build follows a step taken (its gain to be checked)
    cost: wp.array(dtype=wp.float64)  # SSR at ``params``
    gain: wp.array(dtype=wp.float64)  # the SSR the last step took off
    lam: wp.array(dtype=wp.float64)  # λ
    tries: wp.array(dtype=wp.int32)  # λ increases since the last step
    steps: wp.array(dtype=wp.int32)  # steps taken


@wp.struct
class ChunkSums:
    """One evaluation's sums per chunk of samples and waveform: [chunk, w]; JᵀJ packed row by row over the first
    3k parameters of the waveform's k Gaussians (row r's entries c ≥ r)."""

    ssr: wp.array2d(dtype=wp.float64)
    grad: wp.array3d(dtype=wp.float64)  # [r, chunk, w]: r < 3k
    normal: wp.array3d(dtype=wp.float64)  # [packed entry, chunk, w]: as many entries as the most Gaussians need


@wp.func
def _packed(r: int, c: int, m: int) -> int:
    """Index of JᵀJ's entry (r, c ≥ r) in the upper triangle of an m × m matrix packed row by row."""
    return r * m - r * (r - 1) // 2 + c - r


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
def start_fits(count: wp.array(dtype=wp.int32), params: wp.array2d(dtype=wp.float64), state: FitState,
               status: wp.array2d(dtype=wp.int32)):
    """Each waveform's fit of its ``count`` Gaussians from their start ``params`` (find_echo_peaks) set going: none
    for no peak, more than MAX_PEAKS, or a start amplitude below 0 (curve_fit refuses it, so does this fit)."""
    w = wp.tid()
    k = count[w]
    outside = int(0)
    for q in range(wp.min(k, MAX_PEAKS)):
        if params[3 * q, w] < wp.float64(0.0):
            outside = 1
    state.phase[w] = PHASE_DONE
    if k == 0 or k > MAX_PEAKS or outside != 0:
        status[0, w] = STATUS_SKIPPED
        status[1, w] = 0
        return
    state.phase[w] = PHASE_BUILD
    state.accepted[w] = 0
    state.lam[w] = wp.float64(1.0e-3)
    state.tries[w] = 0
    state.steps[w] = 0


@functools.cache
def evaluate_kernel(gaussians: int):
    """:data:`evaluate_chunks` for waveforms of at most ``gaussians`` Gaussians (its per-thread sums sized for them)."""
    parameters = 3 * gaussians
    vec_parameters = wp.types.vector(parameters, wp.float64)
    vec_packed = wp.types.vector(parameters * (parameters + 1) // 2, wp.float64)

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
    def evaluate_chunks(echo: wp.array2d(dtype=wp.float64), t0: wp.array(dtype=wp.float64), dt: wp.float64,
                        sigma: wp.float64, maximum: wp.array2d(dtype=wp.float64), count: wp.array(dtype=wp.int32),
                        params: wp.array2d(dtype=wp.float64), trial: wp.array2d(dtype=wp.float64), state: FitState,
                        sums: ChunkSums):
        """Chunk ``chunk``'s share (samples chunk·FIT_CHUNK …) of the SSR of Σ a·exp(−(x − μ)²/2s²) − y at
        ``params`` (PHASE_BUILD: with JᵀJ and Jᵀr) or ``trial`` (PHASE_TRIAL), of each waveform whose fit goes on."""
        chunk, w = wp.tid()
        phase = state.phase[w]
        if phase == PHASE_DONE:
            return
        k = count[w]
        m = 3 * k
        build = phase == PHASE_BUILD
        p = trial  # the point evaluated
        if build:
            p = params
        start = t0[w]
        scale = maximum[5, w]
        grad = vec_parameters()
        normal = vec_packed()
        jac = vec_parameters()
        ssr = wp.float64(0.0)
        for j in range(chunk * FIT_CHUNK, wp.min((chunk + 1) * FIT_CHUNK, echo.shape[0])):
            x = (_time(start, dt, j) - start) / sigma
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
                if build:
                    jac[3 * q] = e
                    jac[3 * q + 1] = a * e * z / s
                    jac[3 * q + 2] = a * e * z * z / s
            res = model - echo[j, w] / scale
            ssr += res * res
            if build:
                for q in range(k):
                    if jac[3 * q] != wp.float64(0.0):
                        for r in range(3 * q, 3 * q + 3):
                            grad[r] = grad[r] + jac[r] * res
                            for c in range(r, m):
                                i = _packed(r, c, m)
                                normal[i] = normal[i] + jac[r] * jac[c]
        sums.ssr[chunk, w] = ssr
        if build:
            for r in range(m):
                sums.grad[r, chunk, w] = grad[r]
            for i in range(m * (m + 1) // 2):
                sums.normal[i, chunk, w] = normal[i]

    return evaluate_chunks


@wp.func
def _added(sums: ChunkSums, chunks: int, k: int, build: int, normal: wp.array3d(dtype=wp.float64),
           grad: wp.array2d(dtype=wp.float64), w: int) -> wp.float64:
    """The SSR of the evaluation the chunks summed, their sums added in chunk order; with ``build`` also JᵀJ (upper
    triangle) into ``normal`` and Jᵀr into ``grad``."""
    ssr = wp.float64(0.0)
    for chunk in range(chunks):
        ssr += sums.ssr[chunk, w]
    if build != 0:
        m = 3 * k
        for r in range(m):
            g = wp.float64(0.0)
            for chunk in range(chunks):
                g += sums.grad[r, chunk, w]
            grad[r, w] = g
            for c in range(r, m):
                i = _packed(r, c, m)
                v = wp.float64(0.0)
                for chunk in range(chunks):
                    v += sums.normal[i, chunk, w]
                normal[r, c, w] = v
    return ssr


@wp.func
def _propose(normal: wp.array3d(dtype=wp.float64), grad: wp.array2d(dtype=wp.float64),
             free: wp.array2d(dtype=wp.int32), chol: wp.array3d(dtype=wp.float64), delta: wp.array2d(dtype=wp.float64),
             params: wp.array2d(dtype=wp.float64), trial: wp.array2d(dtype=wp.float64), k: int, x_last: wp.float64,
             s_min: wp.float64, state: FitState, w: int):
    """The next trial point: solved at the current λ, λ × 10 while the system is not positive definite; the fit
    ends (converged) once LAMBDA_TRIES increases of λ have found no lower SSR."""
    while state.tries[w] < LAMBDA_TRIES:
        if _solve(normal, grad, free, state.lam[w], 3 * k, chol, delta, w) != 0:
            _clipped_step(params, delta, k, x_last, s_min, trial, w)
            state.phase[w] = PHASE_TRIAL
            return
        state.lam[w] = state.lam[w] * wp.float64(10.0)
        state.tries[w] = state.tries[w] + 1
    state.phase[w] = PHASE_DONE


@wp.kernel
def advance_fits(echo: wp.array2d(dtype=wp.float64), t0: wp.array(dtype=wp.float64), dt: wp.float64,
                 step: wp.array(dtype=wp.float64), sigma: wp.float64, count: wp.array(dtype=wp.int32),
                 sums: ChunkSums, chunks: int, state: FitState, params: wp.array2d(dtype=wp.float64),
                 trial: wp.array2d(dtype=wp.float64), normal: wp.array3d(dtype=wp.float64),
                 chol: wp.array3d(dtype=wp.float64), grad: wp.array2d(dtype=wp.float64),
                 delta: wp.array2d(dtype=wp.float64), free: wp.array2d(dtype=wp.int32), ssr: wp.array(dtype=wp.float64),
                 status: wp.array2d(dtype=wp.int32)):
    """Each going fit's decision on the evaluation just summed (the steps of decompose's curve_fit, one at a time).

    # In:
    echo (N, W) received power [W]; t0 (W,) time of sample 0 [s]; dt: sample interval [s]
    step (W,) t_1 − t_0 of each waveform [s]: s ≥ step/σ; sigma: σ of the pulse [s]; count (W,) Gaussians per waveform
    sums, chunks: evaluate_chunks' sums over ``chunks`` chunks
    # In/Out:
    params (3·MAX_PEAKS, W) (a, μ, s) per Gaussian: a in units of the maximum, μ and s in σ from t0
    # Out (as each fit ends):
    ssr (W,) sum of squared residuals at the end, in units of the maximum squared; status (2, W) STATUS_* and steps
    """
    w = wp.tid()
    phase = state.phase[w]
    if phase == PHASE_DONE:
        return
    k = count[w]
    start = t0[w]
    x_last = (_time(start, dt, echo.shape[0] - 1) - start) / sigma
    s_min = step[w] / sigma
    value = _added(sums, chunks, k, int(phase == PHASE_BUILD), normal, grad, w)
    ending = STATUS_CONVERGED
    if phase == PHASE_BUILD:
        state.cost[w] = value
        if state.accepted[w] != 0 and state.gain[w] <= GAIN_TOLERANCE * value:
            state.phase[w] = PHASE_DONE
        elif state.steps[w] >= MAX_ITERATIONS:
            state.phase[w] = PHASE_DONE
            ending = STATUS_ITERATIONS
        else:
            _hold(params, grad, k, x_last, s_min, free, w)
            state.tries[w] = 0
            _propose(normal, grad, free, chol, delta, params, trial, k, x_last, s_min, state, w)
    elif value < state.cost[w]:  # the trial lowers the SSR: the step is taken
        state.steps[w] = state.steps[w] + 1
        for r in range(3 * k):
            params[r, w] = trial[r, w]
        state.gain[w] = state.cost[w] - value
        state.lam[w] = wp.max(state.lam[w] * wp.float64(0.1), wp.float64(1.0e-12))
        state.accepted[w] = 1
        state.phase[w] = PHASE_BUILD
    else:
        state.lam[w] = state.lam[w] * wp.float64(10.0)
        state.tries[w] = state.tries[w] + 1
        _propose(normal, grad, free, chol, delta, params, trial, k, x_last, s_min, state, w)
    if state.phase[w] == PHASE_DONE:
        ssr[w] = state.cost[w]
        status[0, w] = ending
        status[1, w] = state.steps[w]


@wp.kernel
def clear_going(rounds: wp.int32, left: wp.array(dtype=wp.int32), going: wp.array(dtype=wp.int32)):
    """After ``rounds`` more rounds: ``left`` (1,) rounds a fit may still take counted down, ``going`` (1,) cleared
    for :data:`mark_going` to set."""
    left[0] = left[0] - rounds
    going[0] = 0


@wp.kernel
def mark_going(state: FitState, left: wp.array(dtype=wp.int32), going: wp.array(dtype=wp.int32)):
    """``going`` (1,) set to 1 where waveform w's fit goes on and rounds are left (such threads all write 1)."""
    w = wp.tid()
    if state.phase[w] != PHASE_DONE and left[0] > 0:
        going[0] = 1
