"""The ATL03-style product of a photon-counting pass from orbit: its layout, and its geolocation against the
scene origin's own geodetic coordinates (pyproj) at the shot above it."""
from __future__ import annotations

import h5py
import numpy as np
import pyproj
import pytest

from flightsim.engine.config import set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.engine.run import simulate_to_directory
from flightsim.instrument.pairs import SINGLE_BEAM


def test_atl03_product_from_an_orbit_pass(tmp_path):
    """The single nadir strong beam (ground track gt1)."""
    cfg = preset_config("atlas")
    for key, value in {**SINGLE_BEAM, "flight.duration_s": 0.02, "scene.ccrs": [[0.0, 0.0, 1.5]], "scene.ccr_photons": 5.0,
                       "photon.gate_m": [499850.0, 500150.0]}.items():
        set_value(cfg, key, value)
    summary = simulate_to_directory(validate(cfg), tmp_path / "a")
    assert summary["files"] == ["photons.h5", "photons", "atl03.h5", "atl08.h5"]
    with h5py.File(tmp_path / "a" / "atl03.h5") as f:
        h = {k: f[f"gt1/heights/{k}"][:] for k in ("delta_time", "lat_ph", "lon_ph", "h_ph", "truth_kind",
                                                  "ph_id_pulse", "dist_ph_along")}
        h["signal_conf_ph"] = f["gt1/heights/signal_conf_ph"][:]
        geo = {k: f[f"gt1/footprint/{k}"][:] for k in ("delta_time", "lat", "lon", "h")}
        epoch = float(f["ancillary_data/atlas_sdp_gps_epoch"][0])
    assert len(h["h_ph"]) == summary["photons"]
    assert h["signal_conf_ph"].shape == (len(h["h_ph"]), 5)  # ATL03's five surface types, one surface here
    assert (h["signal_conf_ph"] == h["signal_conf_ph"][:, :1]).all()
    assert set(np.unique(h["signal_conf_ph"])) <= {0, 1, 2, 3, 4}  # from the signal finder, not the truth
    assert (h["signal_conf_ph"][h["truth_kind"] == 1, 0] >= 2).mean() > 0.9
    ground = h["h_ph"][h["truth_kind"] == 1]
    assert abs(np.median(ground) - cfg.scene.origin[2]) < 0.15  # the plane at the origin's height (+ pile-up)
    assert abs(np.median(h["h_ph"][h["truth_kind"] == 2]) - ground.mean() - 1.5) < 0.15  # the CCR 1.5 m up
    # the pass is above the scene origin at mid-run: that shot's footprint centre is the origin
    lon0, lat0 = pyproj.Transformer.from_crs(cfg.scene.crs, "EPSG:4326", always_xy=True).transform(
        *cfg.scene.origin[:2])
    # delta_time: GPS seconds since the SDP epoch 2018-01-01 (1198800018 s); start_gps_time is GPS − 1e9
    assert epoch == 1198800018.0
    mid = np.argmin(np.abs(geo["delta_time"] + epoch - (1e9 + cfg.flight.start_gps_time + 0.01)))
    assert geo["delta_time"][mid] + epoch - 1e9 - cfg.flight.start_gps_time == pytest.approx(0.01, abs=1e-6)
    assert geo["lat"][mid] == pytest.approx(lat0, abs=1e-6)
    assert geo["lon"][mid] == pytest.approx(lon0, abs=1e-6)
    assert geo["h"][mid] == pytest.approx(cfg.scene.origin[2], abs=0.01)
    assert (np.diff(geo["delta_time"]) > 0).all()


def test_three_beams_across_track_give_three_ground_tracks(tmp_path):
    """ATLAS-like strong beams 3.3 km apart: channels at −6.6, 0, +6.6 mrad across track from 500 km."""
    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.005, "instrument.emitter": "channels",
                       "channels.angles_mrad": "-6.6,0,6.6", "photon.gate_m": [499850.0, 500200.0]}.items():
        set_value(cfg, key, value)
    simulate_to_directory(validate(cfg), tmp_path / "b")
    geod = pyproj.Geod(ellps="WGS84")
    with h5py.File(tmp_path / "b" / "atl03.h5") as f:
        assert sorted(n for n in f if n.startswith("gt")) == ["gt1", "gt2", "gt3"]
        centre = [np.mean(f[f"gt{k}/footprint/{c}"][:]) for k in (1, 2, 3) for c in ("lat", "lon")]
        # each track's along-track distance from its own first photon: 0.005 s at ~7 km/s is ~35 m, not 3.3 km
        along = [f[f"gt{k}/heights/x_atc"][:] for k in (1, 2, 3)]
    assert all(a.min() == 0.0 and a.max() < 60.0 for a in along)
    for a, b in ((0, 2), (2, 4)):
        _, _, distance = geod.inv(centre[a + 1], centre[a], centre[b + 1], centre[b])
        assert distance == pytest.approx(500e3 * np.tan(6.6e-3), rel=2e-3)  # 3.30 km on the ground


def test_the_signal_finder_and_atl08_on_worker_processes_give_the_same_products(tmp_path, monkeypatch):
    """Past PARALLEL_PHOTONS photons a run starts worker processes as it goes; at its close the signal finder
    classifies each beam's finished stretches on them while the run goes on and the rest in blocks at its close, and
    ATL08's beams are worked out and written a beam a worker (forced here for a 0.2 s pass of six beams in parts of
    4096 photons, blocks of 1000, two workers): signal_conf_ph, the background rates and every atl08.h5 dataset the
    same as in this process, and no beam's own file left."""
    import flightsim.engine.products.photons as photons
    from flightsim.scoring import finder_stream

    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.2, "photon.gate_m": [499850.0, 500150.0],
                       "run.host_photons": 4096}.items():
        set_value(cfg, key, value)
    started, ran, streamed = [], [], []
    finish = finder_stream.FinderStream.finish
    monkeypatch.setattr(finder_stream, "STREAM_BLOCK", 1000)
    monkeypatch.setattr(finder_stream, "WAITING_PER_WORKER", 1000)  # none left to the close for the workers' start

    def counted(self, streams):  # the blocks classified while the run went on
        left = finish(self, streams)
        streamed.append(sum(map(len, self.pieces.values())))
        return left

    monkeypatch.setattr(finder_stream.FinderStream, "finish", counted)

    class Counted(photons.ProcessMap):
        def __init__(self, count, preload=()):
            super().__init__(count, preload)
            started.append((count, preload))

        def map(self, function, chunks, done=None):
            ran.append(function.__qualname__)
            return super().map(function, chunks, done)

    monkeypatch.setattr(photons, "ProcessMap", Counted)
    monkeypatch.setattr(photons, "usable_cores", lambda: 2)
    for name, parallel in (("serial", 1 << 40), ("workers", 1)):
        monkeypatch.setattr(photons, "PARALLEL_PHOTONS", parallel)
        simulate_to_directory(validate(cfg), tmp_path / name)
    assert started == [(2, photons.PRELOAD)]
    assert streamed[0] == 0 and streamed[1] >= 6  # no workers, no blocks; with them each beam's while it came
    assert "classify_part" in ran and ran[-1] == "write_atl08_track"
    for name in ("serial", "workers"):  # the beams' own atl08 files removed once joined
        assert not [p.name for p in (tmp_path / name).iterdir() if p.name.startswith(".")]
    with h5py.File(tmp_path / "serial" / "atl03.h5") as a, h5py.File(tmp_path / "workers" / "atl03.h5") as b:
        beams = [k for k in a if k.startswith("gt")]
        assert len(beams) == 6
        for beam in beams:
            for name in ("heights/signal_conf_ph", "bckgrd_atlas/bckgrd_rate"):
                np.testing.assert_array_equal(a[f"{beam}/{name}"][:], b[f"{beam}/{name}"][:], err_msg=name)
        assert (a[f"{beams[0]}/heights/signal_conf_ph"][:, 0] >= 3).any()  # the case: signal found
    with h5py.File(tmp_path / "serial" / "atl08.h5") as a, h5py.File(tmp_path / "workers" / "atl08.h5") as b:
        names = []
        a.visititems(lambda name, item: names.append(name) if isinstance(item, h5py.Dataset) else None)
        assert len(names) > 100
        for name in names:
            np.testing.assert_array_equal(a[name][()], b[name][()], err_msg=name)


@pytest.mark.parametrize("cores, pool", [(1, False), (2, False), (4, True)])
def test_two_cores_start_the_worker_processes_later(tmp_path, monkeypatch, cores, pool):
    """A run past PARALLEL_PHOTONS photons starts its workers on more than two cores; on two only past
    TWO_CORES_LATER times as many (their start takes the cores the run itself uses), on one never: a 0.05 s pass
    with PARALLEL_PHOTONS at a quarter of its photons."""
    import flightsim.engine.products.photons as photons

    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.05, "photon.gate_m": [499850.0, 500150.0], "run.host_photons": 4096,
                       "output.atl08": False}.items():
        set_value(cfg, key, value)
    started = []

    class Counted(photons.ProcessMap):
        def __init__(self, count, preload=()):
            started.append(count)
            super().__init__(count, preload)

    monkeypatch.setattr(photons, "ProcessMap", Counted)
    monkeypatch.setattr(photons, "usable_cores", lambda: cores)
    monkeypatch.setattr(photons, "PARALLEL_PHOTONS", 1 << 40)
    total = simulate_to_directory(validate(cfg), tmp_path / "count")["photons"]
    monkeypatch.setattr(photons, "PARALLEL_PHOTONS", total // 4)
    assert photons.PARALLEL_PHOTONS > 1000 and photons.TWO_CORES_LATER * (total // 4) > total  # between the two
    simulate_to_directory(validate(cfg), tmp_path / "run")
    assert started == ([cores] if pool else [])


@pytest.mark.parametrize("failing", ["las", "atl03"])
def test_a_writer_failing_on_its_thread_leaves_no_file_and_stops_the_workers(tmp_path, monkeypatch, failing):
    """The photon product's writers run on threads of their own: one that fails mid-run fails the run with its own
    error, every product file is removed (none renamed into place, no temporary left) and the worker processes end."""
    import flightsim.engine.products.photons as photons
    from flightsim.outputs import atl03_h5, photon_las

    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.05, "photon.gate_m": [499850.0, 500150.0]}.items():
        set_value(cfg, key, value)
    owner = photon_las.PhotonLas if failing == "las" else atl03_h5.Atl03Writer  # each appends in take
    monkeypatch.setattr(owner, "take", lambda self, chunk: (_ for _ in ()).throw(OSError(f"{failing} disk full")))
    pools = []

    class Kept(photons.ProcessMap):
        def __init__(self, count, preload=()):
            super().__init__(count, preload)
            pools.append(self)

    monkeypatch.setattr(photons, "ProcessMap", Kept)
    monkeypatch.setattr(photons, "usable_cores", lambda: 2)
    monkeypatch.setattr(photons, "PARALLEL_PHOTONS", 1)
    with pytest.raises(OSError, match=f"{failing} disk full"):
        simulate_to_directory(validate(cfg), tmp_path / "run")
    left = sorted(p.name for p in (tmp_path / "run").rglob("*") if p.is_file())
    assert [name for name in left if "h5" in name or name.endswith(".las") or ".part" in name] == []
    assert len(pools) == 1 and all(process.poll() is not None for process in pools[0].processes)


@pytest.mark.parametrize("in_order", [True, False])
def test_nearest_is_each_segments_first_least_offset(in_order):
    """_nearest, with segments in order (runs, no sort) and out of order (a sort): per segment, in segment order, the
    index of its least offset, the first on a tie, as a plain loop finds it."""
    from flightsim.outputs.atl03_h5 import _nearest

    rng = np.random.default_rng(7)
    for n in (1, 2, 7, 500):
        segment = rng.integers(0, max(n // 3, 1), n)
        segment = np.sort(segment) if in_order else segment
        offset = rng.integers(0, 3, n) / 2.0  # many ties
        expected = [min((o, i) for i, (s, o) in enumerate(zip(segment, offset)) if s == k)[1]
                    for k in sorted(set(segment.tolist()))]
        assert _nearest(segment, offset).tolist() == expected


@pytest.mark.parametrize("in_order", [True, False])
def test_distinct_shots_are_numpys_unique(in_order):
    """_distinct, on values in order (runs, no sort) and out of order (NumPy's): the distinct values, each one's first
    index and each value's place among them, as ``np.unique`` gives them (values, dtypes), for none, one and many."""
    from flightsim.outputs.atl03_h5 import _distinct

    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 9, 1000):
        values = rng.integers(0, max(n // 4, 1), n).astype(np.int64)
        values = np.sort(values) if in_order else values
        for inverse in (False, True):
            found = _distinct(values, inverse=inverse)
            expected = np.unique(values, return_index=True, return_inverse=inverse)
            assert len(found) == len(expected) == 2 + inverse
            for a, b in zip(found, expected):
                assert a.dtype == b.dtype and np.array_equal(a, b)


def test_horizontal_lengths_are_numpys_norm_bit_for_bit():
    """x_atc's horizontal lengths against ``np.linalg.norm`` of the first two columns of the offsets from an origin:
    the same float64 bits, at offsets from millimetres to thousands of kilometres and of either sign."""
    from flightsim.outputs.atl03_h5 import _horizontal

    rng = np.random.default_rng(3)
    points = rng.normal(0.0, 1.0, (100_000, 3)) * 10.0 ** rng.uniform(-3, 6.5, (100_000, 1))
    for origin in (np.zeros(3), points[7], rng.normal(0.0, 3e5, 3)):
        assert np.array_equal(_horizontal(points, origin), np.linalg.norm((points - origin)[:, :2], axis=1))


def test_reference_photons_over_chunks_are_the_nearest_to_the_centre_first_on_a_tie():
    """Each segment's reference photon over several chunks (a segment across their boundary, offsets that tie within
    and across chunks): the photon of least offset from the segment's centre, the earliest row on a tie, as a plain
    loop over every photon finds it."""
    from flightsim.outputs.atl03_h5 import _keep_reference, _references, _Track

    rng = np.random.default_rng(4)
    track, rows = _Track(), 0
    every = []
    for n in (50, 1, 80, 30):
        segment = np.sort(rng.integers(3 + rows // 40, 8 + rows // 40, n))
        offset = rng.integers(0, 4, n).astype(np.float64)  # many ties
        lat, lon, t = rng.normal(size=(3, n))
        _keep_reference(track, segment, offset, rows, lat, lon, t)
        every += [(int(s), o, rows + i, la, lo, ti)
                  for i, (s, o, la, lo, ti) in enumerate(zip(segment, offset, lat, lon, t))]
        rows += n
    ids = np.arange(1, 14)
    have, row, lat, lon, t = _references(track, ids)
    for k, s in enumerate(ids):
        mine = [p for p in every if p[0] == s]
        assert have[k] == bool(mine)
        if mine:
            best = min(mine, key=lambda p: (p[1], p[2]))
            assert (row[k], lat[k], lon[k], t[k]) == best[2:]
        else:
            assert np.isnan([row[k], lat[k], lon[k], t[k]]).all()


def test_background_frames_over_chunks_count_each_shot_once_and_take_the_first_shots_time():
    """The background frames of a track over several chunks (a frame across their boundary, a chunk's shots out of
    order, a shot of many photons): each frame's shots that detected a photon, summed over the chunks, and the
    delta_time of its first shot, against a plain loop over every photon."""
    from flightsim.outputs.atl03_granule import adjusted_to_delta_time
    from flightsim.outputs.atl03_h5 import FRAME_SHOTS, _frame_counts, _frames, _Track

    rng = np.random.default_rng(8)
    track, start, prf = _Track(), 1.25e9 + 0.3, 10_000.0
    shots: dict[int, set] = {}
    for lo, hi, n in ((0, 120, 200), (120, 130, 1), (130, 260, 90), (260, 400, 300)):
        pulse = rng.integers(lo, hi, n).astype(np.int64)
        pulse = pulse if n == 90 else np.sort(pulse)  # one chunk's photons out of shot order
        frames, shots_found, times = _frame_counts(pulse, start, prf)
        track.frame_counts.append((7 + frames, shots_found, times))  # the line's first frame numbered 7
        frame = 7 + pulse // FRAME_SHOTS
        for f, p in zip(frame.tolist(), pulse.tolist()):
            shots.setdefault(f, set()).add(p)
    ids, counts, times = _frames(track)
    assert ids.tolist() == sorted(shots)
    assert counts.tolist() == [len(shots[f]) for f in sorted(shots)]
    assert times.tolist() == [float(adjusted_to_delta_time(start + (f - 7) * FRAME_SHOTS / prf)) for f in sorted(shots)]
    assert [len(column) for column in _frames(_Track())] == [0, 0, 0]


def test_a_chunk_handed_on_in_parts_gives_the_same_products(tmp_path, monkeypatch):
    """A chunk's photons brought to the host and handed to the writers in parts of whole pulses (run.host_photons;
    the host memory of a long chunk bounded): every dataset of atl03.h5, atl08.h5 and photons.h5 and every LAS tile
    byte the same as with the chunk in one piece (a 0.2 s pass of six beams, one chunk)."""
    from flightsim.engine.products.photons import PhotonProduct

    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.2, "photon.gate_m": [499850.0, 500150.0]}.items():
        set_value(cfg, key, value)
    handed = []
    monkeypatch.setattr(PhotonProduct, "__call__", lambda self, chunk, call=PhotonProduct.__call__: (
        handed.append(len(chunk)), call(self, chunk))[1])
    for name, most in (("whole", 1 << 26), ("parts", 3000)):
        set_value(cfg, "run.host_photons", most)
        handed.clear()
        simulate_to_directory(validate(cfg), tmp_path / name)
        counts = list(handed)
    assert len(counts) > 10 and max(counts) <= 3000  # the case: many parts, none over the limit
    for product in ("atl03.h5", "atl08.h5", "photons.h5"):
        with h5py.File(tmp_path / "whole" / product) as a, h5py.File(tmp_path / "parts" / product) as b:
            names = []
            a.visititems(lambda name, item: names.append(name) if isinstance(item, h5py.Dataset) else None)
            assert len(names) >= 10
            for name in names:
                np.testing.assert_array_equal(a[name][()], b[name][()], err_msg=f"{product} {name}")
    tiles = sorted(p.relative_to(tmp_path / "whole") for p in (tmp_path / "whole").glob("photons/*"))
    assert tiles and tiles == sorted(p.relative_to(tmp_path / "parts") for p in (tmp_path / "parts").glob("photons/*"))
    for tile in tiles:
        assert (tmp_path / "whole" / tile).read_bytes() == (tmp_path / "parts" / tile).read_bytes(), tile


def test_pulse_parts_cover_the_rows_in_whole_pulses_of_at_most_the_limit():
    """Against every row: the parts follow each other from 0 to the end, no pulse is split, and a part holds more
    than the limit only as one pulse of more rows."""
    from flightsim.engine.readouts.photons import pulse_parts

    rng = np.random.default_rng(5)
    for most in (1, 2, 7, 50, 10_000):
        rows = rng.integers(1, 12, 400)
        rows[100] = 40  # one pulse of 40 rows
        pulse = np.repeat(np.arange(400) * 3, rows)
        parts = pulse_parts(pulse, most)
        assert parts[0][0] == 0 and parts[-1][1] == len(pulse)
        assert all(hi == lo for (_, hi), (lo, _) in zip(parts, parts[1:]))
        for lo, hi in parts:
            assert hi > lo
            assert hi - lo <= most or pulse[lo] == pulse[hi - 1]
            assert lo == 0 or pulse[lo - 1] != pulse[lo]
        if most == 7:  # rows of a pulse beyond the limit make a part of their own, others pack up to the limit
            assert (300, 40) in [(pulse[lo], hi - lo) for lo, hi in parts]
            assert sum(hi - lo for lo, hi in parts) / len(parts) > 3
    assert pulse_parts(np.zeros(0, dtype=np.int64), 5) == []


def test_photons_h5_and_the_tiles_get_each_part_behind_atl03_and_the_rest_at_close_at_once(tmp_path, monkeypatch):
    """From orbit atl03.h5 has each part first; photons.h5 and the LAS tiles are handed part k once BEHIND_PHOTONS
    more photons came (3 parts of run.host_photons here), waiting as their writers hold enough; at close they are
    handed the last 3 parts without waiting, so that the signal finder starts as soon as atl03.h5 has its parts."""
    import flightsim.engine.products.photons as product

    cfg = preset_config("atlas")
    for key, value in {"flight.duration_s": 0.1, "photon.gate_m": [499850.0, 500150.0],
                       "run.host_photons": 1500}.items():
        set_value(cfg, key, value)
    calls, kept, call = [], [], product.Background.__call__

    def record(self, chunk, after=None, wait=True):
        kept.append(chunk)  # alive to the end: no two parts share an id
        calls.append((self.writer.__class__.__name__, id(chunk), wait))
        return call(self, chunk, after, wait)

    monkeypatch.setattr(product.Background, "__call__", record)
    monkeypatch.setattr(product, "BEHIND_PHOTONS", 4500)  # 3 parts of 1500
    summary = simulate_to_directory(validate(cfg), tmp_path / "run")
    writers = summary["writers_s"]  # each file's writer's time, its close (atl03.h5's: the signal finder) apart
    assert set(writers) == {"atl03.h5", "photons.h5", "photons/", "atl08.h5"}
    assert all(t["busy"] > 0 and t["cpu"] >= 0 and t["held_back"] >= 0
               for name, t in writers.items() if name != "atl08.h5")
    staged = product.thread_count(product.ORBIT_LAS_THREADS) > 1  # the tiles' records made on threads from orbit
    assert writers["atl03.h5"]["close"] > 0 and (writers["photons/"]["prepare"] > 0) == staged
    assert writers["atl08.h5"]["close"] > 0 and writers["atl08.h5"]["busy"] == 0  # made at close from atl03.h5
    atl03 = [part for name, part, _ in calls if name == "Atl03Writer"]
    assert len(atl03) > 8
    for writer in ("PhotonWriter", "PhotonLas"):
        handed = [(calls.index((writer, part, wait)), part, wait) for name, part, wait in calls if name == writer]
        assert [part for _, part, _ in handed] == atl03  # every part, in order
        for k, (at, part, wait) in enumerate(handed):
            came = sum(1 for name, _, _ in calls[:at] if name == "Atl03Writer")
            assert wait == (k < len(atl03) - 3)
            assert came == (k + 4 if wait else len(atl03))  # part k once part k + 3 came; the rest at close


def test_each_parts_geodetic_transform_is_worked_out_once_for_atl03_and_the_tiles(tmp_path, monkeypatch):
    """From orbit atl03.h5 and the LAS tiles both want every photon's latitude, longitude and height: one transform of
    each part's photons serves both (and each footprint's its own), and the tiles' coordinates are still the photons'
    UTM positions (pyproj from atl03.h5's latitude, longitude; heights its h_ph)."""
    import laspy

    from flightsim.outputs import atl03_h5, photon_las

    calls = []
    transform = photon_las.local_to_geodetic

    def counted(body, scene, local):
        calls.append(len(local))
        return transform(body, scene, local)

    monkeypatch.setattr(photon_las, "local_to_geodetic", counted)
    monkeypatch.setattr(atl03_h5, "local_to_geodetic", counted)
    cfg = preset_config("atlas")
    for key, value in {**SINGLE_BEAM, "flight.duration_s": 0.1, "photon.gate_m": [499850.0, 500150.0],
                       "run.host_photons": 1024}.items():
        set_value(cfg, key, value)
    summary = simulate_to_directory(validate(cfg), tmp_path / "g")
    with h5py.File(tmp_path / "g" / "atl03.h5") as f:
        lat, lon, h = (f[f"gt1/heights/{k}"][:] for k in ("lat_ph", "lon_ph", "h_ph"))
        shots = f["gt1/footprint/lat"].shape[0]
    photons = [n for n in calls if n != 0]
    assert sum(photons) == summary["photons"] + shots and len(photons) >= 6  # each part's photons once, its shots
    tiles = [laspy.read(p) for p in sorted((tmp_path / "g" / "photons").glob("*.la[sz]"))]
    las_xyz = np.concatenate([np.column_stack([t.x, t.y, t.z]) for t in tiles])
    crs = tiles[0].header.parse_crs()
    x, y = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    expected = np.column_stack([x, y, h])
    order = lambda a: a[np.lexsort(np.round(a, 2).T[::-1])]  # noqa: E731 - the tiles hold the photons by tile
    np.testing.assert_allclose(order(las_xyz), order(expected), atol=0.002)  # LAS's millimetre scale
