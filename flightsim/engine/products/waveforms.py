"""The waveform product of the waveforms readout: every beam's waveform, its geolocation and ranging into
``waveforms.h5`` (GEDI L1B layout), and the waveforms' Gaussian components as discrete returns in ``returns.las``."""
from __future__ import annotations

from pathlib import Path

from flightsim.core.registry import register
from flightsim.engine.products.photons import reflectance_source
from flightsim.engine.readouts.waveforms import Waveforms


@register("product", "waveforms")
class WaveformProduct:
    """waveforms.h5 and returns.las."""

    kind = "waveforms"
    files = ("waveforms.h5", "returns.las")
    tracer_options: dict = {}

    def __init__(self, cfg, scene):
        self.cfg, self.scene = cfg, scene

    def open(self, tracer, directory: Path, cfg_text: str) -> None:
        from flightsim.instrument.waveform import system
        from flightsim.outputs.waveforms_h5 import WaveformWriter

        taps, first_lag = tracer.instrument.detector.pulse_taps("cpu")
        tx = (taps.numpy(), first_lag * self.cfg.waveform.sample_interval_s)
        self.writer = WaveformWriter(directory, cfg_text, system(self.cfg.waveform), tracer.timing.prf_hz,
                                     self.scene, tx)

    def readout(self) -> Waveforms:
        return Waveforms()

    def __call__(self, chunk) -> None:
        self.writer(chunk)

    def close(self, counts) -> dict:
        names = self.writer.close()
        return {"reflectance": reflectance_source(self.cfg, self.scene, self.cfg.waveform.reflectance),
                "waveforms": self.writer.shots, "subray_returns": counts.returns,
                "returns": int(sum(len(r) for r in self.writer.returns)), "files": names}

    def empty(self, counts) -> bool:
        return self.writer.shots == 0

    def abort(self) -> None:
        self.writer.abort()
