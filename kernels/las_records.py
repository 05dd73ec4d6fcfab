"""LAS 1.4 point records packed on the device, bucketed by tile (the points path of ``flightsim simulate``).

A chunk's returns (slots of the points kernel, listed by ``kernels.trace.slot_indices``) become point
data record format 6 plus flightsim's extra bytes, byte for byte what
:class:`flightsim.outputs.las_tiles.TileWriter` writes from host arrays, so only finished records cross
to the host. Steps, per georeferencing model:

1. :func:`tile_extent` — the range of tile indices the chunk's points fall in (atomics, 4 ints back);
2. :func:`tile_keys` — each return's tile as one int32 key (column-major over that range), with its
   return index as the value; a stable radix sort by key then keeps slot order within a tile, the
   order the host writer keeps;
3. run-length encoding of the sorted keys (host: Warp's utilities) gives each tile's first record;
4. :func:`pack_records` — each sorted record as 32-bit words (the record length is a multiple of 4),
   and each tile's min/max of the stored X, Y, Z (header bounds) by atomics.

Quantisation is the host writer's float64 arithmetic: X = rint((float64(p) + origin) / 0.001) in mm,
less the tile's lower-left corner; gps time = line start + k / PRF; intensity = rint(clip(cos θ, 0, 1)
· 65535) in float32; scan angle = rint(float64(angle) / 0.006); prism angle = float32(degrees(φ)).
"""
from __future__ import annotations

import functools

import warp as wp

from kernels import frames

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

SCALE_MM = wp.constant(wp.float64(0.001))  # LAS coordinate unit [m]
SCAN_ANGLE_UNIT = wp.constant(wp.float64(0.006))  # LAS 1.4 scan-angle unit [deg]
DEG_PER_RAD = wp.constant(wp.float64(57.29577951308232))  # numpy.degrees' factor 180/π
TWO_PI = wp.constant(wp.float64(6.283185307179586))
BASE_WORDS = 11  # format 6 (30 bytes) + beam_row, beam_col, prism_angle, range, plane_id (14 bytes)
RETURN_BITS = wp.constant(wp.uint32(0x11))  # return number 1 of 1


@wp.struct
class RecordTables:
    """What a chunk's records are made from, besides the points kernel's per-slot outputs."""

    origin: wp.vec3d  # world E, N, H of the local origin [m]
    tile_mm: wp.int64  # tile edge [mm]
    prf_hz: wp.float64  # pulse rate [Hz]
    beams_per_pulse: wp.int32
    returns_per_beam: wp.int32  # slots per beam (over a canopy: the detector's max_returns)
    beam_columns: wp.int32  # beam index b → row b / columns, column b % columns
    face_class: wp.array(dtype=wp.int32)  # ASPRS class of each triangle
    face_plane: wp.array(dtype=wp.int32)  # plane id written for each triangle
    line_start: wp.array(dtype=wp.float64)  # adjusted GPS time of each line's pulse 0 [s]
    line_source: wp.array(dtype=wp.int32)  # point source id (flight line id) of each line
    segment_start: wp.array(dtype=wp.int32)  # first chunk pulse of each of the chunk's segments (+ the end)
    segment_line: wp.array(dtype=wp.int32)  # line index of each segment
    segments: wp.int32


@wp.func
def quantised(p: wp.vec3f, origin: wp.vec3d):
    """World coordinates of local point ``p`` on the 1 mm grid [mm], as the host writer rounds them."""
    x = wp.int64(wp.rint((wp.float64(p[0]) + origin[0]) / SCALE_MM))
    y = wp.int64(wp.rint((wp.float64(p[1]) + origin[1]) / SCALE_MM))
    z = wp.int64(wp.rint((wp.float64(p[2]) + origin[2]) / SCALE_MM))
    return x, y, z


@wp.func
def floor_div(a: wp.int64, b: wp.int64):
    """⌊a / b⌋ for b > 0 (numpy's floor_divide)."""
    q = a / b
    if q * b > a:
        q -= wp.int64(1)
    return q


@wp.kernel
def tile_extent(
    index: wp.array(dtype=wp.int32),  # slot of each return
    points: wp.array(dtype=wp.vec3f),  # per slot, local [m]
    tables: RecordTables,
    extent: wp.array(dtype=wp.int32),  # out: min ix, max ix, min iy, max iy (start at ±max)
):
    """Range of the tile indices of the chunk's returns."""
    x, y, z = quantised(points[index[wp.tid()]], tables.origin)
    ix = wp.int32(floor_div(x, tables.tile_mm))
    iy = wp.int32(floor_div(y, tables.tile_mm))
    wp.atomic_min(extent, 0, ix)
    wp.atomic_max(extent, 1, ix)
    wp.atomic_min(extent, 2, iy)
    wp.atomic_max(extent, 3, iy)


@wp.kernel
def tile_keys(
    index: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3f),
    tables: RecordTables,
    ix0: wp.int32,
    iy0: wp.int32,
    rows: wp.int32,  # tiles along y in the extent
    keys: wp.array(dtype=wp.int32),  # out: (ix − ix0) · rows + (iy − iy0)
    values: wp.array(dtype=wp.int32),  # out: the return's index
):
    i = wp.tid()
    x, y, z = quantised(points[index[i]], tables.origin)
    ix = wp.int32(floor_div(x, tables.tile_mm))
    iy = wp.int32(floor_div(y, tables.tile_mm))
    keys[i] = (ix - ix0) * rows + (iy - iy0)
    values[i] = i


@wp.kernel
def reset_bounds(bounds: wp.array2d(dtype=wp.int32)):
    """Each tile's X, Y, Z min (+max int32) and max (−max int32) before the atomics."""
    r, c = wp.tid()
    bounds[r, c] = wp.where(c < 3, 2147483647, -2147483647)


@wp.func
def _low16(v: wp.int64):
    return wp.uint32(v & wp.int64(0xFFFF))


@functools.cache
def pack_kernel(position_error: bool, edge_distance: bool, multi_return: bool = False):
    """The record-packing kernel with the optional extra bytes compiled in or out, and each record's return
    number and number of returns from ``returns`` (``multi_return``) or 1 of 1."""
    words = BASE_WORDS + int(position_error) + int(edge_distance)

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False)
    def pack_records(
        index: wp.array(dtype=wp.int32),  # slot of each return
        order: wp.array(dtype=wp.int32),  # return index of each sorted record
        starts: wp.array(dtype=wp.int32),  # first sorted record of each tile
        tile_keys: wp.array(dtype=wp.int32),  # key of each tile
        runs: int,
        ix0: wp.int32,
        iy0: wp.int32,
        rows: wp.int32,
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        ranges: wp.array(dtype=wp.float32),
        faces: wp.array(dtype=wp.int32),
        scan_angles: wp.array(dtype=wp.float32),
        cos_incidence: wp.array(dtype=wp.float32),
        edge: wp.array(dtype=wp.float32),
        truth: wp.array(dtype=wp.vec3f),
        points: wp.array(dtype=wp.vec3f),
        returns: wp.array(dtype=wp.int32),  # per slot: return number | number of returns << 4 (multi_return)
        tables: RecordTables,
        records: wp.array2d(dtype=wp.uint32),  # out: one row of words per record
        bounds: wp.array2d(dtype=wp.int32),  # out: per tile min X, Y, Z, max X, Y, Z (atomics)
    ):
        p = wp.tid()
        slot = index[order[p]]
        beam_slot = slot / tables.returns_per_beam
        pulse = beam_slot / tables.beams_per_pulse
        beam = beam_slot - pulse * tables.beams_per_pulse
        r = frames.last_at_or_below(starts, 0, runs + 1, p)
        key = tile_keys[r]
        tx = wp.int64(ix0 + key / rows) * tables.tile_mm
        ty = wp.int64(iy0 + key % rows) * tables.tile_mm
        x, y, z = quantised(points[slot], tables.origin)
        xs = wp.int32(x - tx)
        ys = wp.int32(y - ty)
        zs = wp.int32(z)
        wp.atomic_min(bounds, r, 0, xs)
        wp.atomic_min(bounds, r, 1, ys)
        wp.atomic_min(bounds, r, 2, zs)
        wp.atomic_max(bounds, r, 3, xs)
        wp.atomic_max(bounds, r, 4, ys)
        wp.atomic_max(bounds, r, 5, zs)

        s = frames.last_at_or_below(tables.segment_start, 0, tables.segments + 1, pulse)
        line = tables.segment_line[s]
        k = pulses[frames.ROW_PULSE, pulse]
        gps = tables.line_start[line] + k / tables.prf_hz
        phi = pulses[frames.ROW_PHI, pulse]
        if phi >= TWO_PI:
            phi = wp.float64(0.0)
        cos_i = wp.clamp(cos_incidence[slot], wp.float32(0.0), wp.float32(1.0))
        intensity = wp.uint32(wp.rint(cos_i * wp.float32(65535.0)))
        angle = wp.int32(wp.rint(wp.float64(scan_angles[slot]) / SCAN_ANGLE_UNIT))
        face = faces[slot]
        bits = wp.cast(gps, wp.int64)

        records[p, 0] = wp.cast(xs, wp.uint32)
        records[p, 1] = wp.cast(ys, wp.uint32)
        records[p, 2] = wp.cast(zs, wp.uint32)
        echo = RETURN_BITS
        if wp.static(multi_return):
            echo = wp.uint32(returns[slot])
        records[p, 3] = intensity | (echo << wp.uint32(16))
        records[p, 4] = wp.uint32(tables.face_class[face]) | ((wp.cast(angle, wp.uint32) & wp.uint32(0xFFFF)) << wp.uint32(16))
        records[p, 5] = wp.uint32(tables.line_source[line]) | (_low16(bits) << wp.uint32(16))
        records[p, 6] = wp.uint32((bits >> wp.int64(16)) & wp.int64(0xFFFFFFFF))
        row = wp.uint32(beam / tables.beam_columns)
        column = wp.uint32(beam % tables.beam_columns)
        records[p, 7] = _low16(bits >> wp.int64(48)) | (row << wp.uint32(16)) | (column << wp.uint32(24))
        records[p, 8] = wp.cast(wp.float32(phi * DEG_PER_RAD), wp.uint32)
        records[p, 9] = wp.cast(ranges[slot], wp.uint32)
        records[p, 10] = wp.cast(tables.face_plane[face], wp.uint32)
        w = int(BASE_WORDS)
        if wp.static(position_error):
            d = wp.vec3d(points[slot]) - wp.vec3d(truth[slot])
            records[p, w] = wp.cast(wp.float32(wp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])), wp.uint32)
            w += 1
        if wp.static(edge_distance):
            records[p, w] = wp.cast(edge[slot], wp.uint32)

    pack_records.words = words
    return pack_records
