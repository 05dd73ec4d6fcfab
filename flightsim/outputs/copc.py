"""COPC (Cloud Optimized Point Cloud, https://copc.io, version 1.0) from one model's LAS/LAZ tiles.

The file is LAZ 1.4 (point format and extra bytes of the tiles, WKT1 CRS VLR copied from them)
whose first VLR is the ``copc``/1 info record, whose point data holds one variable-size LAZ chunk
per octree node, and whose one EVLR ``copc``/1000 is the hierarchy page listing every node
(key d, x, y, z; byte offset and size of its chunk; point count). A viewer reads the root node
first and the children where it zooms in.

Octree, all in stored integer coordinates (1 unit = the tiles' scale, 1 mm):

- The root is a cube of 2^k units (the least power of two that holds every point with margin),
  centred on the points' bounds, so every voxel edge is a whole number of units and a point's
  voxel at depth d is ``(X - corner) >> (k - d)``, exact.
- Each node is divided into a grid of ``NODE_GRID``³ cells (``spacing`` = root edge / NODE_GRID,
  halved per level). Points are taken in tile order; a point stays in the shallowest node whose
  grid cell it is the first to reach, while that node holds fewer than ``max_node_points``;
  otherwise it goes one level down. At the deepest level (cells of 1 unit, or depth
  ``MAX_DEPTH``) a node takes every point that reaches it. So each point is stored exactly once
  and every ancestor of a non-empty node is non-empty.

Why lazrs and not copclib: copclib's Python binding can declare extra bytes only as anonymous
bytes (``EbVlr(n)`` gives FIELD_0 …, no names, types, units) and writes no GPS-time or WKT
global-encoding bits, so our ``beam_row`` … ``range`` fields would reach readers as raw bytes.
lazrs writes variable-size chunks directly, and laspy writes the header and VLRs of the tiles.

Memory and disk: tiles are read one at a time (the largest tile's records in memory). A node's
grid occupancy is 4 bytes per point it holds and is kept only while some unread tile's bounds
overlap the node, so it is bounded by the points of the nodes that span unread tiles (the
shallow nodes, each at most ``max_node_points``, and the deep nodes along the boundary between
read and unread tiles). Records are bucketed into an uncompressed spill file beside the output
(one uncompressed copy of the model on disk, deleted at the end) and compressed in batches of
whole nodes (about ``COMPRESS_BATCH_POINTS`` records, or the largest node, in memory at once).
"""
from __future__ import annotations

import copy
import dataclasses
import os
import struct
from collections.abc import Sequence
from pathlib import Path

import laspy
import lazrs
import numpy as np
from laspy.vlrs.known import LasZipVlr

from flightsim.core.errors import InputError

NODE_GRID = 128
"""Grid cells per node edge; the COPC ``spacing`` is the root edge / NODE_GRID [m]."""
MAX_NODE_POINTS = 100_000
"""Default cap on the points of a node above the deepest level."""
COMPRESS_BATCH_POINTS = 1_000_000
"""Nodes are compressed (one LAZ chunk each, in parallel) in batches of about this many points."""
MAX_DEPTH = 20
"""Deepest octree level (a node key packs 3 × 20 bits)."""
_GRID_BITS = NODE_GRID.bit_length() - 1
_EVLR_HEADER = struct.Struct("<H16sHQ32s")
_ENTRY = struct.Struct("<iiiiQii")


@dataclasses.dataclass
class _Cube:
    """Root cube in stored integer units: lower corner [units] and edge 2**k [units]."""

    corner: np.ndarray  # int64[3]
    k: int

    @property
    def max_depth(self) -> int:
        """Deepest level: grid cells of one unit, or MAX_DEPTH."""
        return max(0, min(MAX_DEPTH, self.k - _GRID_BITS))


@dataclasses.dataclass
class _Tile:
    """One input tile: path, shift of its stored coordinates into the COPC frame [units], bounds [units]."""

    path: Path
    shift: np.ndarray  # int64[3]
    lowest: np.ndarray  # int64[3], COPC frame
    highest: np.ndarray  # int64[3], COPC frame
    count: int


def write_copc(tile_paths: Sequence[str | os.PathLike], out_path: str | os.PathLike, *,
               max_node_points: int = MAX_NODE_POINTS) -> dict:
    """Write the points of ``tile_paths`` (LAS/LAZ tiles of one model) as one COPC file.

    The file appears under ``out_path`` only when finished (written to ``.<name>.part`` and
    renamed). Returns ``{"points", "nodes", "depth", "spacing_m"}``.
    """
    if not tile_paths:
        raise InputError("tile_paths", list(tile_paths), "at least one LAS/LAZ tile")
    if not isinstance(max_node_points, int) or max_node_points < 1:
        raise InputError("max_node_points", max_node_points, "an integer >= 1")
    out_path = Path(out_path)
    header, tiles = _survey(tile_paths)
    cube = _root_cube(tiles)
    temp = out_path.with_name(f".{out_path.name}.part")
    spill = out_path.with_name(f".{out_path.name}.spill.part")
    try:
        segments, gps = _bucket(tiles, header.point_format, cube, max_node_points, spill)
        _write_file(temp, header, cube, segments, gps, spill)
        os.replace(temp, out_path)
    finally:
        spill.unlink(missing_ok=True)
        temp.unlink(missing_ok=True)
    scale = float(header.scales[0])
    return {"points": int(header.point_count), "nodes": len(segments),
            "depth": max(key[0] for key in segments), "spacing_m": (1 << cube.k) * scale / NODE_GRID}


def write_run_copc(directory: str | os.PathLike, tiles: dict[str, dict[str, int]]) -> dict[str, str]:
    """One COPC file per model of a run, ``directory/<model>.copc.laz``, from the tiles in
    ``directory/<model>/`` named by ``tiles`` ({model: {tile file name: points}}, models without
    points skipped); returns {model: COPC file name}."""
    names = {model: f"{model}.copc.laz" for model, counts in tiles.items() if counts}
    for model, name in names.items():
        write_copc([Path(directory) / model / tile for tile in sorted(tiles[model])], Path(directory) / name)
    return names


# ------------------------------------------------------------------------------ pass 1: headers


def _survey(tile_paths) -> tuple[laspy.LasHeader, list[_Tile]]:
    """The COPC header (from the first tile's, counts and bounds of all) and the tiles' frames."""
    headers = []
    for path in tile_paths:
        try:
            with laspy.open(path) as reader:
                headers.append((Path(path), reader.header))
        except (OSError, laspy.LaspyException) as err:
            raise InputError("tile_paths", str(path), f"a readable LAS/LAZ file ({err})") from err
    first = headers[0][1]
    for path, h in headers:
        if h.point_format != first.point_format or not np.array_equal(h.scales, first.scales):
            raise InputError("tile_paths", str(path), "tiles of one point format, extra bytes and scale")
    if first.scales[0] != first.scales[1] or first.scales[0] != first.scales[2]:
        raise InputError("tile_paths", str(headers[0][0]), "tiles of one scale on x, y and z (a cube octree)")
    if first.point_format.id not in (6, 7, 8):
        raise InputError("tile_paths", str(headers[0][0]), "tiles of point format 6, 7 or 8 (COPC)")
    header = copy.deepcopy(first)
    header.offsets = np.array([np.floor(min(h.mins[0] for _, h in headers)),
                               np.floor(min(h.mins[1] for _, h in headers)), 0.0])
    tiles = [_tile(path, h, header) for path, h in headers if h.point_count > 0]
    if not tiles:
        raise InputError("tile_paths", [str(p) for p, _ in headers], "tiles holding at least one point")
    header.point_count = sum(t.count for t in tiles)
    header.number_of_points_by_return = sum(np.asarray(h.number_of_points_by_return) for _, h in headers)
    header.mins = np.min([t.lowest for t in tiles], axis=0) * header.scales + header.offsets
    header.maxs = np.max([t.highest for t in tiles], axis=0) * header.scales + header.offsets
    return header, tiles


def _tile(path: Path, h: laspy.LasHeader, copc: laspy.LasHeader) -> _Tile:
    """A tile's shift into the COPC frame (whole units, checked) and its stored bounds there."""
    shift_float = (h.offsets - copc.offsets) / copc.scales
    shift = np.rint(shift_float).astype(np.int64)
    if not np.allclose(shift, shift_float, rtol=0.0, atol=1e-6):
        raise InputError("tile_paths", str(path), "tiles whose offsets differ by whole multiples of the scale")
    lowest = np.rint((h.mins - copc.offsets) / copc.scales).astype(np.int64)
    highest = np.rint((h.maxs - copc.offsets) / copc.scales).astype(np.int64)
    if lowest.min() < np.iinfo(np.int32).min or highest.max() > np.iinfo(np.int32).max:
        raise InputError("tile_paths", str(path), "tiles within 2**31 scale units of the others (int32 LAS coordinates)")
    return _Tile(path, shift, lowest, highest, int(h.point_count))


def _root_cube(tiles: list[_Tile]) -> _Cube:
    """The least power-of-two cube that holds every point with at least one unit of margin."""
    lowest = np.min([t.lowest for t in tiles], axis=0)
    highest = np.max([t.highest for t in tiles], axis=0)
    k = int(np.max(highest - lowest) + 2).bit_length()
    corner = (lowest + highest) // 2 - (1 << (k - 1))
    return _Cube(corner.astype(np.int64), k)


# --------------------------------------------------------------- pass 2: nodes, into the spill


class _Occupancy:
    """Grid cells taken in each node, kept while some unread tile overlaps the node."""

    def __init__(self, tiles: list[_Tile], cube: _Cube) -> None:
        self._lowest = np.array([t.lowest for t in tiles])
        self._highest = np.array([t.highest for t in tiles])
        self._cube = cube
        self.counts: dict[tuple, int] = {}
        self._cells: dict[tuple, np.ndarray] = {}
        self._release: dict[int, list[tuple]] = {}

    def cells(self, key: tuple) -> np.ndarray:
        """Sorted taken cells of node ``key`` (d, x, y, z); registers a new node."""
        if key not in self._cells:
            self.counts.setdefault(key, 0)
            self._cells[key] = np.empty(0, dtype=np.int32)
            self._release.setdefault(self._last_tile(key), []).append(key)
        return self._cells[key]

    def take(self, key: tuple, cells: np.ndarray) -> None:
        """Mark ``cells`` (free ones) of node ``key`` as taken."""
        self._cells[key] = np.union1d(self._cells[key], cells).astype(np.int32)
        self.counts[key] += len(cells)

    def tile_done(self, index: int) -> None:
        """Forget the cells of the nodes that no tile after ``index`` overlaps."""
        for key in self._release.pop(index, ()):
            del self._cells[key]

    def _last_tile(self, key: tuple) -> int:
        d, *xyz = key
        edge = 1 << (self._cube.k - d)
        low = self._cube.corner + np.array(xyz, dtype=np.int64) * edge
        overlaps = np.all((self._lowest < low + edge) & (self._highest >= low), axis=1)
        return int(np.flatnonzero(overlaps).max()) if overlaps.any() else -1


def _bucket(tiles, point_format, cube: _Cube, cap: int, spill: Path):
    """Assign every point to a node, appending records to ``spill`` grouped by node.

    Returns ({node key: [(byte offset, count), ...]}, (gps min, gps max)).
    """
    dtype = point_format.dtype()
    occupancy = _Occupancy(tiles, cube)
    segments: dict[tuple, list[tuple[int, int]]] = {}
    gps = [np.inf, -np.inf]
    with open(spill, "wb") as sink:
        for index, tile in enumerate(tiles):
            records = laspy.read(tile.path).points.array
            if records.dtype != dtype:
                raise InputError("tile_paths", str(tile.path), "tiles of one point format")
            for axis, name in enumerate("XYZ"):
                records[name] = records[name].astype(np.int64) + tile.shift[axis]
            xyz = np.column_stack([records[n].astype(np.int64) for n in "XYZ"]) - cube.corner
            keys = _assign(xyz, cube, cap, occupancy)
            order = np.lexsort(keys.T[::-1])
            keys, records = keys[order], records[order]
            starts = np.flatnonzero(np.r_[True, np.any(keys[1:] != keys[:-1], axis=1)])
            for start, stop in zip(starts, np.r_[starts[1:], len(keys)]):
                segments.setdefault(tuple(int(v) for v in keys[start]), []).append((sink.tell(), int(stop - start)))
                sink.write(records[start:stop].tobytes())
            gps = [min(gps[0], float(records["gps_time"].min())), max(gps[1], float(records["gps_time"].max()))]
            occupancy.tile_done(index)
    return segments, gps


def _assign(xyz: np.ndarray, cube: _Cube, cap: int, occupancy: _Occupancy) -> np.ndarray:
    """Node key (d, x, y, z) of each point, xyz relative to the cube's corner [units] (N×3 int64)."""
    keys = np.zeros((len(xyz), 4), dtype=np.int64)
    waiting = np.arange(len(xyz))
    for d in range(cube.max_depth + 1):
        node = xyz[waiting] >> (cube.k - d)
        if d == cube.max_depth:
            keys[waiting] = np.column_stack([np.full(len(waiting), d), node])
            break
        cell = (xyz[waiting] >> (cube.k - d - _GRID_BITS)) & (NODE_GRID - 1)
        local = (cell[:, 0] << (2 * _GRID_BITS)) | (cell[:, 1] << _GRID_BITS) | cell[:, 2]
        taken = _take_level(d, node, local, cap, occupancy)
        keys[waiting[taken]] = np.column_stack([np.full(taken.sum(), d), node[taken]])
        waiting = waiting[~taken]
        if len(waiting) == 0:
            break
    return keys


def _take_level(d: int, node: np.ndarray, local: np.ndarray, cap: int, occupancy: _Occupancy) -> np.ndarray:
    """Which points stay at depth ``d``: first to reach a free cell of a node with room (bool mask)."""
    order = np.lexsort((local, node[:, 2], node[:, 1], node[:, 0]))  # stable: input order within a cell
    n_sorted, l_sorted = node[order], local[order]
    new_cell = np.r_[True, np.any(n_sorted[1:] != n_sorted[:-1], axis=1) | (l_sorted[1:] != l_sorted[:-1])]
    new_node = np.r_[True, np.any(n_sorted[1:] != n_sorted[:-1], axis=1)]
    taken = np.zeros(len(node), dtype=bool)
    starts = np.flatnonzero(new_node)
    for start, stop in zip(starts, np.r_[starts[1:], len(order)]):
        key = (d, *map(int, n_sorted[start]))
        occupied = occupancy.cells(key)
        first = start + np.flatnonzero(new_cell[start:stop])
        free = first[~np.isin(l_sorted[first], occupied, assume_unique=True)]
        free = np.sort(order[free])[: max(0, cap - occupancy.counts[key])]  # input order, up to the cap
        taken[free] = True
        occupancy.take(key, local[free])
    return taken


# ----------------------------------------------------------------------- pass 3: the COPC file


def _write_file(path: Path, header: laspy.LasHeader, cube: _Cube, segments, gps, spill: Path) -> None:
    """Header and VLRs, one LAZ chunk per node, the hierarchy EVLR; then the final header."""
    laz_vlr = lazrs.LazVlr.new_for_compression(header.point_format.id, header.point_format.num_extra_bytes, True)
    header.set_compressed(True)
    kept = _kept_vlrs(header)
    header.vlrs.clear()  # in place: assigning a list would make laspy rebuild the extra-bytes VLR
    header.vlrs.extend([_info_vlr(header, cube, gps, 0, 0), *kept, LasZipVlr(laz_vlr.record_data())])
    record_size = header.point_format.size
    keys = sorted(segments)
    with open(path, "w+b") as out, open(spill, "rb") as source:
        header.write_to(out)
        data_start = out.tell()
        compressor = lazrs.ParLasZipCompressor(out, laz_vlr)
        for batch in _batches(keys, segments):
            compressor.compress_chunks([_node_bytes(source, segments[key], record_size) for key in batch])
        compressor.done()
        evlr_start = out.tell()
        out.seek(data_start)
        chunks = lazrs.read_chunk_table(out, laz_vlr)
        entries = _hierarchy(keys, chunks, data_start + 8)
        out.seek(evlr_start)
        out.write(_EVLR_HEADER.pack(0, b"copc", 1000, len(entries), b"EPT hierarchy"))
        out.write(entries)
        header.start_of_first_evlr = evlr_start
        header.number_of_evlrs = 1
        header.vlrs[0] = _info_vlr(header, cube, gps, evlr_start + _EVLR_HEADER.size, len(entries))
        out.seek(0)
        header.write_to(out, ensure_same_size=True)
        out.flush()
        os.fsync(out.fileno())


def _kept_vlrs(header: laspy.LasHeader) -> list:
    """The tiles' VLRs but their LAZ and any COPC records."""
    return [v for v in header.vlrs if not isinstance(v, LasZipVlr) and v.user_id != "copc"]


def _batches(keys: list[tuple], segments) -> list[list[tuple]]:
    """``keys`` in runs of at most ``COMPRESS_BATCH_POINTS`` points (or one node), compressed in parallel."""
    batches, size = [[]], 0
    for key in keys:
        n = sum(count for _, count in segments[key])
        if batches[-1] and size + n > COMPRESS_BATCH_POINTS:
            batches.append([])
            size = 0
        batches[-1].append(key)
        size += n
    return batches


def _node_bytes(source, segments: list[tuple[int, int]], record_size: int) -> np.ndarray:
    """One node's records, gathered from its segments of the spill file (uint8)."""
    parts = []
    for offset, count in segments:
        source.seek(offset)
        parts.append(np.frombuffer(source.read(count * record_size), dtype=np.uint8))
    return np.concatenate(parts)


def _hierarchy(keys: list[tuple], chunks: list[tuple[int, int]], first_offset: int) -> bytes:
    """The hierarchy page: one 32-byte entry per node (key, chunk offset, byte size, point count)."""
    if len(chunks) != len(keys):
        raise RuntimeError(f"LAZ chunk table has {len(chunks)} chunks for {len(keys)} octree nodes")
    entries, offset = [], first_offset
    for key, (count, size) in zip(keys, chunks):
        entries.append(_ENTRY.pack(*key, offset, size, count))
        offset += size
    return b"".join(entries)


def _info_vlr(header: laspy.LasHeader, cube: _Cube, gps, hierarchy_offset: int, hierarchy_size: int) -> laspy.VLR:
    """The ``copc``/1 info VLR: cube centre and half edge [m], root spacing [m], hierarchy page, GPS range [s]."""
    scale = header.scales
    half = (1 << (cube.k - 1))
    center = (cube.corner + half) * scale + header.offsets
    data = struct.pack("<5d2Q2d11Q", *center, half * scale[0], 2 * half * scale[0] / NODE_GRID,
                       hierarchy_offset, hierarchy_size, gps[0], gps[1], *([0] * 11))
    return laspy.VLR("copc", 1, "copc info", data)
