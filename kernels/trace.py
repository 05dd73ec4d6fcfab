"""The tracer's kernels: fire the emitter's beams, deflect them, ray-cast the scene, add the ranging
errors and georeference; the points kernel keeps each slot's return (the statistics kernels of
:mod:`kernels.statistics` share the per-slot body).

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
import warp as wp

from kernels.frames import (POSE_ROWS, ROW_ORIGIN, ROW_PHI, ROW_PULSE, ROW_RIGHT, ROW_ROT, ROW_SEED, get3, get33, put3,
                            put33)
from kernels.edges import EdgeGrid, boundary_distance, near_boundary
from kernels.error_models import PoseErrors, RangeErrors, true_pose
from kernels.looks import FIRST_LOOK, SECOND_LOOK, Misses, list_miss
from kernels.mesh_cast import closest_hit
from kernels.mesh_hits import fallback_hit, refine_hit
from kernels.optics import rigid_array_rotation
from kernels.parts import Instrument

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

STATUS_MISS = wp.constant(0)
STATUS_RETURN = wp.constant(1)
STATUS_TIR = wp.constant(2)
STATUS_LEAF = wp.constant(3)  # a return from leaves (kernels.canopy_returns): compacted with the others, never scored
STATUS_RETRY = wp.constant(4)  # missed by the mesh query: listed for the second look (never stored)
HALF_LIGHT_SPEED = wp.constant(wp.float64(149896229.0))  # c / 2 [m/s]: one-way range per time of flight

COUNT_TIR = 0
COUNT_MISS = 1
COUNT_EDGE = 2  # returns left out of the statistics for lying within the edge buffer

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
        boundary_a: wp.array(dtype=wp.vec3f)  # plane-boundary segments' end points [m, local] (edge buffer queries)
        boundary_b: wp.array(dtype=wp.vec3f)
        edge_cap: wp.float32  # edge distances are measured up to this [m]
        edge_grid: EdgeGrid  # where the boundary query can be skipped, and the segments it visits
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

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
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

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
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
            shift, turn = true_pose(table, p, scan.pose)
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


@wp.struct
class SlotTrace:
    """One slot's traced beam: its status and, for a return, what every readout may need of it."""

    status: wp.int32  # STATUS_RETURN, STATUS_MISS or STATUS_TIR
    r: wp.float32  # observed one-way range, exit point to hit, with the ranging errors [m]
    face: wp.int32  # triangle hit (-1: none)
    direction: wp.vec3f  # the true ray's unit direction (local)
    p_exact: wp.vec3f  # the return georeferenced by the exact model [m, local]
    p_nominal: wp.vec3f  # ... by the rigid-array model
    p_true: wp.vec3f  # the true hit [m, local]
    d_exact: wp.vec3f  # d p_exact / d r: the exact model's unit ray (a return at r' lies at p + (r' - r) d)
    d_nominal: wp.vec3f  # ... the rigid-array model's


@wp.func
def _no_return(status: wp.int32, direction: wp.vec3f):
    """A slot without a return (a miss along ``direction``, or a beam the deflector cannot send out)."""
    s = SlotTrace()
    s.status = status
    s.face = -1
    s.direction = direction
    return s


@wp.func
def _a_return(r: wp.float32, face: wp.int32, direction: wp.vec3f, p_exact: wp.vec3f, p_nominal: wp.vec3f,
              p_true: wp.vec3f, d_exact: wp.vec3f, d_nominal: wp.vec3f):
    """A slot's return (the fields of :class:`SlotTrace`)."""
    s = SlotTrace()
    s.status = STATUS_RETURN
    s.r = r
    s.face = face
    s.direction = direction
    s.p_exact = p_exact
    s.p_nominal = p_nominal
    s.p_true = p_true
    s.d_exact = d_exact
    s.d_nominal = d_nominal
    return s


@functools.cache
def slot_function(f: Features, instrument: Instrument, look: int = FIRST_LOOK):
    """Build the per-slot body shared by the points, the statistics and the canopy kernels, for one of the trace
    kernels' two looks (:mod:`kernels.looks`: the first returns STATUS_RETRY where the mesh query misses)."""

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

    @wp.func(module="unique")  # not in this file's module: each variant would replace the last there
    def trace_slot(pulses: wp.array2d(dtype=wp.float64), p: int, beam: int, scan: Scan):
        """Trace beam ``beam`` of pulse ``p`` (a column of the chunk's pulse table).

        Returns its :class:`SlotTrace`; points in the local frame [m].
        """
        zero = wp.vec3f(0.0, 0.0, 0.0)
        if wp.static(f.optics == "lut"):
            s3, exit_point, ok = _lut_lookup(scan.lut_directions, scan.lut_exits, beam,
                                             wp.float32(pulses[ROW_PHI, p]))
        else:
            s3, exit_point, ok = deflector.finish(vec(scan.beam_truth[beam]), pulses, row_truth, p, scan.truth)
        if not ok:
            return _no_return(STATUS_TIR, zero)
        true_origin = vec(get3(pulses, ROW_ORIGIN, p))
        true_rot = mat(get33(pulses, ROW_ROT, p))
        if wp.static(f.pose):  # the pulse's true pose, drawn once per pulse by pulse_optics
            true_origin = true_origin + vec(get3(pulses, row_pose, p))
            true_rot = true_rot * mat(get33(pulses, row_pose + 3, p))
        start = true_origin + true_rot * exit_point
        direction = true_rot * s3
        if wp.static(look == FIRST_LOOK):
            face, t_hit = closest_hit(scan.mesh, wp.vec3f(start), wp.vec3f(direction), scan.max_range)
            if face < 0:
                return _no_return(STATUS_RETRY, wp.vec3f(direction))
        else:
            face, t_second = fallback_hit(scan.padded, scan.vertices64, scan.indices, wp.vec3d(start),
                                           wp.vec3d(direction), scan.max_range)
            if face < 0:
                return _no_return(STATUS_MISS, wp.vec3f(direction))
            t_hit = wp.float32(t_second)
        if wp.static(precise):
            t = refine_hit(scan.vertices64, scan.indices, face, start, direction)
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
        # georeference the observation (scan state, beam, r) with the deflector the processing believes in; the
        # believed pose is read again here rather than held in registers across the ray cast
        origin = vec(get3(pulses, ROW_ORIGIN, p))
        rot = mat(get33(pulses, ROW_ROT, p))
        p_exact = vec()
        p_nominal = vec()
        d_exact = vec()
        d_nominal = vec()
        ok_exact = True
        if wp.static(f.exact):
            if wp.static(f.believed_is_truth):
                d_exact = direction
                p_exact = start + r * direction
            else:
                s3b, exit_b, ok_exact = deflector.finish(vec(scan.beam_believed[beam]), pulses, row_believed, p,
                                                         scan.believed)
                d_exact = rot * s3b
                p_exact = origin + rot * (exit_b + r * s3b)
        if wp.static(f.nominal):
            q = scan.beam_rigid[beam]
            rigid = quat(real(q[0]), real(q[1]), real(q[2]), real(q[3]))
            axis = wp.quat_rotate(rigid, vec(get3(pulses, row_direction, p)))
            d_nominal = rot * axis
            p_nominal = origin + rot * (vec(get3(pulses, row_exit, p)) + r * axis)
        if wp.static(deflector.rigid_nominal):
            ok_exact = ok_exact and pulses[row_ok, p] != wp.float64(0.0)
        if not ok_exact:
            # the believed deflector cannot send this beam out: processing cannot place it
            return _no_return(STATUS_TIR, zero)
        return _a_return(wp.float32(r), face, wp.vec3f(direction), wp.vec3f(p_exact), wp.vec3f(p_nominal),
                         wp.vec3f(true_point), wp.vec3f(d_exact), wp.vec3f(d_nominal))

    return trace_slot


@functools.cache
def points_kernel(f: Features, instrument: Instrument, max_registers: int | None = None, look: int = FIRST_LOOK):
    """Kernel writing every slot's return: one thread per (pulse, beam), or per listed slot in the second look."""
    trace_slot = slot_function(f, instrument, look)
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique", enable_backward=False, cuda_max_registers=max_registers, grid_stride=False)
    def trace_points(
        # In:
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        misses: Misses,  # the first look's misses: listed by the first look, traced by the second
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
        if wp.static(look == SECOND_LOOK):
            if slot >= misses.count[0]:
                return
            slot = misses.slots[slot]
        per_pulse = scan.per_pulse
        pulse = slot // per_pulse
        s = trace_slot(pulses, pulse, slot % per_pulse, scan)
        code, r, face, direction = s.status, s.r, s.face, s.direction
        if code == STATUS_RETRY:
            list_miss(misses, slot)
            return
        p_exact, p_nominal, p_true = s.p_exact, s.p_nominal, s.p_true
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
                if near_boundary(scan.edge_grid, p_true):
                    edge = boundary_distance(scan.edge_grid, scan.boundary_a, scan.boundary_b, p_true, scan.edge_cap)
                edge_distance[slot] = edge
            if wp.static(f.with_truth):
                true_points[slot] = p_true
            if wp.static(f.exact):
                exact_points[slot] = p_exact
            if wp.static(f.nominal):
                nominal_points[slot] = p_nominal

    return trace_points


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

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
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

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
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
    """Nothing but the ray cast (:func:`kernels.mesh_cast.closest_hit`): the baseline the pipeline's throughput is
    compared with."""
    i = wp.tid()
    face, t = closest_hit(mesh, starts[i], directions[i], max_range)
    faces[i] = face


@wp.kernel
def cast_rays_warp(
    mesh: wp.uint64,
    starts: wp.array(dtype=wp.vec3f),
    directions: wp.array(dtype=wp.vec3f),
    max_range: wp.float32,
    # Out:
    faces: wp.array(dtype=wp.int32),  # face hit, -1 for none
):
    """:func:`cast_rays` through Warp's own ``wp.mesh_query_ray`` (what closest_hit is measured against)."""
    i = wp.tid()
    hit = wp.mesh_query_ray(mesh, starts[i], directions[i], max_range)
    faces[i] = wp.where(hit.result, hit.face, -1)
