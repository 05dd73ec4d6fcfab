"""ATL08-like classification and segments (flightsim.outputs.atl08) on synthetic photons whose truth is known.

A strong beam over 1 km: a shot every 0.7 m (10 kHz at 7 km/s), ground on a 5 % slope with Gaussian height
noise (σ 0.3 m, about one photon per shot), a canopy from 100 m to 900 m whose photons (1.5 per shot) lie
uniformly between 2 m and its top at 18 m, and a daytime background of 2 MHz (2·2e6/c photons per metre of
height and shot) over a telemetry band from 30 m below to 50 m above the ground. signal_conf_ph comes from
the project's ATL03 signal finder, as in atl03.h5. Expected values are the truth's: the mean of the true
ground under the ground photons, the 98th percentile of the canopy photons' true heights, the line's
latitude and time at a segment's middle.
"""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from flightsim.core.errors import InputError
from flightsim.outputs.atl08 import FILL, ATL08Settings, atl08_segments
from flightsim.outputs.atl08_h5 import join_atl08, write_atl08
from flightsim.scoring.signal_finder import SignalFinder

C = 299_792_458.0
SPACING, LENGTH, TOP = 0.7, 1000.0, 18.0
LAT0, DLAT, T0, PRF = 10.0, 9e-6, 5000.0, 10_000.0


def _ground(x):
    return 120.0 + 0.05 * x


def _photons(seed: int = 3, canopy: tuple[float, float] = (100.0, 900.0), rate_hz: float = 2e6) -> dict:
    rng = np.random.default_rng(seed)
    shots = np.arange(int(LENGTH / SPACING))
    xs = shots * SPACING
    n_ground = rng.poisson(1.0, len(xs))
    n_canopy = rng.poisson(1.5, len(xs)) * ((xs >= canopy[0]) & (xs < canopy[1]))
    n_noise = rng.poisson(rate_hz * 2.0 * 80.0 / C, len(xs))
    kind = np.concatenate([np.full(n_ground.sum(), 1), np.full(n_canopy.sum(), 2), np.full(n_noise.sum(), 0)])
    pulse = np.concatenate([np.repeat(shots, n) for n in (n_ground, n_canopy, n_noise)])
    x = pulse * SPACING
    above = np.concatenate([rng.normal(0.0, 0.3, n_ground.sum()), rng.uniform(2.0, TOP, n_canopy.sum()),
                            rng.uniform(-30.0, 50.0, n_noise.sum())])
    order = np.argsort(x, kind="stable")
    x, h, pulse, kind, above = x[order], (_ground(x) + above)[order], pulse[order], kind[order], above[order]
    conf = SignalFinder().classify(x, h, pulse)
    return dict(x=x, h=h, pulse=pulse, kind=kind, above=above, conf=conf, lat=LAT0 + DLAT * x, lon=-70.0 + 0 * x,
                t=T0 + pulse / PRF)


def _run(p: dict, **kw) -> dict:
    return atl08_segments(p["x"], p["h"], p["lat"], p["lon"], p["conf"], p["t"], **kw)


@pytest.fixture(scope="module")
def forest():
    p = _photons()
    return p, _run(p)


def test_terrain_heights_and_ground_recall(forest):
    p, out = forest
    seg, cls = out["land_segments"], out["signal_photons"]["classed_pc_flag"]
    assert len(seg["h_te_mean"]) == 10
    for j in range(10):
        ground = (np.floor(p["x"] / 100) == j) & (p["kind"] == 1)
        assert abs(seg["h_te_mean"][j] - _ground(p["x"][ground]).mean()) < 0.2, j
        assert abs(seg["h_te_median"][j] - np.median(p["h"][ground])) < 0.2, j
    assert np.mean(cls[p["kind"] == 1] == 1) >= 0.9
    assert np.mean(cls[p["kind"] == 2] == 1) < 0.02  # canopy starts 2 m up: hardly any in the ground band


def test_canopy_height_is_the_98th_percentile_of_the_canopy_photons(forest):
    p, out = forest
    seg = out["land_segments"]
    for j in range(1, 9):  # the segments the canopy fills
        inside = (np.floor(p["x"] / 100) == j) & (p["kind"] == 2)
        assert abs(seg["h_canopy"][j] - np.percentile(p["above"][inside], 98)) < 1.0, j
    cls = out["signal_photons"]["classed_pc_flag"]
    assert np.mean(cls[(p["kind"] == 0) & (p["above"] > TOP + 3.0)] == 0) > 0.99  # noise above the canopy
    assert np.mean(cls[(p["kind"] == 0) & (p["above"] < -3.0)] == 0) > 0.99  # noise below the ground


def test_bare_ground_has_no_canopy_height():
    p = _photons(seed=4, canopy=(0.0, 0.0))
    seg = _run(p)["land_segments"]
    assert len(seg["h_canopy"]) == 10 and (seg["h_canopy"] == FILL).all()
    assert (seg["h_mean_canopy"] == FILL).all() and (seg["canopy_openness"] == FILL).all()


def test_top_of_canopy_photons_are_the_highest_of_their_window(forest):
    p, out = forest
    cls, rel = out["signal_photons"]["classed_pc_flag"], out["signal_photons"]["ph_h"]
    window = np.floor(p["x"] / 5.0)
    for w in np.unique(window[cls == 3]):
        here = window == w
        assert rel[here & (cls == 3)].min() >= rel[here & (cls == 2)].max(initial=-np.inf)
    share = np.sum(cls == 3) / np.sum(cls >= 2)
    assert 0.03 < share < 0.15  # the top 5 % of each 5 m window, at least one photon each


def test_segment_ids_positions_times_and_counts(forest):
    p, out = forest
    seg, ph = out["land_segments"], out["signal_photons"]
    j = np.arange(10)
    np.testing.assert_array_equal(seg["segment_id_beg"], 5 * j + 1)
    np.testing.assert_array_equal(seg["segment_id_end"], 5 * j + 5)
    middle = (j + 0.5) * 100.0
    np.testing.assert_allclose(seg["latitude"], LAT0 + DLAT * middle, rtol=0, atol=1e-12)
    np.testing.assert_allclose(seg["delta_time"], T0 + middle / SPACING / PRF, rtol=0, atol=1e-9)
    for k, name in ((1, "n_te_photons"), (2, "n_ca_photons"), (3, "n_toc_photons")):
        np.testing.assert_array_equal(seg[name], np.bincount(np.floor(p["x"] / 100).astype(int),
                                                             weights=ph["classed_pc_flag"] == k, minlength=10))
    np.testing.assert_array_equal(ph["ph_segment_id"], np.floor(p["x"] / 20).astype(int) + 1)
    np.testing.assert_array_equal(ph["classed_pc_indx"], np.arange(1, len(p["x"]) + 1))
    assert not any(np.isnan(v).any() for group in out.values() for v in group.values())


def test_input_order_does_not_matter(forest):
    p, out = forest
    order = np.random.default_rng(0).permutation(len(p["x"]))
    shuffled = _run({k: v[order] for k, v in p.items()})
    np.testing.assert_array_equal(shuffled["signal_photons"]["classed_pc_flag"],
                                  out["signal_photons"]["classed_pc_flag"][order])
    np.testing.assert_allclose(shuffled["land_segments"]["h_canopy"], out["land_segments"]["h_canopy"])


@pytest.mark.parametrize("threads", [2, 3])
def test_threads_give_the_same_products(forest, threads):
    """The density filter's counts shared out over threads (its sort and walk in bands of columns): every photon and
    segment column the same as on one thread."""
    p, out = forest
    shared = _run(p, threads=threads)
    for group in ("signal_photons", "land_segments"):
        for name, values in out[group].items():
            np.testing.assert_array_equal(shared[group][name], values, err_msg=f"{group}/{name}")


def test_atl08_threads_shared_out_by_photons(monkeypatch):
    """Tracks side by side share the cores by their photons (a strong beam four times a weak one's threads), one
    after another each takes every core (at most MAX_THREADS); never fewer than one."""
    from flightsim.engine.products import photons as product

    tracks = {"gt1l": 4_000_000, "gt1r": 1_000_000, "gt2l": 4_000_000, "gt2r": 1_000_000, "gt3l": 4_000_000,
              "gt3r": 1_000_000}
    monkeypatch.setattr(product, "usable_cores", lambda: 16)
    assert product.atl08_threads(tracks, True) == {"gt1l": 4, "gt1r": 1, "gt2l": 4, "gt2r": 1, "gt3l": 4, "gt3r": 1}
    assert set(product.atl08_threads(tracks, False).values()) == {16}
    monkeypatch.setattr(product, "usable_cores", lambda: 64)
    assert set(product.atl08_threads(tracks, False).values()) == {product.MAX_THREADS}
    monkeypatch.setattr(product, "usable_cores", lambda: 2)
    assert set(product.atl08_threads(tracks, True).values()) == {1}
    assert product.atl08_threads({"gt1l": 0}, True) == {"gt1l": 1}


def test_no_photons_and_no_signal_give_no_segments():
    empty = atl08_segments([], [], [], [], np.zeros(0, int), [])
    assert all(len(v) == 0 for v in empty["land_segments"].values())
    rng = np.random.default_rng(1)
    x = np.sort(rng.uniform(0, 1000, 300))  # sparse background only
    out = atl08_segments(x, rng.uniform(0, 80, 300), x, x, np.zeros(300, int), x)
    assert (out["signal_photons"]["classed_pc_flag"] == 0).all() and len(out["land_segments"]["h_canopy"]) == 0
    assert (out["signal_photons"]["ph_h"] == FILL).all() and (out["signal_photons"]["d_flag"] == 0).all()


@pytest.mark.parametrize("change, field", [
    ({"h_ph": np.zeros(3)}, "h_ph"),
    ({"h_ph": [0.0, np.nan]}, "h_ph"),
    ({"along_track_m": [-1.0, 2.0]}, "along_track_m"),
    ({"signal_conf_ph": [0.5, 1.0]}, "signal_conf_ph"),
    ({"signal_conf_ph": [0, 5]}, "signal_conf_ph"),
    ({"segment_m": 0.0}, "segment_m"),
    ({"settings": ATL08Settings(min_buffer_m=2.0, max_buffer_m=1.0)}, "atl08.min_buffer_m"),
    ({"settings": ATL08Settings(toc_percentile=101.0)}, "atl08.toc_percentile"),
])
def test_bad_input_is_refused_by_name(change, field):
    args = dict(along_track_m=[1.0, 2.0], h_ph=[0.0, 1.0], lat=[0.0, 0.0], lon=[0.0, 0.0],
                signal_conf_ph=np.array([4, 4]), delta_time=[0.0, 0.1])
    args.update(change)
    with pytest.raises(InputError, match=f"invalid {field}"):
        atl08_segments(**args)


# --- atl08.h5 ------------------------------------------------------------------------------------

# Paths of ATL08's datasets (ATL08 data dictionary, as readers of the product list them: SlideRule's atl08
# fields, PhoREAL, ICESat2VegR): the ones this product writes.
ATL08_PATHS = {f"land_segments/{n}" for n in ("latitude", "longitude", "delta_time", "segment_id_beg",
                                                "segment_id_end", "n_seg_ph")} | \
    {f"land_segments/terrain/{n}" for n in ("h_te_mean", "h_te_median", "n_te_photons")} | \
    {f"land_segments/canopy/{n}" for n in ("h_canopy", "h_mean_canopy", "canopy_openness", "n_ca_photons",
                                           "n_toc_photons")} | \
    {f"signal_photons/{n}" for n in ("classed_pc_flag", "classed_pc_indx", "ph_segment_id", "ph_h", "d_flag",
                                     "delta_time")}


def test_atl08_h5_round_trips_with_atl08_paths_and_types(forest, tmp_path):
    _, out = forest
    path = write_atl08(tmp_path / "atl08.h5", {0: out, "gt2l": out}, {"config_toml": "a = 1"})
    with h5py.File(path) as f:
        assert sorted(f) == ["gt1", "gt2l"] and f.attrs["config_toml"] == "a = 1"
        g = f["gt1"]
        paths = set()
        g.visititems(lambda name, obj: paths.add(name) if isinstance(obj, h5py.Dataset) else None)
        assert paths == ATL08_PATHS
        canopy = g["land_segments/canopy/h_canopy"]
        assert canopy.dtype == np.float32 and canopy.attrs["_FillValue"] == np.float32(FILL)
        np.testing.assert_array_equal(canopy[()], out["land_segments"]["h_canopy"].astype(np.float32))
        np.testing.assert_array_equal(g["land_segments/terrain/h_te_mean"][()],
                                      out["land_segments"]["h_te_mean"].astype(np.float32))
        np.testing.assert_array_equal(g["signal_photons/classed_pc_flag"][()], out["signal_photons"]["classed_pc_flag"])
        assert g["signal_photons/classed_pc_flag"].dtype == np.int8
        assert g["land_segments/segment_id_beg"].dtype == np.int32
        assert g["land_segments/delta_time"].dtype == np.float64
    assert sorted(p.name for p in tmp_path.iterdir()) == ["atl08.h5"]


def _layout(path) -> dict:
    """Every group's and dataset's attributes, and each dataset's values, dtype, chunks, filters and fill value."""
    out = {}
    with h5py.File(path) as f:
        def visit(name, obj):
            out[name] = {k: np.asarray(v).tolist() for k, v in obj.attrs.items()}
            if isinstance(obj, h5py.Dataset):
                out[name].update(values=obj[()].tobytes(), dtype=obj.dtype.str, chunks=obj.chunks,
                                 maxshape=obj.maxshape, gzip=(obj.compression, obj.compression_opts, obj.shuffle),
                                 fill=obj.fillvalue.item())
        f.visititems(visit)
        out["/"] = {k: v for k, v in f.attrs.items()}
    return out


def test_atl08_h5_joined_from_the_tracks_files_is_the_file_written_at_once(forest, tmp_path):
    """join_atl08 of two tracks written to files of their own (as worker processes write them) against write_atl08
    of both at once: the same groups, datasets, values, storage (chunks, gzip, shuffle, fill) and attributes; the
    tracks' files are left for the caller."""
    _, out = forest
    other = {group: {k: v[::-1].copy() for k, v in columns.items()} for group, columns in out.items()}
    at_once = write_atl08(tmp_path / "at_once.h5", {"gt1l": out, "gt2r": other}, {"config_toml": "a = 1"})
    parts = {track: write_atl08(tmp_path / f"{track}.h5", {track: beam})
             for track, beam in (("gt1l", out), ("gt2r", other))}
    joined = join_atl08(tmp_path / "atl08.h5", parts, {"config_toml": "a = 1"})
    assert _layout(joined) == _layout(at_once) and len(_layout(joined)) > 25
    assert sorted(p.name for p in tmp_path.iterdir()) == ["at_once.h5", "atl08.h5", "gt1l.h5", "gt2r.h5"]


@pytest.mark.parametrize("beams, field", [
    ({}, "beams"),
    ({"gt7x": None}, "beams"),
    ({0: {"land_segments": {}}}, r"beams\[0\]"),
    ({0: "gt1", "gt1": "gt1"}, "beams"),
])
def test_atl08_h5_refuses_bad_input_and_writes_nothing(tmp_path, beams, field):
    with pytest.raises(InputError, match=f"invalid {field}"):
        write_atl08(tmp_path / "atl08.h5", beams)
    assert list(tmp_path.iterdir()) == []


def test_atl08_h5_refuses_nan_heights(forest, tmp_path):
    _, out = forest
    bad = {"land_segments": dict(out["land_segments"]), "signal_photons": out["signal_photons"]}
    bad["land_segments"]["h_canopy"] = np.full_like(bad["land_segments"]["h_canopy"], np.nan)
    with pytest.raises(InputError, match=r"invalid beams\[0\].land_segments.h_canopy"):
        write_atl08(tmp_path / "atl08.h5", {0: bad})
    assert list(tmp_path.iterdir()) == []


# --- ground under dense canopy ---------------------------------------------------------------------

def _dense_canopy(slope: float, seed: int, gap: tuple[float, float] | None = None) -> dict:
    """A strong beam over 1 km of ground at ``slope`` (rise over along-track run) under a closed canopy: per shot
    (every 0.7 m) Poisson 0.3 ground photons (σ 0.3 m) and 2.7 canopy photons uniform between 5 m and 30 m above
    the ground (90 % of the signal from the canopy: about 43 ground photons in a 100 m segment against 390 from
    the canopy), a 2 MHz background over a band from 30 m below to 50 m above the ground; no ground photon at all
    between ``gap`` [m] along track."""
    rng = np.random.default_rng(seed)
    shots = np.arange(int(LENGTH / SPACING))
    xs = shots * SPACING
    n_ground = rng.poisson(0.3, len(xs))
    if gap is not None:
        n_ground[(xs >= gap[0]) & (xs < gap[1])] = 0
    n_canopy, n_noise = rng.poisson(2.7, len(xs)), rng.poisson(2e6 * 2.0 * 80.0 / C, len(xs))
    kind = np.repeat([1, 2, 0], [n_ground.sum(), n_canopy.sum(), n_noise.sum()])
    pulse = np.concatenate([np.repeat(shots, n) for n in (n_ground, n_canopy, n_noise)])
    above = np.concatenate([rng.normal(0.0, 0.3, n_ground.sum()), rng.uniform(5.0, 30.0, n_canopy.sum()),
                            rng.uniform(-30.0, 50.0, n_noise.sum())])
    order = np.argsort(pulse, kind="stable")
    x, pulse, kind, above = pulse[order] * SPACING, pulse[order], kind[order], above[order]
    h = 300.0 + slope * x + above
    return dict(x=x, h=h, pulse=pulse, kind=kind, above=above, conf=SignalFinder().classify(x, h, pulse),
                lat=LAT0 + DLAT * x, lon=-70.0 + 0 * x, t=T0 + pulse / PRF)


@pytest.mark.parametrize("slope", [0.0, 0.1, 0.2])
def test_ground_under_dense_canopy_flat_and_sloped(slope):
    """Truth per segment: the mean true ground height under its ground photons (300 m + slope × along track) and
    the 98th percentile of its canopy photons' true heights above the ground. Checked: the inner segments 1–8 (at
    the line's ends the density filter's ellipse, ±50 m along track, holds half the neighbours, and the dim ground
    there is missed). Bounds: h_te_mean within 1.0 m (the ground photons' σ is 0.3 m; a 10 m window of a 20 %
    slope rises 2 m; over seeds 0–19 the largest error was 0.85 m at 20 %), h_canopy within 2.0 m of the true 98th
    percentile (background photons above the crowns taken for canopy raise it, canopy photons left as noise
    lower it: −1.6 … +0.6 m over seeds 0–19). The classifier before this check put the ground 2–11 m up in the
    canopy under such a canopy."""
    p = _dense_canopy(slope, seed=1)
    out = _run(p)
    seg, cls = out["land_segments"], out["signal_photons"]["classed_pc_flag"]
    segment = np.floor(p["x"] / 100.0)
    assert len(seg["h_te_mean"]) == 10
    for j in range(1, 9):
        ground, canopy = (segment == j) & (p["kind"] == 1), (segment == j) & (p["kind"] == 2)
        assert abs(seg["h_te_mean"][j] - (300.0 + slope * p["x"][ground]).mean()) < 1.0, (j, seg["h_te_mean"][j])
        assert abs(seg["h_canopy"][j] - np.percentile(p["above"][canopy], 98)) < 2.0, (j, seg["h_canopy"][j])
    inner = (segment >= 1) & (segment <= 8)
    assert np.mean(cls[inner & (p["kind"] == 2)] == 1) < 0.005  # canopy photons are hardly ever ground
    assert np.mean(cls[inner & (p["kind"] == 1)] == 1) > 0.6  # most ground photons are found


@pytest.mark.parametrize("slope", [0.0, 0.2])
def test_a_segment_without_ground_photons_has_no_terrain_height(slope):
    """No ground photon in segment 4 (400–500 m), the canopy over it as elsewhere: its terrain heights are ATL08's
    fill value (not the canopy's lowest photons), while its canopy height, above the ground surface interpolated
    from the segments around it, is still within 2.0 m of the true 98th percentile."""
    p = _dense_canopy(slope, seed=2, gap=(400.0, 500.0))
    seg = _run(p)["land_segments"]
    assert seg["h_te_mean"][4] == FILL and seg["h_te_median"][4] == FILL
    assert seg["n_te_photons"][4] < 10
    canopy = (np.floor(p["x"] / 100.0) == 4) & (p["kind"] == 2)
    assert abs(seg["h_canopy"][4] - np.percentile(p["above"][canopy], 98)) < 2.0
    for j in (2, 6):  # the segments beside it still have their terrain
        ground = (np.floor(p["x"] / 100.0) == j) & (p["kind"] == 1)
        assert abs(seg["h_te_mean"][j] - (300.0 + slope * p["x"][ground]).mean()) < 1.0


def test_window_floors_take_the_lowest_cluster_not_the_lowest_photon():
    """Hand-made windows: a lone low photon is no cluster; the floor is the median of the lowest 3 photons within
    1 m; a window with no 3 photons within 1 m has none."""
    from flightsim.outputs.atl08_ground import window_floors

    window = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 2, 2, 2, 2])
    h = np.array([-5.0, 0.1, 0.0, 0.4, 7.0, 7.2, 3.0, 5.0, 7.0, 10.0, 10.9, 10.3, 2.0])
    floors, valid = window_floors(window, h, 3, 3, 1.0)
    np.testing.assert_array_equal(valid, [True, False, True])
    np.testing.assert_allclose(floors[[0, 2]], [0.1, 10.3])


def test_a_lone_low_floor_does_not_pull_the_ground_down():
    """One window's floor 50 m below a flat ground (background below it), the others at 0 ± 0.1 m, and three windows
    of canopy 8 m up (two together, one alone): the lone floors are no surface, the two canopy windows are raised,
    the ground windows are kept."""
    from flightsim.outputs.atl08_ground import raised, supported

    s = ATL08Settings()
    centres = np.arange(40) * 10.0 + 5.0
    floors = np.random.default_rng(0).uniform(-0.1, 0.1, 40)
    floors[20], floors[[5, 6, 30]] = -50.0, 8.0
    valid = supported(centres, floors, np.ones(40, dtype=bool), s)
    np.testing.assert_array_equal(np.flatnonzero(~valid), [20, 30])  # lone floors, below and above
    ground = valid & ~raised(centres, floors, valid, s.relief_slope, s.object_height_m)
    np.testing.assert_array_equal(np.flatnonzero(~ground), [5, 6, 20, 30])


def test_background_windows_are_numbered_as_np_unique_ranks_them():
    """Each photon's density window: the rank of its window among the windows holding photons (np.unique's inverse),
    with runs of empty windows between, photons on window edges and out of order."""
    from flightsim.outputs.atl08 import _windows

    s = ATL08Settings()
    rng = np.random.default_rng(3)
    w = s.dragann_window_m
    x = np.concatenate([rng.uniform(0.0, 3 * w, 400), rng.uniform(40 * w, 41 * w, 50), w * np.arange(5.0, 9.0),
                        [1e5 * w]])
    rng.shuffle(x)
    expected = np.unique(np.floor(x / w), return_inverse=True)[1].reshape(-1)
    assert np.array_equal(_windows(x, s), expected) and expected.max() == 8  # 9 windows hold photons
    assert len(_windows(np.zeros(0), s)) == 0
    far = np.array([0.0, 3e15, 1.0, 7e14])  # windows far apart: ranked without counting the empty ones between
    assert _windows(far, s).tolist() == [0, 2, 0, 1]
