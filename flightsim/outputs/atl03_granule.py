"""The granule-level part of ``atl03.h5`` (:mod:`flightsim.outputs.atl03_h5`): what ATL03 readers look up besides the
ground tracks, in the layout of ATL03 release 006 (Neumann et al., ATL03 data dictionary):

/orbit_info/sc_orient, sc_orient_time     the spacecraft orientation (0 backward, 1 forward: ``pairs.sc_orient``)
/orbit_info/rgt, cycle_number, orbit_number   0: a simulated pass lies on none of ICESat-2's reference ground tracks
/ancillary_data/atlas_sdp_gps_epoch       1198800018 s: GPS seconds at the ATLAS SDP epoch 2018-01-01T00:00:00Z
/ancillary_data/data_start_utc, data_end_utc, granule_start_utc, granule_end_utc   the photons' first and last times
/ancillary_data/start_/end_ delta_time, gpsweek, gpssow, geoseg, rgt, cycle, orbit, region; release, version ("006")
/ancillary_data/tep                      n_tep_bins, tep_bin_size: the simulated pulse's histogram below
/ancillary_data/calibrations/dead_time/gtx/dead_time   the detector's dead time [s] (one pixel per beam)
/ancillary_data/calibrations/first_photon_bias/gtx/ffb_corr, strength, width   the first-photon bias [s] of a
                                          Gaussian echo of the run's spread ``width`` against its expected
                                          photo-electrons ``strength`` (flightsim.instrument.photon.first_photon_bias_s)
/atlas_impulse_response/pce1_spot1, pce2_spot3/tep_histogram   tep_hist, tep_hist_time: not a measured transmitter
                                          echo path, the simulated pulse (Gaussian of the echo's σ) in 50 ps bins
/ds_surf_type                             1..5, the dimension scale of signal_conf_ph's surface types
/METADATA/DatasetIdentification           attributes shortName "ATL03", VersionID "006", …
root attributes                           short_name "ATL03", identifier_product_type "ATL03", level, title, …

Every dataset of a ground-track group whose first dimension is its group's ``delta_time`` is attached to it as a
dimension scale, as ATL03's are (xarray and icepyx read the groups through them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SDP_EPOCH_GPS_S = 1198800018.0  # GPS seconds at 2018-01-01T00:00:00Z, ATL03's atlas_sdp_gps_epoch
ADJUSTED_GPS_S = 1.0e9  # adjusted standard GPS time = GPS seconds − 1e9
GPS_WEEK_S = 604800.0
RELEASE = "006"
TEP_BIN_S = 5.0e-11  # the tep histogram's bin [s]
SPOTS = {0: ("gt1l", "gt1r", "gt2l", "gt2r", "gt3l", "gt3r"), 1: ("gt3r", "gt3l", "gt2r", "gt2l", "gt1r", "gt1l")}


def adjusted_to_delta_time(adjusted_gps_s):
    """ATL03's delta_time [s since the SDP epoch] of adjusted standard GPS times (GPS seconds − 1e9) [s]."""
    return np.asarray(adjusted_gps_s, dtype=np.float64) + (ADJUSTED_GPS_S - SDP_EPOCH_GPS_S)


@dataclass(frozen=True)
class Granule:
    """What the granule's metadata needs from the run: the beams' names (None: ``gtN``, N = beam + 1), the spacecraft
    orientation, the range gate [s of time of flight], the echo's spread σ [s], the dead time [s] and the first-photon
    bias table (strengths [photo-electrons], biases [s])."""

    beam_names: tuple[str, ...] | None = None
    sc_orient: int = 0
    gate_s: float = 1.0e-5
    sigma_t_s: float = 6.4e-10
    dead_time_s: float = 0.0
    fpb_strength: tuple[float, ...] = ()
    fpb_bias_s: tuple[float, ...] = ()

    def track_name(self, beam: int) -> str:
        return self.beam_names[beam] if self.beam_names else f"gt{beam + 1}"


def write_granule(f, granule: Granule, tracks: list[str]) -> None:
    """orbit_info, ancillary_data, atlas_impulse_response, METADATA, ds_surf_type and the root attributes of the open
    ``atl03.h5`` ``f`` whose ground-track groups ``tracks`` are complete; then the tracks' dimension scales."""
    times = [f[f"{t}/heights/delta_time"] for t in tracks if f[f"{t}/heights/delta_time"].shape[0]]
    t0 = min((float(d[0]) for d in times), default=0.0)
    t1 = max((float(d[-1]) for d in times), default=0.0)
    segments = [f[f"{t}/geolocation/segment_id"][:] for t in tracks]
    segments = np.concatenate(segments) if segments else np.zeros(0, np.int32)
    _orbit_info(f.create_group("orbit_info"), granule.sc_orient, t0)
    _ancillary(f.create_group("ancillary_data"), t0, t1, segments)
    _calibrations(f.require_group("ancillary_data/calibrations"), granule, tracks)
    _impulse_response(f, granule.sigma_t_s, t0)
    f.create_dataset("ds_surf_type", data=np.arange(1, 6, dtype=np.int32))
    f["ds_surf_type"].make_scale("ds_surf_type")
    _metadata(f, t0, t1)
    for t in tracks:
        _scales(f[t])
        f[f"{t}/heights/signal_conf_ph"].dims[1].attach_scale(f["ds_surf_type"])
        strong = _strong(t, granule.sc_orient)
        if strong is not None:
            f[t].attrs.update(atlas_beam_type="strong" if strong else "weak",
                              atlas_spot_number=str(SPOTS[granule.sc_orient].index(t) + 1), groundtrack_id=t)


def _strong(track: str, sc_orient: int) -> bool | None:
    """Whether an ATL03-named track is a strong beam (ATLAS spots 1, 3, 5), None for other names."""
    return None if track not in SPOTS[0] else SPOTS[sc_orient].index(track) % 2 == 0


def utc(delta_time: float) -> str:
    """ATL03's UTC text of a delta_time, e.g. "2025-12-18T13:19:42.000000Z" (leap seconds by astropy)."""
    from astropy.time import Time

    t = Time(SDP_EPOCH_GPS_S + delta_time, format="gps", precision=6).utc
    return t.isot + "Z"


def _one(g, name: str, value, dtype) -> None:
    g.create_dataset(name, data=np.array([value], dtype=dtype))


def _orbit_info(g, sc_orient: int, t0: float) -> None:
    _one(g, "sc_orient", sc_orient, np.int8)
    _one(g, "sc_orient_time", t0, np.float64)
    for name, dtype in (("rgt", np.int16), ("cycle_number", np.int8), ("orbit_number", np.uint16)):
        _one(g, name, 0, dtype)
    g["sc_orient"].attrs.update(flag_values=np.array([0, 1, 2], np.int8), flag_meanings="backward forward transition")
    g["rgt"].attrs["description"] = "0: a simulated pass, on none of ICESat-2's reference ground tracks"


def _ancillary(g, t0: float, t1: float, segments: np.ndarray) -> None:
    _one(g, "atlas_sdp_gps_epoch", SDP_EPOCH_GPS_S, np.float64)
    for name, t in (("data_start_utc", t0), ("data_end_utc", t1), ("granule_start_utc", t0), ("granule_end_utc", t1)):
        _one(g, name, utc(t).encode(), "S27")
    for end, t in (("start", t0), ("end", t1)):
        gps = SDP_EPOCH_GPS_S + t
        _one(g, f"{end}_delta_time", t, np.float64)
        _one(g, f"{end}_gpsweek", int(gps // GPS_WEEK_S), np.int32)
        _one(g, f"{end}_gpssow", gps - (gps // GPS_WEEK_S) * GPS_WEEK_S, np.float64)
        geoseg = (segments.min() if end == "start" else segments.max()) if len(segments) else 0
        _one(g, f"{end}_geoseg", int(geoseg), np.int32)
        for name, dtype in (("rgt", np.int16), ("cycle", np.int8), ("orbit", np.int32), ("region", np.int8)):
            _one(g, f"{end}_{name}", 0, dtype)
    _one(g, "release", RELEASE.encode(), "S3")
    _one(g, "version", RELEASE.encode(), "S3")
    tep = g.create_group("tep")
    _one(tep, "n_tep_bins", 400, np.int32)
    _one(tep, "tep_bin_size", TEP_BIN_S, np.float64)


def _calibrations(g, granule: Granule, tracks: list[str]) -> None:
    for t in tracks:
        _one(g.require_group(f"dead_time/{t}"), "dead_time", granule.dead_time_s, np.float64)
        fpb = g.require_group(f"first_photon_bias/{t}")
        fpb.create_dataset("strength", data=np.asarray(granule.fpb_strength, dtype=np.float64))
        fpb.create_dataset("ffb_corr", data=np.asarray(granule.fpb_bias_s, dtype=np.float64))
        _one(fpb, "width", granule.sigma_t_s, np.float64)


def _impulse_response(f, sigma_s: float, t0: float) -> None:
    """The simulated pulse as ATL03's TEP histograms (a Gaussian of the echo's σ, 400 bins of 50 ps, summing to 1)."""
    time = (np.arange(400) - 200 + 0.5) * TEP_BIN_S
    hist = np.exp(-0.5 * (time / sigma_s) ** 2)
    hist /= hist.sum()
    for spot in ("pce1_spot1", "pce2_spot3"):
        g = f.create_group(f"atlas_impulse_response/{spot}/tep_histogram")
        g.create_dataset("tep_hist", data=hist)
        g.create_dataset("tep_hist_time", data=time)
        _one(g, "tep_hist_sum", 1.0, np.float64)
        _one(g, "tep_tod", t0, np.float64)
        g.attrs["description"] = "the simulated pulse shape (flightsim), not a measured transmitter echo path"


def _metadata(f, t0: float, t1: float) -> None:
    from flightsim.core.version import __version__

    about = {"short_name": "ATL03", "identifier_product_type": "ATL03", "level": "L2",
             "title": "ATLAS/ICESat-2 L2A Global Geolocated Photon Data (simulated)",
             "identifier_product_format_version": RELEASE, "Conventions": "CF-1.6",
             "source": f"flightsim {__version__}: a simulated pass, not an ICESat-2 granule",
             "time_coverage_start": utc(t0), "time_coverage_end": utc(t1),
             "references": "Neumann et al. 2019, Remote Sens. Environ. 233:111325; ATL03 ATBD and data dictionary"}
    f.attrs.update(about)
    ident = f.create_group("METADATA/DatasetIdentification")
    ident.attrs.update(shortName="ATL03", VersionID=RELEASE, longName=about["title"], fileName="atl03.h5",
                       originatorOrganizationName="flightsim (simulation)", status="simulated",
                       abstract="Photons of a simulated photon-counting pass in ATL03's layout.",
                       spatialRepresentationType="along-track", language="eng", characterSet="utf8")
    extent = f.create_group("METADATA/Extent")
    extent.attrs.update(rangeBeginningDateTime=utc(t0), rangeEndingDateTime=utc(t1))


def _scales(track) -> None:
    """Make each subgroup's delta_time a dimension scale and attach it to the datasets of its length."""
    for sub in track.values():
        if "delta_time" not in sub:
            continue
        scale = sub["delta_time"]
        scale.make_scale("delta_time")
        for name, d in sub.items():
            if name != "delta_time" and d.ndim >= 1 and d.shape[0] == scale.shape[0]:
                d.dims[0].attach_scale(scale)
