"""pyproj transforms of many points on threads: the values of one call, part boundaries included."""
import numpy as np
import pyproj
import pytest

from flightsim.core import transform as tr
from flightsim.core.process_map import usable_cores


@pytest.mark.parametrize("source, target, dims", [("EPSG:4978", "EPSG:4979", 3), ("EPSG:4326", "EPSG:32611", 2)])
def test_threads_give_the_values_of_one_transform(monkeypatch, source, target, dims):
    monkeypatch.setattr(tr, "PART_POINTS", 1000)
    rng = np.random.default_rng(5)
    n = 10_007  # parts of unequal length
    if source == "EPSG:4978":
        lat, lon = np.radians(rng.uniform(-80, 80, n)), np.radians(rng.uniform(-180, 180, n))
        r = 6.371e6 + rng.uniform(-500, 9000, n)
        points = (r * np.cos(lat) * np.cos(lon), r * np.cos(lat) * np.sin(lon), r * np.sin(lat))
    else:
        points = (rng.uniform(-118.5, -116.5, n), rng.uniform(30, 40, n))
    expected = pyproj.Transformer.from_crs(source, target, always_xy=True).transform(*points)
    used = []
    original = tr._transform
    monkeypatch.setattr(tr, "_transform", lambda s, t, part: used.append(len(part[0])) or original(s, t, part))
    got = tr.transform(source, target, *points)
    assert len(used) == min(16, usable_cores(), n // 1000) > 1 and sum(used) == n
    assert len(got) == dims
    for a, b in zip(got, expected):
        assert a.dtype == np.float64 and a.shape == (n,)
        np.testing.assert_array_equal(a, b)


def test_few_points_take_one_call(monkeypatch):
    used = []
    original = tr._transform
    monkeypatch.setattr(tr, "_transform", lambda s, t, part: used.append(len(part[0])) or original(s, t, part))
    x, y = tr.transform("EPSG:4326", "EPSG:32611", np.array([-117.0]), np.array([33.0]))
    assert used == [1] and x.shape == (1,) and 400_000 < x[0] < 600_000


def test_scalars_and_grids_keep_their_shape():
    """Coordinates broadcast together and come back in their shape: a point given as numbers, a grid as 2-D arrays."""
    expected = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    got = tr.transform("EPSG:4979", "EPSG:4978", 105.5, 21.0, 12.5)
    assert all(np.shape(a) == () for a in got)
    assert [float(a) for a in got] == list(expected.transform(105.5, 21.0, 12.5))
    lon, lat = np.meshgrid(np.linspace(105.0, 106.0, 4), np.linspace(20.0, 21.0, 3))
    x, y, z = tr.transform("EPSG:4979", "EPSG:4978", lon, lat, 0.0)
    assert x.shape == y.shape == z.shape == (3, 4)
    np.testing.assert_array_equal(x, expected.transform(lon, lat, np.zeros_like(lon))[0])


def test_one_transformer_a_pair_of_crss_shared_by_threads_kept_for_the_process(monkeypatch):
    """A pair of CRSs is made into a pyproj transformer once (the same pair given as strings or as pyproj CRSs), and
    the parts of transforms run on the threads of one pool kept for the process (a thread makes its PROJ object at its
    first use), alive after the calls."""
    made = []
    original = pyproj.Transformer.from_crs
    monkeypatch.setattr(tr, "_TRANSFORMERS", {})
    monkeypatch.setattr(pyproj.Transformer, "from_crs", staticmethod(lambda *a, **k: made.append(a) or original(*a, **k)))
    first = tr.transformer("EPSG:4326", "EPSG:32611")
    assert tr.transformer(pyproj.CRS.from_user_input("EPSG:4326"), "EPSG:32611") is first and len(made) == 1
    assert tr.transformer("EPSG:32611", "EPSG:4326") is not first and len(made) == 2

    import threading
    monkeypatch.setattr(tr, "PART_POINTS", 1000)
    threads, original_transform = [], tr._transform
    monkeypatch.setattr(tr, "_transform", lambda s, t, part: threads.append(threading.current_thread())
                        or original_transform(s, t, part))
    lon, lat = np.linspace(-118.0, -117.0, 8000), np.linspace(30.0, 31.0, 8000)
    calls = [tr.transform("EPSG:4326", "EPSG:32611", lon, lat) for _ in range(3)]
    assert len(threads) // 3 == min(16, usable_cores(), 8)
    # the parts ran on the kept pool's threads, alive after the calls (a pool a call joins its own), one part too
    assert all(t.name.startswith("pyproj") and t.is_alive() for t in threads)
    before = len(threads)
    tr.transform("EPSG:4326", "EPSG:32611", lon[:5], lat[:5])
    assert len(threads) == before + 1 and threads[-1].name.startswith("pyproj")
    for got in calls[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(got, calls[0]))
    assert len(made) == 2  # the pair made above served every part
