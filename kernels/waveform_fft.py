"""The waveforms' convolution with the pulse by overlap-save over Warp's tile FFT (float64 complex, ``wp.vec2d``).

The direct sum (kernels/waveform.py ``convolve``) makes out[i] = Σ_j x[j] · h[i − j − f] from a beam's impulse
train x (float64, non-zero only within its touched span [lo, hi]) and the T pulse taps h (lags f … f + T − 1
samples): the outputs that can be non-zero are the reach [lo + f, hi + f + T − 1] (within the window). Overlap-save
makes them in blocks of L = N − T + 1 consecutive outputs from FFTs of size N: the block starting at output o needs
the N impulses x[s … s + N − 1], s = o − f − (T − 1); their circular convolution with h zero-padded to N equals the
linear one at positions m = T − 1 … N − 1 (output o + m − (T − 1)); the first T − 1 positions wrap and are not
stored. As x and h are real, two consecutive blocks share one complex FFT (the first block's impulses as the real
part, the second's as the imaginary part: the inverse transform of H·(A + iB) is h⊛a + i h⊛b).

One tile of the launch (row, pair) makes blocks 2·pair and 2·pair + 1 of the reach of its row's slot (the launch runs
over the rows listed by ``split_spans``); a tile beyond the reach returns at once. The outputs are float32 [W]
rounded from the float64 sums, clamped at 0 (the exact sums of non-negative impulses and taps are ≥ 0, so the clamp only removes the FFT's rounding, ~1e−16 of the block's
largest value). Outputs before the reach are never written and those after it only with 0 (the tail of the
reach's last pair of blocks), so with ``out`` zeroed beforehand every sample beyond the reach stays exactly 0, as the
direct sums leave it (they too write 0 to a few samples past the reach).
"""
import functools

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

FFT_SIZE = 8192  # N: samples per FFT (a power of two greater than the pulse's taps)
DIRECT_BELOW = 256  # rows whose touched span is narrower [samples] are summed directly (fewer products than an FFT)
FFT_BLOCK_DIM = 256  # threads per tile on a GPU (cuFFTDx: at most N/2); a CPU tile runs on one
OUTSIDE = -(1 << 30)  # a store index that lands outside every row: nothing written


@wp.struct
class Overlap:
    """What every tile of one launch reads (samples, taps and lags as ``convolve``'s)."""

    impulses: wp.array2d(dtype=wp.float64)  # (slots, samples) the impulse trains [1]
    span: wp.array2d(dtype=wp.int32)  # (slots, 2) lowest and highest sample touched ((samples, −1): none)
    spectrum: wp.array2d(dtype=wp.vec2d)  # (1, N) FFT of the taps zero-padded to N, divided by N [W]
    taps: int  # T, taps of the pulse
    first_lag: int  # f, lag of the first tap [samples]


@wp.func
def _segments(m: int, o: Overlap, slot: int, start: int, step: int) -> wp.vec2d:
    """(x[start + m], x[start + step + m]) of ``slot``'s impulse train as one complex number; 0 outside the row
    and outside its touched span (the rest of the row is 0)."""
    a = wp.float64(0.0)
    b = wp.float64(0.0)
    lo = o.span[slot, 0]
    hi = o.span[slot, 1]
    j = start + m
    if j >= lo and j <= hi:
        a = o.impulses[slot, j]
    j = j + step
    if j >= lo and j <= hi:
        b = o.impulses[slot, j]
    return wp.vec2d(a, b)


@wp.func
def _filtered(z: wp.vec2d, m: int, o: Overlap) -> wp.vec2d:
    """z times the pulse's spectrum at bin m (the complex product)."""
    h = o.spectrum[0, m]
    return wp.vec2d(z[0] * h[0] - z[1] * h[1], z[0] * h[1] + z[1] * h[0])


@wp.func
def _clamped(value: wp.float64, output: int, last: int) -> wp.float32:
    """``value`` as float32 power [W], clamped at 0; 0 where its output lies past ``last`` (the reach's end)."""
    power = wp.float32(0.0)
    if output <= last:
        power = wp.float32(wp.max(value, wp.float64(0.0)))
    return power


@wp.func
def _real_power(z: wp.vec2d, m: int, first: int, last: int) -> wp.float32:
    """The real part (the first block's output first + m) as :func:`_clamped` power."""
    return _clamped(z[0], first + m, last)


@wp.func
def _imag_power(z: wp.vec2d, m: int, first: int, last: int) -> wp.float32:
    """The imaginary part (the second block's output first + m) as :func:`_clamped` power."""
    return _clamped(z[1], first + m, last)


@wp.func
def _store_index(m: int, wrapped: int) -> int:
    """Output offset of position m (m − wrapped) past the block's start; OUTSIDE for the wrapped positions."""
    index = OUTSIDE
    if m >= wrapped:
        index = m - wrapped
    return index


@functools.cache
def convolve_fft_kernel(n: int = FFT_SIZE, block_dim: int = FFT_BLOCK_DIM):
    """The overlap-save kernel of FFT size ``n`` (a power of two) for tiles of ``block_dim`` threads (its module's
    block_dim, so that compiling it ahead compiles what runs; n divisible by block_dim). The FFTs are Warp's own
    cooperative radix-2 FFT on every device: cuFFTDx (Warp's default on a GPU) failed to build the float64
    8192-point FFT for an H100 with Warp 1.19 (LTO error), and at 512 or 1024 threads per tile the kernel asks for
    more registers than a block has. Launch with ``wp.launch_tiled`` over (slots, pairs of blocks) with the same
    block_dim."""

    options = {"block_dim": block_dim, "enable_mathdx_fft": False}

    @wp.kernel(enable_backward=False, module="unique", module_options=options, grid_stride=False)
    def convolve_fft(
        # In:
        o: Overlap,  # the impulse trains, their spans, the pulse's spectrum
        rows: wp.array(dtype=wp.int32),  # the slots of the launch's rows (split_spans)
        block: int,  # L = n − taps + 1: outputs per block
        # Out:
        out: wp.array2d(dtype=wp.float32),  # (slots, samples) power [W], zeroed beforehand: only the reach is written
    ):
        """out[slot, i] = Σ_j impulses[slot, j] · taps[i − j − first_lag] [W] for the outputs of blocks 2·pair
        and 2·pair + 1 of L outputs each, counted from the start of the reach of slot rows[row]."""
        row, pair = wp.tid()
        slot = rows[row]
        samples = o.impulses.shape[1]
        lo = o.span[slot, 0]
        hi = o.span[slot, 1]
        reach_lo = wp.max(lo + o.first_lag, 0)
        reach_hi = wp.min(hi + o.first_lag + o.taps - 1, samples - 1)
        origin = reach_lo + 2 * pair * block
        if hi < lo or origin > reach_hi:
            return
        wrapped = o.taps - 1
        start = origin - o.first_lag - wrapped
        lanes = wp.tile_reshape(wp.tile_arange(n, dtype=int), shape=(1, n))
        z = wp.tile_map(_segments, lanes, o, slot, start, block)
        wp.tile_fft(z)
        z = wp.tile_map(_filtered, z, lanes, o)
        wp.tile_ifft(z)
        first = origin - wrapped
        index = wp.tile_map(_store_index, wp.tile_arange(n, dtype=int), wrapped)
        power = wp.tile_map(_real_power, z, lanes, first, reach_hi)
        wp.tile_store_indexed(out, index, power, offset=(slot, origin), axis=1)
        power = wp.tile_map(_imag_power, z, lanes, first + block, reach_hi)
        wp.tile_store_indexed(out, index, power, offset=(slot, origin + block), axis=1)

    return convolve_fft


@wp.kernel
def split_spans(
    # In:
    span: wp.array2d(dtype=wp.int32),  # (slots, 2) lowest and highest sample touched
    direct_below: int,  # [samples]
    # Out:
    direct: wp.array2d(dtype=wp.int32),  # (slots, 2) the spans the direct sums make
    fft: wp.array2d(dtype=wp.int32),  # (slots, 2) the spans the FFTs make
    rows: wp.array(dtype=wp.int32),  # the slots the FFTs make (count[0] of them, in any order)
    count: wp.array(dtype=wp.int32),  # [1], zeroed beforehand
):
    """Each row's touched span to ``direct`` if narrower than ``direct_below`` samples, else to ``fft`` and the row
    listed in ``rows`` (so that the FFTs are launched over those rows only: a tile that returns at once still holds
    its multiprocessor's shared memory while it is scheduled); the other gets an empty span (2³⁰, −1), which both
    convolution kernels skip."""
    slot = wp.tid()
    lo = span[slot, 0]
    hi = span[slot, 1]
    narrow = hi - lo + 1 < direct_below
    direct[slot, 0] = wp.where(narrow, lo, 1 << 30)
    direct[slot, 1] = wp.where(narrow, hi, -1)
    fft[slot, 0] = wp.where(narrow, 1 << 30, lo)
    fft[slot, 1] = wp.where(narrow, -1, hi)
    if not narrow:
        rows[wp.atomic_add(count, 0, 1)] = slot
