"""The waveforms' convolution with the pulse by overlap-save over float64 FFTs in a tile's shared memory.

The direct sum (kernels/waveform.py ``convolve``) makes out[i] = Σ_j x[j] · h[i − j − f] from a beam's impulse
train x (float64, non-zero only within its touched span [lo, hi]) and the T pulse taps h (lags f … f + T − 1
samples): the outputs that can be non-zero are the reach [lo + f, hi + f + T − 1] (within the window). Overlap-save
makes them in blocks of L = N − T + 1 consecutive outputs from FFTs of size N: the block starting at output o needs
the N impulses x[s … s + N − 1], s = o − f − (T − 1); their circular convolution with h zero-padded to N equals the
linear one at positions m = T − 1 … N − 1 (output o + m − (T − 1)); the first T − 1 positions wrap and are not
stored. As x and h are real, two consecutive blocks share one complex FFT (the first block's impulses as the real
part, the second's as the imaginary part: the inverse transform of H·(A + iB) is h⊛a + i h⊛b).

The FFTs run over the N complex float64 points of one shared-memory tile: the forward transform by decimation in
frequency (natural order in, bit-reversed order out), the product with the pulse's spectrum in that bit-reversed
order, the inverse by decimation in time (bit-reversed in, natural out), so no permutation is ever made. Each pass
gives every thread groups of 2^RADIX_LEVELS points that it takes through as many levels of radix-2 butterflies in
registers (:func:`fft_passes`); the twiddles exp(−2πik/N) come from a float64 table made on the host
(``flightsim.engine.readouts.convolution.twiddles``), not from sines per butterfly; a level whose twiddle index steps
by TABLE_STRIDE or more per point reads them from a copy in shared memory (:func:`twiddle_tables`). Each butterfly's
arithmetic is the same whichever thread makes it, so every device and block size gives the same bits.

Where the pulse's spectrum is 0 to float64's rounding beyond the bins |k| ≤ K (``kept_bins``: change1's ±36 of
8192), the transforms are pruned (:func:`kept_levels`, :func:`_kept_bins`): the forward stops once each kept bin has a
block of its own, those bins are summed from their blocks, and the inverse starts from them.

A tile makes one row at a time (the rows those listed by ``split_spans``; the launch has a tile per multiprocessor, each
taking the rows in turn, their count read on the device: the host never waits for it), its pairs of blocks in turn from
the start of the reach, pair p making blocks 2p and 2p + 1. Once a pair's FFT has read its impulses, the tile zeroes
those of the row's touched span that no later pair reads (after the last pair, the rest of the span), so the rows the
FFTs make leave zero impulse trains behind: the next chunk's deposits need no clearing of them. The outputs are float32
[W] rounded from the float64 sums, clamped at 0 (the exact sums of non-negative impulses and taps are ≥ 0, so the clamp
only removes the FFT's rounding, ~1e−16 of the block's largest value). Outputs before the reach are never written and
those after it only with 0 (the tail of the reach's last pair of blocks), so with ``out`` zeroed beforehand every sample
beyond the reach stays exactly 0, as the direct sums leave it (they too write 0 to a few samples past the reach).
"""
import functools

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

FFT_SIZE = 8192  # N: samples per FFT (a power of two greater than the pulse's taps)
DIRECT_BELOW = 256  # rows whose touched span is narrower [samples] are summed directly (fewer products than an FFT)
FFT_BLOCK_DIM = 256  # threads per tile on a GPU (at most N/2)
PRUNED_BLOCK_DIM = 512  # ... for a pruned transform (kept_levels), whose fewer live values let twice as many run
# (H100, 500 sloped change1 shots: 0.336-0.344 ms a chunk against 0.362-0.364 at 256; profile-experiments.md, 36)
SM_REGISTERS = 65536  # 32-bit registers of a multiprocessor: a tile of more than 256 threads gets at most its share


@wp.struct
class Overlap:
    """What every tile of one launch reads (samples, taps and lags as ``convolve``'s)."""

    impulses: wp.array2d(dtype=wp.float64)  # (slots, samples) the impulse trains [1]
    span: wp.array2d(dtype=wp.int32)  # (slots, 2) lowest and highest sample touched ((samples, −1): none)
    spectrum: wp.array(dtype=wp.vec2d)  # (N,) FFT of the taps zero-padded to N, divided by N, bit-reversed order [W]
    twiddles: wp.array(dtype=wp.vec2d)  # (N/2,) exp(−2πik/N) [1]
    taps: int  # T, taps of the pulse
    first_lag: int  # f, lag of the first tap [samples]


RADIX_LEVELS = 4  # butterfly levels a thread makes in registers between two passes through shared memory (radix 16)
PAD_EVERY = 16  # one padding element after every 16 in shared memory (spreads strided accesses over the banks)

_HELPERS = """
    wp::vec2d* z = tile.data.ptr;
    auto at = [](int e) { return e + e / %(pad)d; };  // the padded shared-memory index of position e
    auto sample = [&](int e) {  // (x[start + e], x[start + step + e]), 0 outside the touched span [lo, hi]
        int j = start + e;
        const double a = (j >= lo && j <= hi) ? *wp::address(impulses, slot, j) : 0.0;
        j += step;
        const double b = (j >= lo && j <= hi) ? *wp::address(impulses, slot, j) : 0.0;
        return wp::vec2d(a, b);
    };
    auto twiddle = [&](int k) { return *wp::address(twiddles, k); };  // exp(−2πik/N), k < N/2
    auto turn = [&](int k) {  // exp(−2πik/N), 0 ≤ k < N
        const wp::vec2d w = twiddle(k & (%(n)d / 2 - 1));
        return k < %(n)d / 2 ? w : wp::vec2d(-w[0], -w[1]);
    };
    auto dif = [&](wp::vec2d& u, wp::vec2d& v, const wp::vec2d& w) {  // (u + v, (u − v) · w)
        const double dr = u[0] - v[0], di = u[1] - v[1];
        u = wp::vec2d(u[0] + v[0], u[1] + v[1]);
        v = wp::vec2d(dr * w[0] - di * w[1], dr * w[1] + di * w[0]);
    };
    auto dit = [&](wp::vec2d& u, wp::vec2d& v, const wp::vec2d& w) {  // (u + t, u − t), t = v · conj(w)
        const double tr = v[0] * w[0] + v[1] * w[1], ti = v[1] * w[0] - v[0] * w[1];
        v = wp::vec2d(u[0] - tr, u[1] - ti);
        u = wp::vec2d(u[0] + tr, u[1] + ti);
    };
    auto filter = [&](wp::vec2d& v, int e) {  // times the pulse's spectrum at bit-reversed position e
        const wp::vec2d h = *wp::address(spectrum, e);
        v = wp::vec2d(v[0] * h[0] - v[1] * h[1], v[0] * h[1] + v[1] * h[0]);
    };
    const int samples = out.shape[1];
    auto emit = [&](int e, const wp::vec2d& v) {  // position e ≥ wrapped: real part to output first + e, imaginary
        if (e < wrapped) return;                 // part to first + step + e; float32, clamped at 0, 0 past last
        int output = first + e;
        if (output < samples)
            *wp::address(out, slot, output) = output <= last ? wp::float32(v[0] > 0.0 ? v[0] : 0.0) : wp::float32(0.0);
        output += step;
        if (output < samples)
            *wp::address(out, slot, output) = output <= last ? wp::float32(v[1] > 0.0 ? v[1] : 0.0) : wp::float32(0.0);
    };
"""


def fft_passes(n: int) -> list[tuple[int, int]]:
    """The forward FFT's passes as (half of its first level, levels): all log₂ n levels (:func:`_passes`)."""
    return _passes(n.bit_length() - 1, n)


def _levels(half: int, count: int, n: int, inverse: bool, tables: dict[int, int] | None = None) -> list[str]:
    """The butterflies of ``count`` levels (halves half, half/2, …; reversed for the inverse) on a group's
    registers v[0 … 2^count − 1], the elements pos + j·q of their block (q = half / 2^(count − 1)); each level
    reads each of its distinct twiddles once, from ``tables`` (stride → offset in shared memory: twiddle
    (k·stride) at ``table[offset + k]``) where it has the level's stride, else from global memory."""
    group, q, lines, tables = 1 << count, half >> (count - 1), [], tables or {}
    order = range(count - 1, -1, -1) if inverse else range(count)
    for level in order:
        jh = group >> (level + 1)  # the butterfly's half in elements of the group
        stride = n // (2 * jh * q)  # twiddle index per position
        name = f"w{'i' if inverse else 'f'}{level}_"  # the twiddles' names (the middle pass has both directions)
        for c in range(jh):
            position = f"pos + {c * q}" if c else "pos"
            load = f"table[{tables[stride]} + {position}]" if stride in tables else f"twiddle(({position}) * {stride})"
            lines.append(f"const wp::vec2d {name}{c} = {load};")
        for j in range(group):
            if not j & jh:
                lines.append(f"{'dit' if inverse else 'dif'}(v[{j}], v[{j + jh}], {name}{j & (2 * jh - 1)});")
    return lines


def _pass(half: int, count: int, n: int, source: str, body: list[str], sink: str) -> str:
    """One pass over the groups of 2^count elements (every thread of the tile taking every block_dim-th group):
    each group's elements loaded by ``source`` (``shared`` or ``impulses``), ``body`` applied, stored by ``sink``
    (``shared`` or ``out``); a sync after."""
    group, q = 1 << count, half >> (count - 1)
    load = {"shared": "v[{j}] = z[at(base + {o})];", "impulses": "v[{j}] = sample(base + {o});",
            "kept": "v[{j}] = expand(base + {o});"}[source]
    store = {"shared": "z[at(base + {o})] = v[{j}];", "out": "emit(base + {o}, v[{j}]);"}[sink]
    lines = [f"for (int g = WP_TILE_THREAD_IDX; g < {n // group}; g += WP_TILE_BLOCK_DIM) {{",
             f"    const int pos = g & {q - 1}, base = (g / {q}) * {2 * half} + pos;",
             f"    wp::vec2d v[{group}];",
             *(f"    {load.format(j=j, o=j * q)}" for j in range(group)),
             *(f"    {line}" for line in body),
             *(f"    {store.format(j=j, o=j * q)}" for j in range(group)),
             "}", "WP_TILE_SYNC();"]
    return "\n".join(lines)


def kept_levels(n: int, keep: int) -> int:
    """The forward levels a transform of size ``n`` makes in full when only the bins |k| ≤ ``keep`` are kept: the
    fewest whose 2^levels sub-transforms give each of those bins its own (2^levels ≥ 2·keep + 1), or all log₂ n
    (nothing pruned) where that saves fewer than two levels or ``keep`` < 0 (keep every bin)."""
    levels = n.bit_length() - 1
    if keep < 0:
        return levels
    kept = max(1, (2 * keep).bit_length())
    return kept if levels - kept >= 2 else levels


def is_pruned(n: int, levels: int) -> bool:
    """Whether a size-``n`` transform making ``levels`` forward levels (:func:`kept_levels`) is pruned."""
    return levels < n.bit_length() - 1


def _kept_bins(n: int, keep: int, levels: int) -> str:
    """The native code between a pruned transform's forward and inverse passes. After ``levels`` levels of
    decimation in frequency the tile holds 2^levels blocks of m = n / 2^levels points; block b's m-point DFT gives
    the bins r + 2^levels·j (r = b with its ``levels`` bits reversed), so bin r ≤ keep is its j = 0 output, the sum
    of its points, and bin n − (2^levels − r) its j = m − 1 output, Σ z[i] exp(+2πi·i/m); every other block holds
    no kept bin. Thread b sums block b from its point b mod m on (neighbouring threads' loads on different banks).
    Each such sum times the pulse's spectrum there is stored after the tile's points (kept[b] for
    j = 0, kept[blocks + b] for j = m − 1, 0 elsewhere), from which ``expand`` makes what the inverse's first log₂ m
    levels would make of a block holding one non-zero bin: its m-point inverse DFT, that bin times exp(−2πi·i/m)^j
    (2^levels > 2·keep, so no block holds two). The m roots
    exp(−2πi·i/m) come from shared memory too (``roots``, after the kept bins: :func:`_prologue`), not from the
    twiddles in global memory: each point of the expand would otherwise load one, 2 kB from its neighbour's."""
    blocks, m = 1 << levels, n >> levels
    return f"""
    for (int b = WP_TILE_THREAD_IDX; b < {blocks}; b += WP_TILE_BLOCK_DIM) {{
        int r = 0;
        for (int bit = 0; bit < {levels}; ++bit) r |= ((b >> bit) & 1) << ({levels} - 1 - bit);
        wp::vec2d low(0.0, 0.0), high(0.0, 0.0);
        if (r <= {keep}) {{
            double re = 0.0, im = 0.0;
            for (int s = 0; s < {m}; ++s) {{
                const wp::vec2d v = z[at(b * {m} + ((s + b) & {m - 1}))];
                re += v[0];
                im += v[1];
            }}
            low = wp::vec2d(re, im);
            filter(low, b * {m});
        }} else if (r >= {blocks - keep}) {{
            double re = 0.0, im = 0.0;
            for (int s = 0; s < {m}; ++s) {{
                const int i = (s + b) & {m - 1};
                const wp::vec2d v = z[at(b * {m} + i)], w = roots[i];
                re += v[0] * w[0] + v[1] * w[1];
                im += v[1] * w[0] - v[0] * w[1];
            }}
            high = wp::vec2d(re, im);
            filter(high, b * {m} + {m - 1});
        }}
        kept[b] = low;
        kept[{blocks} + b] = high;
    }}
    WP_TILE_SYNC();
    auto expand = [&](int e) {{  // the inverse's input after its first levels: position e of block e / m
        const wp::vec2d a = kept[e / {m}], c = kept[{blocks} + e / {m}], w = roots[e % {m}];
        return wp::vec2d(a[0] + c[0] * w[0] - c[1] * w[1], a[1] + c[0] * w[1] + c[1] * w[0]);
    }};
"""


_ZERO_SAMPLES = """
    for (int j = lo + WP_TILE_THREAD_IDX; j <= hi; j += WP_TILE_BLOCK_DIM) *wp::address(impulses, slot, j) = 0.0;
"""  # a tile's threads zero samples lo … hi of a row, neighbouring threads neighbouring samples (after the tile's
# last sync: every thread's loads of them are done)


TABLE_STRIDE = 16  # twiddles of a level whose index steps by this or more per position come from shared memory


def twiddle_tables(n: int, levels: int) -> tuple[dict[int, int], int]:
    """The shared-memory twiddle tables of a transform making the first ``levels`` levels of a size-``n`` FFT: per
    level whose twiddle index steps by ``stride`` ≥ TABLE_STRIDE per position (half h = n / (2·stride)), its h
    twiddles exp(−2πi·k·stride/n) in a row; (stride → offset, total entries). A warp's positions then read
    neighbouring entries, where from the global table each would load a line of its own."""
    offsets, total = {}, 0
    for level in range(levels):
        stride = 1 << level
        if stride >= TABLE_STRIDE:
            offsets[stride], total = total, total + n // (2 * stride)
    return offsets, total


def shared_extra(n: int, levels: int) -> int:
    """The elements a tile keeps after its points (:func:`_prologue`): for a pruned transform (``levels`` short of
    log₂ n) the kept bins' two rows and the m roots, then the twiddle tables."""
    pruned = (2 << levels) + (n >> levels) if is_pruned(n, levels) else 0
    return pruned + twiddle_tables(n, levels)[1]


def _prologue(n: int, levels: int) -> str:
    """The native code, before the first pass (whose sync it shares: that pass's levels, strides 1 … 2^(RADIX_LEVELS
    − 1) < TABLE_STRIDE, read no table), that puts after the tile's points: for a pruned transform the kept bins'
    rows and the m = n / 2^levels roots exp(−2πi·i/m) (``kept``, ``roots``: :func:`_kept_bins`); the twiddle tables
    (``table``: :func:`twiddle_tables`)."""
    offsets, total = twiddle_tables(n, levels)
    fill = "".join(f"""
        if (i >= {offset} && i < {offset + n // (2 * stride)}) table[i] = twiddle((i - {offset}) * {stride});"""
                   for stride, offset in offsets.items())
    code = f"""
    wp::vec2d* table = z + {n + n // PAD_EVERY + shared_extra(n, levels) - total};"""
    if is_pruned(n, levels):
        blocks, m = 1 << levels, n >> levels
        code += f"""
    wp::vec2d* kept = z + {n + n // PAD_EVERY};
    wp::vec2d* roots = kept + {2 * blocks};
    for (int i = WP_TILE_THREAD_IDX; i < {m}; i += WP_TILE_BLOCK_DIM) roots[i] = turn(i * {n // m});"""
    return code + f"""
    for (int i = WP_TILE_THREAD_IDX; i < {total}; i += WP_TILE_BLOCK_DIM) {{{fill}
    }}
"""


def _passes(levels: int, n: int) -> list[tuple[int, int]]:
    """The first ``levels`` levels of a size-``n`` forward FFT as passes (half of their first level, levels) of
    RADIX_LEVELS levels, the remainder second, so that the first pass (which reads the impulses from global memory,
    and its inverse, which writes the outputs) and the last (down to the half 1, which the product with the
    spectrum joins) have RADIX_LEVELS levels each: a thread then has that many independent global loads in
    flight."""
    full, rest = divmod(levels, RADIX_LEVELS)
    counts = [RADIX_LEVELS] * full
    if rest:
        counts.insert(1 if full else 0, rest)
    passes, half = [], n // 2
    for count in counts:
        passes.append((half, count))
        half >>= count
    return passes


def overlap_save_snippet(n: int, keep: int = -1) -> str:
    """The native code of one tile's overlap-save: the forward passes (the first loading the impulses), the last
    forward pass, the product with the spectrum and the first inverse pass on the same registers, the inverse
    passes (the last writing the outputs). Positions are natural in the forward passes' input and the inverse
    passes' output, bit-reversed between. With ``keep`` ≥ 0 (the pulse's spectrum is 0 to float64's rounding
    beyond the bins |k| ≤ keep) and :func:`kept_levels` short of log₂ n, the forward transform stops after those
    levels, the kept bins are summed from its blocks (:func:`_kept_bins`) and the inverse starts from them: the
    same circular convolution with the other bins' products dropped, in fewer butterflies."""
    helpers = _HELPERS % {"pad": PAD_EVERY, "n": n}
    levels = kept_levels(n, keep)
    if is_pruned(n, levels):
        passes, tables = _passes(levels, n), twiddle_tables(n, levels)[0]
        code = [_prologue(n, levels), _pass(*passes[0], n, "impulses", _levels(*passes[0], n, False, tables),
                                            "shared")]
        code += [_pass(*p, n, "shared", _levels(*p, n, False, tables), "shared") for p in passes[1:]]
        code += [_kept_bins(n, keep, levels)]
        inverse = passes[::-1]
        sources = ["kept"] + ["shared"] * (len(inverse) - 1)
        sinks = ["shared"] * (len(inverse) - 1) + ["out"]
        code += [_pass(*p, n, source, _levels(*p, n, True, tables), sink)
                 for p, source, sink in zip(inverse, sources, sinks)]
        return helpers + "\n".join(code)
    passes, tables = fft_passes(n), twiddle_tables(n, levels)[0]
    group = 1 << passes[-1][1]
    middle = [*_levels(*passes[-1], n, False, tables), *(f"filter(v[{j}], base + {j});" for j in range(group)),
              *_levels(*passes[-1], n, True, tables)]
    if len(passes) == 1:  # n ≤ 2^RADIX_LEVELS: no table (strides < TABLE_STRIDE)
        return helpers + _pass(*passes[0], n, "impulses", middle, "out")
    code = [_prologue(n, levels), _pass(*passes[0], n, "impulses", _levels(*passes[0], n, False), "shared")]
    code += [_pass(*p, n, "shared", _levels(*p, n, False, tables), "shared") for p in passes[1:-1]]
    code += [_pass(*passes[-1], n, "shared", middle, "shared")]
    code += [_pass(*p, n, "shared", _levels(*p, n, True, tables), "shared") for p in passes[-2:0:-1]]
    code += [_pass(*passes[0], n, "shared", _levels(*passes[0], n, True), "out")]
    return helpers + "\n".join(code)


@functools.cache
def convolve_fft_kernel(n: int = FFT_SIZE, block_dim: int = FFT_BLOCK_DIM, keep: int = -1):
    """The overlap-save kernel of FFT size ``n`` (a power of two) for tiles of ``block_dim`` threads (its module's
    block_dim, so that compiling it ahead compiles what runs), keeping the spectrum's bins |k| ≤ ``keep`` (< 0:
    every bin; :func:`overlap_save_snippet`). Launch with ``wp.launch_tiled`` over ``tiles`` tiles (one per
    multiprocessor: a tile holds one's shared memory) with the same block_dim; the tiles take the listed rows in
    turn, their count read on the device (no wait for it on the host), zeroing the impulses they read."""

    options = {"block_dim": block_dim}
    cap = SM_REGISTERS // block_dim if block_dim > 256 else None  # so that one tile's threads fit a multiprocessor
    levels = kept_levels(n, keep)
    kept = shared_extra(n, levels)  # a pruned transform's kept bins and roots, the twiddle tables
    padded = n + n // PAD_EVERY + kept  # shared-memory elements of the tile
    @wp.func_native(overlap_save_snippet(n, keep))
    def overlap_save(tile: wp.tile(dtype=wp.vec2d, shape=(padded,), storage="shared"),
                     impulses: wp.array2d(dtype=wp.float64), slot: int, lo: int, hi: int, start: int, step: int,
                     spectrum: wp.array(dtype=wp.vec2d), twiddles: wp.array(dtype=wp.vec2d), wrapped: int,
                     first: int, last: int, out: wp.array2d(dtype=wp.float32)): ...

    @wp.func_native(_ZERO_SAMPLES)
    def zero_samples(impulses: wp.array2d(dtype=wp.float64), slot: int, lo: int, hi: int): ...

    @wp.kernel(enable_backward=False, module="unique", module_options=options, grid_stride=False,
               cuda_max_registers=cap)
    def convolve_fft(
        # In:
        o: Overlap,  # the impulse trains (zeroed here as they are read), their spans, the pulse's spectrum, twiddles
        rows: wp.array(dtype=wp.int32),  # the slots of the rows the FFTs make (split_spans)
        count: wp.array(dtype=wp.int32),  # [1] how many of them
        tiles: int,  # the launch's tiles
        block: int,  # L = n − taps + 1: outputs per block
        # Out:
        out: wp.array2d(dtype=wp.float32),  # (slots, samples) power [W], zeroed beforehand: only the reach is written
    ):
        """out[slot, i] = Σ_j impulses[slot, j] · taps[i − j − first_lag] [W]: tile t makes the rows t, t + tiles, …
        of the count[0] listed, each row's pairs of blocks of L outputs in turn from the start of the reach of its
        slot rows[row]; then impulses[slot, j] = 0 over the row's touched span [lo, hi], each stretch zeroed once no
        later pair reads it (pair p reads the impulses from its start s_p = origin − first_lag − (taps − 1) on, and
        s_{p+1} = s_p + 2L)."""
        first = wp.tid()
        samples = o.impulses.shape[1]
        wrapped = o.taps - 1
        z = wp.tile_empty(shape=padded, dtype=wp.vec2d, storage="shared")
        for row in range(first, count[0], tiles):
            slot = rows[row]
            lo = o.span[slot, 0]
            hi = o.span[slot, 1]
            reach_hi = wp.min(hi + o.first_lag + wrapped, samples - 1)
            origin = wp.max(lo + o.first_lag, 0)
            cleared = lo  # the impulses below are zero
            while cleared <= hi:
                start = origin - o.first_lag - wrapped  # the pair's first impulse
                end = hi  # the last impulse that no later pair reads
                if origin <= reach_hi:
                    overlap_save(z, o.impulses, slot, lo, hi, start, block, o.spectrum, o.twiddles, wrapped,
                                 origin - wrapped, reach_hi, out)
                    if origin + 2 * block <= reach_hi:
                        end = wp.min(start + 2 * block - 1, hi)
                zero_samples(o.impulses, slot, cleared, end)
                cleared = wp.max(cleared, end + 1)
                origin += 2 * block

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
    listed in ``rows`` (the FFT tiles take those rows only); the other gets an empty span (2³⁰, −1), which both
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
