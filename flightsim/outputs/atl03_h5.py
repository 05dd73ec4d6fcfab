"""Photon events as an ATL03 granule (h5py), for photon-counting runs from orbit: per beam a ground-track group laid
out as ICESat-2's ATL03 (Neumann et al., ATL03 ATBD and data dictionary), named ``gt1l`` … ``gt3r`` for ATLAS's
beam pairs (the ``pairs`` emitter) and ``gtN`` (N = beam + 1) for any other emitter. ``atl03.h5``:

gtx/heights/delta_time        float64  time of the photon's shot since the ATLAS SDP epoch 2018-01-01T00:00:00Z [s]
                                       (GPS seconds − ancillary_data/atlas_sdp_gps_epoch), a dimension scale
gtx/heights/lat_ph, lon_ph    float64  geodetic latitude, longitude of the photon [deg]
gtx/heights/h_ph              float64  its height [m] above the WGS84 ellipsoid (or the Moon's sphere)
gtx/heights/signal_conf_ph    int8     (n, 5) ATL03's confidence per surface type (land, ocean, sea ice, land ice,
                                       inland water): −2 TEP, −1 not considered, 0 noise, 1 buffer, 2 low,
                                       3 medium, 4 high. The signal finder's (flightsim.scoring.signal_finder, from the
                                       photons' height histograms in 20 m segments, not from the truth) in every
                                       column: the simulated scene has one surface, classified once
gtx/heights/dist_ph_along     float64  along-track distance of the photon's shot from its 20 m segment's start [m]
gtx/heights/x_atc             float64  flightsim: horizontal distance from the line's first photon [m] (what the
                                       signal finder and atl08.h5 bin along track)
gtx/heights/truth_kind        int8     flightsim's truth: 0 background or dark count, 1 the surface's echo, 2 a corner
                                       cube's, 3 leaves' (a canopy)
gtx/heights/ph_id_pulse       int64    pulse index within its line
gtx/geolocation/...           per 20 m along-track segment (ATL03's geolocation segments): segment_id (1-based,
                                       counted from the pass's first footprint, not from the equator crossing),
                                       segment_ph_cnt, ph_index_beg (1-based row of its first photon; 0 when empty),
                                       reference_photon_index (1-based within the segment: the photon whose shot is
                                       nearest the segment's centre; 0 when empty), reference_photon_lat/lon and
                                       delta_time (that photon's), segment_length (20 m), segment_dist_x (the
                                       segment's start along track [m])
gtx/bckgrd_atlas/bckgrd_rate  float32  per 50 shots (ATL03's 200 Hz): photons the signal finder calls noise per second
                                       of range gate [Hz] (dead time not undone); ``delta_time`` its first shot's
gtx/geophys_corr/...          per segment: delta_time and the geophysical corrections, 0 (the simulated world has no
                                       tides, atmosphere or geoid)
gtx/footprint/delta_time, lat, lon, h: flightsim: per shot that has photons, the beam's footprint centre (its
                                       believed axis where it meets the scene's ground height)

The granule-level groups (orbit_info, ancillary_data, METADATA, atlas_impulse_response, the root attributes):
:mod:`flightsim.outputs.atl03_granule`. Geolocation is the processing's (the believed instrument), as the product's
is. Written under a temporary name and renamed when complete; signal_conf_ph is computed at close, reading each
beam's heights back block by block (memory bounded by the block, not the run), the segment and background tables
from per-photon indices kept in memory (4 bytes a photon).
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flightsim.core.process_map import ProcessMap, thread_count
from flightsim.outputs.atl03_granule import Granule, adjusted_to_delta_time, write_granule
from flightsim.outputs.h5_product import H5Product
from flightsim.outputs.photon_las import photon_geodetic
from flightsim.platforms.orbit import local_to_geodetic
from flightsim.scoring.finder_stream import FinderStream
from flightsim.scoring.signal_finder import SignalFinder, along_spread

SEGMENT_M = 20.0  # ATL03's geolocation segment along track [m]
FRAME_SHOTS = 50  # ATL03's background rate: every 50 shots (200 Hz at 10 kHz)
SURFACE_TYPES = 5  # land, ocean, sea ice, land ice, inland water
LIGHT_SPEED = 299_792_458.0  # [m/s]
FINDER_BLOCK = 1 << 20  # photons the signal finder classifies at a time (its memory)


@dataclass
class _Track:
    """One ground track's running state: each line's first photon and first footprint, its first segment and frame
    numbers, and per photon its segment and background frame (int32, in memory)."""

    first_photon: dict = field(default_factory=dict)
    first_footprint: dict = field(default_factory=dict)
    segment_base: dict = field(default_factory=dict)
    frame_base: dict = field(default_factory=dict)
    next_segment: int = 1
    next_frame: int = 0
    segments: list = field(default_factory=list)
    frames: list = field(default_factory=list)
    frame_counts: list = field(default_factory=list)  # per chunk: (frames, their shots that detected a photon,
    # the delta_time of each frame's first shot) (_frame_counts); _frames sums them
    reference: list = field(default_factory=list)  # per chunk: its best photon of each segment (_keep_reference)
    rows: int = 0
    spread: float = 0.0  # the most a photon's x_atc lies behind an earlier photon's [m] (the signal finder's blocks)
    furthest: float = -np.inf  # the furthest x_atc so far [m]


@dataclass(frozen=True)
class _BeamPart:
    """One beam's photons of a chunk as :meth:`Atl03Writer.prepare` works them out (nothing from earlier chunks)."""

    name: str  # its ground track
    rows: np.ndarray  # the chunk's rows of the beam's photons
    pulse: np.ndarray  # their shots (pulse index within the line)
    inverse: np.ndarray  # each photon's shot among the footprints
    centre: np.ndarray  # (shots, 3) local footprint centres [m]
    footprint: dict  # the footprint group's columns
    delta_time: np.ndarray  # each photon's shot's delta_time [s]
    frames: tuple  # the background frames (numbered from the line's first), as _frame_counts gives them


class Atl03Writer:
    """Appends PhotonChunks to ``directory/atl03.h5``; ``close()`` renames it into place."""

    def __init__(self, directory: Path, body: str, cfg_text: str, prf_hz: float, scene, granule: Granule | None = None,
                 stream: bool = False):
        """body: the body orbited (earth, moon); granule: the run's beams and instrument for the metadata; stream: hold
        each beam's photons for the signal finder to classify while the run goes on, once :meth:`stream_to` gives
        it workers (:class:`~flightsim.scoring.finder_stream.FinderStream`)."""
        self.product = H5Product(directory / "atl03.h5", config_toml=cfg_text)
        self.body, self.prf_hz, self.scene = body, prf_hz, scene
        self.granule = granule or Granule()
        self.tracks: dict[str, _Track] = {}
        self.stream = FinderStream(SignalFinder()) if stream else None
        self.count = 0

    def stream_to(self, workers: ProcessMap) -> None:
        """Classify the beams' finished stretches on ``workers`` from the next chunk on (with ``stream``)."""
        if self.stream is not None:
            self.stream.start(workers)

    def __call__(self, chunk) -> None:
        """Append the chunk's photons: ``take(prepare(chunk))``."""
        self.take(self.prepare(chunk))

    def prepare(self, chunk) -> tuple:
        """The chunk with what its appends need that depends on no earlier chunk: its photons' geodetic columns (every
        beam's at once, and later the LAS tiles') and each beam's photons, shots, footprints and times
        (:class:`_BeamPart`, a beam a thread); so it may run for several chunks at once on threads
        (:class:`~flightsim.core.background.Background`) while :meth:`take` appends an earlier one."""
        photon_geodetic(chunk, self.body, self.scene)
        beams = [(self.granule.track_name(int(beam)), np.flatnonzero(chunk.pixel == beam))
                 for beam in np.flatnonzero(np.bincount(chunk.pixel))]
        with ThreadPoolExecutor(thread_count(len(beams)), thread_name_prefix="atl03-prepare") as pool:
            return chunk, list(pool.map(lambda beam: self._beam_part(chunk, *beam), beams))

    def take(self, prepared: tuple) -> None:
        """Append a prepared chunk's photons (chunks in their order), each beam's columns finished on a thread of its
        own (NumPy lets go of Python's lock), then written in beam order."""
        chunk, beams = prepared
        for beam in beams:
            self.tracks.setdefault(beam.name, _Track())
        geodetic = photon_geodetic(chunk, self.body, self.scene)  # prepared: kept in the chunk
        with ThreadPoolExecutor(thread_count(len(beams)), thread_name_prefix="atl03") as pool:
            heights = list(pool.map(lambda beam: self._heights(self.tracks[beam.name], chunk, beam, geodetic), beams))
        for beam, columns in zip(beams, heights):
            self.product.append(f"{beam.name}/footprint", beam.footprint)
            self.product.append(f"{beam.name}/heights", columns)
            if self.stream is not None:
                self.stream.add(beam.name, columns["x_atc"], columns["h_ph"], columns["ph_id_pulse"],
                                self.tracks[beam.name].spread)
        self.count += len(chunk)

    def _beam_part(self, chunk, name: str, rows: np.ndarray) -> _BeamPart:
        """One beam's photons ``rows`` of the chunk, with the centres of their shots' footprints (the beam's believed
        axis where it meets the scene's ground height), the footprint columns and each photon's delta_time."""
        pulse = chunk.pulse[rows]
        pulses, first, inverse = _distinct(pulse, inverse=True)
        i = rows[first]
        d = chunk.directions[i].astype(np.float64)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        start = chunk.points[i] - (chunk.time_of_flight_s[i] * (LIGHT_SPEED / 2.0))[:, None] * d  # the exit point
        centre = start + ((self.scene.ground_z - start[:, 2]) / d[:, 2])[:, None] * d
        lat, lon, h = local_to_geodetic(self.body, self.scene, centre)
        footprint = {"delta_time": adjusted_to_delta_time(chunk.start_time + pulses / self.prf_hz), "lat": lat,
                     "lon": lon, "h": h}
        t = adjusted_to_delta_time(chunk.start_time + pulse / self.prf_hz)
        frames = _frame_counts(pulse, chunk.start_time, self.prf_hz)
        return _BeamPart(name, rows, pulse, inverse, centre, footprint, t, frames)

    def _heights(self, track: _Track, chunk, beam: _BeamPart, geodetic: tuple) -> dict:
        """The heights columns of one beam's photons (its line's first photon and footprint, segments, frames and
        reference photons kept in its track)."""
        line, rows, pulse, t = chunk.line_id, beam.rows, beam.pulse, beam.delta_time
        origin = track.first_footprint.setdefault(line, beam.centre[0].copy())
        along = _horizontal(beam.centre, origin)[beam.inverse]  # each photon's shot from the line's first footprint
        points = np.take(chunk.points, rows, axis=0)  # rows at once: half the time of chunk.points[rows]
        lat, lon, h = (column[rows] for column in geodetic)
        start = track.first_photon.setdefault(line, points[0].copy())
        base = track.segment_base.setdefault(line, track.next_segment)
        local = np.floor(along / SEGMENT_M).astype(np.int64)
        segment = base + local
        track.next_segment = max(track.next_segment, int(segment.max()) + 1)
        frame_base = track.frame_base.setdefault(line, track.next_frame)
        frame = frame_base + pulse // FRAME_SHOTS
        track.next_frame = max(track.next_frame, int(frame.max()) + 1)
        frames, shots, times = beam.frames
        track.frame_counts.append((frame_base + frames, shots, times))
        dist = along - local * SEGMENT_M
        _keep_reference(track, segment, np.abs(dist - SEGMENT_M / 2.0), track.rows, lat, lon, t)
        track.segments.append(segment.astype(np.int32))
        track.frames.append(frame.astype(np.int32))
        track.rows += len(rows)
        x_atc = _horizontal(points, start)
        spread, track.furthest = along_spread(x_atc, track.furthest)
        track.spread = max(track.spread, spread)
        return {"delta_time": t, "lat_ph": lat, "lon_ph": lon, "h_ph": h, "dist_ph_along": dist, "x_atc": x_atc,
                "truth_kind": chunk.kind[rows].astype(np.int8), "ph_id_pulse": pulse}

    def close(self, workers: ProcessMap | None = None) -> str:
        """Classify the photons (the signal finder in blocks over ``workers`` when given), write the per-segment and
        granule groups and rename the file into place; its name."""
        f = self.product.file
        streams = [self._confidence(f[f"{name}/heights"], track.spread, workers) for name, track in self.tracks.items()]
        beams = {name: stream for name, (stream, _) in zip(self.tracks, streams)}
        if self.stream is None:
            SignalFinder().classify_streams(list(beams.values()), workers)  # the beams' blocks in one go
        else:  # what the stream left of them
            SignalFinder().classify_spans(self.stream.finish(beams), workers)
        for (name, track), (_, conf) in zip(self.tracks.items(), streams):
            _segments(f.require_group(f"{name}/geolocation"), track)
            _zero_corrections(f.require_group(f"{name}/geophys_corr"), f[f"{name}/geolocation/delta_time"][:])
            _background(f.require_group(f"{name}/bckgrd_atlas"), track, conf, self.granule.gate_s)
        write_granule(f, self.granule, sorted(self.tracks))
        return self.product.close()

    @staticmethod
    def _confidence(heights, spread: float, workers: ProcessMap | None = None) -> tuple[tuple, np.ndarray]:
        """signal_conf_ph of one beam's heights group, made: the signal finder's stream of its photons (blocks
        sized to spread a beam over ``workers`` when given; ``spread``: :func:`along_spread` of its x_atc [m]), and
        the first column, which the stream's writes fill (every surface type's column the same)."""
        n = heights["h_ph"].shape[0]
        conf = heights.create_dataset("signal_conf_ph", shape=(n, SURFACE_TYPES), dtype=np.int8,
                                      chunks=(min(max(n, 1), 1 << 16), SURFACE_TYPES))
        first = np.zeros(n, dtype=np.int8)

        def read(lo: int, hi: int) -> tuple:
            return heights["x_atc"][lo:hi], heights["h_ph"][lo:hi], heights["ph_id_pulse"][lo:hi]

        def write(lo: int, values: np.ndarray) -> None:
            columns = np.empty((len(values), SURFACE_TYPES), dtype=np.int8)
            columns[:] = values[:, None]  # a broadcast copy lets go of Python's lock (np.repeat holds it)
            conf[lo:lo + len(values)] = columns
            first[lo:lo + len(values)] = values

        block = FINDER_BLOCK if workers is None else min(FINDER_BLOCK, max(FINDER_BLOCK >> 4,
                                                                          -(-n // len(workers.processes))))
        return (n, read, write, block, spread), first

    def abort(self) -> None:
        if self.stream is not None:
            self.stream.stop()
        self.product.abort()


def _horizontal(points: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """The horizontal distance of (n, 3) ``points`` from ``origin`` [m]: ``np.linalg.norm((points − origin)[:, :2],
    axis=1)`` bit for bit (the same differences and squares added in the same order), without the third column's
    difference and the reduction over a short axis (a quarter of the time)."""
    x, y = points[:, 0] - origin[0], points[:, 1] - origin[1]
    return np.sqrt(x * x + y * y)


def _distinct(values: np.ndarray, inverse: bool = False) -> tuple[np.ndarray, ...]:
    """``np.unique(values, return_index=True, return_inverse=inverse)`` bit for bit: from the runs of equal values
    where they never decrease (a beam's shots and frames come in order: no sort), else NumPy's."""
    if len(values) and np.all(values[1:] >= values[:-1]):
        new = np.r_[True, values[1:] != values[:-1]]
        first = np.flatnonzero(new)
        return (values[first], first) + ((np.cumsum(new) - 1,) if inverse else ())
    return np.unique(values, return_index=True, return_inverse=inverse)


def _frame_counts(pulse: np.ndarray, start_time: float, prf_hz: float) -> tuple:
    """The background frames of photons of shots ``pulse`` (frame f: shots f · FRAME_SHOTS …), each one's shots
    that detected a photon (a shot's photons are all in one chunk) and its first shot's delta_time [s]."""
    frame = pulse // FRAME_SHOTS
    _, first = _distinct(pulse)  # a photon of each shot
    frames, _ = _distinct(frame)  # each frame
    shots = np.bincount(np.searchsorted(frames, frame[first]), minlength=len(frames))
    return frames, shots, adjusted_to_delta_time(start_time + frames * FRAME_SHOTS / prf_hz)


def _frames(track: _Track) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The track's background frames in order, their shots that detected a photon (summed over the chunks) and
    their first shot's delta_time [s] (from the first chunk that has the frame)."""
    if not track.frame_counts:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    frames, shots, times = (np.concatenate(column) for column in zip(*track.frame_counts))
    ids, first, inverse = np.unique(frames, return_index=True, return_inverse=True)
    return ids, np.bincount(inverse, weights=shots, minlength=len(ids)), times[first]


def _keep_reference(track: _Track, segment: np.ndarray, offset: np.ndarray, row0: int, lat, lon, t) -> None:
    """Keep, for each segment of these photons, the photon whose shot is nearest the segment's centre (the first such
    photon of the chunk): (segment, |dist − centre|, row, lat, lon, delta_time) arrays; :func:`_references` picks
    among the chunks'."""
    firsts = _nearest(segment, offset)
    track.reference.append((segment[firsts], offset[firsts], row0 + firsts, lat[firsts], lon[firsts], t[firsts]))


def _nearest(segment: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Per segment present, the index of its least offset (the first such on a tie), in segment order: each segment's
    run of a stable sort by segment (none where they come in order; a beam's photons come along track, a shot near a
    segment's edge now and then back in the one before, which NumPy's stable sort takes nearly as fast), its least
    offset found in the run (a tenth of the time of a sort by segment, then offset)."""
    order = None if np.all(segment[1:] >= segment[:-1]) else np.argsort(segment, kind="stable")
    if order is not None:
        segment, offset = segment[order], offset[order]
    starts = np.flatnonzero(np.r_[True, segment[1:] != segment[:-1]])
    run = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(segment)]))
    hits = np.flatnonzero(offset == np.minimum.reduceat(offset, starts)[run])  # each run's least, ties too
    firsts = hits[np.r_[True, run[hits][1:] != run[hits][:-1]]]
    return firsts if order is None else order[firsts]


def _references(track: _Track, ids: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per segment of ``ids`` (consecutive): whether it has a reference photon, and that photon's row, latitude,
    longitude and time (NaN where none): the photon nearest the segment's centre over every chunk, the first chunk's
    on a tie."""
    have = np.zeros(len(ids), dtype=bool)
    values = [np.full(len(ids), np.nan) for _ in range(4)]
    if track.reference:
        segment, offset, *found = (np.concatenate(column) for column in zip(*track.reference))
        best = _nearest(segment, offset)  # the chunks in order: on a tie the earlier chunk's
        slot = segment[best] - ids[0]
        have[slot] = True
        for value, column in zip(values, found):
            value[slot] = column[best]
    return (have, *values)


def _segments(g, track: _Track) -> None:
    """ATL03's geolocation segments of one track: every 20 m segment from its first to its last, empty ones too."""
    segment = np.concatenate(track.segments) if track.segments else np.zeros(0, np.int32)
    ids = np.arange(int(segment.min()), int(segment.max()) + 1) if len(segment) else np.zeros(0, np.int64)
    count = np.bincount(segment - (ids[0] if len(ids) else 0), minlength=len(ids)).astype(np.int32)
    begin = np.where(count > 0, np.concatenate([[0], np.cumsum(count)[:-1]]) + 1, 0).astype(np.int64)
    have, row, lat, lon, t = _references(track, ids)
    index = np.where(have, row - (begin - 1) + 1, 0).astype(np.int32)
    if have.any() and not have.all():  # empty segments: the time interpolated between their neighbours
        t[~have] = np.interp(ids[~have], ids[have], t[have])
    bases = np.sort(np.array(list(track.segment_base.values()), dtype=np.int64))
    starts = bases[np.searchsorted(bases, ids, "right") - 1] if len(ids) else ids  # each line's first segment
    columns = {"delta_time": t, "segment_id": ids.astype(np.int32), "segment_ph_cnt": count, "ph_index_beg": begin,
               "reference_photon_index": index, "reference_photon_lat": lat, "reference_photon_lon": lon,
               "segment_length": np.full(len(ids), SEGMENT_M), "segment_dist_x": (ids - starts) * SEGMENT_M}
    for name, values in columns.items():
        g.create_dataset(name, data=values)


def _zero_corrections(g, delta_time: np.ndarray) -> None:
    """geophys_corr per segment: its time and ATL03's corrections, none of which the simulated world has (0 m)."""
    g.create_dataset("delta_time", data=delta_time)
    for name in ("dac", "tide_earth", "tide_load", "tide_ocean", "tide_pole", "tide_equilibrium", "geoid"):
        g.create_dataset(name, data=np.zeros(len(delta_time), dtype=np.float32))


def _background(g, track: _Track, conf: np.ndarray, gate_s: float) -> None:
    """bckgrd_atlas: per 50-shot frame, the photons the signal finder calls noise per second of gate [Hz], over the
    frame's shots that detected anything."""
    frame = np.concatenate(track.frames) if track.frames else np.zeros(0, np.int32)
    ids, shots, times = _frames(track)
    noise = np.bincount(np.searchsorted(ids, frame[conf == 0]), minlength=len(ids))
    g.create_dataset("delta_time", data=times)
    g.create_dataset("bckgrd_rate", data=(noise / np.maximum(shots, 1) / gate_s).astype(np.float32))
