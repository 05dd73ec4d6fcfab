"""The photon product of the photons readout: every detection into ``photons.h5``, LAS tiles in ``photons/`` (in
``output.crs``) and, from orbit, the ATL03-style ``atl03.h5`` and (``output.atl08``) the ATL08-like ``atl08.h5``."""
from __future__ import annotations

import shutil
from pathlib import Path

from flightsim.core.process_map import ProcessMap, map_rows, usable_cores
from flightsim.core.registry import register
from flightsim.engine.readouts.photons import Photons
from flightsim.outputs.photon_las import FOLDER

ATL08_SEGMENT_M = 100.0  # ATL08's land segment [m]
ATL08_PARALLEL = 1 << 20  # a granule's photons from which ATL08's beams are worked out on worker processes
MAX_ATL08_WORKERS = 16  # the most worker processes ATL08 starts (one a beam)
ATL08_INPUTS = {"along_track_m": "x_atc", "h_ph": "h_ph", "lat": "lat_ph", "lon": "lon_ph",
                "signal_conf_ph": "signal_conf_ph", "delta_time": "delta_time"}  # atl08_segments' argument: atl03 name


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

    def __init__(self, cfg, scene):
        self.cfg, self.scene = cfg, scene

    def open(self, tracer, directory: Path, cfg_text: str) -> None:
        from flightsim.outputs.atl03_h5 import Atl03Writer
        from flightsim.outputs.photon_las import PhotonLas
        from flightsim.outputs.photons_h5 import PhotonWriter

        cfg, scene, prf = self.cfg, self.scene, tracer.timing.prf_hz
        self.directory, self.cfg_text = directory, cfg_text
        shutil.rmtree(directory / FOLDER, ignore_errors=True)  # tiles of a run being redone
        self.h5 = PhotonWriter(directory, cfg_text, prf, scene.origin, scene.crs.to_wkt())
        body = cfg.flight.body if cfg.flight.platform == "orbit" else None
        self.las = PhotonLas(directory, cfg.output, scene, tracer.timing, tracer.instrument.emitter.beam_columns, body,
                             cfg.flight.start_gps_time)
        self.writers = [self.h5, self.las] + ([Atl03Writer(directory, body, cfg_text, prf, scene,
                                                           atl03_granule(cfg, tracer.instrument.emitter))] if body else [])
        self.atl08 = body is not None and cfg.output.atl08

    def readout(self) -> Photons:
        return Photons()

    def __call__(self, chunk) -> None:
        for writer in self.writers:
            writer(chunk)

    def close(self, counts) -> dict:
        names = [writer.close() for writer in self.writers]
        atl08 = atl08_from_atl03(self.directory, self.cfg_text) if self.atl08 else None
        names += [atl08] if atl08 is not None else []
        return {"reflectance": reflectance_source(self.cfg, self.scene, self.cfg.photon.reflectance),
                "photons": self.h5.count, "signal_photons": self.h5.signal, "photon_tiles": self.las.tiles,
                "files": names}

    def empty(self, counts) -> bool:
        return self.h5.count == 0

    def abort(self) -> None:
        for writer in self.writers:
            writer.abort()


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
                   fpb_bias_s=tuple(first_photon_bias_s(n, spread) for n in strength))


def ground_tracks(f) -> list[str]:
    """The ground-track groups of an open atl03.h5 (gt1l … gt3r, or gt1, gt2, …), in name order."""
    return sorted(name for name in f if name.startswith("gt") and "heights" in f[name])


def atl08_from_atl03(directory: Path, cfg_text: str) -> str | None:
    """Write ``directory/atl08.h5`` from the finished ``atl03.h5`` beside it: each beam's photons read back (only
    the columns ATL08 needs: along-track distance ``x_atc``, height, latitude, longitude, the land column of the
    signal confidence, time), classified
    and cut into 100 m land segments (:func:`flightsim.outputs.atl08.atl08_segments`, default settings). Over bare
    ground the segments have terrain heights and fill values for the canopy. Its name, or None when atl03.h5 holds
    no photon."""
    import h5py

    from flightsim.outputs.atl08 import atl08_beam
    from flightsim.outputs.atl08_h5 import write_atl08

    with h5py.File(directory / "atl03.h5") as f:
        tracks = ground_tracks(f)
        photons = sum(f[f"{track}/heights/h_ph"].shape[0] for track in tracks)
        workers = _atl08_workers(photons, len(tracks))
        beams, at_once = {}, len(workers.processes) if workers is not None else 1  # beams read and worked at once
        try:
            for first in range(0, len(tracks), at_once):
                group = tracks[first:first + at_once]
                done = map_rows(atl08_beam, [(_atl08_columns(f[f"{track}/heights"]), ATL08_SEGMENT_M)
                                             for track in group], workers)
                beams.update(zip(group, done))
        finally:
            if workers is not None:
                workers.stop()
    if not beams:
        return None
    return write_atl08(directory / "atl08.h5", beams, {"config_toml": cfg_text}).name


def _atl08_columns(heights) -> dict:
    """The columns of one beam's heights group that ATL08 reads, by atl08_segments' argument names."""
    columns = {arg: heights[name][:] for arg, name in ATL08_INPUTS.items()}
    if columns["signal_conf_ph"].ndim == 2:  # ATL03's (n, 5): ATL08 reads the land surface type's column
        columns["signal_conf_ph"] = columns["signal_conf_ph"][:, 0]
    return columns


def _atl08_workers(photons: int, beams: int) -> ProcessMap | None:
    """Worker processes that work out ATL08 a beam each: from ATL08_PARALLEL photons and two beams on a machine
    with more than one usable core, else None."""
    count = min(usable_cores(), beams, MAX_ATL08_WORKERS)
    return ProcessMap(count) if photons >= ATL08_PARALLEL and count > 1 else None
