"""A stand's crowns as leaf area density voxels, on the device: the integrals of
:func:`flightsim.scenes.forest_voxels.crown_volumes` (its module's docstring gives the method), a thread per voxel
column that some crown's bounding box covers.

The thread walks its column's layers from the bottom; in each it adds, tree after tree (ascending), the volume of
the voxel inside that tree's crown, itself the sum of the crown's smooth pieces in the voxel (split at the crown's
ends, the voxel's floor and ceiling and the heights where the crown's radius reaches a side or a corner of the
column), each integrated by Gauss–Legendre after the cosine substitution, with the host's nodes and weights. The
pieces, their nodes and the order of the sums are the NumPy build's, and so are the operations: the module is
compiled without fused multiply-adds (``fuse_fp``), which would change the host's exact zeros such as r² − r·r at a
disc's edge into the rounding error of r² (√ of it: ~1e-8 r, an error of 1e-8 of the voxel where the disc misses a
side). The numbers then agree with the host's to a few float64 ulps (CUDA's asin and the host's may differ in the
last bit), so the float32 densities are the same but for a voxel whose float64 value lies within those ulps of a
float32 rounding boundary, or whose crowns barely touch it (~1e-16 m²/m³ of cancellation either way).
"""
import warp as wp

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})
wp.set_module_options({"fuse_fp": False})  # no fused multiply-adds: the host's roundings (see above)

CONE = wp.constant(0)
ELLIPSOID = wp.constant(1)
CYLINDER = wp.constant(2)
vec8d = wp.types.vector(length=8, dtype=wp.float64)


@wp.func
def _sign(x: wp.float64) -> wp.float64:
    """−1, 0 or 1 (NumPy's sign: 0 for 0)."""
    s = wp.float64(0.0)
    if x > wp.float64(0.0):
        s = wp.float64(1.0)
    elif x < wp.float64(0.0):
        s = wp.float64(-1.0)
    return s


@wp.func
def _primitive(x: wp.float64, r2: wp.float64, scale: wp.float64) -> wp.float64:
    """The circle's primitive S(x) = (x√(r² − x²) + r² asin(x/r)) / 2 [m²] (``scale``: r, or 1 for r = 0)."""
    root = wp.sqrt(wp.max(r2 - x * x, wp.float64(0.0)))
    return wp.float64(0.5) * (x * root + r2 * wp.asin(wp.min(x / scale, wp.float64(1.0))))


@wp.func
def _corner(u: wp.float64, v: wp.float64, a: wp.float64, s_a: wp.float64, b: wp.float64, w: wp.float64,
            r2: wp.float64, scale: wp.float64) -> wp.float64:
    """Signed area [m²] of the disc inside the rectangle between its centre and the corner (u, v), from the corner's
    a = min(|u|, r), S(a), b = min(|v|, r) and w = √(r² − b²)."""
    c = wp.min(w, a)
    return _sign(u) * _sign(v) * (c * b + s_a - _primitive(c, r2, scale))


@wp.func
def disc_square_area(r: wp.float64, x0: wp.float64, x1: wp.float64, y0: wp.float64, y1: wp.float64) -> wp.float64:
    """Area [m²] of the disc of radius ``r`` about (0, 0) inside [x0, x1] × [y0, y1] [m]:
    :func:`flightsim.scenes.forest_voxels.disc_square_area`, the same operations."""
    r2 = r * r
    scale = wp.float64(1.0)
    if r > wp.float64(0.0):
        scale = r
    a0 = wp.min(wp.abs(x0), r)
    a1 = wp.min(wp.abs(x1), r)
    s0 = _primitive(a0, r2, scale)
    s1 = _primitive(a1, r2, scale)
    b0 = wp.min(wp.abs(y0), r)
    b1 = wp.min(wp.abs(y1), r)
    w0 = wp.sqrt(wp.max(r2 - b0 * b0, wp.float64(0.0)))
    w1 = wp.sqrt(wp.max(r2 - b1 * b1, wp.float64(0.0)))
    return (_corner(x1, y1, a1, s1, b1, w1, r2, scale) - _corner(x0, y1, a0, s0, b1, w1, r2, scale)
            - _corner(x1, y0, a1, s1, b0, w0, r2, scale) + _corner(x0, y0, a0, s0, b0, w0, r2, scale))


@wp.func
def radius_fraction(shape: int, t: wp.float64) -> wp.float64:
    """Crown radius as a fraction of the largest at relative height ``t`` (clipped to [0, 1])."""
    t = wp.clamp(t, wp.float64(0.0), wp.float64(1.0))
    f = wp.float64(1.0)
    if shape == CONE:
        f = wp.float64(1.0) - t
    elif shape == ELLIPSOID:
        f = wp.float64(2.0) * wp.sqrt(t * (wp.float64(1.0) - t))
    return f


@wp.func
def _next_boundary(shape: int, q: vec8d, a: wp.float64, hi: wp.float64, bottom: wp.float64,
                   top: wp.float64) -> wp.float64:
    """The least of ``hi`` and the heights in (a, hi) where the crown's radius is q[m] × its largest [m] (each
    q < 1 gives one on a cone's side, two on an ellipsoid's, none on a cylinder's)."""
    length = top - bottom
    b = hi
    for m in range(8):
        if q[m] < wp.float64(1.0) and shape != CYLINDER:
            low = top
            high = top
            if shape == CONE:
                low = bottom + length * (wp.float64(1.0) - q[m])
            else:
                half = wp.float64(0.5) * wp.sqrt(wp.max(wp.float64(1.0) - q[m] * q[m], wp.float64(0.0)))
                low = bottom + length * (wp.float64(0.5) - half)
                high = bottom + length * (wp.float64(0.5) + half)
            low = wp.clamp(low, bottom, top)
            high = wp.clamp(high, bottom, top)
            if low > a and low < b:
                b = low
            if high > a and high < b:
                b = high
    return b


@wp.func
def _piece(a: wp.float64, b: wp.float64, shape: int, bottom: wp.float64, crown_length: wp.float64,
           radius: wp.float64, x0: wp.float64, y0: wp.float64, cell: wp.float64, sub: wp.array(dtype=wp.float64),
           jac: wp.array(dtype=wp.float64)) -> wp.float64:
    """Volume [m³] of the crown inside the column [x0, x0 + cell] × [y0, y0 + cell] (relative to its axis) between
    heights a and b [m], one smooth piece: Σ area(z_n)·jac[n] × (b − a), z_n = a + (b − a)·sub[n]."""
    total = wp.float64(0.0)
    for n in range(sub.shape[0]):
        z = a + (b - a) * sub[n]
        r = radius * radius_fraction(shape, (z - bottom) / crown_length)
        area = wp.clamp(disc_square_area(r, x0, x0 + cell, y0, y0 + cell), wp.float64(0.0), cell * cell)
        total += area * jac[n]
    return total * (b - a)


@wp.func
def _tree_in_voxel(shape: int, k: wp.float64, x0: wp.float64, y0: wp.float64, cell: wp.float64,
                   lower_z: wp.float64, bottom: wp.float64, top: wp.float64, crown_length: wp.float64,
                   radius: wp.float64, sub: wp.array(dtype=wp.float64), jac: wp.array(dtype=wp.float64)) -> wp.float64:
    """Volume [m³] of voxel layer ``k`` of the column whose lower corner is (x0, y0) from the crown's axis [m]
    inside that crown: its pieces' sum, bottom to top (0 where the layer misses the crown)."""
    k0 = wp.floor((bottom - lower_z) / cell)
    lo = bottom
    if k > k0:
        lo = wp.clamp(lower_z + k * cell, bottom, top)
    hi = wp.clamp(lower_z + (k + wp.float64(1.0)) * cell, bottom, top)
    total = wp.float64(0.0)
    dx = wp.max(wp.max(x0, -x0 - cell), wp.float64(0.0))
    dy = wp.max(wp.max(y0, -y0 - cell), wp.float64(0.0))
    if k < k0 or not (hi > lo) or not (wp.sqrt(dx * dx + dy * dy) < radius):
        return total
    x1 = x0 + cell
    y1 = y0 + cell
    q = vec8d(wp.abs(x0), wp.abs(x1), wp.abs(y0), wp.abs(y1), wp.sqrt(x0 * x0 + y0 * y0),
              wp.sqrt(x0 * x0 + y1 * y1), wp.sqrt(x1 * x1 + y0 * y0), wp.sqrt(x1 * x1 + y1 * y1)) / radius
    a = lo
    while a < hi:
        b = _next_boundary(shape, q, a, hi, bottom, top)
        total += _piece(a, b, shape, bottom, crown_length, radius, x0, y0, cell, sub, jac)
        a = b
    return total


@wp.kernel
def column_lad(
    columns: wp.array(dtype=wp.int32),  # flat index i·ny + j of each voxel column a crown's box covers
    first: wp.array(dtype=wp.int32),  # its trees are members[first[c] : first[c + 1]], ascending
    members: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.float64),  # per tree: its axis, local [m]
    y: wp.array(dtype=wp.float64),
    bottom: wp.array(dtype=wp.float64),  # per tree: its crown's lowest and highest z, local [m]
    top: wp.array(dtype=wp.float64),
    crown_length: wp.array(dtype=wp.float64),  # per tree: its crown's length [m] (height − crown base)
    radius: wp.array(dtype=wp.float64),  # per tree: its crown's largest radius [m]
    shape: int,  # CONE, ELLIPSOID or CYLINDER
    lower: wp.vec3d,  # local corner of voxel (0, 0, 0) [m]
    cell: wp.float64,  # voxel side [m]
    ny: int,
    nz: int,
    sub: wp.array(dtype=wp.float64),  # quadrature nodes on [0, 1] after the substitution
    jac: wp.array(dtype=wp.float64),  # their weights × dz/dt / (b − a)
    factor: wp.float64,  # crown leaf area density / cell³ [m²/m³ per m³]
    lad: wp.array(dtype=wp.float32),  # out: (nx·ny·nz) leaf area density [m²/m³], C order; this column's nz
):
    c = wp.tid()
    column = columns[c]
    x0 = lower[0] + wp.float64(column // ny) * cell
    y0 = lower[1] + wp.float64(column % ny) * cell
    for k in range(nz):
        volume = wp.float64(0.0)
        for p in range(first[c], first[c + 1]):
            t = members[p]
            volume += _tree_in_voxel(shape, wp.float64(k), x0 - x[t], y0 - y[t], cell, lower[2], bottom[t], top[t],
                                     crown_length[t], radius[t], sub, jac)
        lad[column * nz + k] = wp.float32(volume * factor)
