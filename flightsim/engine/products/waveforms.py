"""The waveform product of the waveform detector's readouts: every beam's waveform, its geolocation and ranging into
``waveforms.h5`` (GEDI L1B layout), the waveforms' Gaussian components as discrete returns in ``returns.las`` and,
with ``waveform.l2a``, their GEDI L2A metrics in ``l2a.h5``.

The readout: ``waveforms`` (sub-rays traced against the scene), or over a point-cloud scene with
``waveform.cloud_method = "gedi"`` (the default) ``cloud_waveforms`` (the ALS points summed by the GEDI simulator's
method). Each beam group of both files carries the beam's attributes (:meth:`WaveformProduct.beam_attrs`).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.engine.products.photons import reflectance_source
from flightsim.engine.readouts.waveforms import CloudWaveforms, Waveforms


@register("product", "waveforms")
class WaveformProduct:
    """waveforms.h5, returns.las and (with ``waveform.l2a``) l2a.h5."""

    kind = "waveforms"
    files = ("waveforms.h5", "returns.las", "l2a.h5")
    tracer_options: dict = {}

    @staticmethod
    def setup_kernels(cfg) -> list:
        """(kernel, device) of waveforms.h5's ranging on the run's device (``waveform.processing = "device"``), for
        :func:`flightsim.engine.run.compile_setup`: loaded while the run is set up, not at its first batch."""
        if cfg.waveform.processing != "device":
            return []
        from flightsim.instrument.waveform_batch import kernels

        return [(kernel, None) for kernel in kernels()]

    def __init__(self, cfg, scene):
        self.cfg, self.scene = cfg, scene
        self.cloud = scene.cloud is not None and cfg.waveform.cloud_method == "gedi"
        if self.cloud and cfg.flight.platform == "shots":
            check_cloud_footprints(cfg, scene)

    @staticmethod
    def reads_cloud_leaves(cfg) -> bool:
        """Whether a run over a point cloud reads the leaf area its points imply: not when it sums the points
        by the GEDI method (``waveform.cloud_method = "gedi"``)."""
        return cfg.waveform.cloud_method != "gedi"

    def open(self, tracer, directory: Path, cfg_text: str) -> None:
        from flightsim.instrument.waveform import system
        from flightsim.outputs.waveforms_h5 import L2AProduct, WaveformWriter

        det, dt = tracer.instrument.detector, self.cfg.waveform.sample_interval_s
        taps, first_lag = det.pulse_taps("cpu")
        attrs = self.beam_attrs(det)
        l2a = L2AProduct(directory / "l2a.h5", dt, det.pulse_sigma_s(), attrs["footprint_sigma_m"], attrs,
                         {"config_toml": cfg_text, "crs_wkt": self.scene.crs.to_wkt()}) if self.cfg.waveform.l2a else None
        self.writer = WaveformWriter(directory, cfg_text, system(self.cfg.waveform), tracer.timing.prf_hz,
                                     self.scene, (taps.numpy(), first_lag * dt), attrs, l2a,
                                     tracer.device if self.cfg.waveform.processing == "device" else None)

    def beam_attrs(self, det) -> dict[str, float]:
        """Each beam group's attributes: ``pulse_sigma_s``, σ of the pulse as the waveforms hold it (widened by the
        receiver's response) [s]; ``footprint_sigma_m``, the footprint's σ_f = r α / 2 at the range
        r = flight.altitude_m [m]; ``rho_ground``, ``rho_canopy``: over a point cloud summed by the GEDI method,
        ``scene.rho_ground`` and ``scene.rho_canopy``; else the surfaces' Lambertian albedo π·waveform.reflectance
        (left out when the scene carries its own per triangle) and the canopy's leaf reflectance (left out
        without a canopy)."""
        cfg, scene = self.cfg, self.scene
        attrs = {"pulse_sigma_s": det.pulse_sigma_s(), "footprint_sigma_m": det.footprint_sigma_m(cfg.flight.altitude_m)}
        if self.cloud:
            return {**attrs, "rho_ground": cfg.scene.rho_ground, "rho_canopy": cfg.scene.rho_canopy}
        if scene.reflectance is None:
            attrs["rho_ground"] = math.pi * cfg.waveform.reflectance
        if scene.canopy is not None:
            attrs["rho_canopy"] = scene.canopy.leaf_reflectance
        return attrs

    def readout(self) -> Waveforms | CloudWaveforms:
        keep = self.cfg.waveform.l2a  # the truth's rh needs each waveform before the receiver
        return CloudWaveforms(keep_clean=keep) if self.cloud else Waveforms(keep_clean=keep)

    def __call__(self, chunk) -> None:
        self.writer(chunk)

    def close(self, counts) -> dict:
        self.writer.flush()
        out = {"reflectance": reflectance_source(self.cfg, self.scene, self.cfg.waveform.reflectance)}
        if self.scene.cloud is not None:
            out["cloud_method"] = self.cfg.waveform.cloud_method
        names = []
        if self.writer.l2a is not None:
            out["l2a"] = {"shots": 0, "quality_flag": 0}
            if self.writer.shots:
                name, out["l2a"] = self.writer.l2a.close()
                names.append(name)
        names = self.writer.close() + names
        return {**out, "waveforms": self.writer.shots, "subray_returns": 0 if self.cloud else counts.returns,
                "returns": int(sum(len(r) for r in self.writer.returns)), "files": names}

    def empty(self, counts) -> bool:
        return self.writer.shots == 0

    def abort(self) -> None:
        self.writer.abort()


def check_cloud_footprints(cfg, scene) -> None:
    """Footprints given to the shots platform over a point cloud: InputError naming the first with no ALS point
    within COVER_SIGMAS σ_f of its (nadir) axis, the rule by which the GEDI method calls a footprint outside the
    cloud (:func:`flightsim.engine.cloud_waveforms.cloud_waveforms`), before anything is written."""
    from flightsim.instrument.cloud_waveform_model import COVER_SIGMAS
    from flightsim.platforms.shots import FIELD, read_footprints
    from flightsim.scenes.pointcloud import centres_beyond

    shots = read_footprints(cfg.flight.footprints)
    reach = COVER_SIGMAS * cfg.detector_part(cfg.waveform).footprint_sigma_m(cfg.flight.altitude_m)
    local = scene.world_to_local(np.column_stack([shots.x, shots.y, np.zeros(len(shots))]))
    far = centres_beyond(scene.cloud, local[:, :2], reach)
    if far.size:
        nearest = np.hypot(*(scene.cloud.xyz[:, :2] - local[far[0], :2]).T).min()
        lo, hi = (scene.local_to_world(corner) for corner in scene.cloud.bounds())
        raise InputError(FIELD, shots.name(int(far[0])),
                         f"footprints with ALS points within {COVER_SIGMAS:g} σ_f = {reach:.2f} m of their centre "
                         f"(this one's nearest is {nearest:.2f} m away: it lies outside the cloud, which "
                         f"spans x {lo[0]:.1f} … {hi[0]:.1f}, y {lo[1]:.1f} … {hi[1]:.1f} m)")
