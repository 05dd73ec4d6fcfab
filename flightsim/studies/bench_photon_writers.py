"""`flightsim bench` section photons, the writers alone: the photon LAS writer on a SPAD run's photons on one thread
and on several, and each of ATLAS's products handed an ATLAS run's photons again, one at a time on this thread
(photons.h5, the LAS tiles from orbit, atl03.h5's appends and its close with the signal finder, ATL08 on one beam):
the host's cost per photon of each, without the others beside it. The photons are read back from the run's
photons.h5 in the parts the run handed its writers."""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np


def las_writer(run: Path, threads: int | None = None) -> dict:
    """Photons/s of the photon LAS writer (``photons/`` of the run in ``run``, written again elsewhere) on one thread
    and on ``threads`` (None: ``thread_count(LAS_THREADS)``, as a run off orbit has), the two in turn, best of two each
    (the photons' beam directions taken as nadir: photons.h5 keeps none; the scan angle costs the same)."""
    from flightsim.core.background import Background
    from flightsim.core.process_map import thread_count
    from flightsim.engine.products.photons import LAS_THREADS
    from flightsim.outputs.photon_las import PhotonLas

    cfg, scene, instrument, timing = _run_setup(run, "spad")
    parts = run_parts(run / "photons.h5", scene.origin, timing.prf_hz, cfg.run.host_photons)
    photons, threads = sum(len(part) for part in parts), threads or thread_count(LAS_THREADS)
    walls = {1: [], threads: []}
    for _ in range(2):
        for count in walls:
            with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as out:
                writer = Background(PhotonLas(Path(out), cfg.output, scene, timing, instrument.emitter.beam_columns,
                                              None, cfg.flight.start_gps_time), "bench-las", threads=count)
                started = time.perf_counter()
                for part in parts:
                    writer(part)
                writer.close()
                walls[count].append(time.perf_counter() - started)
    one, many = min(walls[1]), min(walls[threads])
    return {"photons": photons, "parts": len(parts), "threads": threads, "one_thread_s": one, "threads_s": many,
            "one_thread_photons_per_s": photons / one, "threads_photons_per_s": photons / many, "speedup": one / many}


def run_parts(path: Path, origin, prf_hz: float, most: int) -> list:
    """The photons of photons.h5 at ``path`` (a run of one flight line, as the SPAD frame is) as PhotonChunks (local to
    the scene ``origin`` [m]) in the parts the run hands its writers (whole pulses, at most ``most``: its
    ``run.host_photons``)."""
    import h5py

    from flightsim.engine.readouts.photons import PhotonChunk, pulse_parts

    with h5py.File(path) as f:
        c = {name: f["photons"][name][:] for name in ("line_id", "pulse", "pixel", "time_of_flight_s", "signal",
                                                      "delta_time", "x", "y", "z")}
    points = np.column_stack([c["x"], c["y"], c["z"]]) - np.asarray(origin, dtype=np.float64)
    nadir = np.tile(np.float32([0.0, 0.0, -1.0]), (len(points), 1))
    start = float(c["delta_time"][0]) - float(c["pulse"][0]) / prf_hz  # the line's pulse 0 [s]
    return [PhotonChunk(int(c["line_id"][a]), start, c["pulse"][a:b], c["pixel"][a:b], c["time_of_flight_s"][a:b],
                        c["signal"][a:b] > 0, c["signal"][a:b].astype(np.int8), points[a:b], nadir[a:b])
            for a, b in pulse_parts(c["pulse"], most)]


def atlas_products(run: Path) -> dict:
    """Each ATLAS product's time on the photons of the ATLAS run in ``run`` (photons.h5, then the LAS tiles on one
    thread, then atl03.h5's appends and close, into a folder of their own; then ``atl08_of_track`` on the finished
    atl03.h5's beam of most photons), one pass each in turn in this process (the close's signal finder without worker
    processes)."""
    import h5py

    from flightsim.engine.products.photons import atl03_granule, ground_tracks
    from flightsim.outputs.atl03_h5 import Atl03Writer
    from flightsim.outputs.atl08_h5 import atl08_of_track
    from flightsim.outputs.photon_las import PhotonLas
    from flightsim.outputs.photons_h5 import PhotonWriter

    cfg, scene, instrument, timing = _run_setup(run, "atlas")
    parts = run_parts(run / "photons.h5", scene.origin, timing.prf_hz, cfg.run.host_photons)
    text, body, prf = (run / "run.toml").read_text(), cfg.flight.body, timing.prf_hz
    steps = []
    with tempfile.TemporaryDirectory(dir=os.environ.get("FLIGHTSIM_BENCH_DIR")) as tmp:
        out = Path(tmp)
        for name, writer in (
                ("photons.h5", PhotonWriter(out, text, prf, scene.origin, scene.crs.to_wkt())),
                ("photons/ (one thread)", PhotonLas(out, cfg.output, scene, timing, instrument.emitter.beam_columns,
                                                   body, cfg.flight.start_gps_time)),
                ("atl03.h5", Atl03Writer(out, body, text, prf, scene, atl03_granule(cfg, instrument.emitter)))):
            for part in parts:  # each product alone works out the photons' geodetic columns (a run shares them)
                part.geodetic = None
            calls = _timed(lambda: [writer(part) for part in parts])
            steps.append({"step": name, "photons": sum(map(len, parts)), "calls_s": calls,
                          "close_s": _timed(writer.close)})
        with h5py.File(out / "atl03.h5") as f:
            beam = max(ground_tracks(f), key=lambda track: f[f"{track}/heights/h_ph"].shape[0])
            photons = f[f"{beam}/heights/h_ph"].shape[0]
        steps.append({"step": f"atl08.h5, beam {beam}", "photons": photons, "calls_s": 0.0,
                      "close_s": _timed(lambda: atl08_of_track(str(out / "atl03.h5"), beam, 100.0))})
    return {"parts": len(parts), "steps": steps}


def _timed(work) -> float:
    """The wall of ``work()`` [s]."""
    started = time.perf_counter()
    work()
    return time.perf_counter() - started


def _run_setup(run: Path, instrument: str) -> tuple:
    """(config, scene, instrument, pulse timing) of the run in ``run`` (its run.toml over the instrument's preset)."""
    from flightsim.engine.config import validate
    from flightsim.engine.config_io import load_toml, preset_config
    from flightsim.engine.instrument import Instrument
    from flightsim.engine.world import build_scene

    cfg = validate(load_toml(run / "run.toml", preset_config(instrument)))
    built = Instrument(cfg)
    return cfg, build_scene(cfg), built, built.deflector.timing()


def writer_lines(las: dict, products: dict | None) -> list[str]:
    """bench.md's lines of the writers alone: the LAS writer's sentence and ATLAS's products' table."""
    parts = f"{las['parts']} part" + ("s" if las["parts"] != 1 else "")
    lines = ["", f"The photon LAS writer alone on the SPAD run's {las['photons']:.3g} photons ({parts}): "
                 f"{las['one_thread_photons_per_s']:.3g} photons/s on one thread, "
                 f"{las['threads_photons_per_s']:.3g} on {las['threads']} ({las['speedup']:.2f}×, best of two each "
                 "in turn; the tiles as a run off orbit makes them).", ""]
    if not products:
        return lines
    rows = [f"| {p['step']} | {p['photons']:.3g} | {p['calls_s']:.2f} | {p['close_s']:.2f} | "
            f"{p['photons'] / (p['calls_s'] + p['close_s']):.3g} |" for p in products["steps"]]
    return lines + [f"ATLAS's products alone on the photons of the run in parts of the default size "
                    f"({products['parts']} parts; one at a time on one thread, in turn; atl03.h5's close is its signal "
                    "finder, here without worker processes; ATL08 on the beam of most photons):", "",
                    "| product | photons | calls [s] | close [s] | photons/s |", "| --- | --- | --- | --- | --- |",
                    *rows, ""]


