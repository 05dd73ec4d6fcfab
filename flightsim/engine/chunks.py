"""Which pulses go into which launch: every line's samples uploaded once, pulses packed into chunks.

A chunk holds up to a fixed number of pulses taken from one or more lines (segments), so a
flight of many short lines costs few launches, and every device table a chunk needs is uploaded
before the first launch, so the launch loop only queues work.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.scenes.scene import Scene
from kernels import frames
from trajectories import PulseTiming, Trajectory, prime_quaternions

SLOTS_PER_CHUNK = {"cpu": 1 << 18, "cuda": 1 << 24}  # automatic chunk size, in beam slots
POINT_SLOTS_PER_CHUNK = {"cpu": 1 << 18, "cuda": 1 << 22}  # readouts that bring every return to the host


@dataclass(frozen=True)
class Segment:
    """Pulses first ≤ k < first + count of one line, held by a chunk."""

    line: int  # index of the line in the run's line table
    first: int
    count: int


def line_table(trajectories: list[Trajectory], scene: Scene, timing: PulseTiming, boresight: wp.quatd,
               lever_arm: tuple[float, float, float], seed: int, device: str) -> frames.Lines:
    """Every line's samples in the scene's local frame (float64), concatenated, on the device.

    Times are relative to each line's first pulse; the noise seed of a line mixes the run's seed
    and the line id, so noise is keyed by (seed, line, pulse, beam).
    """
    prime_quaternions(trajectories)
    counts = np.array([len(t.gps_time) for t in trajectories], dtype=np.int32)
    lines = frames.Lines()
    lines.times = wp.array(np.concatenate([t.gps_time - t.start_time for t in trajectories]), dtype=wp.float64,
                           device=device)
    lines.positions = wp.array(np.concatenate([scene.world_to_local(t.position) for t in trajectories]),
                               dtype=wp.vec3d, device=device)
    lines.attitudes = wp.array(np.concatenate([t.quaternions() for t in trajectories]), dtype=wp.quatd, device=device)
    lines.sample_start = wp.array(np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32), dtype=wp.int32,
                                  device=device)
    lines.sample_count = wp.array(counts, dtype=wp.int32, device=device)
    lines.cycles0 = wp.array([timing.phase_cycles_at(t.start_time) for t in trajectories], dtype=wp.float64,
                             device=device)
    lines.seed = wp.array([(seed * 1_000_003 + t.line_id) % (1 << 31) for t in trajectories], dtype=wp.int32,
                          device=device)
    lines.boresight = boresight
    lines.lever_arm = wp.vec3d(*lever_arm)
    lines.pulse_period = timing.pulse_period_s
    lines.cycles_per_pulse = timing.cycles_per_pulse
    return lines


def pack(pieces: list[tuple[int, int, int]], capacity: int) -> list[list[Segment]]:
    """Chunks of at most ``capacity`` pulses from pieces (line, k0, k1), in order."""
    chunks: list[list[Segment]] = []
    current: list[Segment] = []
    room = capacity
    for line, k0, k1 in pieces:
        while k0 < k1:
            take = min(room, k1 - k0)
            current.append(Segment(line, k0, take))
            k0 += take
            room -= take
            if room == 0:
                chunks.append(current)
                current, room = [], capacity
    if current:
        chunks.append(current)
    return chunks


def segment_tables(chunks: list[list[Segment]], device: str) -> list[frames.Segments]:
    """Each chunk's segment table, all uploaded at once (the tables are views of three arrays).

    ``pulse_start`` of a chunk holds one entry more than its segments: the chunk's pulse count.
    """
    starts, lines, firsts, bounds = [], [], [], [0]
    for chunk in chunks:
        offsets = np.concatenate([[0], np.cumsum([s.count for s in chunk])])
        starts.append(offsets)
        lines.append([s.line for s in chunk] + [chunk[-1].line])
        firsts.append([s.first for s in chunk] + [chunk[-1].first])
        bounds.append(bounds[-1] + len(offsets))
    if not chunks:
        return []
    all_starts = wp.array(np.concatenate(starts).astype(np.int32), dtype=wp.int32, device=device)
    all_lines = wp.array(np.concatenate(lines).astype(np.int32), dtype=wp.int32, device=device)
    all_firsts = wp.array(np.concatenate(firsts).astype(np.int64), dtype=wp.int64, device=device)
    tables = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        table = frames.Segments()
        table.pulse_start, table.line, table.first_pulse = all_starts[a:b], all_lines[a:b], all_firsts[a:b]
        tables.append(table)
    return tables
