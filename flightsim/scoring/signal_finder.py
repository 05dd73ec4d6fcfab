"""ATL03-style signal confidence of photon heights from their histograms (after the ICESat-2 ATL03 ATBD,
§5 "signal finding"), not from the simulator's truth.

Along track the photons of a beam are cut into segments of ``segment_m`` (ATBD: 20 m). Per segment:

1. **Background** around each photon's height: the photons of the segment and of ``background_segments``
   segments on each side whose heights lie between ``window_m`` and ``background_m``/2 from it (a ring
   that leaves out the photon's own surface), per metre of the ring inside the band the photons span
   (the telemetry band) and per shot pooled: the background density β [photons per m of height and per
   shot]. A ring rather than the whole band, because the detector's dead time and its limit of events
   per shot make the background thin out towards the far end of the band.
2. **Significance** of each photon: the number k of the segment's other photons within ±``window_m``/2
   of its height, against the Poisson count the background puts there, λ = β · window_m · shots: the
   tail probability p = P(K ≥ k | λ).
3. **Confidence** (ATL03's signal_conf_ph): 4 high (p < p_high), 3 medium (p < p_medium), 2 low
   (p < p_low), 1 buffer (a photon within ±window_m of a photon of confidence ≥ 2 in its segment),
   0 noise. The defaults are the one-sided normal tails of 5, 4 and 3 σ.

ATL03 gives one confidence per surface type (land, ocean, sea ice, land ice, inland water); this finder
gives one. The shots of a segment are the distinct pulse ids among its photons.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.process_map import ProcessMap, map_rows
from flightsim.core.poisson import at_least
from flightsim.core.radix import by_key_then_value, stable_order
from flightsim.core.warp_runtime import init_warp
from kernels.signal_finder import segment_counts

NOISE, BUFFER, LOW, MEDIUM, HIGH = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class SignalFinder:
    """The finder's parameters (lengths [m], tail probabilities)."""

    segment_m: float = 20.0  # along-track segment (ATBD: 20 m)
    window_m: float = 1.0  # height window a photon's neighbours are counted in
    background_m: float = 60.0  # height span of the background ring around a photon
    background_segments: int = 2  # segments on each side pooled into the background
    p_low: float = 1.35e-3  # 3 σ one-sided
    p_medium: float = 3.17e-5  # 4 σ
    p_high: float = 2.87e-7  # 5 σ

    def classify(self, along_m, h_m, pulse) -> np.ndarray:
        """Confidence 0–4 (int8) of photons given by along-track distance [m], height [m] and pulse id; a photon
        whose distance or height is not finite (no position) is noise and no other photon's neighbour."""
        along, h, pulse = np.asarray(along_m), np.asarray(h_m, dtype=np.float64), np.asarray(pulse)
        if not len(h):
            return np.zeros(0, dtype=np.int8)
        placed = np.isfinite(along) & np.isfinite(h)
        if not placed.all():
            out = np.zeros(len(h), dtype=np.int8)
            out[placed] = self.classify(along[placed], h[placed], pulse[placed])
            return out
        segment = np.floor(along / self.segment_m).astype(np.int64)
        order = by_key_then_value(segment, h)
        ordered = segment[order]
        starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])  # each segment's first photon (sorted)
        ids, bounds = ordered[starts], np.append(starts, len(order))
        k = self.background_segments
        pools = np.searchsorted(ids, ids - k), np.searchsorted(ids, ids + k + 1)  # segments lo … hi − 1
        of = np.repeat(np.arange(len(ids), dtype=np.int32), np.diff(bounds))  # each photon's segment (sorted order)
        came, shots = _shots(of, pulse[order])
        hs = h[order]
        ring, others, band = self._counts(hs, bounds, *pools)
        pooled = np.array([np.count_nonzero(came[shots[lo]:shots[hi]] < lo) for lo, hi in zip(*pools)])
        lam = self._expected(hs, of, ring, band, pooled, np.diff(shots))
        p = _tail_above_mean(others, lam) if self.p_low <= 0.5 else at_least(others, lam)
        conf = np.select([p < self.p_high, p < self.p_medium, p < self.p_low], [np.int8(HIGH), np.int8(MEDIUM),
                                                                                   np.int8(LOW)], np.int8(NOISE))
        out = np.empty(len(h), dtype=np.int8)
        out[order] = self._buffered(conf, hs, bounds, of)
        return out

    def _expected(self, hs, of, ring, band, pooled_shots, shots) -> np.ndarray:
        """The background count λ in each photon's ±window_m/2 (sorted order; ``of`` its segment): β [photons per m
        of height per shot] from its ``ring`` count over the ring's length within its pool's ``band`` and the
        pool's shots, times its segment's ``shots`` and window_m."""
        inner, outer = self.window_m, self.background_m / 2.0
        low, high = band[0][of], band[1][of]
        length = _overlap(hs - outer, hs - inner, low, high) + _overlap(hs + inner, hs + outer, low, high)
        beta = ring / np.maximum(length, self.window_m) / pooled_shots[of]
        return beta * shots[of] * self.window_m

    def _counts(self, hs: np.ndarray, bounds: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple:
        """Per photon (heights ``hs`` sorted by segment, then height; segment j's rows bounds[j] … bounds[j+1] − 1,
        its pool segments lo[j] … hi[j] − 1): the pool's photons in its background ring, and its segment's other
        photons within ±window_m/2; per segment the pool's band (least, greatest height). A Warp kernel on the CPU
        (:func:`kernels.signal_finder.segment_counts`), a thread a segment."""
        init_warp()
        ring, others = (wp.empty(len(hs), dtype=wp.int32, device="cpu") for _ in range(2))
        band = wp.empty((2, len(lo)), dtype=wp.float64, device="cpu")
        wp.launch(segment_counts, len(lo), inputs=[hs, *(a.astype(np.int32) for a in (bounds, lo, hi)), self.window_m,
                                                   self.background_m / 2.0, self.window_m / 2.0],
                  outputs=[ring, others, band], device="cpu")
        return ring.numpy(), others.numpy(), band.numpy()

    def _buffered(self, conf: np.ndarray, hs: np.ndarray, bounds: np.ndarray, of: np.ndarray) -> np.ndarray:
        """``conf`` (sorted order) with the noise photons within ±window_m of a photon of confidence ≥ LOW of their
        segment made BUFFER: the nearest such photon below and above in the sort, within the segment."""
        place = np.arange(len(hs), dtype=np.int32)
        below = np.maximum.accumulate(np.where(conf >= LOW, place, -1))
        above = np.minimum.accumulate(np.where(conf >= LOW, place, len(hs))[::-1])[::-1]
        near = np.full(len(hs), np.inf)
        ok = below >= bounds[of]
        near[ok] = np.abs(hs[ok] - hs[below[ok]])
        ok = above < bounds[of + 1]
        near[ok] = np.minimum(near[ok], np.abs(hs[above[ok]] - hs[ok]))
        conf[(conf == NOISE) & (near <= self.window_m)] = BUFFER
        return conf

    def classify_stream(self, n: int, read: Callable[[int, int], tuple], write: Callable[[int, np.ndarray], None],
                        block: int = 1 << 20, workers: ProcessMap | None = None, spread_m: float | None = None) -> None:
        """Classify ``n`` photons stored in along-track order block by block (memory ∝ ``block``): ``read(lo,
        hi)`` gives (along, h, pulse) of rows [lo, hi), ``write(lo, conf)`` stores rows from lo. Each block is
        read with enough rows on both sides to hold every photon of its segments' background pools, so that it
        classifies as the whole stream would. ``spread_m``: how far a photon lies behind one stored before it at
        most (:func:`along_spread`; None: found by reading the distances once). ``workers``: worker processes
        (:class:`~flightsim.core.process_map.ProcessMap`) that classify the blocks side by side (the same values);
        None: this process, a block at a time."""
        if spread_m is None:
            spread_m, furthest = 0.0, -np.inf
            for lo in range(0, n, block):
                spread, furthest = along_spread(read(lo, min(n, lo + block))[0], furthest)
                spread_m = max(spread_m, spread)
        self.classify_streams([(n, read, write, block, spread_m)], workers)

    def classify_streams(self, streams: list[tuple], workers: ProcessMap | None = None) -> None:
        """:meth:`classify_stream` of several streams (``(n, read, write, block, spread_m)`` each, e.g. a granule's
        beams) at once: :meth:`classify_spans` of their blocks."""
        self.classify_spans([span for stream in streams for span in block_spans(stream, [(0, stream[0])])], workers)

    def classify_spans(self, spans: list[tuple], workers: ProcessMap | None = None) -> None:
        """Rows [start, end) of streams (``(stream, start, end)`` each), in order, each read as a worker frees to take
        it (this process reads and sends while the workers classify), their confidences written in order once every
        span is done (1 byte a photon held)."""
        blocks = ((self, *self._padded(n, read, start, end, block, spread))
                  for (n, read, _, block, spread), start, end in spans)
        for ((_, _, write, _, _), start, _), conf in zip(spans, map_rows(classify_part, blocks, workers)):
            write(start, conf)

    def reach_m(self, spread_m: float) -> float:
        """How far along track [m] beyond a block's nearest and furthest photon the rows read must reach so that they
        hold every photon of its background pools, when photons lie up to ``spread_m`` behind ones stored before
        them: a photon is pooled with those of the segments within ``background_segments`` of its own, so none
        further than (background_segments + 1) · segment_m from it; one segment more against rounding at a
        segment's edge, and the spread, since a row past the last read may lie that much behind it."""
        return (self.background_segments + 2) * self.segment_m + spread_m

    def _padded(self, n: int, read: Callable[[int, int], tuple], start: int, end: int, block: int,
                spread_m: float) -> tuple:
        """(along, h, pulse, first, past) of rows [start, end) read with enough rows on both sides (rows
        [first, past) of the arrays are the block's): :func:`reached`."""
        lo, _, (along, h, pulse), _, _ = padded_rows(n, read, start, end, block, self.reach_m(spread_m))
        return along, h, pulse, start - lo, end - lo


def padded_rows(n: int, read: Callable[[int, int], tuple], start: int, end: int, block: int, reach_m: float,
                from_start: bool = True, to_end: bool = True) -> tuple:
    """(lo, hi, read(lo, hi), near, far): rows [lo, hi) of a stream of ``n`` rows read around rows [start, end), with
    pads from block/64 rows a side doubled while a side short of ``reach_m`` (:func:`reached`: ``near`` before the
    block's photons, ``far`` beyond) can still grow. Rows 0 and n are the stream's start and end when ``from_start``
    and ``to_end`` (a side reaching them needs no more); else rows held of a longer stream, where a side may stay
    short."""
    pad = max(block // 64, 1)  # ~3 % of a block
    while True:
        lo, hi = max(0, start - pad), min(n, end + pad)
        rows = read(lo, hi)
        near, far = reached(rows[0], start - lo, end - lo, lo == 0 and from_start, hi == n and to_end)
        if not ((near <= reach_m and lo > 0) or (far <= reach_m and hi < n)):
            return lo, hi, rows, near, far
        pad *= 2


def block_spans(stream: tuple, ranges: list[tuple[int, int]]) -> list[tuple]:
    """(stream, start, end) of the blocks of the stream's block size (``(n, read, write, block, spread_m)``) that
    cover rows [a, b) of each of ``ranges``."""
    block = stream[3]
    return [(stream, start, min(b, start + block)) for a, b in ranges for start in range(a, b, block)]


def along_spread(along: np.ndarray, furthest: float = -np.inf) -> tuple[float, float]:
    """(spread, furthest): the most a photon of ``along`` [m] (in stored order) lies behind one stored before it,
    max over i < j of along[i] − along[j] (0 when none; over these photons and, before them, photons that reached
    ``furthest``), and the furthest distance reached; photons without a finite distance left out. Off nadir, a
    shot's photons at different heights lie at different distances along track (ATLAS's 2 km window: ~16 m)."""
    finite = along[np.isfinite(along)]
    if not finite.size:
        return 0.0, furthest
    reached = np.maximum(np.maximum.accumulate(finite), furthest)
    return max(0.0, float((reached - finite).max())), float(reached[-1])


def reached(along: np.ndarray, first: int, past: int, at_start: bool, at_end: bool) -> tuple[float, float]:
    """How far rows ``along`` [m] read around a block (rows [first, past)) reach before the block's nearest photon and
    beyond its furthest (−inf where no row read there has a finite distance). The rows hold every photon of the
    block's background pools when both exceed :meth:`SignalFinder.reach_m`: a photon stored before the first row
    read lies at most the spread ahead of it, one stored after the last at most the spread behind it, so neither
    shares a pool with the block's. inf at the stream's start (``at_start``) or end (``at_end``), and both for a
    block without a finite distance (its photons are noise whatever is read)."""
    inside = along[first:past]
    inside = inside[np.isfinite(inside)]
    if not inside.size:
        return np.inf, np.inf
    return (np.inf if at_start else _largest(inside.min() - along[:first]),
            np.inf if at_end else _largest(along[past:] - inside.max()))


def _largest(gaps: np.ndarray) -> float:
    """The largest finite of ``gaps`` [m]; −inf for none."""
    gaps = gaps[np.isfinite(gaps)]
    return float(gaps.max()) if gaps.size else -np.inf


def classify_part(finder: SignalFinder, along, h, pulse, first: int, past: int) -> np.ndarray:
    """``finder``'s confidence of rows [first, past) of the photons (a module-level function: a worker process runs
    it on a block)."""
    return finder.classify(along, h, pulse)[first:past]


def _shots(segment: np.ndarray, pulse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct shots of segments 0 … m − 1 (``segment``, ascending, and ``pulse``, a photon each) as (segment,
    pulse) pairs in segment order (a pulse whose photons span several segments is a pair in each): for each pair the
    last earlier segment its pulse came in (−1: none), and where each segment's pairs start (m + 1 bounds). The
    distinct shots of segments lo … hi − 1 are their pairs whose pulse came in no segment from lo on before."""
    by_pulse = stable_order(pulse - pulse.min())  # the rows come in segment order: so by (pulse, segment)
    s, p = segment[by_pulse], pulse[by_pulse]
    new = np.r_[True, (s[1:] != s[:-1]) | (p[1:] != p[:-1])]  # each distinct pair once
    s, p = s[new], p[new]
    repeat = np.r_[False, p[1:] == p[:-1]]  # the pulse came in an earlier segment
    came = np.where(repeat, np.r_[0, s[:-1]], -1)  # that segment; −1 its first
    in_order = stable_order(s)
    return came[in_order], np.searchsorted(s[in_order], np.arange(int(segment[-1]) + 2))


def _tail_above_mean(k: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """:func:`at_least` where a count ``k`` exceeds its mean ``lam``, else 1: there P(K ≥ k) ≥ 1/2, not below a
    p_low ≤ 1/2, so the photon is noise either way (a Poisson median m is at least λ − ln 2, Choi 1994, so an integer
    k ≤ λ is ≤ m and P(K ≥ k) ≥ P(K ≥ m) ≥ 1/2). Four in five of an ATLAS beam's photons are at or below their mean."""
    p = np.ones(len(k))
    above = k > lam
    p[above] = at_least(k[above], lam[above])
    return p


def _overlap(lo: np.ndarray, hi: np.ndarray, band_lo: float, band_hi: float) -> np.ndarray:
    """Length of [lo, hi] ∩ [band_lo, band_hi] [m]."""
    return np.clip(np.minimum(hi, band_hi) - np.maximum(lo, band_lo), 0.0, None)
