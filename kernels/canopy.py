"""A turbid-medium canopy on the device: leaf area density in voxels, walked along a ray.

The canopy is a regular grid of voxels (:class:`Canopy`) in the scene's local frame; voxel (ix, iy, iz)
spans ``lower + (ix, iy, iz) * cell`` to ``lower + (ix + 1, iy + 1, iz + 1) * cell``. A ray
``start + t * direction``, t in [t0, t1], is walked voxel by voxel with the 3-D DDA of Amanatides & Woo
(1987): :func:`walk_begin` clips the segment to the grid's box and gives the first voxel, :func:`walk_next`
each following one, as a :class:`VoxelWalk` holding the voxel's index, its leaf area density and the
ray parameters where the ray enters and leaves it (``t_in``, ``t_out``; the path length in it is
``(t_out − t_in) · |direction|``, metres for a unit direction).

Along a ray of |cos zenith| μ, leaves of area density u [m²/m³] with the canopy's leaf angle distribution
extinguish G(μ) u per metre (``g_table``, :mod:`flightsim.scenes.leaf_angles`), so the optical depth of a
segment is G(μ) Σ u·length (:func:`optical_depth`), and a photon that survives with probability 1 − ξ has
its first interaction where the depth reaches −ln(1 − ξ) (:func:`first_interaction`, exact: the depth grows
linearly within a voxel).

Robustness:

* all arithmetic is float64; a plane crossing is always ``(lower + k·cell − start) · (1 / direction)`` for
  the same plane k, so the box's exit and the last voxel's exit are the same number and the voxel lengths
  add up to the clipped segment exactly (each voxel's ``t_in`` is the previous one's ``t_out``);
* a ray crossing an edge or corner (two or three planes at the same t) steps those axes together, so it
  visits no voxel for a zero length there; near ties may give a voxel of length ~1e-12 m;
* a direction component of magnitude below :data:`PARALLEL` is parallel to that axis: the ray stays in the
  voxel layer holding ``start`` on it (the upper voxel where ``start`` lies on a face, the last one on the
  box's upper face); the box is closed: such a ray lying on the box's face walks its outer voxels;
* a segment that misses the box, or meets it for zero length (t0 == t1, a ray grazing an edge), has no
  voxel (``done = 1`` from :func:`walk_begin`);
* a walk takes at most nx + ny + nz steps (every step crosses at least one of the nx + ny + nz − 3
  interior planes it can meet), whatever t0 and t1 are.

Every function returns at once for a canopy with ``present == 0`` (:func:`flightsim.scenes.canopy.no_canopy`):
depth 0, no voxel, no interaction.
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

PARALLEL = wp.constant(wp.float64(1.0e-290))
"""|direction component| below which a ray is taken as parallel to that axis."""

NO_INTERACTION = wp.constant(wp.float64(wp.inf))
"""What :func:`first_interaction` returns for a segment whose optical depth stays below the target."""


@wp.struct
class Canopy:
    """A voxel grid of leaf area density in the local frame (:meth:`flightsim.scenes.canopy.VoxelCanopy.to_device`)."""

    lad: wp.array3d(dtype=wp.float32)  # leaf area density [m²/m³], [ix, iy, iz] = local east, north, up
    lad_flat: wp.array(dtype=wp.float32)  # the same, C order: voxel (ix, iy, iz) at (ix · ny + iy) · nz + iz
    lower: wp.vec3d  # local coordinates [m] of the grid's lower corner
    cell: wp.vec3d  # voxel edge lengths [m] (east, north, up)
    dims: wp.vec3i  # voxels per axis
    g_table: wp.array(dtype=wp.float64)  # G(μ) at μ = |cos zenith| = i / (n − 1), i = 0 … n − 1
    present: wp.int32  # 0: no canopy (every function returns at once: depth 0, no voxel)
    leaf_layers: wp.array3d(dtype=wp.int32)  # per tile of tile × tile columns: lowest leafy layer, one past the highest
    tile: wp.int32  # voxel columns per tile side of leaf_layers


@wp.struct
class VoxelWalk:
    """One voxel of a walk along ``start + t · direction``, t in [t0, t1] (:func:`walk_begin`, :func:`walk_next`)."""

    t_in: wp.float64  # ray parameter where the ray enters this voxel (or t0 where the segment starts inside it)
    t_out: wp.float64  # where it leaves it (or the clipped segment's end)
    lad: wp.float32  # the voxel's leaf area density [m²/m³]
    index: wp.vec3i  # the voxel (ix, iy, iz)
    done: wp.int32  # 1: no voxel (the walk has ended, or the segment misses the grid); the fields above are stale
    # Private stepping state:
    start: wp.vec3d  # the ray's start [m]
    inv_dir: wp.vec3d  # 1 / direction per axis; 0 on parallel axes
    step: wp.vec3i  # +1 or −1 along each axis the ray moves along, 0 on parallel axes
    t_next: wp.vec3d  # per axis, t where the ray leaves the current voxel's layer (+inf on parallel axes)
    t_end: wp.float64  # end of the segment clipped to the grid's box
    steps: wp.int32  # voxels visited so far
    max_steps: wp.int32  # nx + ny + nz: no walk visits more


@wp.func
def _plane_t(c: Canopy, w: VoxelWalk, axis: int, k: int) -> wp.float64:
    """t where the ray crosses plane k (0 … dims) of ``axis``; the one formula for every plane crossing."""
    plane = c.lower[axis] + wp.float64(k) * c.cell[axis]
    return (plane - w.start[axis]) * w.inv_dir[axis]


@wp.func
def _earlier(a: wp.float64, b: wp.float64) -> wp.float64:
    """The smaller of two ray parameters of a walk, which are never NaN: a select (``wp.min`` also orders NaN)."""
    return wp.where(a <= b, a, b)


@wp.func
def _later(a: wp.float64, b: wp.float64) -> wp.float64:
    """The larger of two ray parameters of a walk, which are never NaN: a select (``wp.max`` also orders NaN)."""
    return wp.where(a >= b, a, b)


@wp.func
def _lad(c: Canopy, index: wp.vec3i) -> wp.float32:
    """The leaf area density [m²/m³] of voxel ``index`` (in the grid), read from the flat copy: two products for its
    place rather than one per axis (32-bit: a grid holds at most ``flightsim.scenes.canopy.MAX_VOXELS``)."""
    return c.lad_flat[(index[0] * c.dims[1] + index[1]) * c.dims[2] + index[2]]


@wp.func
def _exit_plane(index: int, step: int) -> int:
    """The plane through which a ray stepping ``step`` (±1) leaves voxel layer ``index``."""
    if step > 0:
        return index + 1
    return index


@wp.func
def g_of(c: Canopy, direction: wp.vec3d) -> wp.float64:
    """G(μ) for a ray along ``direction`` (μ = |cos zenith|), linearly interpolated in ``c.g_table``."""
    n = c.g_table.shape[0]
    if n < 2:
        return c.g_table[0]
    mu = wp.abs(direction[2]) / wp.length(direction)
    x = wp.clamp(mu, wp.float64(0.0), wp.float64(1.0)) * wp.float64(n - 1)
    i = wp.min(int(wp.floor(x)), n - 2)
    f = x - wp.float64(i)
    return c.g_table[i] * (wp.float64(1.0) - f) + c.g_table[i + 1] * f


@wp.func
def walk_begin(c: Canopy, start: wp.vec3d, direction: wp.vec3d, t0: wp.float64, t1: wp.float64) -> VoxelWalk:
    """The first voxel of the walk along ``start + t · direction``, t in [t0, t1], clipped to the grid's box;
    ``done = 1`` when the segment misses the box or meets it for zero length."""
    w = VoxelWalk()
    w.t_in = t0
    w.t_out = t0
    w.lad = wp.float32(0.0)
    w.index = wp.vec3i(0, 0, 0)
    w.done = 1
    w.start = start
    w.steps = 0
    w.max_steps = 0
    if c.present == 0:
        return w
    inv = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    step = wp.vec3i(0, 0, 0)
    miss = int(0)
    for a in range(3):
        d = direction[a]
        if wp.abs(d) < PARALLEL:
            upper = c.lower[a] + wp.float64(c.dims[a]) * c.cell[a]
            if start[a] < c.lower[a] or start[a] > upper:
                miss = 1
        else:
            inv[a] = wp.float64(1.0) / d
            if d > wp.float64(0.0):
                step[a] = 1
            else:
                step[a] = -1
    w.inv_dir = inv
    w.step = step
    if miss != 0:
        return w
    ta = t0
    tb = t1
    for a in range(3):
        if step[a] != 0:
            t_lo = _plane_t(c, w, a, 0)
            t_hi = _plane_t(c, w, a, c.dims[a])
            if step[a] < 0:
                swap = t_lo
                t_lo = t_hi
                t_hi = swap
            ta = wp.max(ta, t_lo)
            tb = wp.min(tb, t_hi)
    if not (ta < tb):  # empty, zero length, or NaN
        return w
    index = wp.vec3i(0, 0, 0)
    t_next = wp.vec3d(wp.float64(wp.inf), wp.float64(wp.inf), wp.float64(wp.inf))
    for a in range(3):
        p = start[a]
        if step[a] != 0:
            p = start[a] + ta * direction[a]
        i = wp.clamp(int(wp.floor((p - c.lower[a]) / c.cell[a])), 0, c.dims[a] - 1)
        if step[a] != 0:
            tn = _plane_t(c, w, a, _exit_plane(i, step[a]))
            if tn <= ta:  # on the exit face (or past it by rounding): the ray is in the next layer already
                j = i + step[a]
                if j >= 0 and j < c.dims[a]:
                    i = j
                    tn = _plane_t(c, w, a, _exit_plane(i, step[a]))
            t_next[a] = tn
        index[a] = i
    w.index = index
    w.t_next = t_next
    w.t_end = tb
    w.t_in = ta
    w.t_out = wp.max(ta, wp.min(wp.min(wp.min(t_next[0], t_next[1]), t_next[2]), tb))
    w.lad = c.lad[index[0], index[1], index[2]]
    w.steps = 1
    w.max_steps = c.dims[0] + c.dims[1] + c.dims[2]
    w.done = 0
    return w


@wp.func
def walk_next(c: Canopy, w: VoxelWalk) -> VoxelWalk:
    """The voxel after ``w`` along the ray; ``done = 1`` past the clipped segment's end or the grid.

    Every axis is stepped by selects, not branches (the ray crosses one axis's plane in most steps, so branches would
    split a warp's lanes three ways): each axis's next exit plane is computed whether or not the ray crosses it at t
    and kept only where it does (parallel axes have ``t_next`` = +inf, never ≤ t)."""
    v = w
    if v.done != 0:
        return v
    if v.t_out >= v.t_end or v.steps >= v.max_steps:
        v.done = 1
        return v
    t = v.t_out
    index = v.index
    t_next = v.t_next
    outside = int(0)
    for a in range(3):
        crossed = t_next[a] <= t  # every axis whose plane the ray crosses at t (edges, corners)
        i = index[a] + v.step[a]
        outside += wp.where(crossed and wp.uint32(i) >= wp.uint32(c.dims[a]), 1, 0)  # i < 0 or i ≥ dims
        index[a] = wp.where(crossed, i, index[a])
        t_next[a] = wp.where(crossed, _plane_t(c, v, a, _exit_plane(i, v.step[a])), t_next[a])
    if outside != 0:
        v.done = 1
        return v
    v.index = index
    v.t_next = t_next
    v.t_in = t
    v.t_out = _later(t, _earlier(_earlier(_earlier(t_next[0], t_next[1]), t_next[2]), v.t_end))
    v.lad = _lad(c, index)
    v.steps = v.steps + 1
    return v


MAX_SPAN_TILES = wp.constant(4)
"""Tiles per axis above which :func:`leaf_span` keeps the whole segment (a far slanted ray)."""


@wp.func
def _column(c: Canopy, axis: int, x: wp.float64) -> int:
    """The voxel column index along ``axis`` (0 east, 1 north) holding coordinate ``x``, clamped to the grid."""
    f = wp.clamp((x - c.lower[axis]) / c.cell[axis], wp.float64(-1.0), wp.float64(c.dims[axis]))
    return wp.clamp(int(wp.floor(f)), 0, c.dims[axis] - 1)


@wp.func
def leaf_span(c: Canopy, start: wp.vec3d, direction: wp.vec3d, t1: wp.float64) -> wp.vec2d:
    """The part [s0, s1] of the segment ``start + t · direction``, t in [0, t1], beyond which it crosses no leaves:
    from one voxel layer above the highest leaves of the tiles of columns its horizontal path may cross (a column's
    margin each side) to one layer below their lowest. A walk over [s0, s1] visits the same leafy voxels with the same
    entry and exit parameters as one over [0, t1] (each is a plane crossing of the same start and direction); s0 > s1
    where the path meets no leaves; [0, t1] for a horizontal ray or one across more than MAX_SPAN_TILES tiles."""
    whole = wp.vec2d(wp.float64(0.0), t1)
    dz = direction[2]
    if c.present == 0 or wp.abs(dz) < PARALLEL:
        return whole
    end = start + t1 * direction
    tile_lo = wp.vec2i(0, 0)
    tile_hi = wp.vec2i(0, 0)
    for a in range(2):
        first = _column(c, a, start[a])
        last = _column(c, a, end[a])
        tile_lo[a] = wp.max(wp.min(first, last) - 1, 0) // c.tile
        tile_hi[a] = wp.min(wp.max(first, last) + 1, c.dims[a] - 1) // c.tile
        if tile_hi[a] - tile_lo[a] >= MAX_SPAN_TILES:
            return whole
    lowest = c.dims[2]
    highest = int(0)
    for i in range(tile_lo[0], tile_hi[0] + 1):
        for j in range(tile_lo[1], tile_hi[1] + 1):
            lowest = wp.min(lowest, c.leaf_layers[i, j, 0])
            highest = wp.max(highest, c.leaf_layers[i, j, 1])
    if highest <= lowest:
        return wp.vec2d(t1, wp.float64(0.0))
    above = (c.lower[2] + wp.float64(highest + 1) * c.cell[2] - start[2]) / dz
    below = (c.lower[2] + wp.float64(lowest - 1) * c.cell[2] - start[2]) / dz
    return wp.vec2d(wp.max(wp.float64(0.0), wp.min(above, below)), wp.min(t1, wp.max(above, below)))


@wp.func
def optical_depth(c: Canopy, start: wp.vec3d, direction: wp.vec3d, t0: wp.float64, t1: wp.float64) -> wp.float64:
    """G(μ) Σ lad · length over the voxels of the segment t in [t0, t1] (unit ``direction``: lengths in m)."""
    if c.present == 0:
        return wp.float64(0.0)
    w = walk_begin(c, start, direction, t0, t1)
    depth = wp.float64(0.0)
    while w.done == 0:
        depth += wp.float64(w.lad) * (w.t_out - w.t_in)
        w = walk_next(c, w)
    if depth > wp.float64(0.0):
        depth *= g_of(c, direction)
    return depth


@wp.func
def survival_depth(xi: wp.float64) -> wp.float64:
    """−ln(1 − ξ): the optical depth at which a photon of uniform random ξ in [0, 1) interacts (accurate
    for small ξ too; +inf for ξ ≥ 1)."""
    if xi >= wp.float64(1.0):
        return wp.float64(wp.inf)
    if xi < wp.float64(1.0e-4):  # the series of −ln(1 − ξ); the next term is below 2e-21
        return xi * (wp.float64(1.0) + xi * (wp.float64(0.5) + xi * (wp.float64(1.0 / 3.0) + xi * wp.float64(0.25))))
    return -wp.log(wp.float64(1.0) - xi)


@wp.func
def first_interaction(c: Canopy, start: wp.vec3d, direction: wp.vec3d, t0: wp.float64, t1: wp.float64,
                      xi: wp.float64) -> wp.float64:
    """The t in [t0, t1] where the optical depth from t0 first reaches −ln(1 − ``xi``) (exact: the depth is
    linear within a voxel; in a voxel with leaves), or :data:`NO_INTERACTION` (+inf, > t1) when the
    segment's depth stays below it (and always for ``present == 0``)."""
    if c.present == 0:
        return NO_INTERACTION
    target = survival_depth(xi)
    w = walk_begin(c, start, direction, t0, t1)
    if w.done != 0:
        return NO_INTERACTION
    g = g_of(c, direction)
    depth = wp.float64(0.0)
    while w.done == 0:
        rate = g * wp.float64(w.lad)  # optical depth per unit t
        if rate > wp.float64(0.0):
            grown = depth + rate * (w.t_out - w.t_in)
            if grown >= target:
                return wp.min(w.t_in + (target - depth) / rate, w.t_out)
            depth = grown
        w = walk_next(c, w)
    return NO_INTERACTION


@wp.func
def voxel_of(c: Canopy, p: wp.vec3d) -> wp.vec3i:
    """The voxel holding local point ``p`` [m] (floor of its offset from ``lower`` in cells); (−1, −1, −1)
    outside the grid (or NaN) and with ``present == 0``."""
    if c.present == 0:
        return wp.vec3i(-1, -1, -1)
    index = wp.vec3i(0, 0, 0)
    for a in range(3):
        f = (p[a] - c.lower[a]) / c.cell[a]
        if not (f >= wp.float64(0.0) and f < wp.float64(c.dims[a])):  # checked as a float: no overflow, NaN out
            return wp.vec3i(-1, -1, -1)
        index[a] = wp.min(int(f), c.dims[a] - 1)
    return index


@wp.func
def lad_at(c: Canopy, p: wp.vec3d) -> wp.float32:
    """Leaf area density [m²/m³] at local point ``p`` [m]; 0 outside the grid."""
    v = voxel_of(c, p)
    if v[0] < 0:
        return wp.float32(0.0)
    return c.lad[v[0], v[1], v[2]]


@wp.kernel
def walk_steps(c: Canopy, starts: wp.array(dtype=wp.vec3d), directions: wp.array(dtype=wp.vec3d),
               steps: wp.array(dtype=wp.int32), depth: wp.array(dtype=wp.float64)):
    """Walk each ray through the whole grid: the voxels it visits and Σ lad · length along it (the voxel walk's
    throughput benchmark, ``flightsim bench`` section forest)."""
    i = wp.tid()
    w = walk_begin(c, starts[i], directions[i], wp.float64(0.0), wp.float64(1.0e30))
    n = int(0)
    total = wp.float64(0.0)
    while w.done == 0:
        n += 1
        total += wp.float64(w.lad) * (w.t_out - w.t_in)
        w = walk_next(c, w)
    steps[i] = n
    depth[i] = total


@wp.kernel
def interactions(c: Canopy, starts: wp.array(dtype=wp.vec3d), directions: wp.array(dtype=wp.vec3d),
                 t_end: wp.float64, xi: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.float64)):
    """Each ray's first interaction with the leaves between t = 0 and ``t_end`` for its uniform deviate ``xi``
    (:data:`NO_INTERACTION` where it has none): a Monte Carlo of photons through the canopy."""
    i = wp.tid()
    out[i] = first_interaction(c, starts[i], directions[i], wp.float64(0.0), t_end, xi[i])
