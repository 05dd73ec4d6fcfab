"""The photon product of the photons readout: every detection into ``photons.h5``, LAS tiles in ``photons/`` (in
``output.crs``) and, from orbit, the ATL03-style ``atl03.h5`` and (``output.atl08``) the ATL08-like ``atl08.h5``."""
from __future__ import annotations

import shutil
import time
from collections import deque
from pathlib import Path

from flightsim.core.atomic import temporary_name
from flightsim.core.background import Background
from flightsim.core.process_map import MAX_THREADS, ProcessMap, map_rows, thread_count, usable_cores
from flightsim.core.registry import register
from flightsim.engine.readouts.photons import Photons
from flightsim.outputs.photon_las import FOLDER

ATL08_SEGMENT_M = 100.0  # ATL08's land segment [m]
PARALLEL_PHOTONS = 1 << 19  # photons from which atl03.h5's signal finder and atl08.h5 run on worker processes
TWO_CORES_LATER = 8  # on two cores the workers start at 8 × PARALLEL_PHOTONS: their start (imports, Warp) takes the
# cores the run uses, and a 2 s pass took 7.0 s without them, 8.3-9.8 s with (results/profile-experiments.md 92)
MAX_WORKERS = 32  # the most worker processes they start
BEHIND_PHOTONS = 8 << 20  # photons.h5 and the LAS tiles are handed a part once about this many photons came after
# it (the parts of run.host_photons that make them up, at least one): atl03.h5 has them first
LAS_THREADS = 12  # the most threads making the LAS tiles' records side by side (off orbit): on a 16-core GPU host the
# SPAD frame's trace stage 3.16 s on 4, 2.75 on 8, 2.36 on 12 (mean of 3; the run's peak 1.85 -> 2.35 GB, 2.9-3.3 GB
# with photons.h5's second thread beside on another host; results/profile-experiments.md section 95)
H5_THREADS = 2  # photons.h5's columns of the next part made while its writer appends a part's
ORBIT_LAS_THREADS = 2  # from orbit (the geodetic transform has PROJ's threads, the finder and ATL08 the cores): on one,
# the tiles held the trace back ~6 s of a 30 s pass on a 16-core GPU host (results/profile-experiments.md section 87)
ATL03_THREADS = 2  # the most chunks atl03.h5 prepares at once (their geodetic columns) while it appends another
PRELOAD = ("flightsim.scoring.signal_finder", "flightsim.outputs.atl08_h5",  # what the workers run, imported early,
           "flightsim.core.warp_runtime:init_warp")  # and Warp started (the finder's and ATL08's CPU kernels)


def _pool_from(cores: int) -> int:
    """The photons from which a run on ``cores`` (> 1) usable cores starts its worker processes."""
    return PARALLEL_PHOTONS * (TWO_CORES_LATER if cores <= 2 else 1)


def reflectance_source(cfg, scene, value: float) -> float | str:
    """Where a photon or waveform run's reflectance came from: the scene's per-triangle albedo (a land-cover
    raster's, or the scene's own), else the run's one ``value`` (ρ, or the waveform's f)."""
    if scene.reflectance is None:
        return value
    return "per triangle (land cover)" if cfg.scene.values().get("landcover") else "per triangle (scene)"


@register("product", "photons")
class PhotonProduct:
    """photons.h5, the photon LAS tiles and, from orbit, atl03.h5 and atl08.h5."""

    kind = "photons"
    files = ("photons.h5", FOLDER, "atl03.h5", "atl08.h5")
    tracer_options: dict = {}

    @staticmethod
    def setup_kernels(cfg) -> list:
        """(kernel, device) of what atl03.h5 and atl08.h5 launch at close on the CPU, on the workers (the signal
        finder's counts, :mod:`kernels.signal_finder`, and ATL08's density filter's, :mod:`kernels.ellipse`), for
        :func:`flightsim.engine.run.compile_setup`: compiled, or loaded from the kernel cache, once while the run is
        set up rather than by each worker."""
        if cfg.flight.platform != "orbit":
            return []
        from kernels.ellipse import ellipse_pairs
        from kernels.signal_finder import segment_counts

        return [(segment_counts, "cpu")] + ([(ellipse_pairs, "cpu")] if cfg.output.atl08 else [])

    def __init__(self, cfg, scene):
        self.cfg, self.scene = cfg, scene

    def open(self, tracer, directory: Path, cfg_text: str) -> None:
        from flightsim.outputs.photon_las import PhotonLas
        from flightsim.outputs.photons_h5 import PhotonWriter

        cfg, scene, prf = self.cfg, self.scene, tracer.timing.prf_hz
        self.directory, self.cfg_text = directory, cfg_text
        shutil.rmtree(directory / FOLDER, ignore_errors=True)  # tiles of a run being redone
        h5 = PhotonWriter(directory, cfg_text, prf, scene.origin, scene.crs.to_wkt())
        body = cfg.flight.body if cfg.flight.platform == "orbit" else None
        las = PhotonLas(directory, cfg.output, scene, tracer.timing, tracer.instrument.emitter.beam_columns, body,
                        cfg.flight.start_gps_time)
        atl03 = [_atl03_writer(directory, body, cfg_text, prf, scene, atl03_granule(cfg, tracer.instrument.emitter))
                 ] if body else []
        las_threads = thread_count(ORBIT_LAS_THREADS if atl03 else LAS_THREADS)
        self.h5 = Background(h5, "photons-h5", threads=thread_count(H5_THREADS))
        self.las = Background(las, "photon-las", threads=las_threads)
        self.atl03 = [Background(writer, "atl03", threads=thread_count(ATL03_THREADS)) for writer in atl03]
        self.atl08 = body is not None and cfg.output.atl08
        self.photons, self.workers, self.placed = 0, None, []
        self.behind: deque = deque()  # (part, atl03.h5's future of it) not yet handed to photons.h5 and the tiles
        self.behind_parts = max(1, BEHIND_PHOTONS // cfg.run.host_photons)

    def readout(self) -> Photons:
        return Photons()

    @property
    def writers(self) -> list[Background]:
        return [self.h5, self.las, *self.atl03]

    def __call__(self, chunk) -> None:
        """Hand the chunk (a part of at most ``run.host_photons`` photons) to every writer: each converts and writes it
        on a thread of its own. From orbit atl03.h5 has it first, photons.h5 and the LAS tiles get it once
        ``behind_parts`` more parts came (or at close) and start on it when atl03.h5 has it: Python's lock is shared,
        and atl03.h5 leads to the signal finder and atl08.h5, which the others are written beside; ``behind_parts``
        bounds the parts held."""
        first = self.atl03[0](chunk) if self.atl03 else None
        self.behind.append((chunk, first))
        self._hand_on(self.behind_parts if self.atl03 else 0)
        self.photons += len(chunk)
        if self.atl03 and self.workers is None and usable_cores() > 1 and self.photons >= _pool_from(usable_cores()):
            self.workers = ProcessMap(min(usable_cores(), MAX_WORKERS), PRELOAD)  # they start while the run goes on
            for writer in self.atl03:  # and classify the beams' finished stretches as it goes on
                writer.writer.stream_to(self.workers)

    def _hand_on(self, keep: int, wait: bool = True) -> None:
        """Hand photons.h5 and the LAS tiles the parts waiting for them but the last ``keep``; without ``wait`` all at
        once, however many they already hold (at close: the signal finder is not kept waiting for them)."""
        while len(self.behind) > keep:
            chunk, first = self.behind.popleft()
            self.h5(chunk, after=first, wait=wait)
            self.las(chunk, after=first, wait=wait)

    def close(self, counts) -> dict:
        """Close the files: atl03.h5 (its signal finder) and atl08.h5 first (on the worker processes once the run
        passed _pool_from photons), while photons.h5 and the LAS tiles are written on."""
        self._hand_on(0, wait=False)
        try:
            names = {writer: self._placed(writer.close(self.workers)) for writer in self.atl03}
            started = time.perf_counter()
            atl08 = atl08_from_atl03(self.directory, self.cfg_text, self.workers) if self.atl08 else None
            atl08_s = time.perf_counter() - started
            self._placed(atl08)
        finally:
            self._stop_workers()
        names.update({self.h5: self._placed(self.h5.close()), self.las: self.las.close()})
        files = [names[writer] for writer in self.writers] + ([atl08] if atl08 is not None else [])
        timing = {"photons.h5": self.h5, f"{FOLDER}/": self.las, **{"atl03.h5": writer for writer in self.atl03}}
        writers_s = {name: writer.timing() for name, writer in timing.items()}
        if atl08 is not None:  # made from the finished atl03.h5 at close: only a close
            writers_s["atl08.h5"] = {**dict.fromkeys(writers_s["photons.h5"], 0.0), "close": round(atl08_s, 3)}
        return {"reflectance": reflectance_source(self.cfg, self.scene, self.cfg.photon.reflectance),
                "photons": self.h5.writer.count, "signal_photons": self.h5.writer.signal,
                "photon_tiles": self.las.writer.tiles, "files": files, "writers_s": writers_s}

    def empty(self, counts) -> bool:
        return self.h5.writer.count == 0

    def _placed(self, name: str | None) -> str | None:
        """Note a file this close put in place (removed again should a later writer fail)."""
        if name is not None:
            self.placed.append(name)
        return name

    def abort(self) -> None:
        """Drop every file: the writers' unfinished ones, and those this close had already put in place (a writer
        still at work failed after them)."""
        self._stop_workers()
        for writer in self.writers:
            writer.abort()
        for name in self.placed:
            (self.directory / name).unlink(missing_ok=True)

    def _stop_workers(self) -> None:
        if self.workers is not None:
            self.workers.stop()
            self.workers = None


def atl03_granule(cfg, emitter):
    """The run's beams and instrument as atl03.h5's granule metadata needs them (flightsim.outputs.atl03_granule)."""
    from flightsim.instrument.photon import first_photon_bias_s, sigma_t
    from flightsim.outputs.atl03_granule import Granule

    p = cfg.photon
    spread = sigma_t(p)
    strength = (0.1, 0.2, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)  # expected photo-electrons of an echo
    return Granule(beam_names=getattr(emitter, "beam_names", None), sc_orient=getattr(emitter, "sc_orient", 0),
                   gate_s=2.0 * (p.gate_m[1] - p.gate_m[0]) / 299_792_458.0, sigma_t_s=spread,
                   dead_time_s=p.dead_time_s, fpb_strength=strength,
                   fpb_bias_s=tuple(first_photon_bias_s(strength, spread).tolist()))


def ground_tracks(f) -> list[str]:
    """The ground-track groups of an open atl03.h5 (gt1l … gt3r, or gt1, gt2, …), in name order."""
    return sorted(name for name in f if name.startswith("gt") and "heights" in f[name])


def atl08_threads(photons: dict[str, int], side_by_side: bool) -> dict[str, int]:
    """Threads for each track's ATL08 (track → its photons): the usable cores shared out by photons where the tracks
    run side by side (a strong beam, four times a weak one's photons, takes four times its threads), every core
    for each where they run one after another; at least one, at most MAX_THREADS."""
    cores = usable_cores()
    total = max(sum(photons.values()), 1)
    return {track: max(1, min(MAX_THREADS, cores * n // total if side_by_side else cores))
            for track, n in photons.items()}


def atl08_from_atl03(directory: Path, cfg_text: str, workers: ProcessMap | None = None) -> str | None:
    """Write ``directory/atl08.h5`` from the finished ``atl03.h5`` beside it: each beam's photons classified and cut
    into 100 m land segments (:func:`flightsim.outputs.atl08_h5.atl08_of_track`, default settings) and written to a
    file of its own, a beam a worker when ``workers`` are given, then the beams' groups copied into atl08.h5 as they
    were compressed. Over bare ground the segments have terrain heights and fill values for the canopy. Its name, or
    None when atl03.h5 holds no photon."""
    import h5py

    from flightsim.outputs.atl08_h5 import join_atl08, write_atl08_track

    atl03 = directory / "atl03.h5"
    with h5py.File(atl03) as f:
        photons = {track: f[f"{track}/heights/h_ph"].shape[0] for track in ground_tracks(f)}
    if not photons:
        return None
    parts = {track: temporary_name(directory / f"atl08.{track}.h5") for track in photons}
    threads = atl08_threads(photons, workers is not None)
    try:
        map_rows(write_atl08_track, [(str(part), str(atl03), track, ATL08_SEGMENT_M, threads[track])
                                     for track, part in parts.items()], workers)
        return join_atl08(directory / "atl08.h5", parts, {"config_toml": cfg_text}).name
    finally:
        for part in parts.values():
            for name in (part, temporary_name(part)):  # a track's file, or one a failing worker left half-written
                name.unlink(missing_ok=True)


def _atl03_writer(directory: Path, body: str, cfg_text: str, prf_hz: float, scene, granule):
    """atl03.h5's writer (imported only from orbit: its signal finder brings SciPy's special functions, ~0.3 s at a
    run's start that a run off orbit does not pay)."""
    from flightsim.outputs.atl03_h5 import Atl03Writer

    return Atl03Writer(directory, body, cfg_text, prf_hz, scene, granule, stream=usable_cores() > 1)
