"""Statistics mode on the device: each slot's record (the plane it hit and its points), the settling of records near
plane boundaries, and the reduction of the records to per-plane float64 moments (several copies of the sums,
added at the end); the plane and patch codes of the points path's reductions."""
import functools

import warp as wp

from kernels.edges import boundary_distance, near_boundary
from kernels.parts import Instrument
from kernels.looks import FIRST_LOOK, SECOND_LOOK, Misses, list_miss
from kernels.trace import (COUNT_EDGE, COUNT_MISS, COUNT_TIR, STATUS_MISS, STATUS_RETRY, STATUS_RETURN, STATUS_TIR,
                           Features, scan_struct, slot_function)

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

# statistics-mode record codes of slots that do not count (a plane id otherwise)
CODE_MISS = wp.constant(-1)
CODE_TIR = wp.constant(-2)
CODE_EDGE = wp.constant(-3)  # a return within the edge buffer of its plane's boundary
CODE_NEAR = wp.constant(-4)  # CODE_NEAR − plane id: a return on that plane still to be checked against the buffer
CODE_SCORED = wp.constant(-100)  # _left_out's answer for a scored return (never stored: its group is)


vec6d = wp.types.vector(6, wp.float64)


@wp.func
def _outer6(d: wp.vec3d):
    """Upper triangle of d·dᵀ: xx, xy, xz, yy, yz, zz."""
    return vec6d(d[0] * d[0], d[0] * d[1], d[0] * d[2], d[1] * d[1], d[1] * d[2], d[2] * d[2])


@functools.cache
def records_kernel(f: Features, instrument: Instrument, max_registers: int | None = None, look: int = FIRST_LOOK):
    """Statistics mode, step 1: one thread per slot traces and georeferences its beam and writes a
    compact record: the plane it hit (or why it does not count) and its points.

    One slot per thread keeps a warp's rays as coherent as the bare ray cast's and the per-thread
    state small. A return the edge grid cannot place clear of the plane boundaries is written as
    CODE_NEAR − plane and listed, with its true point, for :data:`check_edges` to settle (a short
    dense list, so the boundary queries do not hold up whole warps of returns that need none); the
    per-plane sums are left to :func:`reduce_records`.
    """
    trace_slot = slot_function(f, instrument, look)
    Scan = scan_struct(instrument)

    @wp.kernel(module="unique", enable_backward=False, cuda_max_registers=max_registers, grid_stride=False)
    def trace_records(
        # In:
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        face_plane: wp.array(dtype=wp.int32),  # plane id of each triangle
        misses: Misses,  # the first look's misses: listed by the first look, traced by the second
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
        if wp.static(look == SECOND_LOOK):
            if slot >= misses.count[0]:
                return
            slot = misses.slots[slot]
        per_pulse = scan.per_pulse
        s = trace_slot(pulses, slot // per_pulse, slot % per_pulse, scan)
        code, face, p_exact, p_nominal, p_true = s.status, s.face, s.p_exact, s.p_nominal, s.p_true
        if code == STATUS_RETRY:
            list_miss(misses, slot)
        elif code == STATUS_TIR:
            codes[slot] = CODE_TIR
        elif code == STATUS_MISS:
            codes[slot] = CODE_MISS
        else:
            plane = face_plane[face]
            if wp.static(f.edges):
                if near_boundary(scan.edge_grid, p_true):
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

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
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
            distance = boundary_distance(scan.edge_grid, scan.boundary_a, scan.boundary_b, near_points[k],
                                          scan.edge_cap)
            codes[slot] = wp.where(distance < edge_buffer, CODE_EDGE, CODE_NEAR - codes[slot])

    return check_edges


_REDUCE_RUN = f"""
    const int code_tir = {CODE_TIR}, code_miss = {CODE_MISS}, code_edge = {CODE_EDGE};
    const int count_tir = {COUNT_TIR}, count_miss = {COUNT_MISS}, count_edge = {COUNT_EDGE};
""" + r"""
    // the reference of the run's plane and the run's sums held in registers: loaded and reset when the plane changes
    int plane = -1;
    wp::int64 n = 0;
    double r0 = 0.0, r1 = 0.0, r2 = 0.0;
    double s0 = 0.0, s1 = 0.0, s2 = 0.0;
    double q0 = 0.0, q1 = 0.0, q2 = 0.0, q3 = 0.0, q4 = 0.0, q5 = 0.0;
    int tir = 0, miss = 0, excluded = 0;
    auto flush = [&]() {
        wp::atomic_add(counts, replica, model, plane, n);
        wp::atomic_add(first, replica, model, plane, wp::vec_t<3, wp::float64>(s0, s1, s2));
        wp::vec_t<6, wp::float64> q;
        q.c[0] = q0; q.c[1] = q1; q.c[2] = q2; q.c[3] = q3; q.c[4] = q4; q.c[5] = q5;
        wp::atomic_add(second, replica, model, plane, q);
    };
    auto take = [&](const int code, const float x, const float y, const float z) {  // one slot's record
        if (code < 0) {
            tir += code == code_tir ? 1 : 0;
            miss += code == code_miss ? 1 : 0;
            excluded += code == code_edge ? 1 : 0;
            return;
        }
        if (code != plane) {
            if (plane >= 0)
                flush();
            plane = code;
            const wp::vec_t<3, wp::float64> reference = *wp::address(references, plane);
            r0 = reference[0]; r1 = reference[1]; r2 = reference[2];
            n = 0;
            s0 = 0.0; s1 = 0.0; s2 = 0.0;
            q0 = 0.0; q1 = 0.0; q2 = 0.0; q3 = 0.0; q4 = 0.0; q5 = 0.0;
        }
        const double d0 = (double)x - r0;
        const double d1 = (double)y - r1;
        const double d2 = (double)z - r2;
        n += 1;
        s0 = s0 + d0; s1 = s1 + d1; s2 = s2 + d2;
        // each product a statement of its own, then its sum: the operations Warp's generated code makes
        const double xx = d0 * d0; const double xy = d0 * d1; const double xz = d0 * d2;
        const double yy = d1 * d1; const double yz = d1 * d2; const double zz = d2 * d2;
        q0 = q0 + xx; q1 = q1 + xy; q2 = q2 + xz; q3 = q3 + yy; q4 = q4 + yz; q5 = q5 + zz;
    };
    int slot = begin;
#if defined(__CUDA_ARCH__)
    // four slots' records in four 16-byte loads (a code each, then their twelve coordinates) where the arrays are
    // dense and aligned: a thread's slots are consecutive, so a warp's scalar loads touch 32 cache lines each
    const bool dense = codes.strides[0] == 4 && points.strides[0] == 12 && (begin & 3) == 0
        && (reinterpret_cast<unsigned long long>(codes.data) & 15) == 0 && (reinterpret_cast<unsigned long long>(points.data) & 15) == 0;
    if (dense) {
        for (; slot + 4 <= end; slot += 4) {
            const int4 c = *reinterpret_cast<const int4*>(codes.data + slot);
            const float4* xyz = reinterpret_cast<const float4*>(reinterpret_cast<const float*>(points.data) + 3 * slot);
            const float4 a = xyz[0], b = xyz[1], e = xyz[2];
            take(c.x, a.x, a.y, a.z);
            take(c.y, a.w, b.x, b.y);
            take(c.z, b.z, b.w, e.x);
            take(c.w, e.y, e.z, e.w);
        }
    }
#endif
    for (; slot < end; ++slot) {
        const int code = *wp::address(codes, slot);
        if (code < 0) {
            take(code, 0.0f, 0.0f, 0.0f);
        } else {
            const wp::vec3 p = *wp::address(points, slot);
            take(code, p[0], p[1], p[2]);
        }
    }
    if (plane >= 0)
        flush();
    if (count_codes != 0) {
        if (tir > 0) wp::atomic_add(counters, count_tir, tir);
        if (miss > 0) wp::atomic_add(counters, count_miss, miss);
        if (excluded > 0) wp::atomic_add(counters, count_edge, excluded);
    }
"""


@wp.func_native(_REDUCE_RUN)
def _reduce_run(codes: wp.array(dtype=wp.int32), points: wp.array(dtype=wp.vec3f), model: int, count_codes: int,
                begin: int, end: int, replica: int, references: wp.array(dtype=wp.vec3d),
                counts: wp.array3d(dtype=wp.int64), first: wp.array3d(dtype=wp.vec3d),
                second: wp.array3d(dtype=vec6d), counters: wp.array(dtype=wp.int32)): ...


@wp.kernel
def reduce_records(
    # In:
    codes: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3f),  # one model's points [m, local]
    model: wp.int32,  # its index in the sums (exact 0, nominal 1)
    count_codes: wp.int32,  # 1: also count the TIR, missed and edge-excluded slots (once per chunk)
    n_slots: wp.int32,
    slots_per_thread: wp.int32,
    references: wp.array(dtype=wp.vec3d),  # reference point of each plane [m, local]
    # Out: per replica, per model, per plane
    counts: wp.array3d(dtype=wp.int64),
    first: wp.array3d(dtype=wp.vec3d),  # Σ (p − ref)
    second: wp.array3d(dtype=vec6d),  # Σ upper triangle of (p − ref)(p − ref)ᵀ
    counters: wp.array(dtype=wp.int32),  # [TIR, misses, edge-excluded]
):
    """Statistics mode, step 2: per-plane float64 moments of one model's records of a chunk (a launch per
    model, so that a thread holds one model's running sums: half the registers of both at once).

    Each thread takes a run of consecutive slots (consecutive beams of a pulse, then the next pulse: the
    order in which the beams' footprints lie closest) and keeps running sums while the plane stays the same,
    adding them to the global sums (atomics) only when the plane changes. Neighbouring threads mostly hold
    the same plane too, so thread t adds to replica t mod R of the sums (R = the sums' first dimension),
    spreading the atomics on a busy plane over R addresses; the host adds the replicas.

    The loop is native code (:data:`_REDUCE_RUN`): written in Warp, each branch's assignments became selects
    over every running sum (Warp's code is in static single assignment), ~170 instructions a slot against ~45
    (results/profile-experiments.md, section 44).
    """
    begin = wp.tid() * slots_per_thread
    end = wp.min(begin + slots_per_thread, n_slots)
    _reduce_run(codes, points, model, count_codes, begin, end, wp.tid() % counts.shape[0], references, counts,
                first, second, counters)


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
    codes: wp.array(dtype=wp.int32),  # out: the plane of a return, else a CODE_* (reduce_records' input)
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
    model: int,
    plane: int,
    n: wp.int64,
    s: wp.vec3d,
    ss: vec6d,
):
    """Add one thread's running sums of a model for ``plane`` to a replica of the global per-plane sums."""
    wp.atomic_add(counts, replica, model, plane, n)
    wp.atomic_add(first, replica, model, plane, s)
    wp.atomic_add(second, replica, model, plane, ss)


@wp.kernel
def add_replicas(
    counts: wp.array3d(dtype=wp.int64),  # per replica, model, group (reduce_records' sums)
    first: wp.array3d(dtype=wp.vec3d),
    second: wp.array3d(dtype=vec6d),
    block: wp.int32,  # replicas a thread adds
    # Out: per block of replicas, model, group
    block_counts: wp.array3d(dtype=wp.int64),
    block_first: wp.array3d(dtype=wp.vec3d),
    block_second: wp.array3d(dtype=vec6d),
):
    """Add the replicas of the reduction's sums in blocks of ``block`` (the block's first replica first): one
    thread per (block, model, group), so that few groups still make threads enough to hide the loads' latency and
    only the totals leave the device."""
    b, model, group = wp.tid()
    n = wp.int64(0)
    s = wp.vec3d()
    ss = vec6d()
    for replica in range(b * block, wp.min((b + 1) * block, counts.shape[0])):
        n += counts[replica, model, group]
        s += first[replica, model, group]
        ss += second[replica, model, group]
    block_counts[b, model, group] = n
    block_first[b, model, group] = s
    block_second[b, model, group] = ss
