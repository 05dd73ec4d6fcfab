"""Per-beam kernels: fire the emitter's beams, deflect them, ray-cast the scene, add the ranging
errors, georeference, and either keep each return (points mode) or reduce the returns to per-plane
moments (statistics mode).

Kernels are built for one instrument (:class:`kernels.parts.Instrument`: its emitter and deflector
functions and parameter structs) and specialised for the features a run asks for (``wp.static``),
so a part or feature that is off costs nothing per beam. Work is done where it varies: what
depends only on the beam (the emitter's direction, the deflector's beam stage, the rigid-array
rotation) once per run in a table, what depends only on the pulse (the deflector's pulse stage:
the wedge's back-face normal, the galvo's mirror normals; the on-axis ray of the nominal model)
once per pulse in the pulse table, and only the rest per beam.
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp

from kernels.frames import (POSE_ROWS, ROW_ORIGIN, ROW_PHI, ROW_PULSE, ROW_RIGHT, ROW_ROT, ROW_SEED, get3, get33, put3,
                            put33)
from kernels.optics import rigid_array_rotation
from kernels.parts import Instrument, standard_normal64

wp.set_module_options({"enable_backward": False})

STATUS_MISS = wp.constant(0)
STATUS_RETURN = wp.constant(1)
STATUS_TIR = wp.constant(2)
HALF_LIGHT_SPEED = wp.constant(wp.float64(149896229.0))  # c / 2 [m/s]: one-way range per time of flight

COUNT_TIR = 0
COUNT_MISS = 1
COUNT_EDGE = 2  # returns left out of the statistics for lying within the edge buffer

# statistics-mode record codes of slots that do not count (a plane id otherwise)
CODE_MISS = wp.constant(-1)
CODE_TIR = wp.constant(-2)
CODE_EDGE = wp.constant(-3)  # a return within the edge buffer of its plane's boundary
CODE_NEAR = wp.constant(-4)  # CODE_NEAR − plane id: a return on that plane still to be checked against the buffer
CODE_SCORED = wp.constant(-100)  # _left_out's answer for a scored return (never stored: its group is)

vec6d = wp.types.vector(6, wp.float64)


@wp.struct
class EdgeGrid:
    """A grid over the scene's x–y extent marking the cells a plane boundary may come within the
    edge cap of; a return in an unmarked cell is at least the cap from every boundary, so the
    boundary query is skipped for it."""

    near: wp.array2d(dtype=wp.uint8)  # [ix, iy]: 1 where a boundary may be within the cap
    origin: wp.vec2f  # lower corner of cell (0, 0) [m, local]
    inv_cell: wp.float32  # 1 / cell side [1/m]


@wp.struct
class RangeErrors:
    """The ranging chain's systematic and quantisation errors (seed paper §2.1), applied to the truth."""

    tdc_bin: wp.float32  # TDC bin as one-way range, c·τ/2 [m]; start and stop each rounded on its own clock phase
    drift: wp.float32  # clock frequency drift e_df: the range reads R·(1 + e_df)
    delays: wp.array(dtype=wp.float32)  # fixed delay of each beam's channel, as one-way range [m]


@wp.struct
class PoseErrors:
    """Errors of the pose the processing believes (platform and mounting), applied to the truth."""

    mount: wp.mat33d  # boresight error: the true sensor axes in the believed sensor frame
    position_sigma: wp.float64  # POS position noise per local axis and pulse, 1σ [m]
    attitude_sigma: wp.float64  # POS attitude noise about each sensor axis per pulse, 1σ [rad]


POSE_STREAM = wp.constant(0x2545F491)  # seed key of the pose-noise random stream


@wp.func
def _small_rotation(a: wp.vec3d):
    """The rotation matrix of rotation vector ``a`` [rad] (Rodrigues)."""
    angle = wp.length(a)
    eye = wp.identity(n=3, dtype=wp.float64)
    if angle == wp.float64(0.0):
        return eye
    k = a / angle
    skew = wp.mat33d(wp.float64(0.0), -k[2], k[1], k[2], wp.float64(0.0), -k[0], -k[1], k[0], wp.float64(0.0))
    return eye + wp.sin(angle) * skew + (wp.float64(1.0) - wp.cos(angle)) * (skew * skew)


@wp.func
def _true_pose(pulses: wp.array2d(dtype=wp.float64), p: int, pose: PoseErrors):
    """(position offset [m, local], rotation true sensor ← believed sensor) of pulse p: the boresight
    error, then the POS noise keyed by (seed, pulse); pulse_optics writes it once for the pulse's beams."""
    shift = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    turn = pose.mount
    if pose.position_sigma > wp.float64(0.0) or pose.attitude_sigma > wp.float64(0.0):
        state = wp.rand_init(int(pulses[ROW_SEED, p]) ^ POSE_STREAM,
                             int(wp.int64(pulses[ROW_PULSE, p]) % wp.int64(2147483647)))
        x, state = standard_normal64(state)
        y, state = standard_normal64(state)
        z, state = standard_normal64(state)
        shift = pose.position_sigma * wp.vec3d(x, y, z)
        rx, state = standard_normal64(state)
        ry, state = standard_normal64(state)
        rz, state = standard_normal64(state)
        turn = turn * _small_rotation(pose.attitude_sigma * wp.vec3d(rx, ry, rz))
    return shift, turn


@functools.cache
def scan_struct(instrument: Instrument) -> type:
    """The struct of everything a slot needs besides its pose, for one instrument's parts."""

    @wp.struct
    class Scan:
        mesh: wp.uint64
        max_range: wp.float32  # [m]
        per_pulse: wp.int32  # beams per pulse
        emitter: instrument.emitter.params
        truth: instrument.deflector.params
        believed: instrument.deflector.params  # the deflector the georeferencing believes in
        noise_sigma: wp.float32  # Gaussian range noise, 1σ [m]
        ranging: RangeErrors
        pose: PoseErrors
        boundary: wp.uint64  # BVH of the plane-boundary segments (edge buffer queries)
        boundary_a: wp.array(dtype=wp.vec3f)  # segment end points [m, local]
        boundary_b: wp.array(dtype=wp.vec3f)
        edge_cap: wp.float32  # edge distances are measured up to this [m]
        edge_grid: EdgeGrid  # where the boundary query can be skipped
        lut_directions: wp.array2d(dtype=wp.vec3f)  # [φ sample, beam] exit directions (optics "lut")
        lut_exits: wp.array2d(dtype=wp.vec3f)  # exit points [m]; a zero direction marks reflection
        beam_truth: wp.array(dtype=wp.vec3d)  # per-beam deflector state of the true deflector
        beam_believed: wp.array(dtype=wp.vec3d)  # ... of the deflector the processing believes in
        beam_rigid: wp.array(dtype=wp.quatd)  # rigid-array rotation Q of each beam
        vertices64: wp.array(dtype=wp.vec3d)  # scene vertices in float64 (float64 optics path) [m]
        indices: wp.array(dtype=wp.int32)  # 3 per triangle
        padded: wp.uint64  # BVH of slightly padded triangle boxes, for rays the mesh query misses

    return Scan


@dataclass(frozen=True)
class Features:
    """What a kernel build evaluates per beam."""

    exact: bool = True  # georeference by the exact model
    nominal: bool = True  # georeference by the rigid-array model
    believed_is_truth: bool = True  # processing prism == simulated prism: reuse the traced ray
    with_truth: bool = False  # keep the true hit point
    noisy: bool = False  # Gaussian range noise
    ranging: bool = False  # ranging-chain errors: channel delays, clock drift, TDC quantisation
    pose: bool = False  # pose errors on the truth: boresight error, POS position and attitude noise
    edges: bool = False  # measure the true hit's distance to its plane boundary
    optics: str = "float32"  # "float32"; "float64" (optics, hit and georeferencing in float64, the ray
    # cast itself in float32 then refined on the hit triangle); "lut" (float32, exit rays tabulated over φ)


@dataclass(frozen=True)
class Rows:
    """Rows of the per-pulse table (kernels.frames) that hold, in float64, what the optics of one
    pulse share across its beams: the true deflector's pulse stage, the believed one's, and (for a
    deflector with the rigid-array model) the believed on-axis ray."""

    truth: int  # deflector.pulse_rows rows
    believed: int  # deflector.pulse_rows rows
    axis_direction: int  # 3 rows: exit direction of the on-axis ray (believed deflector)
    axis_exit: int  # 3 rows: its exit point [m]
    axis_ok: int  # 1 where the on-axis ray leaves the believed deflector
    true_pose: int  # 12 rows with pose errors: the truth's position offset [m, local], then R_true←believed; else -1
    total: int  # rows of the table


def pulse_rows(instrument: Instrument, pose: bool = False) -> Rows:
    """The pulse-table row layout of an instrument (with the true-pose rows when ``pose``)."""
    n = instrument.deflector.pulse_rows
    nominal = 7 if instrument.deflector.rigid_nominal else 0
    end = POSE_ROWS + 2 * n + nominal
    return Rows(POSE_ROWS, POSE_ROWS + n, POSE_ROWS + 2 * n, POSE_ROWS + 2 * n + 3, POSE_ROWS + 2 * n + 6,
                end if pose else -1, end + 12 if pose else end)


@functools.cache
def beam_table_kernel(instrument: Instrument):
    """Kernel tabulating the per-beam part of the optics, in float64, once per run (one thread per beam)."""
    deflector = instrument.deflector
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique")
    def beam_table(scan: Scan):  # Out: scan.beam_truth, beam_believed, beam_rigid
        b = wp.tid()
        s1 = instrument.emitter.direction(b, scan.emitter)
        scan.beam_truth[b] = deflector.beam_stage(s1, scan.truth)
        scan.beam_believed[b] = deflector.beam_stage(s1, scan.believed)
        scan.beam_rigid[b] = rigid_array_rotation(s1)

    return beam_table


@functools.cache
def pulse_optics_kernel(instrument: Instrument, pose: bool = False):
    """Kernel filling the per-pulse optics rows of a chunk's pulse table (float64), one thread per pulse,
    and with ``pose`` the pulse's true pose (boresight error and POS noise, shared by its beams)."""
    deflector = instrument.deflector
    Scan = scan_struct(instrument)
    rows = pulse_rows(instrument, pose)
    row_pose = rows.true_pose
    row_truth, row_believed = rows.truth, rows.believed
    row_direction, row_exit, row_ok = rows.axis_direction, rows.axis_exit, rows.axis_ok

    @wp.kernel(module="unique")
    def pulse_optics(
        scan: Scan,
        # In: the pose rows; out: the optics rows
        table: wp.array2d(dtype=wp.float64),
    ):
        p = wp.tid()
        deflector.pulse_stage(table, row_truth, p, scan.truth)
        deflector.pulse_stage(table, row_believed, p, scan.believed)
        if wp.static(deflector.rigid_nominal):
            axis = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
            direction, exit_point, ok = deflector.finish(deflector.beam_stage(axis, scan.believed), table,
                                                         row_believed, p, scan.believed)
            put3(table, row_direction, p, direction)
            put3(table, row_exit, p, exit_point)
            table[row_ok, p] = wp.where(ok, wp.float64(1.0), wp.float64(0.0))
        if wp.static(pose):
            shift, turn = _true_pose(table, p, scan.pose)
            put3(table, row_pose, p, shift)
            put33(table, row_pose + 3, p, turn)

    return pulse_optics


@wp.func
def signed_off_nadir(direction: wp.vec3f, right: wp.vec3f):
    """Signed off-nadir angle of a local-frame direction [deg]; positive towards the right wing."""
    off_nadir = wp.acos(wp.clamp(-direction[2], -1.0, 1.0))
    return wp.where(wp.dot(direction, right) < 0.0, -off_nadir, off_nadir) * 57.29577951308232


@wp.func
def _gaussian(state: wp.uint32):
    """(standard normal deviate, advanced state) by Box–Muller, the two uniforms drawn in separate
    statements; the caller carries on with the returned state (Warp passes it by value)."""
    u1 = wp.randf(state)
    u2 = wp.randf(state)
    return wp.sqrt(-2.0 * wp.log(wp.max(u1, 1.0e-12))) * wp.cos(6.283185307179586 * u2), state


@wp.func
def _segment_distance(p: Any, a: Any, b: Any):
    """Distance from point p to the segment a–b (2-D or 3-D) [m]."""
    ab = b - a
    u = wp.clamp(wp.dot(p - a, ab) / wp.max(wp.dot(ab, ab), type(ab[0])(1.0e-20)), type(ab[0])(0.0),
                 type(ab[0])(1.0))
    return wp.length(p - (a + u * ab))


@wp.kernel
def mark_near_cells(
    seg_a: wp.array(dtype=wp.vec3f),  # boundary segments [m, local]
    seg_b: wp.array(dtype=wp.vec3f),
    cap: wp.float32,  # [m]
    # Out:
    grid: EdgeGrid,
):
    """Mark every cell a boundary segment may come within ``cap`` of, one thread per segment.

    The x–y distance never exceeds the 3-D one, and no point of a cell is farther than half its
    diagonal from its centre, so a cell whose centre is at least cap + half a diagonal (and a
    rounding margin) from the segment's x–y projection is at least ``cap`` from the segment.
    """
    k = wp.tid()
    a = wp.vec2f(seg_a[k][0], seg_a[k][1])
    b = wp.vec2f(seg_b[k][0], seg_b[k][1])
    cell = 1.0 / grid.inv_cell
    reach = cap + 0.7072 * cell + 1.0e-3 * (cap + cell)
    nx = grid.near.shape[0]
    ny = grid.near.shape[1]
    x0 = wp.max(int(wp.floor((wp.min(a[0], b[0]) - reach - grid.origin[0]) * grid.inv_cell)), 0)
    x1 = wp.min(int(wp.floor((wp.max(a[0], b[0]) + reach - grid.origin[0]) * grid.inv_cell)), nx - 1)
    y0 = wp.max(int(wp.floor((wp.min(a[1], b[1]) - reach - grid.origin[1]) * grid.inv_cell)), 0)
    y1 = wp.min(int(wp.floor((wp.max(a[1], b[1]) + reach - grid.origin[1]) * grid.inv_cell)), ny - 1)
    for ix in range(x0, x1 + 1):
        for iy in range(y0, y1 + 1):
            centre = grid.origin + wp.vec2f((float(ix) + 0.5) * cell, (float(iy) + 0.5) * cell)
            if _segment_distance(centre, a, b) < reach:
                grid.near[ix, iy] = wp.uint8(1)


@wp.func
def _near_boundary(grid: EdgeGrid, p: wp.vec3f):
    """False where the edge grid shows p at least the edge cap from every plane boundary."""
    ix = int(wp.floor((p[0] - grid.origin[0]) * grid.inv_cell))
    iy = int(wp.floor((p[1] - grid.origin[1]) * grid.inv_cell))
    if ix >= 0 and iy >= 0 and ix < grid.near.shape[0] and iy < grid.near.shape[1]:
        return grid.near[ix, iy] != wp.uint8(0)
    return True


@wp.func
def _boundary_distance(boundary: wp.uint64, seg_a: wp.array(dtype=wp.vec3f), seg_b: wp.array(dtype=wp.vec3f),
                       p: wp.vec3f, cap: wp.float32):
    """Distance from p to the nearest plane-boundary segment, at most ``cap`` [m].

    Only segments whose boxes overlap the cube of half side ``cap`` around p are visited, then
    the exact point–segment distance is taken.
    """
    best = cap
    extent = wp.vec3f(cap, cap, cap)
    query = wp.bvh_query_aabb(boundary, p - extent, p + extent)
    k = int(0)
    while wp.bvh_query_next(query, k):
        best = wp.min(best, _segment_distance(p, seg_a[k], seg_b[k]))
    return best


@wp.kernel
def corner_extent(
    points: wp.array(dtype=wp.vec3f),  # mesh vertices [m, local]
    indices: wp.array(dtype=wp.int32),  # 3 vertex indices per triangle
    extent: wp.array(dtype=wp.float32),  # in/out (1,): the largest |coordinate| of a triangle corner [m]
):
    """Grow ``extent[0]`` (start it at 0) to the largest absolute coordinate of any triangle's corners:
    the vertices the triangles use, not the unused ones."""
    t = wp.tid()
    largest = wp.float32(0.0)
    for k in range(3):
        p = points[indices[3 * t + k]]
        largest = wp.max(largest, wp.max(wp.abs(p[0]), wp.max(wp.abs(p[1]), wp.abs(p[2]))))
    wp.atomic_max(extent, 0, largest)


@wp.kernel
def padded_boxes(
    points: wp.array(dtype=wp.vec3f),  # mesh vertices [m, local]
    indices: wp.array(dtype=wp.int32),  # 3 vertex indices per triangle
    pad: wp.float32,  # margin added on every side [m]
    lowers: wp.array(dtype=wp.vec3f),  # out: per triangle, lower box corner [m]
    uppers: wp.array(dtype=wp.vec3f),  # out: per triangle, upper box corner [m]
):
    """The boxes of :func:`_fallback_hit`'s BVH: each triangle's bounds widened by ``pad``."""
    t = wp.tid()
    a = points[indices[3 * t]]
    b = points[indices[3 * t + 1]]
    c = points[indices[3 * t + 2]]
    margin = wp.vec3f(pad, pad, pad)
    lowers[t] = wp.min(wp.min(a, b), c) - margin
    uppers[t] = wp.max(wp.max(a, b), c) + margin


@wp.func
def _fallback_hit(bvh: wp.uint64, vertices: wp.array(dtype=wp.vec3d), indices: wp.array(dtype=wp.int32),
                  start: wp.vec3d, direction: wp.vec3d, max_range: wp.float32):
    """(face, t [m]) of the closest triangle on the ray, or (-1, max_range): a second look for rays the
    mesh query reports as misses.

    Warp's mesh BVH tests boxes without a margin, so a ray through an edge or vertex shared by
    flat triangles (boxes of zero thickness) can slip between them. Here the boxes are padded and
    each candidate gets an exact float64 ray–triangle test (Möller–Trumbore) that keeps the edges.
    """
    best_face = int(-1)
    best_t = wp.float64(max_range)
    query = wp.bvh_query_ray(bvh, wp.vec3f(start), wp.vec3f(direction))
    tri = int(0)
    while wp.bvh_query_next(query, tri, wp.float32(best_t) + 1.0):
        v0 = vertices[indices[3 * tri]]
        e1 = vertices[indices[3 * tri + 1]] - v0
        e2 = vertices[indices[3 * tri + 2]] - v0
        p = wp.cross(direction, e2)
        det = wp.dot(e1, p)
        if det != wp.float64(0.0):
            inv = wp.float64(1.0) / det
            d = start - v0
            u = wp.dot(d, p) * inv
            q = wp.cross(d, e1)
            v = wp.dot(direction, q) * inv
            t = wp.dot(e2, q) * inv
            eps = wp.float64(-1.0e-9)
            if u >= eps and v >= eps and u + v <= wp.float64(1.0) - eps and t >= wp.float64(0.0) and t < best_t:
                best_face = tri
                best_t = t
    return best_face, best_t


@wp.func
def _refine_hit(vertices: wp.array(dtype=wp.vec3d), indices: wp.array(dtype=wp.int32), face: int,
                start: wp.vec3d, direction: wp.vec3d):
    """Distance along a float64 ray to the plane of a triangle given by float64 vertices [m]."""
    v0 = vertices[indices[3 * face]]
    normal = wp.cross(vertices[indices[3 * face + 1]] - v0, vertices[indices[3 * face + 2]] - v0)
    return wp.dot(normal, v0 - start) / wp.dot(normal, direction)


@wp.func
def _lut_lookup(directions: wp.array2d(dtype=wp.vec3f), exits: wp.array2d(dtype=wp.vec3f), column: int,
                phi: wp.float32):
    """Exit ray of a beam interpolated linearly in φ from a table of M + 1 samples over [0, 2π]."""
    m = directions.shape[0] - 1
    x = wp.clamp(phi * (float(m) / 6.283185307179586), 0.0, float(m))
    i = wp.min(int(x), m - 1)
    w = x - float(i)
    a = directions[i, column]
    b = directions[i + 1, column]
    ok = wp.length_sq(a) > 0.5 and wp.length_sq(b) > 0.5
    s3 = wp.normalize(a + w * (b - a))
    return s3, exits[i, column] + w * (exits[i + 1, column] - exits[i, column]), ok


@functools.cache
def _slot_function(f: Features, instrument: Instrument):
    """Build the per-slot body shared by the points and the statistics kernels."""

    deflector = instrument.deflector
    Scan = scan_struct(instrument)
    rows = pulse_rows(instrument, f.pose)
    row_truth, row_believed = rows.truth, rows.believed
    row_direction, row_exit, row_ok = rows.axis_direction, rows.axis_exit, rows.axis_ok
    row_pose = rows.true_pose
    precise = f.optics == "float64"
    real = wp.float64 if precise else wp.float32
    vec = wp.types.vector(3, real)
    mat = wp.types.matrix((3, 3), real)
    quat = wp.types.quaternion(real)

    @wp.func
    def trace_slot(pulses: wp.array2d(dtype=wp.float64), p: int, beam: int, scan: Scan):
        """Trace beam ``beam`` of pulse ``p`` (a column of the chunk's pulse table).

        Returns (status, range [m], face, direction, exact point, nominal point, true point);
        points in the local frame [m].
        """
        zero = wp.vec3f(0.0, 0.0, 0.0)
        origin = vec(get3(pulses, ROW_ORIGIN, p))
        rot = mat(get33(pulses, ROW_ROT, p))
        if wp.static(f.optics == "lut"):
            s3, exit_point, ok = _lut_lookup(scan.lut_directions, scan.lut_exits, beam,
                                             wp.float32(pulses[ROW_PHI, p]))
        else:
            s3, exit_point, ok = deflector.finish(vec(scan.beam_truth[beam]), pulses, row_truth, p, scan.truth)
        if not ok:
            return STATUS_TIR, 0.0, -1, zero, zero, zero, zero
        true_origin = origin
        true_rot = rot
        if wp.static(f.pose):  # the pulse's true pose, drawn once per pulse by pulse_optics
            true_origin = origin + vec(get3(pulses, row_pose, p))
            true_rot = rot * mat(get33(pulses, row_pose + 3, p))
        start = true_origin + true_rot * exit_point
        direction = true_rot * s3
        hit = wp.mesh_query_ray(scan.mesh, wp.vec3f(start), wp.vec3f(direction), scan.max_range)
        face = hit.face
        t_hit = hit.t
        if not hit.result:
            face, t_second = _fallback_hit(scan.padded, scan.vertices64, scan.indices, wp.vec3d(start),
                                           wp.vec3d(direction), scan.max_range)
            if face < 0:
                return STATUS_MISS, 0.0, -1, wp.vec3f(direction), zero, zero, zero
            t_hit = wp.float32(t_second)
        if wp.static(precise):
            t = _refine_hit(scan.vertices64, scan.indices, face, start, direction)
        else:
            t = t_hit
        true_point = start + t * direction
        r = t
        if wp.static(f.noisy or f.ranging):  # keyed by (seed, line, pulse, beam): chunking never changes it
            per_pulse = wp.int64(scan.per_pulse)
            pulse = wp.int64(pulses[ROW_PULSE, p])
            state = wp.rand_init(int(pulses[ROW_SEED, p]), int((pulse * per_pulse + wp.int64(beam)) % wp.int64(2147483647)))
            if wp.static(f.noisy):
                gauss, state = _gaussian(state)
                r = r + real(scan.noise_sigma * gauss)
            if wp.static(f.ranging):
                g = scan.ranging
                u1 = wp.randf(state)
                u2 = wp.randf(state)
                r = r + real(g.drift) * t + real(g.delays[beam]) + real(g.tdc_bin * (u1 - u2))
        # georeference the observation (scan state, beam, r) with the deflector the processing believes in
        p_exact = vec()
        p_nominal = vec()
        ok_exact = True
        if wp.static(f.exact):
            if wp.static(f.believed_is_truth):
                p_exact = start + r * direction
            else:
                s3b, exit_b, ok_exact = deflector.finish(vec(scan.beam_believed[beam]), pulses, row_believed, p,
                                                         scan.believed)
                p_exact = origin + rot * (exit_b + r * s3b)
        if wp.static(f.nominal):
            q = scan.beam_rigid[beam]
            rigid = quat(real(q[0]), real(q[1]), real(q[2]), real(q[3]))
            p_nominal = origin + rot * (vec(get3(pulses, row_exit, p))
                                        + r * wp.quat_rotate(rigid, vec(get3(pulses, row_direction, p))))
        if wp.static(deflector.rigid_nominal):
            ok_exact = ok_exact and pulses[row_ok, p] != wp.float64(0.0)
        if not ok_exact:
            # the believed deflector cannot send this beam out: processing cannot place it
            return STATUS_TIR, 0.0, -1, zero, zero, zero, zero
        return (STATUS_RETURN, wp.float32(r), face, wp.vec3f(direction), wp.vec3f(p_exact), wp.vec3f(p_nominal),
                wp.vec3f(true_point))

    return trace_slot


@functools.cache
def points_kernel(f: Features, instrument: Instrument, max_registers: int | None = None):
    """Kernel writing every slot's return: one thread per (pulse, beam)."""
    trace_slot = _slot_function(f, instrument)
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique", cuda_max_registers=max_registers)
    def trace_points(
        # In:
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        # Out: per slot
        status: wp.array(dtype=wp.int32),
        ranges: wp.array(dtype=wp.float32),  # observed one-way range, exit point to hit [m]
        faces: wp.array(dtype=wp.int32),
        scan_angles: wp.array(dtype=wp.float32),  # [deg]
        cos_incidence: wp.array(dtype=wp.float32),
        edge_distance: wp.array(dtype=wp.float32),  # true hit to plane boundary, capped [m]
        true_points: wp.array(dtype=wp.vec3f),  # [m, local]
        exact_points: wp.array(dtype=wp.vec3f),
        nominal_points: wp.array(dtype=wp.vec3f),
        counters: wp.array(dtype=wp.int32),  # [TIR, misses, -]
    ):
        slot = wp.tid()
        per_pulse = scan.per_pulse
        pulse = slot // per_pulse
        code, r, face, direction, p_exact, p_nominal, p_true = trace_slot(pulses, pulse, slot % per_pulse, scan)
        status[slot] = code
        if code == STATUS_TIR:
            wp.atomic_add(counters, COUNT_TIR, 1)
        elif code == STATUS_MISS:
            wp.atomic_add(counters, COUNT_MISS, 1)
        else:
            ranges[slot] = r
            faces[slot] = face
            scan_angles[slot] = signed_off_nadir(direction, wp.vec3f(get3(pulses, ROW_RIGHT, pulse)))
            cos_incidence[slot] = wp.abs(wp.dot(direction, wp.mesh_eval_face_normal(scan.mesh, face)))
            if wp.static(f.edges):
                edge = scan.edge_cap
                if _near_boundary(scan.edge_grid, p_true):
                    edge = _boundary_distance(scan.boundary, scan.boundary_a, scan.boundary_b, p_true, scan.edge_cap)
                edge_distance[slot] = edge
            if wp.static(f.with_truth):
                true_points[slot] = p_true
            if wp.static(f.exact):
                exact_points[slot] = p_exact
            if wp.static(f.nominal):
                nominal_points[slot] = p_nominal

    return trace_points


@wp.func
def _outer6(d: wp.vec3d):
    """Upper triangle of d·dᵀ: xx, xy, xz, yy, yz, zz."""
    return vec6d(d[0] * d[0], d[0] * d[1], d[0] * d[2], d[1] * d[1], d[1] * d[2], d[2] * d[2])


@functools.cache
def records_kernel(f: Features, instrument: Instrument, max_registers: int | None = None):
    """Statistics mode, step 1: one thread per slot traces and georeferences its beam and writes a
    compact record: the plane it hit (or why it does not count) and its points.

    One slot per thread keeps a warp's rays as coherent as the bare ray cast's and the per-thread
    state small. A return the edge grid cannot place clear of the plane boundaries is written as
    CODE_NEAR − plane and listed, with its true point, for :data:`check_edges` to settle (a short
    dense list, so the boundary queries do not hold up whole warps of returns that need none); the
    per-plane sums are left to :func:`reduce_kernel`.
    """
    trace_slot = _slot_function(f, instrument)
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique", cuda_max_registers=max_registers)
    def trace_records(
        # In:
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        face_plane: wp.array(dtype=wp.int32),  # plane id of each triangle
        # Out: per slot
        codes: wp.array(dtype=wp.int32),  # plane id, CODE_MISS, CODE_TIR, or CODE_NEAR − plane id
        exact_points: wp.array(dtype=wp.vec3f),  # [m, local]
        nominal_points: wp.array(dtype=wp.vec3f),
        # Out: the list of CODE_NEAR slots (append only; near_count[0] holds its length)
        near_count: wp.array(dtype=wp.int32),
        near_slots: wp.array(dtype=wp.int32),
        near_points: wp.array(dtype=wp.vec3f),  # their true points [m, local]
    ):
        slot = wp.tid()
        per_pulse = scan.per_pulse
        code, r, face, direction, p_exact, p_nominal, p_true = trace_slot(pulses, slot // per_pulse,
                                                                          slot % per_pulse, scan)
        if code == STATUS_TIR:
            codes[slot] = CODE_TIR
        elif code == STATUS_MISS:
            codes[slot] = CODE_MISS
        else:
            plane = face_plane[face]
            if wp.static(f.edges):
                if _near_boundary(scan.edge_grid, p_true):
                    plane = CODE_NEAR - plane
                    k = wp.atomic_add(near_count, 0, 1)
                    near_slots[k] = slot
                    near_points[k] = p_true
            codes[slot] = plane
            if wp.static(f.exact):
                exact_points[slot] = p_exact
            if wp.static(f.nominal):
                nominal_points[slot] = p_nominal

    return trace_records


@functools.cache
def check_edges_kernel(instrument: Instrument):
    """The kernel settling near-boundary records (:func:`_check_edges`) for one instrument's scan struct."""
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique")
    def check_edges(
        scan: Scan,
        edge_buffer: wp.float32,  # returns closer than this to a plane boundary do not count [m]
        near_count: wp.array(dtype=wp.int32),
        near_slots: wp.array(dtype=wp.int32),
        near_points: wp.array(dtype=wp.vec3f),  # [m, local]
        # In and out:
        codes: wp.array(dtype=wp.int32),
    ):
        """Settle the records the edge grid could not: CODE_NEAR − plane becomes the plane, or CODE_EDGE
        where the true hit lies within the edge buffer of a plane boundary. One thread per listed slot
        (threads past the list's length do nothing)."""
        k = wp.tid()
        if k < near_count[0]:
            slot = near_slots[k]
            distance = _boundary_distance(scan.boundary, scan.boundary_a, scan.boundary_b, near_points[k],
                                          scan.edge_cap)
            codes[slot] = wp.where(distance < edge_buffer, CODE_EDGE, CODE_NEAR - codes[slot])

    return check_edges


@functools.cache
def reduce_kernel(f: Features):
    """Statistics mode, step 2: per-plane float64 moments of the records of a chunk.

    Each thread takes a run of consecutive slots (consecutive beams of a pulse, then the next
    pulse: the order in which the beams' footprints lie closest) and keeps running sums while the
    plane stays the same, adding them to the global sums (atomics) only when the plane changes.
    Neighbouring threads mostly hold the same plane too, so thread t adds to replica t mod R of the
    sums (R = the sums' first dimension), spreading the atomics on a busy plane over R addresses;
    the host adds the replicas.
    """

    @wp.kernel(module="unique")
    def reduce_records(
        # In:
        codes: wp.array(dtype=wp.int32),
        exact_points: wp.array(dtype=wp.vec3f),
        nominal_points: wp.array(dtype=wp.vec3f),
        n_slots: wp.int32,
        slots_per_thread: wp.int32,
        references: wp.array(dtype=wp.vec3d),  # reference point of each plane [m, local]
        # Out: per replica, per model (exact [0], nominal [1]), per plane
        counts: wp.array3d(dtype=wp.int64),
        first: wp.array3d(dtype=wp.vec3d),  # Σ (p − ref)
        second: wp.array3d(dtype=vec6d),  # Σ upper triangle of (p − ref)(p − ref)ᵀ
        counters: wp.array(dtype=wp.int32),  # [TIR, misses, edge-excluded]
    ):
        begin = wp.tid() * slots_per_thread
        end = wp.min(begin + slots_per_thread, n_slots)
        replica = wp.tid() % counts.shape[0]
        plane = int(-1)
        n = wp.int64(0)
        s_exact = wp.vec3d()
        s_nominal = wp.vec3d()
        ss_exact = vec6d()
        ss_nominal = vec6d()
        tir = int(0)
        miss = int(0)
        excluded = int(0)
        for slot in range(begin, end):
            code = codes[slot]
            if code == CODE_TIR:
                tir += 1
            elif code == CODE_MISS:
                miss += 1
            elif code == CODE_EDGE:
                excluded += 1
            else:
                if code != plane:
                    if plane >= 0:
                        _flush(counts, first, second, replica, plane, n, s_exact, ss_exact, s_nominal, ss_nominal)
                    plane = code
                    n = wp.int64(0)
                    s_exact = wp.vec3d()
                    s_nominal = wp.vec3d()
                    ss_exact = vec6d()
                    ss_nominal = vec6d()
                n += wp.int64(1)
                ref = references[plane]
                if wp.static(f.exact):
                    d = wp.vec3d(exact_points[slot]) - ref
                    s_exact += d
                    ss_exact += _outer6(d)
                if wp.static(f.nominal):
                    d = wp.vec3d(nominal_points[slot]) - ref
                    s_nominal += d
                    ss_nominal += _outer6(d)
        if plane >= 0:
            _flush(counts, first, second, replica, plane, n, s_exact, ss_exact, s_nominal, ss_nominal)
        if tir > 0:
            wp.atomic_add(counters, COUNT_TIR, tir)
        if miss > 0:
            wp.atomic_add(counters, COUNT_MISS, miss)
        if excluded > 0:
            wp.atomic_add(counters, COUNT_EDGE, excluded)

    return reduce_records


@wp.func
def _left_out(status: wp.int32, edge_distance: wp.float32, edge_buffer: wp.float32) -> int:
    """The reduction's code of a slot that is not scored (CODE_MISS: no return; CODE_EDGE: nearer a plane
    boundary than ``edge_buffer`` > 0 [m]), else CODE_SCORED."""
    if status != STATUS_RETURN:
        return CODE_MISS
    if edge_buffer > wp.float32(0.0) and edge_distance < edge_buffer:
        return CODE_EDGE
    return CODE_SCORED


@wp.kernel
def plane_codes(
    status: wp.array(dtype=wp.int32),
    faces: wp.array(dtype=wp.int32),
    edge_distance: wp.array(dtype=wp.float32),
    face_plane: wp.array(dtype=wp.int32),
    edge_buffer: wp.float32,  # > 0: returns nearer a plane boundary than this are left out [m]
    codes: wp.array(dtype=wp.int32),  # out: the plane of a return, else a CODE_* (reduce_kernel's input)
):
    """Points mode: the statistics reduction's code of each slot the points kernel traced."""
    slot = wp.tid()
    code = _left_out(status[slot], edge_distance[slot], edge_buffer)
    if code == CODE_SCORED:
        code = face_plane[faces[slot]]
    codes[slot] = code


@wp.kernel
def patch_codes(
    status: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3f),  # the return positions that pick the patch [m, local]
    edge_distance: wp.array(dtype=wp.float32),
    edge_buffer: wp.float32,  # > 0: returns nearer a plane boundary than this are left out [m]
    low: wp.vec2d,  # local (x, y) of the patch grid's lower-left corner [m]
    patch_m: wp.float64,  # side of a patch [m]
    nx: wp.int32,  # patches along x
    ny: wp.int32,  # patches along y
    codes: wp.array(dtype=wp.int32),  # out: the patch (row-major from ``low``) of a return, else a CODE_*
):
    """Points mode on curved ground: the statistics reduction's code of each slot is the square patch
    holding the return (x, y); returns beyond the grid count in its border patches."""
    slot = wp.tid()
    code = _left_out(status[slot], edge_distance[slot], edge_buffer)
    if code == CODE_SCORED:
        p = points[slot]
        i = wp.clamp(int(wp.floor((wp.float64(p[0]) - low[0]) / patch_m)), 0, nx - 1)
        j = wp.clamp(int(wp.floor((wp.float64(p[1]) - low[1]) / patch_m)), 0, ny - 1)
        code = j * nx + i
    codes[slot] = code


@wp.func
def _flush(
    counts: wp.array3d(dtype=wp.int64),
    first: wp.array3d(dtype=wp.vec3d),
    second: wp.array3d(dtype=vec6d),
    replica: int,
    plane: int,
    n: wp.int64,
    s_exact: wp.vec3d,
    ss_exact: vec6d,
    s_nominal: wp.vec3d,
    ss_nominal: vec6d,
):
    """Add one thread's running sums for ``plane`` to a replica of the global per-plane sums."""
    wp.atomic_add(counts, replica, 0, plane, n)
    wp.atomic_add(counts, replica, 1, plane, n)
    wp.atomic_add(first, replica, 0, plane, s_exact)
    wp.atomic_add(first, replica, 1, plane, s_nominal)
    wp.atomic_add(second, replica, 0, plane, ss_exact)
    wp.atomic_add(second, replica, 1, plane, ss_nominal)


@wp.kernel
def add_replicas(
    counts: wp.array3d(dtype=wp.int64),  # per replica, model, group (reduce_kernel's sums)
    first: wp.array3d(dtype=wp.vec3d),
    second: wp.array3d(dtype=vec6d),
    # Out: per model, group
    total_counts: wp.array2d(dtype=wp.int64),
    total_first: wp.array2d(dtype=wp.vec3d),
    total_second: wp.array2d(dtype=vec6d),
):
    """Add the replicas of the reduction's sums, replica 0 first: one thread per (model, group), so only
    the totals leave the device."""
    model, group = wp.tid()
    n = wp.int64(0)
    s = wp.vec3d()
    ss = vec6d()
    for replica in range(counts.shape[0]):
        n += counts[replica, model, group]
        s += first[replica, model, group]
        ss += second[replica, model, group]
    total_counts[model, group] = n
    total_first[model, group] = s
    total_second[model, group] = ss


@wp.kernel
def flag_returns(status: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where slot i produced a return."""
    i = wp.tid()
    flags[i] = wp.where(status[i] == STATUS_RETURN, 1, 0)


@wp.kernel
def compact_slots(
    flags: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),  # exclusive prefix sum of flags
    src: wp.array(dtype=Any),
    dst: wp.array(dtype=Any),
):
    """Gather the returning slots of ``src`` into ``dst``, keeping their order."""
    i = wp.tid()
    if flags[i] != 0:
        dst[offsets[i]] = src[i]


@wp.kernel
def slot_indices(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), dst: wp.array(dtype=wp.int32)):
    """dst[k] = slot index of the k-th return of the chunk."""
    i = wp.tid()
    if flags[i] != 0:
        dst[offsets[i]] = i


@wp.kernel
def returns_before(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), n_slots: int,
                   bounds: wp.array(dtype=wp.int32)):
    """bounds[i] ← the number of returns among the slots before slot bounds[i] (0 ≤ bounds[i] ≤ n_slots)."""
    i = wp.tid()
    b = bounds[i]
    if b == n_slots:
        bounds[i] = offsets[n_slots - 1] + flags[n_slots - 1]
    else:
        bounds[i] = offsets[b]


@functools.cache
def emit_rays_kernel(instrument: Instrument, precise: bool = False, pose: bool = False):
    """Kernel writing the rays the pipeline casts, one per slot: rounded to float32 as the ray cast takes
    them (for timing the bare ray cast), or in float64 with ``precise`` (the waveform detector's beams and
    the retroreflectors' footprints); ``pose``: from the pulse's true pose (its pose-error rows), as
    trace_slot casts them."""
    deflector = instrument.deflector
    Scan = scan_struct(instrument)
    rows = pulse_rows(instrument, pose)
    row_truth, row_pose = rows.truth, rows.true_pose
    vec = wp.vec3d if precise else wp.vec3f

    @wp.kernel(module="unique")
    def emit_rays(
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        # Out:
        starts: wp.array(dtype=vec),  # [m, local]
        directions: wp.array(dtype=vec),  # unit; zero where the beam does not leave the deflector
    ):
        slot = wp.tid()
        per_pulse = scan.per_pulse
        p = slot // per_pulse
        origin = get3(pulses, ROW_ORIGIN, p)
        rot = get33(pulses, ROW_ROT, p)
        if wp.static(pose):
            origin = origin + get3(pulses, row_pose, p)
            rot = rot * get33(pulses, row_pose + 3, p)
        s3, exit_point, ok = deflector.finish(scan.beam_truth[slot % per_pulse], pulses, row_truth, p, scan.truth)
        starts[slot] = vec(origin + rot * exit_point)
        directions[slot] = wp.where(ok, vec(rot * s3), vec())

    return emit_rays


@functools.cache
def photon_points_kernel(instrument: Instrument):
    """Kernel placing each photon detection: its beam as the processing believes it (float64), at the
    photon's range c·t/2 — the georeferencing of the exact model, per photon."""
    deflector = instrument.deflector
    Scan = scan_struct(instrument)
    row_believed = pulse_rows(instrument).believed

    @wp.kernel(module="unique")
    def photon_points(
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        slots: wp.array(dtype=wp.int32),  # slot within the chunk of each photon
        times: wp.array(dtype=wp.float64),  # time of flight of each photon [s]
        # Out:
        points: wp.array(dtype=wp.vec3d),  # [m, local]; NaN where the believed deflector cannot send the beam out
        directions: wp.array(dtype=wp.vec3f),  # the believed beam's unit direction, local
    ):
        i = wp.tid()
        slot = slots[i]
        per_pulse = scan.per_pulse
        p = slot // per_pulse
        s3, exit_point, ok = deflector.finish(scan.beam_believed[slot % per_pulse], pulses, row_believed, p,
                                              scan.believed)
        r = times[i] * HALF_LIGHT_SPEED
        point = get3(pulses, ROW_ORIGIN, p) + get33(pulses, ROW_ROT, p) * (exit_point + r * s3)
        nan = wp.float64(wp.nan)
        points[i] = wp.where(ok, point, wp.vec3d(nan, nan, nan))
        directions[i] = wp.vec3f(get33(pulses, ROW_ROT, p) * s3)

    return photon_points


@wp.kernel
def cast_rays(
    mesh: wp.uint64,
    starts: wp.array(dtype=wp.vec3f),
    directions: wp.array(dtype=wp.vec3f),
    max_range: wp.float32,
    # Out:
    faces: wp.array(dtype=wp.int32),  # face hit, -1 for none
):
    """Nothing but ``wp.mesh_query_ray``: the baseline the pipeline's throughput is compared with."""
    i = wp.tid()
    hit = wp.mesh_query_ray(mesh, starts[i], directions[i], max_range)
    faces[i] = wp.where(hit.result, hit.face, -1)
