"""Per-beam kernels: fire the fan, deflect it, ray-cast the scene, georeference, and either keep
each return (points mode) or reduce the returns to per-plane moments (statistics mode).

Kernels are specialised at build time for the features a run asks for (``wp.static``), so a
feature that is off costs nothing per beam. Work is done where it varies: what depends only on
the sub-beam (its entry into the prism, its rigid-array rotation) once per run in a table, what
depends only on the prism angle (the back-face normal, the on-axis ray of the nominal model) once
per pulse, and only the rest per beam. The deflector is a parameter of the build (:class:`Deflector`);
the rotating wedge is the one flightsim ships.
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp

from kernels.frames import PulsePose
from kernels.optics import back_face_normal, doe_direction, enter_prism, leave_prism, rigid_array_rotation

wp.set_module_options({"enable_backward": False})

STATUS_MISS = wp.constant(0)
STATUS_RETURN = wp.constant(1)
STATUS_TIR = wp.constant(2)

COUNT_TIR = 0
COUNT_MISS = 1
COUNT_EDGE = 2  # returns left out of the statistics for lying within the edge buffer

vec6d = wp.types.vector(6, wp.float64)


@wp.struct
class Prism:
    """Wedge prism parameters as one side (truth or processing) believes them."""

    n_glass: wp.float64  # refractive index of the glass (air = 1)
    apex: wp.float64  # apex angle α [rad]
    thickness: wp.float64  # d1, centre thickness [m]


@wp.func
def wedge_beam_stage(s1: Any, prism: Prism):
    """Per-beam part of the wedge: the direction inside the glass after the front face."""
    return enter_prism(s1, type(s1[0])(prism.n_glass))


@wp.func
def wedge_pulse_stage(phi: Any, prism: Prism):
    """Per-pulse part of the wedge: the back face's normal at prism angle phi [rad]."""
    return back_face_normal(phi, type(phi)(prism.apex))


@wp.func
def wedge_finish(inside: Any, normal: Any, prism: Prism):
    """Per-beam, per-pulse rest of the wedge: (exit direction, exit point [m], ok) in the inputs' precision."""
    return leave_prism(inside, normal, type(inside[0])(prism.n_glass), type(inside[0])(prism.thickness))


@dataclass(frozen=True)
class Deflector:
    """A beam deflector split by what each part depends on.

    beam_stage(s1, prism) -> vector: depends on the sub-beam only (tabulated once per run, float64);
    pulse_stage(phi, prism) -> vector: depends on the scan angle only (once per pulse, float64);
    finish(beam_state, pulse_state, prism) -> (s3, exit point [m], ok): the rest, per beam.
    """

    beam_stage: wp.Function
    pulse_stage: wp.Function
    finish: wp.Function


WEDGE = Deflector(wedge_beam_stage, wedge_pulse_stage, wedge_finish)


@wp.struct
class BeamArray:
    """The DOE fan: n×n sub-beams spaced by ``spacing`` [rad]."""

    n: wp.int32
    spacing: wp.float32


@wp.struct
class Scan:
    """Everything a slot needs besides its pose: scene, instrument, processing, noise."""

    mesh: wp.uint64
    max_range: wp.float32  # [m]
    beams: BeamArray
    truth: Prism
    believed: Prism  # the prism the georeferencing believes in
    noise_sigma: wp.float32  # range noise, 1σ [m]
    boundary: wp.uint64  # BVH of the plane-boundary segments (edge buffer queries)
    boundary_a: wp.array(dtype=wp.vec3f)  # segment end points [m, local]
    boundary_b: wp.array(dtype=wp.vec3f)
    edge_cap: wp.float32  # edge distances are measured up to this [m]
    lut_directions: wp.array2d(dtype=wp.vec3f)  # [φ sample, beam] exit directions (optics "lut")
    lut_exits: wp.array2d(dtype=wp.vec3f)  # exit points [m]; a zero direction marks reflection
    beam_truth: wp.array(dtype=wp.vec3d)  # per-beam deflector state of the true prism
    beam_believed: wp.array(dtype=wp.vec3d)  # ... of the prism the processing believes in
    beam_rigid: wp.array(dtype=wp.quatd)  # rigid-array rotation Q of each beam
    vertices64: wp.array(dtype=wp.vec3d)  # scene vertices in float64 (float64 optics path) [m]
    indices: wp.array(dtype=wp.int32)  # 3 per triangle
    padded: wp.uint64  # BVH of slightly padded triangle boxes, for rays the mesh query misses


@dataclass(frozen=True)
class Features:
    """What a kernel build evaluates per beam."""

    exact: bool = True  # georeference by the exact model
    nominal: bool = True  # georeference by the rigid-array model
    believed_is_truth: bool = True  # processing prism == simulated prism: reuse the traced ray
    with_truth: bool = False  # keep the true hit point
    noisy: bool = False  # Gaussian range noise
    edges: bool = False  # measure the true hit's distance to its plane boundary
    optics: str = "float32"  # "float32"; "float64" (optics, hit and georeferencing in float64, the ray
    # cast itself in float32 then refined on the hit triangle); "lut" (float32, exit rays tabulated over φ)


@wp.struct
class PulseOptics:
    """What the optics of one pulse share across its beams (float64)."""

    truth: wp.vec3d  # per-pulse deflector state of the true prism
    believed: wp.vec3d  # ... of the prism the processing believes in
    axis_direction: wp.vec3d  # exit direction of the on-axis ray through the believed prism
    axis_exit: wp.vec3d  # its exit point [m]
    axis_ok: wp.int32


@functools.cache
def beam_table_kernel(deflector: Deflector):
    """Kernel tabulating the per-beam part of the optics, in float64, once per run."""

    @wp.kernel(module="unique")
    def beam_table(
        beams: BeamArray,
        truth: Prism,
        believed: Prism,
        # Out: per beam i·n + j
        beam_truth: wp.array(dtype=wp.vec3d),
        beam_believed: wp.array(dtype=wp.vec3d),
        beam_rigid: wp.array(dtype=wp.quatd),
    ):
        b = wp.tid()
        s1 = doe_direction(b // beams.n, b % beams.n, beams.n, wp.float64(beams.spacing))
        beam_truth[b] = deflector.beam_stage(s1, truth)
        beam_believed[b] = deflector.beam_stage(s1, believed)
        beam_rigid[b] = rigid_array_rotation(s1)

    return beam_table


@functools.cache
def _pulse_function(deflector: Deflector):
    @wp.func
    def pulse_optics(phi: wp.float64, scan: Scan):
        """The per-pulse part of the optics at prism angle phi [rad]."""
        po = PulseOptics()
        po.truth = deflector.pulse_stage(phi, scan.truth)
        po.believed = deflector.pulse_stage(phi, scan.believed)
        axis = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
        direction, exit_point, ok = deflector.finish(deflector.beam_stage(axis, scan.believed), po.believed,
                                                     scan.believed)
        po.axis_direction = direction
        po.axis_exit = exit_point
        po.axis_ok = wp.where(ok, 1, 0)
        return po

    return pulse_optics


@wp.func
def signed_off_nadir(direction: wp.vec3f, right: wp.vec3f):
    """Signed off-nadir angle of a local-frame direction [deg]; positive towards the right wing."""
    off_nadir = wp.acos(wp.clamp(-direction[2], -1.0, 1.0))
    return wp.where(wp.dot(direction, right) < 0.0, -off_nadir, off_nadir) * 57.29577951308232


@wp.func
def _gaussian(state: wp.uint32):
    """Standard normal deviate by Box–Muller, the two uniforms drawn in separate statements."""
    u1 = wp.randf(state)
    u2 = wp.randf(state)
    return wp.sqrt(-2.0 * wp.log(wp.max(u1, 1.0e-12))) * wp.cos(6.283185307179586 * u2)


@wp.func
def _edge_distance(boundary: wp.uint64, seg_a: wp.array(dtype=wp.vec3f), seg_b: wp.array(dtype=wp.vec3f),
                   p: wp.vec3f, cap: wp.float32):
    """Distance from p to the nearest plane-boundary segment, at most ``cap`` [m].

    Only segments whose boxes overlap the cube of half side ``cap`` around p are visited (none,
    for most points), then the exact point–segment distance is taken.
    """
    best = cap
    extent = wp.vec3f(cap, cap, cap)
    query = wp.bvh_query_aabb(boundary, p - extent, p + extent)
    k = int(0)
    while wp.bvh_query_next(query, k):
        a = seg_a[k]
        ab = seg_b[k] - a
        u = wp.clamp(wp.dot(p - a, ab) / wp.max(wp.dot(ab, ab), 1.0e-20), 0.0, 1.0)
        best = wp.min(best, wp.length(p - (a + u * ab)))
    return best


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
def _slot_function(f: Features, deflector: Deflector):
    """Build the per-slot body shared by the points and the statistics kernels."""

    precise = f.optics == "float64"
    real = wp.float64 if precise else wp.float32
    vec = wp.types.vector(3, real)
    quat = wp.types.quaternion(real)

    @wp.func
    def trace_slot(pose: PulsePose, po: PulseOptics, beam: int, scan: Scan):
        """Trace one sub-beam of one pulse.

        Returns (status, range [m], face, direction, exact point, nominal point, true point,
        edge distance [m]); points in the local frame [m].
        """
        zero = wp.vec3f(0.0, 0.0, 0.0)
        if wp.static(precise):
            origin = pose.origin64
            rot = pose.rot64
        else:
            origin = pose.origin
            rot = pose.rot
        if wp.static(f.optics == "lut"):
            s3, exit_point, ok = _lut_lookup(scan.lut_directions, scan.lut_exits, beam, pose.phi)
        else:
            s3, exit_point, ok = deflector.finish(vec(scan.beam_truth[beam]), vec(po.truth), scan.truth)
        if not ok:
            return STATUS_TIR, 0.0, -1, zero, zero, zero, zero, 0.0
        start = origin + rot * exit_point
        direction = rot * s3
        hit = wp.mesh_query_ray(scan.mesh, wp.vec3f(start), wp.vec3f(direction), scan.max_range)
        face = hit.face
        t_hit = hit.t
        if not hit.result:
            face, t_second = _fallback_hit(scan.padded, scan.vertices64, scan.indices, wp.vec3d(start),
                                           wp.vec3d(direction), scan.max_range)
            if face < 0:
                return STATUS_MISS, 0.0, -1, wp.vec3f(direction), zero, zero, zero, 0.0
            t_hit = wp.float32(t_second)
        if wp.static(precise):
            t = _refine_hit(scan.vertices64, scan.indices, face, start, direction)
        else:
            t = t_hit
        true_point = start + t * direction
        r = t
        if wp.static(f.noisy):  # keyed by (seed, line, pulse, beam): chunking never changes it
            per_pulse = wp.int64(scan.beams.n * scan.beams.n)
            state = wp.rand_init(pose.seed, int((pose.pulse * per_pulse + wp.int64(beam)) % wp.int64(2147483647)))
            r = r + real(scan.noise_sigma * _gaussian(state))
        # georeference the observation (φ, i, j, r) with the deflector the processing believes in
        p_exact = vec()
        p_nominal = vec()
        ok_exact = True
        if wp.static(f.exact):
            if wp.static(f.believed_is_truth):
                p_exact = start + r * direction
            else:
                s3b, exit_b, ok_exact = deflector.finish(vec(scan.beam_believed[beam]), vec(po.believed),
                                                         scan.believed)
                p_exact = origin + rot * (exit_b + r * s3b)
        if wp.static(f.nominal):
            q = scan.beam_rigid[beam]
            rigid = quat(real(q[0]), real(q[1]), real(q[2]), real(q[3]))
            p_nominal = origin + rot * (vec(po.axis_exit) + r * wp.quat_rotate(rigid, vec(po.axis_direction)))
        if not (ok_exact and po.axis_ok != 0):
            # the believed deflector reflects this beam internally: processing cannot place it
            return STATUS_TIR, 0.0, -1, zero, zero, zero, zero, 0.0
        true32 = wp.vec3f(true_point)
        edge = scan.edge_cap
        if wp.static(f.edges):
            edge = _edge_distance(scan.boundary, scan.boundary_a, scan.boundary_b, true32, scan.edge_cap)
        return (STATUS_RETURN, wp.float32(r), face, wp.vec3f(direction), wp.vec3f(p_exact), wp.vec3f(p_nominal),
                true32, edge)

    return trace_slot


@functools.cache
def points_kernel(f: Features, deflector: Deflector = WEDGE):
    """Kernel writing every slot's return: one thread per (pulse, sub-beam)."""
    trace_slot = _slot_function(f, deflector)
    pulse_optics = _pulse_function(deflector)

    @wp.kernel(module="unique")
    def trace_points(
        # In:
        poses: wp.array(dtype=PulsePose),
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
        per_pulse = scan.beams.n * scan.beams.n
        pose = poses[slot // per_pulse]
        code, r, face, direction, p_exact, p_nominal, p_true, edge = trace_slot(
            pose, pulse_optics(pose.phi64, scan), slot % per_pulse, scan)
        status[slot] = code
        if code == STATUS_TIR:
            wp.atomic_add(counters, COUNT_TIR, 1)
        elif code == STATUS_MISS:
            wp.atomic_add(counters, COUNT_MISS, 1)
        else:
            ranges[slot] = r
            faces[slot] = face
            scan_angles[slot] = signed_off_nadir(direction, pose.right)
            cos_incidence[slot] = wp.abs(wp.dot(direction, wp.mesh_eval_face_normal(scan.mesh, face)))
            if wp.static(f.edges):
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
def statistics_kernel(f: Features, deflector: Deflector = WEDGE):
    """Kernel reducing returns to per-plane float64 moments, no per-point output.

    Each thread traces a run of consecutive slots: it computes a pulse's shared optics once for
    all the pulse's beams it holds, and keeps running sums while the plane stays the same,
    adding them to the global sums (atomics) only when the plane changes — neighbouring beams
    mostly hit the same plane, so the atomics are few and rarely contended.
    """
    trace_slot = _slot_function(f, deflector)
    pulse_optics = _pulse_function(deflector)

    @wp.kernel(module="unique")
    def trace_statistics(
        # In:
        poses: wp.array(dtype=PulsePose),
        scan: Scan,
        n_slots: wp.int32,
        slots_per_thread: wp.int32,
        face_plane: wp.array(dtype=wp.int32),  # plane id of each triangle
        references: wp.array(dtype=wp.vec3d),  # reference point of each plane [m, local]
        edge_buffer: wp.float32,  # returns closer than this to a plane boundary are left out [m]
        # Out: per plane, for the exact [0] and nominal [1] model
        counts: wp.array2d(dtype=wp.int64),
        first: wp.array2d(dtype=wp.vec3d),  # Σ (p − ref)
        second: wp.array2d(dtype=vec6d),  # Σ upper triangle of (p − ref)(p − ref)ᵀ
        counters: wp.array(dtype=wp.int32),  # [TIR, misses, edge-excluded]
    ):
        begin = wp.tid() * slots_per_thread
        end = wp.min(begin + slots_per_thread, n_slots)
        per_pulse = scan.beams.n * scan.beams.n
        pulse = begin // per_pulse
        pose = poses[pulse]
        po = pulse_optics(pose.phi64, scan)
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
            if slot // per_pulse != pulse:
                pulse = slot // per_pulse
                pose = poses[pulse]
                po = pulse_optics(pose.phi64, scan)
            code, r, face, direction, p_exact, p_nominal, p_true, edge = trace_slot(pose, po, slot % per_pulse, scan)
            if code == STATUS_TIR:
                tir += 1
            elif code == STATUS_MISS:
                miss += 1
            elif edge < edge_buffer:
                excluded += 1
            else:
                hit_plane = face_plane[face]
                if hit_plane != plane:
                    if plane >= 0:
                        _flush(counts, first, second, plane, n, s_exact, ss_exact, s_nominal, ss_nominal)
                    plane = hit_plane
                    n = wp.int64(0)
                    s_exact = wp.vec3d()
                    s_nominal = wp.vec3d()
                    ss_exact = vec6d()
                    ss_nominal = vec6d()
                n += wp.int64(1)
                ref = references[plane]
                if wp.static(f.exact):
                    d = wp.vec3d(p_exact) - ref
                    s_exact += d
                    ss_exact += _outer6(d)
                if wp.static(f.nominal):
                    d = wp.vec3d(p_nominal) - ref
                    s_nominal += d
                    ss_nominal += _outer6(d)
        if plane >= 0:
            _flush(counts, first, second, plane, n, s_exact, ss_exact, s_nominal, ss_nominal)
        if tir > 0:
            wp.atomic_add(counters, COUNT_TIR, tir)
        if miss > 0:
            wp.atomic_add(counters, COUNT_MISS, miss)
        if excluded > 0:
            wp.atomic_add(counters, COUNT_EDGE, excluded)

    return trace_statistics


@wp.func
def _flush(
    counts: wp.array2d(dtype=wp.int64),
    first: wp.array2d(dtype=wp.vec3d),
    second: wp.array2d(dtype=vec6d),
    plane: int,
    n: wp.int64,
    s_exact: wp.vec3d,
    ss_exact: vec6d,
    s_nominal: wp.vec3d,
    ss_nominal: vec6d,
):
    """Add one thread's running sums for ``plane`` to the global per-plane sums."""
    wp.atomic_add(counts, 0, plane, n)
    wp.atomic_add(counts, 1, plane, n)
    wp.atomic_add(first, 0, plane, s_exact)
    wp.atomic_add(first, 1, plane, s_nominal)
    wp.atomic_add(second, 0, plane, ss_exact)
    wp.atomic_add(second, 1, plane, ss_nominal)


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
def emit_rays(
    poses: wp.array(dtype=PulsePose),
    scan: Scan,
    # Out:
    starts: wp.array(dtype=wp.vec3f),  # [m, local]
    directions: wp.array(dtype=wp.vec3f),  # unit; zero where the beam is reflected internally
):
    """The rays the pipeline casts, one per slot, rounded to float32 as the ray cast takes them
    (for timing the bare ray cast)."""
    slot = wp.tid()
    per_pulse = scan.beams.n * scan.beams.n
    pose = poses[slot // per_pulse]
    s3, exit_point, ok = wedge_finish(scan.beam_truth[slot % per_pulse], wedge_pulse_stage(pose.phi64, scan.truth),
                                      scan.truth)
    starts[slot] = wp.vec3f(pose.origin64 + pose.rot64 * exit_point)
    directions[slot] = wp.where(ok, wp.vec3f(pose.rot64 * s3), wp.vec3f(0.0, 0.0, 0.0))


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
