"""Photons to points on the device: angle cells, the photons sorted by (cell, height bin) keys, then one thread
per cell for its fullest pair of adjacent height bins, background rejection and the windowed mean (the algorithm
is described in flightsim.scoring.photon_grid, which drives these kernels).

A photon is *valid* when its position is finite and its cell's column and row are ≥ 0. Keys are
``cell · stride + zbin`` (int64) with ``cell = row · columns + column`` and ``stride`` = highest height bin + 2,
so bin + 1 never leaves its cell; invalid photons get the key ``invalid`` (above every valid key) and sort last.
The sort is stable, so a cell's photons are added up in one order on the CPU and on a GPU alike (height bin,
then the order they were made in): the points do not depend on the order the threads ran in. The photons'
positions are gathered into that order once (:func:`cell_bounds`), so that each cell's thread reads its own
photons side by side rather than through the sort's permutation.
"""
from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

PACK_LOW = wp.constant(wp.int64(0x7FFFFFFF))  # the bin's place in a packed (window, bin) best pair


@wp.func
def valid(p: wp.vec3d, cell: wp.vec2i) -> bool:
    """Finite position inside the grid."""
    return wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]) and cell[0] >= 0 and cell[1] >= 0


@wp.func
def angle_cell(d: wp.vec3f, half_field: wp.float64, cells: int) -> wp.vec2i:
    """Column and row of a downward direction in a cells × cells grid of angles from nadir over
    ±half_field [rad] (atan of east and of north over the depth); (−1, −1) outside."""
    depth = -wp.float64(d[2])
    scale = wp.float64(2.0) * half_field
    col = int(wp.floor((wp.atan2(wp.float64(d[0]), depth) + half_field) / scale * wp.float64(cells)))
    row = int(wp.floor((wp.atan2(wp.float64(d[1]), depth) + half_field) / scale * wp.float64(cells)))
    if col < 0 or col >= cells or row < 0 or row >= cells:
        return wp.vec2i(-1, -1)
    return wp.vec2i(col, row)


@wp.kernel
def angle_cells(directions: wp.array(dtype=wp.vec3f), half_field: wp.float64, cells: int,
                out: wp.array(dtype=wp.vec2i)):
    """The angle cell of every direction."""
    i = wp.tid()
    out[i] = angle_cell(directions[i], half_field, cells)


@wp.kernel
def append_photons(points: wp.array(dtype=wp.vec3d), directions: wp.array(dtype=wp.vec3f),
                   flags: wp.array(dtype=wp.int8), half_field: wp.float64, cells: int, base: int,
                   xyz: wp.array(dtype=wp.vec3d), cell: wp.array(dtype=wp.vec2i),
                   signal_count: wp.array(dtype=wp.int64)):
    """Copy a chunk's photons to a frame's arrays from ``base``, with their angle cells; count the signal
    photons into 1024 counters (spread so the atomics do not queue on one address)."""
    i = wp.tid()
    xyz[base + i] = points[i]
    cell[base + i] = angle_cell(directions[i], half_field, cells)
    if flags[i] != wp.int8(0):
        wp.atomic_add(signal_count, i & 1023, wp.int64(1))


@wp.kernel
def extent(xyz: wp.array(dtype=wp.vec3d), cell: wp.array(dtype=wp.vec2i), n: int, threads: int,
           zmin: wp.array(dtype=wp.float64), zmax: wp.array(dtype=wp.float64), top: wp.array(dtype=wp.vec2i)):
    """Per thread (grid-stride over the valid photons): lowest and highest height [m] and highest
    column and row; the host reduces the threads' values."""
    t = wp.tid()
    lo = wp.float64(wp.inf)
    hi = wp.float64(-wp.inf)
    c = wp.vec2i(-1, -1)
    i = t
    while i < n:
        if valid(xyz[i], cell[i]):
            lo = wp.min(lo, xyz[i][2])
            hi = wp.max(hi, xyz[i][2])
            c = wp.max(c, cell[i])
        i += threads
    zmin[t] = lo
    zmax[t] = hi
    top[t] = c


@wp.kernel
def merge_extent(zmin: wp.array(dtype=wp.float64), zmax: wp.array(dtype=wp.float64), top: wp.array(dtype=wp.vec2i),
                 n: int, threads: int, out_min: wp.array(dtype=wp.float64), out_max: wp.array(dtype=wp.float64),
                 out_top: wp.array(dtype=wp.vec2i)):
    """Per thread (grid-stride over ``n`` partials of :func:`extent`): their lowest and highest height [m] and
    highest column and row, so the host reads a few partials rather than every thread's."""
    t = wp.tid()
    lo = wp.float64(wp.inf)
    hi = wp.float64(-wp.inf)
    c = wp.vec2i(-1, -1)
    i = t
    while i < n:
        lo = wp.min(lo, zmin[i])
        hi = wp.max(hi, zmax[i])
        c = wp.max(c, top[i])
        i += threads
    out_min[t] = lo
    out_max[t] = hi
    out_top[t] = c


@wp.kernel
def bin_keys(xyz: wp.array(dtype=wp.vec3d), cell: wp.array(dtype=wp.vec2i), lo: wp.float64, bin_m: wp.float64,
             stride: wp.int64, columns: wp.int64, invalid: wp.int64,
             keys: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32)):
    """The (cell, height bin) key of every photon."""
    i = wp.tid()
    order[i] = i
    keys[i] = invalid
    if valid(xyz[i], cell[i]):
        zbin = wp.int64(wp.floor((xyz[i][2] - lo) / bin_m))
        keys[i] = (wp.int64(cell[i][1]) * columns + wp.int64(cell[i][0])) * stride + zbin


@wp.kernel
def cell_bounds(keys: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32), xyz: wp.array(dtype=wp.vec3d),
                n: int, stride: wp.int64, invalid: wp.int64, first: wp.array(dtype=wp.int32),
                last: wp.array(dtype=wp.int32), sorted_xyz: wp.array(dtype=wp.vec3d)):
    """Where each cell's photons start and end in the sorted keys (cells without photons keep 0, 0), and the valid
    photons' positions in sorted order (``sorted_xyz[j] = xyz[order[j]]`` [m])."""
    j = wp.tid()
    key = keys[j]
    if key == invalid:
        return
    sorted_xyz[j] = xyz[order[j]]
    c = key / stride
    if j == 0 or keys[j - 1] / stride != c:
        first[int(c)] = j
    if j + 1 == n or keys[j + 1] == invalid or keys[j + 1] / stride != c:
        last[int(c)] = j + 1


@wp.func
def _pack(window: int, zbin: wp.int64) -> wp.int64:
    """A pair of bins as _best_pair ranks them: window · 2³² + (2³¹ − 1 − bin) (ties to the lower bin)."""
    return (wp.int64(window) << wp.int64(32)) | (PACK_LOW - zbin)


@wp.func
def _best_pair(keys: wp.array(dtype=wp.int64), a: int, b: int, base: wp.int64):
    """The fullest pair of adjacent height bins (an occupied bin and the next one up) of the sorted keys[a:b] (bins
    key − base, a < b), the lowest on a tie, packed by :func:`_pack`. One pass over the keys: each run of one bin
    settles the pair of the run before it (that run's photons, and this run's when its bin is the next one up)."""
    best = wp.int64(0)
    prev_bin = wp.int64(-2)
    prev_count = int(0)
    run_bin = keys[a] - base
    run_count = int(0)
    for j in range(a, b):
        zbin = keys[j] - base
        if zbin != run_bin:
            if prev_count > 0:
                best = wp.max(best, _pack(prev_count + wp.where(run_bin == prev_bin + wp.int64(1), run_count, 0),
                                          prev_bin))
            prev_bin = run_bin
            prev_count = run_count
            run_bin = zbin
            run_count = 0
        run_count += 1
    if prev_count > 0:
        best = wp.max(best, _pack(prev_count + wp.where(run_bin == prev_bin + wp.int64(1), run_count, 0), prev_bin))
    return wp.max(best, _pack(run_count, run_bin))


@wp.func
def _window_sum(sorted_xyz: wp.array(dtype=wp.vec3d), keys: wp.array(dtype=wp.int64), a: int, b: int,
                base: wp.int64, lo: wp.float64, bin_m: wp.float64, z: wp.float64, window_m: wp.float64):
    """(count, sum of positions [m]) of the sorted photons [a, b) within ``window_m`` of height ``z``, added in their
    sorted order (height bin, then the order they were made in); only the photons of the bins the window reaches are
    read, and no key above them."""
    low = wp.int64(wp.floor((z - window_m - lo) / bin_m)) - wp.int64(1)
    high = wp.int64(wp.floor((z + window_m - lo) / bin_m)) + wp.int64(1)
    count = int(0)
    total = wp.vec3d()
    for j in range(a, b):
        zbin = keys[j] - base
        if zbin > high:  # the keys are sorted: none further on is in the window
            break
        if zbin >= low:
            p = sorted_xyz[j]
            if wp.abs(p[2] - z) <= window_m:
                count += 1
                total += p
    return count, total


@wp.kernel
def cell_points(sorted_xyz: wp.array(dtype=wp.vec3d), keys: wp.array(dtype=wp.int64), first: wp.array(dtype=wp.int32),
                last: wp.array(dtype=wp.int32), stride: wp.int64, lo: wp.float64, bin_m: wp.float64, min_count: int,
                window_m: wp.float64, totals: wp.array(dtype=wp.int32), centre: wp.array(dtype=wp.float64),
                peak: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), sums: wp.array(dtype=wp.vec3d)):
    """One cell's surface from its photons (sorted by height bin): the fullest pair of adjacent height bins is the
    surface when it holds >= min_count photons and beats the cell's own background per pair of bins by 5σ
    (``centre``: the pair's middle height [m], else NaN; ``peak``: its photons); then the photons within
    ``window_m`` of that centre are summed, and once more within ``window_m`` of their mean (``count``, ``sums``
    [m]). ``totals``: the cell's photons."""
    c = wp.tid()
    a = first[c]
    b = last[c]
    totals[c] = b - a
    centre[c] = wp.float64(wp.nan)
    peak[c] = 0
    count[c] = 0
    sums[c] = wp.vec3d()
    if b == a:
        return
    base = wp.int64(c) * stride
    best = _best_pair(keys, a, b, base)
    window = int(best >> wp.int64(32))
    zbin = PACK_LOW - (best & PACK_LOW)
    background = wp.float64(2.0) * wp.float64(wp.max(b - a - window, 0)) / wp.float64(wp.max(stride - wp.int64(1), wp.int64(1)))
    need = wp.max(wp.float64(min_count), background + wp.float64(5.0) * wp.sqrt(background))
    if wp.float64(window) < need:
        return
    z = lo + wp.float64(zbin + wp.int64(1)) * bin_m
    peak[c] = window
    n, total = _window_sum(sorted_xyz, keys, a, b, base, lo, bin_m, z, window_m)
    if n > 0:
        z = total[2] / wp.float64(n)
        n, total = _window_sum(sorted_xyz, keys, a, b, base, lo, bin_m, z, window_m)
    centre[c] = z
    count[c] = n
    sums[c] = total


@wp.kernel
def point_flags(centre: wp.array(dtype=wp.float64), count: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """1 for an accepted cell whose window holds photons (it becomes a point)."""
    c = wp.tid()
    flags[c] = 0
    if not wp.isnan(centre[c]) and count[c] > 0:
        flags[c] = 1


@wp.kernel
def compact_points(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), columns: int,
                   count: wp.array(dtype=wp.int32), sums: wp.array(dtype=wp.vec3d), peak: wp.array(dtype=wp.int32),
                   points: wp.array(dtype=wp.vec3d), cells: wp.array(dtype=wp.vec2i),
                   photons: wp.array(dtype=wp.int32), peaks: wp.array(dtype=wp.int32)):
    """Each point (mean of its window) at its cell's place in row-major cell order."""
    c = wp.tid()
    if flags[c] == 0:
        return
    k = offsets[c]
    points[k] = sums[c] / wp.float64(count[c])
    cells[k] = wp.vec2i(c % columns, c / columns)
    photons[k] = count[c]
    peaks[k] = peak[c]


@wp.kernel
def occupied(totals: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """1 for a cell holding any photon."""
    c = wp.tid()
    flags[c] = wp.where(totals[c] > 0, 1, 0)
