"""Large-footprint waveforms summed from an ALS point cloud (the GEDI simulator's method; the float64 model and
the method's notes: ``flightsim/instrument/cloud_waveform_model.py``).

One thread block per footprint. The points are sorted by the cells of a horizontal grid, row by row, so the
cells of one row that a footprint reaches are one run of points: the block walks the rows its search region
covers (a disc of radius cut σ_f / cos θ swept along the axis's horizontal offsets over the cloud's heights: the
region every point within cut σ_f of the axis lies in) and, per row, the run of the cells within the region's
chord; its threads take the run's points in turn. A point within cut σ_f of the axis adds its weight
w exp(−ρ²/2σ_f²) to a histogram in shared memory (ground and the rest apart) of ``sub`` bins per sample,
split between the two bins around its range in proportion to its distance from each (its weight and first
moment kept exactly, so a point's range error is nil to first order; the split widens each pulse by at most
bin²/4 in variance), through the block's shared-memory atomics: no global atomics. The block then convolves
the histogram with the pulse (Gaussian, sampled at the bins over ±PULSE_SIGMAS σ_r, as a density [1/m]) at each
sample and divides by the footprint's total weight, so ∫ rx dr = 1 as the model's.

Units: local metres (float32: a cloud's local frame keeps |x|, |y| within ~1e4 m, 1 mm); ranges in bins of
the histogram (``inv_bin`` [1/m]).
"""
import functools

import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

PULSE_SIGMAS = 5.0  # the pulse's half length [σ_r]: beyond it 5.7e-7 of its energy


@wp.struct
class CloudGrid:
    """The points sorted by grid cell (cell (i, j) = j·nx + i, rows of constant j consecutive)."""

    points: wp.array(dtype=wp.vec4f)  # x, y, z local [m]; weight (ρ, normalised), negative for a ground point
    cell_start: wp.array(dtype=wp.int32)  # first point of each cell; the last entry is the number of points
    x0: wp.float32  # the grid's lower-left corner, local [m]
    y0: wp.float32
    cell: wp.float32  # cell side [m]
    nx: wp.int32
    ny: wp.int32


@wp.struct
class CloudBeamParams:
    """The beam, the search region and the histogram."""

    d: wp.vec3f  # unit beam direction, pointing down
    centre_z: wp.float32  # local height where the axis passes through a footprint's centre [m]
    inv_two_sigma2: wp.float32  # 1 / (2 σ_f²) [1/m²]
    cut2: wp.float32  # (cut σ_f)²: points farther from the axis are left out [m²]
    near2: wp.float32  # (3 σ_f)²: a point this close counts the footprint as inside the cloud [m²]
    reach: wp.float32  # radius of the search disc, cut σ_f / cos θ [m]
    seg_lo: wp.vec2f  # least horizontal offset of the axis from the centre over the cloud's heights [m]
    seg_hi: wp.vec2f  # greatest [m]
    inv_bin: wp.float32  # 1 / histogram bin [1/m]
    sub: wp.int32  # histogram bins per sample
    pad: wp.int32  # histogram bins before the first sample: the pulse's half length
    samples: wp.int32


@wp.kernel
def cloud_cells(xyz: wp.array(dtype=wp.vec3d), x0: wp.float64, y0: wp.float64, cell: wp.float64, nx: int, ny: int,
                keys: wp.array(dtype=wp.int32), order: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32)):
    """Each point's grid cell (row-major, the last column and row taking the highest edge) as its sort key, its
    index as the value sorted with it, and each cell's count of points."""
    i = wp.tid()
    p = xyz[i]
    key = wp.min(int((p[1] - y0) / cell), ny - 1) * nx + wp.min(int((p[0] - x0) / cell), nx - 1)
    keys[i] = key
    order[i] = i
    wp.atomic_add(counts, key, 1)


@wp.kernel
def cloud_points(xyz: wp.array(dtype=wp.vec3d), weights: wp.array(dtype=wp.float32), order: wp.array(dtype=wp.int32),
                 points: wp.array(dtype=wp.vec4f)):
    """The points in their cells' order (``order``) as CloudGrid holds them: float32 x, y, z and ``weights`` (negative
    for a ground point)."""
    i = wp.tid()
    j = order[i]
    p = xyz[j]
    points[i] = wp.vec4f(wp.float32(p[0]), wp.float32(p[1]), wp.float32(p[2]), weights[j])


@wp.func
def _rows(g: CloudGrid, b: CloudBeamParams, c: wp.vec2f):
    """First and last grid row of the search region (last < first: none)."""
    lo = (c[1] + b.seg_lo[1] - b.reach - g.y0) / g.cell
    hi = (c[1] + b.seg_hi[1] + b.reach - g.y0) / g.cell
    lo = wp.clamp(lo, -1.0, wp.float32(g.ny))
    hi = wp.clamp(hi, -1.0, wp.float32(g.ny))
    return wp.max(int(wp.floor(lo)), 0), wp.min(int(wp.floor(hi)), g.ny - 1)


@wp.func
def _row_run(g: CloudGrid, b: CloudBeamParams, c: wp.vec2f, j: int):
    """First and end (exclusive) point of the cells of row ``j`` within the search region's chord."""
    band0 = g.y0 + wp.float32(j) * g.cell
    dy = wp.max(wp.max(band0 - (c[1] + b.seg_hi[1]), (c[1] + b.seg_lo[1]) - (band0 + g.cell)), 0.0)
    first = int(0)
    end = int(0)
    if dy < b.reach:
        half = wp.sqrt(b.reach * b.reach - dy * dy)
        lo = wp.clamp((c[0] + b.seg_lo[0] - half - g.x0) / g.cell, -1.0, wp.float32(g.nx))
        hi = wp.clamp((c[0] + b.seg_hi[0] + half - g.x0) / g.cell, -1.0, wp.float32(g.nx))
        i0 = wp.max(int(wp.floor(lo)), 0)
        i1 = wp.min(int(wp.floor(hi)), g.nx - 1)
        if i0 <= i1:
            first = g.cell_start[j * g.nx + i0]
            end = g.cell_start[j * g.nx + i1 + 1]
    return first, end


@functools.cache
def cloud_waveform_kernel(bins: int):
    """The waveform kernel for a shared histogram of ``bins`` bins per component (launch tiled, one block per
    footprint)."""

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
    def cloud_waveforms(
        # In:
        g: CloudGrid,
        b: CloudBeamParams,
        pulse: wp.array(dtype=wp.float32),  # the pulse at bin offsets −pad … pad, a density [1/m]
        centres: wp.array(dtype=wp.vec2f),  # footprint centres, local [m]
        origin_bin: wp.array(dtype=wp.float32),  # histogram coordinate of each axis's point at centre_z
        # Out:
        rx: wp.array2d(dtype=wp.float32),  # (F, samples) [1/m]
        ground: wp.array2d(dtype=wp.float32),
        canopy: wp.array2d(dtype=wp.float32),
        near: wp.array(dtype=wp.int32),  # points within 3 σ_f of each axis
    ):
        f, lane = wp.tid()
        hist = wp.tile_zeros(shape=(2, bins), dtype=wp.float32, storage="shared")
        c = centres[f]
        axis = wp.vec3f(c[0], c[1], b.centre_z)
        u0 = origin_bin[f]
        total = wp.float32(0.0)
        close = int(0)
        rows = _rows(g, b, c)
        for j in range(rows[0], rows[1] + 1):
            run = _row_run(g, b, c, j)
            for base in range(run[0], run[1], wp.block_dim()):
                k = base + lane
                has = False
                kind = int(0)
                at = int(0)
                w0 = wp.float32(0.0)
                w1 = wp.float32(0.0)
                if k < run[1]:
                    p = g.points[k]
                    q = wp.vec3f(p[0], p[1], p[2]) - axis
                    t = wp.dot(q, b.d)
                    across = q - t * b.d
                    rho2 = wp.dot(across, across)
                    if rho2 < b.near2:
                        close += 1
                    if rho2 <= b.cut2:
                        w = wp.abs(p[3]) * wp.exp(-rho2 * b.inv_two_sigma2)
                        total += w
                        u = u0 + t * b.inv_bin
                        cell = wp.floor(u)
                        if cell >= 0.0 and cell < wp.float32(bins - 1):
                            has = True
                            at = int(cell)
                            w1 = w * (u - cell)
                            w0 = w - w1
                            if p[3] >= 0.0:
                                kind = 1
                wp.tile_scatter_add(hist, kind, at, w0, has)
                wp.tile_scatter_add(hist, kind, at + 1, w1, has)
        weight = wp.tile_extract(wp.tile_sum(wp.tile(total)), 0)
        count = wp.tile_extract(wp.tile_sum(wp.tile(close)), 0)
        if lane == 0:
            near[f] = count
        scale = wp.float32(0.0)
        if weight > 0.0:
            scale = 1.0 / weight
        taps = 2 * b.pad + 1
        for i in range(lane, b.samples, wp.block_dim()):
            first = i * b.sub
            sum_g = wp.float32(0.0)
            sum_c = wp.float32(0.0)
            for m in range(taps):
                sum_g += pulse[m] * hist[0, first + m]
                sum_c += pulse[m] * hist[1, first + m]
            ground[f, i] = sum_g * scale
            canopy[f, i] = sum_c * scale
            rx[f, i] = (sum_g + sum_c) * scale

    return cloud_waveforms
