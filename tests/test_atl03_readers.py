"""The six-beam ATL03 granule of an `atlas` pass opened in the readers ICESat-2 users have (icesat2_toolkit's
``io.ATL03.read_granule``, icepyx's ``Read``): what they read is what flightsim wrote, and the geometry and photon
counts they give match closed forms from the preset's values (ICESat-2's: 90 m across track within a pair, 3.3 km
between pairs at 500 km, strong:weak energy 4:1, Neumann et al. 2019, Markus et al. 2017) and the lidar equation."""
from __future__ import annotations

import math
import warnings

import h5py
import numpy as np
import pyproj
import pytest

from flightsim.engine.config import set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.engine.run import simulate_to_directory

TRACKS = ["gt1l", "gt1r", "gt2l", "gt2r", "gt3l", "gt3r"]
ACROSS_MRAD = {"gt1l": -6.69, "gt1r": -6.51, "gt2l": -0.09, "gt2r": 0.09, "gt3l": 6.51, "gt3r": 6.69}  # ± 0.18 / 2
SHOTS = 300
H = 6.62607015e-34
C = 299_792_458.0


def _run(directory, **settings):
    """A 300-shot pass of the atlas preset over its bright plane, without dead time (each beam's signal photons are
    then Poisson with the lidar equation's mean), in a 300 m range window."""
    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": (SHOTS - 0.5) / 1e4, "photon.reflectance": 0.9,
                       "photon.dead_time_s": 0.0, "photon.max_events": 128,
                       "photon.gate_m": [499850.0, 500150.0], **settings}.items():
        set_value(cfg, key, value)
    cfg = validate(cfg)
    simulate_to_directory(cfg, directory)
    return cfg, directory / "atl03.h5"


@pytest.fixture(scope="module")
def granule(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("atl03") / "run")


def _written(path) -> dict:
    """What flightsim wrote, read back by h5py: per track its heights columns by name, the others as group/name."""
    with h5py.File(path) as f:
        return {t: {(k if g == "heights" else f"{g}/{k}"): f[f"{t}/{g}/{k}"][:] for g, names in (
            ("heights", ("h_ph", "lat_ph", "lon_ph", "delta_time", "signal_conf_ph", "truth_kind", "dist_ph_along")),
            ("geolocation", ("segment_id", "segment_ph_cnt", "ph_index_beg", "reference_photon_index", "delta_time",
                             "segment_length")),
            ("bckgrd_atlas", ("bckgrd_rate",))) for k in names} for t in TRACKS}


def test_icesat2_toolkit_reads_the_six_beams_as_written(granule):
    from icesat2_toolkit.io import ATL03

    cfg, path = granule
    mds, attrs, beams = ATL03.read_granule(str(path), ATTRIBUTES=True)
    assert beams == TRACKS
    assert mds["orbit_info"]["sc_orient"][0] == 0 and attrs["short_name"] == "ATL03"
    assert mds["ancillary_data"]["atlas_sdp_gps_epoch"][0] == 1198800018.0
    written = _written(path)
    for t in TRACKS:
        for k in ("h_ph", "lat_ph", "lon_ph", "delta_time", "signal_conf_ph"):
            np.testing.assert_array_equal(mds[t]["heights"][k], written[t][k], err_msg=f"{t}/{k}")
        assert mds[t]["heights"]["signal_conf_ph"].shape[1] == 5
        for k in ("segment_id", "segment_ph_cnt", "ph_index_beg"):
            np.testing.assert_array_equal(mds[t]["geolocation"][k], written[t][f"geolocation/{k}"], err_msg=k)
    _check_geometry(cfg, path, {t: tuple(mds[t]["heights"][k] for k in ("lat_ph", "lon_ph", "signal_conf_ph", "delta_time"))
                          for t in TRACKS})


def test_icepyx_reads_the_six_beams_as_written(granule):
    import icepyx

    cfg, path = granule
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # icepyx warns about its own earlier spot numbers on every ground track
        reader = icepyx.Read(data_source=str(path))
        assert reader.product == "ATL03"
        reader.variables.append(var_list=["h_ph", "lat_ph", "lon_ph", "signal_conf_ph"])
        ds = reader.load()
    assert int(ds.sc_orient.values[0]) == 0 and int(ds.rgt.values[0]) == 0
    written = _written(path)
    read = {}
    for spot in ds.spot.values:
        one = ds.sel(spot=spot).isel(gran_idx=0)
        track = str(one.gt.values)
        mine = np.isfinite(one.h_ph.values)
        read[track] = (one.lat_ph.values[mine], one.lon_ph.values[mine], one.signal_conf_ph.values[mine],
                       one.delta_time.values[mine])
        for k in ("h_ph", "lat_ph", "lon_ph"):
            np.testing.assert_array_equal(one[k].values[mine], written[track][k], err_msg=f"{track}/{k}")
        np.testing.assert_array_equal(one.delta_time.values[mine], written[track]["delta_time"])
    assert sorted(read) == TRACKS
    # ATLAS's spots as ATL03 numbers them (backward: spots 1, 3, 5 strong on gt1l, gt2l, gt3l)
    assert dict(zip(ds.gt.values[0], ds.spot.values)) == {"gt1l": 1, "gt1r": 2, "gt2l": 3, "gt2r": 4, "gt3l": 5,
                                                          "gt3r": 6}
    _check_geometry(cfg, path, read)


def _height_above_plane(path) -> float:
    """The spacecraft's height above the plane [m]: the median one-way range of gt2l's surface photons (photons.h5
    beside the granule; beam 2 of six), times the cosine of its angle from nadir."""
    with h5py.File(path.parent / "photons.h5") as f:
        mine = (f["photons/pixel"][:] == 2) & (f["photons/signal"][:] == 1)
        return float(np.median(f["photons/range_m"][:][mine])) * math.cos(ACROSS_MRAD["gt2l"] * 1e-3)


def _check_geometry(cfg, path, tracks: dict) -> None:
    """From the readers' lat/lon of the photons they call high-confidence signal: each track's across-track position
    against (H − h) · tan θ of the preset's angles, so 90 m within a pair and 3.3 km between pairs."""
    lon0, lat0 = pyproj.Transformer.from_crs(cfg.scene.crs, "EPSG:4326", always_xy=True).transform(
        *cfg.scene.origin[:2])
    local = pyproj.CRS.from_proj4(f"+proj=aeqd +lat_0={lat0} +lon_0={lon0} +ellps=WGS84 +units=m")  # true distances
    to_local = pyproj.Transformer.from_crs("EPSG:4326", local, always_xy=True)
    centre = {}
    for t, (lat, lon, conf, time) in tracks.items():
        conf = conf if conf.ndim == 1 else conf[:, 0]  # land, of the five surface types
        x, y = to_local.transform(lon[conf == 4], lat[conf == 4])
        centre[t] = np.array([np.mean(x), np.mean(y)])
        if t == "gt2l":  # the direction of flight: the slope of gt2l's signal photons' positions against time
            along = np.polyfit(time[conf == 4] - time[0], np.column_stack([x, y]), 1)[0]
            along /= np.linalg.norm(along)
    right = np.array([along[1], -along[0]])  # to the right of the direction of flight
    height = _height_above_plane(path)
    across = {t: float((centre[t] - centre["gt2l"]) @ right) for t in TRACKS}
    for t in TRACKS:
        expected = height * (math.tan(ACROSS_MRAD[t] * 1e-3) - math.tan(ACROSS_MRAD["gt2l"] * 1e-3))
        assert across[t] == pytest.approx(expected, abs=1.0), (t, across[t], expected)
    for pair in ("gt1", "gt2", "gt3"):
        assert across[f"{pair}r"] - across[f"{pair}l"] == pytest.approx(90.0, abs=1.0)
    assert (across["gt3l"] + across["gt3r"]) / 2 - (across["gt2l"] + across["gt2r"]) / 2 == pytest.approx(3300.0,
                                                                                                          abs=10.0)


def _signal_per_shot(cfg, strong: bool) -> float:
    """The lidar equation's expected photo-electrons of a beam over the plane (nadir within 7 mrad: cos θ = 1 to 2e-5)."""
    p = cfg.photon
    energy = p.pulse_energy_j / (1.0 if strong else cfg.pairs.energy_ratio)
    distance = cfg.flight.altitude_m - cfg.scene.origin[2]
    return (energy * p.wavelength_nm * 1e-9 / (H * C) * p.reflectance / math.pi * math.pi * (p.aperture_m / 2) ** 2
            / distance ** 2 * p.optics_transmission * p.pde)


def test_strong_and_weak_beams_and_background_against_the_truth(granule):
    cfg, path = granule
    written = _written(path)
    with h5py.File(path) as f:
        kind = {t: f[t].attrs["atlas_beam_type"] for t in TRACKS}
    assert kind == {"gt1l": "strong", "gt1r": "weak", "gt2l": "strong", "gt2r": "weak", "gt3l": "strong",
                    "gt3r": "weak"}
    for pair in ("gt1", "gt2", "gt3"):
        strong = int((written[f"{pair}l"]["truth_kind"] == 1).sum())
        weak = int((written[f"{pair}r"]["truth_kind"] == 1).sum())
        # Poisson counts without dead time: each beam's mean per shot is the lidar equation's (±4σ)
        for count, is_strong in ((strong, True), (weak, False)):
            mean = _signal_per_shot(cfg, is_strong) * SHOTS
            assert abs(count - mean) < 4.0 * math.sqrt(mean), (pair, is_strong, count, mean)
        ratio, sigma = strong / weak, strong / weak * math.sqrt(1.0 / strong + 1.0 / weak)
        assert abs(ratio - 4.0) < 4.0 * sigma, (pair, ratio, sigma)
    for t in TRACKS:  # the background per 50 shots from the photons called noise, against the run's noise rate
        rate = written[t]["bckgrd_atlas/bckgrd_rate"]
        assert len(rate) == SHOTS // 50 and abs(rate.mean() / cfg.photon.noise_hz - 1.0) < 0.1, (t, rate)


def test_segments_are_atl03s_20_m_segments(granule):
    cfg, path = granule
    written = _written(path)
    geod = pyproj.Geod(ellps="WGS84")
    with h5py.File(path) as f:
        foot = {t: (f[f"{t}/footprint/lat"][:], f[f"{t}/footprint/lon"][:]) for t in TRACKS}
    for t in TRACKS:
        w = written[t]
        count, begin = w["geolocation/segment_ph_cnt"], w["geolocation/ph_index_beg"]
        assert count.sum() == len(w["h_ph"]) and (w["geolocation/segment_length"] == 20.0).all()
        assert (np.diff(w["geolocation/segment_id"]) == 1).all() and (np.diff(w["geolocation/delta_time"]) > 0).all()
        assert np.array_equal(begin[count > 0], 1 + np.concatenate([[0], np.cumsum(count)[:-1]])[count > 0])
        assert ((w["geolocation/reference_photon_index"] >= 1) & (w["geolocation/reference_photon_index"] <= count)).all()
        assert (w["dist_ph_along"] >= 0).all() and (w["dist_ph_along"] < 20.0).all()
        lat, lon = foot[t]
        _, _, length = geod.inv(lon[0], lat[0], lon[-1], lat[-1])  # the track flown, by pyproj's geodesic
        assert len(count) == math.floor(length / 20.0) + 1


def test_forward_orientation_makes_the_right_beams_strong(tmp_path):
    cfg, path = _run(tmp_path / "fwd", **{"pairs.sc_orient": 1, "flight.duration_s": 0.01})
    with h5py.File(path) as f:
        assert f["orbit_info/sc_orient"][0] == 1
        signal = {t: int((f[f"{t}/heights/truth_kind"][:] == 1).sum()) for t in TRACKS}
        assert f["gt1r"].attrs["atlas_beam_type"] == "strong" and f["gt1r"].attrs["atlas_spot_number"] == "5"
    for pair in ("gt1", "gt2", "gt3"):
        assert signal[f"{pair}r"] > 2 * signal[f"{pair}l"]
