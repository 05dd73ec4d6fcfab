"""A chunk's photon detections straight into a frame's gridding arrays, in one pass over the slots.

The photons readout samples each slot's detections into rows of ``times`` / ``signal`` (kernels/photon.py);
a frame to be gridded (flightsim.scoring.photon_grid.PhotonFrame) wants each detection's position on its
believed beam and its beam's angle cell, in slot order, after the frame's earlier chunks. One thread per
slot does it: the believed beam is worked out once per slot (not once per detection), every detection is
placed at c·t/2 along it and written at ``total[0] + offsets[slot] + k`` (``offsets``: the exclusive scan of
the slot counts; ``total``: the frame's photons so far, kept on the device), so no count has to come to the
host between chunks. Writes past ``capacity`` are dropped; the frame's total still counts them, so the host
sees the overflow once, at the end of the frame, and runs the frame again in larger arrays (the photons are
keyed by slot: the same photons again). Per detection it reads 9 bytes and writes 32, where the separate
gather, placing and appending passes moved about 150.
"""
import functools

import warp as wp

from kernels.frames import ROW_ORIGIN, ROW_ROT, get3, get33
from kernels.parts import Instrument
from kernels.photon_grid import angle_cell
from kernels.trace import HALF_LIGHT_SPEED, pulse_rows, scan_struct

wp.set_module_options({"enable_backward": False, "default_grid_stride": False})

MAX_REGISTERS = 64  # on a GPU: 72 uncapped (38 % occupancy); at 64 (50 %), with 56/64 B spilled, the frame kernel
# takes 2.36 ms of a MODE-A frame against 2.77 (H100; results/profile-experiments.md, section 50)


@functools.cache
def frame_photons_kernel(instrument: Instrument):
    """The kernel placing a chunk's detections into a frame's arrays (one thread per slot), for one instrument's
    believed deflector."""
    deflector = instrument.deflector
    Scan = scan_struct(instrument)
    row_believed = pulse_rows(instrument).believed

    @wp.kernel(module="unique", enable_backward=False, grid_stride=False, cuda_max_registers=MAX_REGISTERS)
    def frame_photons(
        pulses: wp.array2d(dtype=wp.float64),  # the chunk's pulse table
        scan: Scan,
        counts: wp.array(dtype=wp.int32),  # detections of each slot
        offsets: wp.array(dtype=wp.int32),  # exclusive scan of counts
        times: wp.array2d(dtype=wp.float64),  # [slot, k] time of flight of each detection [s]
        signal: wp.array2d(dtype=wp.int8),  # [slot, k] 0 noise, else the echo it came from
        total: wp.array(dtype=wp.int32),  # [0]: the frame's photons before this chunk
        capacity: int,  # rows of xyz and cell
        half_field: wp.float64,  # the angle grid's half field [rad]
        cells: int,  # angle cells per side
        # Out:
        xyz: wp.array(dtype=wp.vec3d),  # the frame's photon positions [m, local]; NaN where the believed beam cannot leave
        cell: wp.array(dtype=wp.vec2i),  # the frame's photon angle cells (column, row; −1 outside the field)
        signal_count: wp.array(dtype=wp.int64),  # 1024 counters of signal photons (summed by the host)
    ):
        slot = wp.tid()
        n = counts[slot]
        if n == 0:
            return
        per_pulse = scan.per_pulse
        p = slot // per_pulse
        s3, exit_point, ok = deflector.finish(scan.beam_believed[slot % per_pulse], pulses, row_believed, p,
                                              scan.believed)
        origin = get3(pulses, ROW_ORIGIN, p)
        rot = get33(pulses, ROW_ROT, p)
        beam_cell = angle_cell(wp.vec3f(rot * s3), half_field, cells)
        nan = wp.float64(wp.nan)
        base = total[0] + offsets[slot]
        flagged = int(0)
        for k in range(n):
            r = times[slot, k] * HALF_LIGHT_SPEED
            i = base + k
            if i < capacity:
                xyz[i] = wp.where(ok, origin + rot * (exit_point + r * s3), wp.vec3d(nan, nan, nan))
                cell[i] = beam_cell
            if signal[slot, k] != wp.int8(0):
                flagged += 1
        if flagged > 0:
            wp.atomic_add(signal_count, slot & 1023, wp.int64(flagged))

    return frame_photons


@wp.kernel
def advance_total(counts: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), last: int,
                  total: wp.array(dtype=wp.int32), found: wp.array(dtype=wp.int32)):
    """Add a chunk's detections (``offsets[last] + counts[last]``, the last slot's) to the frame's ``total[0]`` and
    the run's ``found[0]`` (one thread)."""
    n = offsets[last] + counts[last]
    total[0] = total[0] + n
    found[0] = found[0] + n
