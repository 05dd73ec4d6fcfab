"""An uncompressed LAS 1.4 tile written without a laspy writer per tile: the bytes laspy's own ``LasWriter`` starts
and finishes a file with are made once per tile writer (:func:`header_bytes`: the header and VLRs of the tiles'
template), and a tile changes only the header fields that differ between tiles, at their fixed places in the LAS 1.4
public header block (ASPRS LAS 1.4 R15, Table 3): the offsets when it is made, the bounds and point counts when it is
closed. The bytes are those laspy's writer makes (``tests/test_las.py`` compares them); a writer per tile deep-copied
the template's header and VLRs under Python's lock (~0.7 ms a tile, ~1,650 tiles in a 30 s ATLAS pass).

Every record is return 1 of 1 (the tiles' format), so the points by return are the point count in the first place.
"""
from __future__ import annotations

import io
import os
import struct

import numpy as np

from flightsim.core.atomic import write_back_since

OFFSETS_AT = 155  # X, Y, Z offset: three float64
BOUNDS_AT = 179  # max X, min X, max Y, min Y, max Z, min Z: six float64
COUNTS_AT = 247  # number of point records (uint64), then the points by return (15 uint64)
HEADER_SIZE = 375
_FLOAT64 = np.finfo(np.float64)


def header_bytes(template) -> bytes:
    """The bytes of an uncompressed LAS file of laspy header ``template`` (its VLRs included) holding no points, as
    laspy's ``LasWriter`` writes it (the template itself is left as it is: the writer works on a copy)."""
    import laspy
    with io.BytesIO() as out:
        laspy.LasWriter(out, template, do_compress=False, closefd=False).close()
        return out.getvalue()


class PlainTile:
    """One uncompressed tile's temporary file: records appended as they come (a durable tile's handed to the disk's
    write-back as they are written), the header's bounds and counts written at :meth:`close`."""

    held_points = 0  # an uncompressed tile holds no records back

    def __init__(self, file, scales: np.ndarray, offsets: np.ndarray, count: int, mins: np.ndarray,
                 maxs: np.ndarray, durable: bool) -> None:
        self._file = file
        self._scales, self._offsets = scales, offsets
        self._count, self._mins, self._maxs = count, mins, maxs
        self._durable = durable
        self._written = file.tell()  # where the bytes not yet handed to the disk's write-back start

    @classmethod
    def create(cls, path, head: bytes, scales: np.ndarray, offsets: np.ndarray, durable: bool) -> PlainTile:
        """A new tile at ``path``: ``head`` (:func:`header_bytes`) with the tile's ``offsets`` [m]."""
        offsets = np.asarray(offsets, dtype=np.float64)
        file = open(path, "w+b")
        try:
            file.write(head[:OFFSETS_AT] + struct.pack("<3d", *offsets) + head[OFFSETS_AT + 24:])
        except BaseException:
            file.close()
            raise
        return cls(file, np.asarray(scales, dtype=np.float64), offsets, 0, np.full(3, _FLOAT64.max),
                   np.full(3, _FLOAT64.min), durable)

    @classmethod
    def reopen(cls, path, durable: bool) -> PlainTile:
        """A closed tile opened again to append to: its scales, offsets, bounds and count read from its header."""
        file = open(path, "r+b")
        try:
            head = file.read(HEADER_SIZE)
            file.seek(0, os.SEEK_END)
        except BaseException:
            file.close()
            raise
        scales, offsets = (np.array(struct.unpack_from("<3d", head, at)) for at in (OFFSETS_AT - 24, OFFSETS_AT))
        bounds = np.array(struct.unpack_from("<6d", head, BOUNDS_AT))
        (count,) = struct.unpack_from("<Q", head, COUNTS_AT)
        return cls(file, scales, offsets, count, bounds[1::2].copy(), bounds[0::2].copy(), durable)

    def write(self, records: np.ndarray, lowest, highest) -> None:
        """Append ``records`` (the tile format's structured array) whose stored X, Y, Z range over [lowest, highest]
        (ints, mm); the bounds grow as laspy's writer grows them (stored integer · scale + offset)."""
        self._file.write(np.ascontiguousarray(records).data)
        if self._durable:
            self._written = write_back_since(self._file, self._written)
        self._maxs = np.maximum(self._maxs, np.asarray(highest, dtype=np.int64) * self._scales + self._offsets)
        self._mins = np.minimum(self._mins, np.asarray(lowest, dtype=np.int64) * self._scales + self._offsets)
        self._count += len(records)

    def flush(self) -> None:
        """Nothing is held back."""

    def close(self) -> None:
        """Write the header's bounds (0 for a tile without points, as laspy's writer) and counts, and close."""
        try:
            mins, maxs = (self._mins, self._maxs) if self._count else (np.zeros(3), np.zeros(3))
            self._file.seek(BOUNDS_AT)
            self._file.write(struct.pack("<6d", maxs[0], mins[0], maxs[1], mins[1], maxs[2], mins[2]))
            self._file.seek(COUNTS_AT)
            self._file.write(struct.pack("<16Q", self._count, self._count, *([0] * 14)))
            self._file.flush()
        finally:
            self._file.close()

    def discard(self) -> None:
        """Close the file without finishing it (its contents are to be deleted)."""
        self._file.close()
