"""The photon product of the photons readout: every detection into ``photons.h5``, LAS tiles in ``photons/`` (in
``output.crs``) and, from orbit, the ATL03-style ``atl03.h5``."""
from __future__ import annotations

import shutil
from pathlib import Path

from flightsim.core.registry import register
from flightsim.engine.readouts.photons import Photons
from flightsim.outputs.photon_las import FOLDER


def reflectance_source(cfg, scene, value: float) -> float | str:
    """Where a photon or waveform run's reflectance came from: the scene's per-triangle albedo (a land-cover
    raster's, or the scene's own), else the run's one ``value`` (ρ, or the waveform's f)."""
    if scene.reflectance is None:
        return value
    return "per triangle (land cover)" if cfg.scene.values().get("landcover") else "per triangle (scene)"


@register("product", "photons")
class PhotonProduct:
    """photons.h5, the photon LAS tiles and, from orbit, atl03.h5."""

    kind = "photons"
    files = ("photons.h5", FOLDER, "atl03.h5")
    tracer_options: dict = {}

    def __init__(self, cfg, scene):
        self.cfg, self.scene = cfg, scene

    def open(self, tracer, directory: Path, cfg_text: str) -> None:
        from flightsim.outputs.atl03_h5 import Atl03Writer
        from flightsim.outputs.photon_las import PhotonLas
        from flightsim.outputs.photons_h5 import PhotonWriter

        cfg, scene, prf = self.cfg, self.scene, tracer.timing.prf_hz
        shutil.rmtree(directory / FOLDER, ignore_errors=True)  # tiles of a run being redone
        self.h5 = PhotonWriter(directory, cfg_text, prf, scene.origin, scene.crs.to_wkt())
        body = cfg.flight.body if cfg.flight.platform == "orbit" else None
        self.las = PhotonLas(directory, cfg.output, scene, tracer.timing, tracer.instrument.emitter.beam_columns, body,
                             cfg.flight.start_gps_time)
        self.writers = [self.h5, self.las] + ([Atl03Writer(directory, body, cfg_text, prf, scene)] if body else [])

    def readout(self) -> Photons:
        return Photons()

    def __call__(self, chunk) -> None:
        for writer in self.writers:
            writer(chunk)

    def close(self, counts) -> dict:
        names = [writer.close() for writer in self.writers]
        return {"reflectance": reflectance_source(self.cfg, self.scene, self.cfg.photon.reflectance),
                "photons": self.h5.count, "signal_photons": self.h5.signal, "photon_tiles": self.las.tiles,
                "files": names}

    def empty(self, counts) -> bool:
        return self.h5.count == 0

    def abort(self) -> None:
        for writer in self.writers:
            writer.abort()
