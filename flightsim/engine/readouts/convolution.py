"""The waveform readout's convolution of each beam's impulse train with the pulse (``waveform.convolution``):
``direct`` sums the taps per output (kernels/waveform.py ``convolve``), ``fft`` runs overlap-save over float64 tile
FFTs (kernels/waveform_fft.py). Both write float32 power [W] into rows zeroed outside each row's reach (the outputs
within the taps of its touched span), the whole reach, so the samples beyond stay exactly 0; the FFTs zero the
impulse trains they read."""
from __future__ import annotations

import numpy as np
import warp as wp

from flightsim.core.lazy import lazy_module

kw = lazy_module("kernels.waveform")
kf = lazy_module("kernels.waveform_fft")


def fft_size(taps: int, samples: int, least: int | None = None) -> int:
    """N: the smallest power of two that exceeds the taps and reaches ``least`` (by default the kernels'
    FFT_SIZE), or the samples plus the taps − 1 (one FFT then makes a whole row's outputs) if fewer; each FFT makes
    N − taps + 1 outputs."""
    least = kf.FFT_SIZE if least is None else least
    n = 1
    while n < max(min(least, samples + taps - 1), taps + 1):
        n *= 2
    return n


def bit_reversed(n: int) -> np.ndarray:
    """The indices 0 … n − 1 (n a power of two) with their log₂ n bits reversed."""
    bits = n.bit_length() - 1
    index = np.arange(n)
    return np.array([int(format(i, f"0{bits}b")[::-1], 2) for i in index]) if bits else index


def twiddles(n: int) -> np.ndarray:
    """(n/2, 2) float64: exp(−2πik/n), k = 0 … n/2 − 1, as (real, imaginary)."""
    angle = -2.0 * np.pi * np.arange(n // 2) / n
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def pulse_spectrum(taps: np.ndarray, n: int) -> np.ndarray:
    """(n, 2) float64: the FFT of the taps zero-padded to n, divided by n (the inverse FFT is unscaled), as (real,
    imaginary), in bit-reversed order (the order the kernel's forward FFT leaves its bins in)."""
    h = np.fft.fft(np.asarray(taps, dtype=np.float64), n)[bit_reversed(n)] / n
    return np.stack([h.real, h.imag], axis=-1)


SPECTRUM_FLOOR = 1e-15  # |H(k)| ÷ max |H| under which a bin of the pulse's spectrum is float64 rounding: dropped


def kept_bins(taps: np.ndarray, n: int, floor: float = SPECTRUM_FLOOR) -> int:
    """K: the FFTs keep the bins |k| ≤ K of the pulse's spectrum (the taps zero-padded to n), the highest k ≤ n/2
    where it reaches ``floor`` of its largest magnitude (real taps: |H(n − k)| = |H(k)|). Beyond it the products
    with the impulses' spectrum are below float64's rounding of the largest (a Gaussian pulse of σ samples:
    K ≈ 8.4·n / (2πσ); change1: 36 of 8192 bins)."""
    magnitude = np.abs(np.fft.fft(np.asarray(taps, dtype=np.float64), n))[: n // 2 + 1]
    above = np.flatnonzero(magnitude > floor * magnitude.max())
    return int(above.max()) if len(above) else n // 2  # taps that underflowed to 0: nothing to prune by


class PulseConvolution:
    """One run's convolution of rows of ``samples`` samples with the pulse taps (float64 on ``device``, first lag
    ``first_lag`` samples): ``method`` ``direct`` or ``fft``. With fft, the rows whose touched span is narrower
    than ``direct_below`` samples are still summed directly (bit for bit as with direct: a flat footprint's few
    samples need fewer products than an FFT), the others by FFTs of size :func:`fft_size` of ``fft_least`` (a power
    of two) launched with ``block_dim`` threads per tile (at most N/2; None: kernels.waveform_fft's choice for the
    transform), keeping the bins of the pulse's spectrum above ``floor`` of its largest (:func:`kept_bins`; 0:
    every bin). ``fft_least`` and ``direct_below`` default (None) to kernels.waveform_fft's FFT_SIZE and
    DIRECT_BELOW."""

    def __init__(self, method: str, taps: wp.array, first_lag: int, samples: int, device: str,
                 fft_least: int | None = None, block_dim: int | None = None, direct_below: int | None = None,
                 floor: float = SPECTRUM_FLOOR):
        direct_below = kf.DIRECT_BELOW if direct_below is None else direct_below
        self.method, self.taps, self.first_lag, self.device = method, taps, first_lag, device
        self.direct_below, self.spans, self.rows, self.fft_rows = direct_below, None, None, None
        self.zeroes_narrower = direct_below if method == "fft" else 1 << 30  # the rows whose impulse trains the
        # convolution does not zero as it reads them: those narrower than this [samples] (the FFTs zero theirs)
        if method == "fft":
            self.n = fft_size(len(taps), samples, fft_least)
            self.keep = kept_bins(taps.numpy(), self.n, floor) if floor > 0.0 else -1
            pruned = kf.is_pruned(self.n, kf.kept_levels(self.n, self.keep))
            self.block_dim = min(block_dim or (kf.PRUNED_BLOCK_DIM if pruned else kf.FFT_BLOCK_DIM), self.n // 2)
            self.block = self.n - len(taps) + 1  # L: outputs per FFT
            device_info = wp.get_device(device)
            self.tiles = device_info.sm_count if device_info.is_cuda else 1  # one tile per multiprocessor
            spectrum = pulse_spectrum(taps.numpy(), self.n)
            self.overlap = kf.Overlap()
            self.overlap.spectrum = wp.array(spectrum, dtype=wp.vec2d, device=device)
            self.overlap.twiddles = wp.array(twiddles(self.n), dtype=wp.vec2d, device=device)
            self.overlap.taps, self.overlap.first_lag = len(taps), first_lag

    def kernels(self) -> list:
        """The kernels :meth:`launch` runs."""
        if self.method == "direct":
            return [kw.convolve]
        return [kw.convolve, kf.split_spans, kf.convolve_fft_kernel(self.n, self.block_dim, self.keep)]

    def launch(self, impulses: wp.array, span: wp.array, out: wp.array, n: int, zeroed: bool = False) -> None:
        """Rows 0 … n − 1 of ``out`` (zeroed here first, unless ``zeroed``: they are 0 already, or 0 outside the
        reach of ``span``, which is written whole) = rows of ``impulses`` (touched within ``span``) convolved with the
        pulse [W]; the impulse trains of the rows the FFTs make (not narrower than ``zeroes_narrower``) are left 0."""
        samples, d = impulses.shape[1], self.device
        if not zeroed:
            out[:n].zero_()
        if self.method == "fft":
            if self.spans is None or self.spans[0].shape[0] < n:
                self.spans = tuple(wp.empty((span.shape[0], 2), dtype=wp.int32, device=d) for _ in range(2))
                self.rows = wp.empty(span.shape[0], dtype=wp.int32, device=d)  # the rows the FFTs make
                self.fft_rows = wp.zeros(1, dtype=wp.int32, device=d)  # how many rows the FFTs make
            self.fft_rows.zero_()
            wp.launch(kf.split_spans, n, inputs=[span, self.direct_below],
                      outputs=[*self.spans, self.rows, self.fft_rows], device=d)
            span, self.overlap.span = self.spans
        blocks = -(-samples // kw.CONVOLVE_OUTPUTS)  # the whole row
        if self.method == "fft":  # the direct rows' reach: narrower than direct_below + taps − 1 samples
            blocks = min(blocks, -(-(self.direct_below + len(self.taps) - 2) // kw.CONVOLVE_OUTPUTS) + 1)
        wp.launch(kw.convolve, (n, blocks), inputs=[impulses, span, self.taps, self.first_lag,
                                                    int(self.method == "fft")], outputs=[out], device=d)
        if self.method == "direct":
            return
        self.overlap.impulses = impulses
        wp.launch_tiled(self.kernels()[-1], dim=self.tiles, inputs=[self.overlap, self.rows, self.fft_rows, self.tiles,
                                                                     self.block],
                        outputs=[out], block_dim=self.block_dim, device=self.device)
