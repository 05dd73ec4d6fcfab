"""The built-in lunar landing zone: crater and boulder shapes and populations, the mesh, and the
Chang'e-3 imager hovering over it."""
from __future__ import annotations

import numpy as np
import pytest

from flightsim.scenes import lunar
from flightsim.scenes.lunar import lunar_scene


def test_crater_profile_closed_form():
    d = 10.0
    r = np.array([0.0, 2.5, 5.0, 10.0, 20.0, 30.0])
    z = lunar._crater(r, d)
    rim, floor = 0.4, 2.0
    assert z[0] == pytest.approx(rim - floor)  # the floor: 0.2 D below the rim crest
    assert z[1] == pytest.approx(rim - floor * 0.75)  # parabolic bowl
    assert z[2] == pytest.approx(rim)  # the crest, continuous from inside and outside
    assert z[3] == pytest.approx(rim * (1 / 8 - 1 / 64) / (1 - 1 / 64))  # (R/r)³ ejecta, faded to 0 at 4 R
    assert z[4] == pytest.approx(0.0, abs=1e-15) and z[5] == 0.0


def test_crater_sizes_follow_the_cumulative_power_law():
    rng = np.random.default_rng(3)
    craters = lunar._craters(rng, 2000.0)[1:]  # the fixed large crater aside
    d = np.array([c[2] for c in craters])
    area = 4000.0 ** 2
    for size in (1.0, 2.0, 4.0):
        expected = lunar.CRATER_K * area * (size ** -2 - 1000.0 ** -2)
        assert (d > size).sum() == pytest.approx(expected, rel=5 / np.sqrt(expected))
    assert d.max() <= 1000.0


def test_mesh_is_a_heightfield_over_the_square_with_the_large_crater():
    scene = lunar_scene(30.0, seed=7, cell_m=0.5, slope=0.1)
    lo, hi = scene.bounds()
    assert lo[:2] == pytest.approx([-30.0, -30.0]) and hi[:2] == pytest.approx([30.0, 30.0])
    v = scene.vertices[scene.triangles]
    normal_z = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])[:, 2]
    assert (normal_z > 0).all()  # counter-clockwise from above, no overhangs
    assert np.abs(normal_z - 0.25).max() < 1e-9  # |cross|_z = twice the area: every triangle is half a 0.5 m cell
    nodes = 121
    z = scene.vertices[:, 2].reshape(nodes, nodes)
    assert scene.ground_z == z[60, 60]
    # the large crater (D = 12 m at (10.5, −7.5)) sits 0.16 D below the regional slope at its centre
    row, col = round((-7.5 + 30) / 0.5), round((10.5 + 30) / 0.5)
    regional = -0.1 * -7.5
    assert z[row, col] - regional == pytest.approx(0.04 * 12 - 0.2 * 12, abs=0.25)
    assert np.isfinite(z).all() and z.std() < 2.0


def test_seed_repeats_and_varies_the_zone():
    a, b, c = (lunar_scene(20.0, seed=s, cell_m=0.5).vertices for s in (1, 1, 2))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_large_zones_coarsen_the_grid():
    scene = lunar_scene(2000.0, cell_m=0.25)
    assert len(scene.vertices) == lunar.MAX_NODES ** 2


@pytest.mark.parametrize("kwargs, field", [({"cell_m": 0.0}, "scene.cell_m"), ({"slope": float("nan")}, "scene.slope")])
def test_bad_zone_parameters_name_the_field(kwargs, field):
    from flightsim.core.errors import InputError

    with pytest.raises(InputError, match=field):
        lunar_scene(20.0, **kwargs)


def test_change3_imager_over_the_zone_returns_every_beam_on_the_surface():
    import flightsim

    cfg = flightsim.load_config(instrument="change3", overrides={"scene.name": "lunar", "galvo.columns": 8,
                                                                 "ranging.channel_delay_m": 0.0, "ranging.jitter_s": 0.0,
                                                                 "ranging.tdc_bin_s": 0.0, "ranging.rise_time_s": 0.0,
                                                                 "ranging.clock_drift": 0.0})
    result = flightsim.simulate(cfg, with_truth=True)
    assert result.counts.returns == result.counts.beams_fired == result.counts.pulses * 16
    # no errors on: each processed point is its true hit (float32 points at ~100 m: tens of µm)
    assert np.abs(result.returns.points["exact"] - result.returns.true_points).max() < 1e-4
    local = result.returns.true_points - result.scene.origin
    lo, hi = result.scene.bounds()
    assert (local[:, 2] >= lo[2] - 1e-6).all() and (local[:, 2] <= hi[2] + 1e-6).all()
    assert result.returns.range_m.min() > 90.0
