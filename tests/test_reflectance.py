"""Per-triangle reflectance (a land-cover raster's) in the photon and waveform detectors: the signal of each
half of a flat DEM against the lidar equation written out in float64, the per-triangle path against the
run's one value, the scene cache, the buildings' values and bad input."""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.core.errors import InputError
from flightsim.engine.run import simulate_to_directory
from flightsim.engine.tracer import Tracer
from flightsim.instrument import waveform_model as model
from flightsim.instrument.waveform import system
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.scenes import cache
from flightsim.scenes.dem import dem_scene
from flightsim.scenes.landcover import triangle_reflectance
from flightsim.scenes.plane import plane_scene
from flightsim.scenes.scene import DEFAULT_CRS
from flightsim.studies.waveform import waveform_config
from flightsim.engine.readouts.waveforms import Waveforms
from flightsim.engine.readouts.photons import Photons

C = 299_792_458.0  # [m/s]
H_PLANCK = 6.62607015e-34  # [J s]
E0, N0, H0 = 409000.0, 3393000.0, 300.0  # world middle of the test DEM [m]
CELL = 2.0  # DEM node spacing [m]
HALF = 100.0  # DEM half side [m]
WATER, TREES = 9, 3  # ASPRS classes of the two halves: ρ = 0.05 and 0.45 (landcover.REFLECTANCE)
RHO = {WATER: 0.05, TREES: 0.45}
ALTITUDE = 100.0  # photon runs [m above the DEM]
PHOTON = {"photon.wavelength_nm": 532.0, "photon.pulse_energy_j": 1.0e-9, "photon.aperture_m": 0.05,
          "photon.optics_transmission": 0.5, "photon.pde": 0.2, "photon.noise_hz": 0.0, "photon.dead_time_s": 0.0,
          "photon.max_events": 64}
SMALL_WAVEFORM = {"waveform.n_rings": 24, "waveform.n_sectors": 48, "waveform.sample_interval_s": 5e-11,
                  "waveform.samples": 8192}
LINK = {"waveform.aperture_m": 0.8, "waveform.atmosphere_transmission": 0.9, "waveform.receiver_efficiency": 0.7}
ALBEDO_LINK = 0.9 ** 2 * 0.8 ** 2 * 0.7 / 4.0  # eq. 1's π f T_A² D² η_t η_r / 4 of LINK at π f = ρ = 1


def _write_tif(path, values, west, north, cell, dtype, nodata=None):
    with rasterio.open(path, "w", driver="GTiff", width=values.shape[1], height=values.shape[0], count=1, dtype=dtype,
                       crs=DEFAULT_CRS, transform=from_origin(west, north, cell, cell), nodata=nodata) as dst:
        dst.write(values.astype(dtype), 1)


def _halves_dem(folder, split_m: float = 0.0):
    """A flat DEM at H0 (nodes CELL apart, pixel centres, middle node at E0, N0) and a land cover of water west
    of E0 + ``split_m`` and trees east of it (a node line: every triangle lies wholly in one half); paths."""
    nodes = round(2 * HALF / CELL) + 1
    dem, cover = folder / "dem.tif", folder / "cover.tif"
    _write_tif(dem, np.full((nodes, nodes), H0), E0 - HALF - CELL / 2, N0 + HALF + CELL / 2, CELL, "float32")
    pixels = round(2 * HALF / CELL)  # land-cover pixels CELL wide, edges on node lines
    codes = np.where(E0 - HALF + CELL * (np.arange(pixels) + 0.5) < E0 + split_m, WATER, TREES)
    _write_tif(cover, np.tile(codes, (pixels, 1)), E0 - HALF, N0 + HALF, CELL, "uint8")
    return str(dem), str(cover)


def _photon_cfg(dem: str, cover: str, **settings) -> RunConfig:
    """A single nadir beam flying east at ALTITUDE over the DEM's middle, 40 m of line, no background or dead time."""
    cfg = RunConfig()
    for key, value in {"scene.name": dem, "scene.landcover": cover, "scene.origin": [E0, N0, H0],
                       "instrument.detector": "photon", "instrument.deflector": "fixed", "fan.array": 1,
                       "flight.altitude_m": ALTITUDE, "flight.heading_deg": 90.0, "flight.speed_kmh": 36.0,
                       "flight.duration_s": 4.0, "fixed.prf_hz": 1000.0,
                       **PHOTON, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def _expected_signal(rho: float, r: float) -> float:
    """The lidar equation at normal incidence, as documented: E·(λ/hc)·ρ/π·A/R²·η [photo-electrons]."""
    photons = PHOTON["photon.pulse_energy_j"] * PHOTON["photon.wavelength_nm"] * 1e-9 / (H_PLANCK * C)
    area = math.pi * (PHOTON["photon.aperture_m"] / 2.0) ** 2
    return photons * rho / math.pi * area / r ** 2 * PHOTON["photon.optics_transmission"] * PHOTON["photon.pde"]


def _photons(cfg: RunConfig, scene=None):
    """(photons per pulse, local x of each pulse's nadir [m], the photon chunks) of a photon run over ``scene``."""
    scene = build_scene(cfg) if scene is None else scene
    trajectories = flight_trajectories(cfg, scene)
    sim = Tracer(cfg, scene, trajectories)
    chunks = []
    counts = sim.run(Photons(), chunks.append)
    pulse = np.concatenate([c.pulse for c in chunks])
    (line,) = trajectories
    position, _ = line.interpolate(sim.timing.pulse_times(line.start_time, np.arange(counts.pulses)))
    return np.bincount(pulse, minlength=counts.pulses), scene.world_to_local(position)[:, 0], chunks


def test_photon_signal_of_each_land_cover_half_is_its_lidar_equation(tmp_path, device):
    """Water (ρ 0.05) west, trees (ρ 0.45) east: the mean signal photo-electrons per shot over each half is
    Poisson with the lidar equation's mean at that half's ρ, and the halves' ratio is 9."""
    cfg = _photon_cfg(*_halves_dem(tmp_path), **{"run.device": device})
    per_pulse, x, chunks = _photons(cfg)
    assert all(c.signal.all() for c in chunks)  # no background: every photon is the surface's
    means = {}
    for code, side in ((WATER, x < -1.0), (TREES, x > 1.0)):
        n = _expected_signal(RHO[code], ALTITUDE)
        shots = int(side.sum())
        assert shots > 1800
        means[code] = per_pulse[side].mean()
        assert abs(means[code] - n) < 4.0 * math.sqrt(n / shots), (code, means[code], n)
    ratio = means[TREES] / means[WATER]
    n_w, n_t = _expected_signal(RHO[WATER], ALTITUDE), _expected_signal(RHO[TREES], ALTITUDE)
    sigma = 9.0 * math.sqrt(1.0 / (n_w * (x < -1.0).sum()) + 1.0 / (n_t * (x > 1.0).sum()))
    assert abs(ratio - 9.0) < 4.0 * sigma


def test_photons_of_a_uniform_per_triangle_reflectance_are_those_of_the_run_value(tmp_path):
    """ρ = 0.25 on every triangle (exact in float32) gives bit for bit the photons of photon.reflectance = 0.25
    on a scene without per-triangle values."""
    cfg = _photon_cfg(*_halves_dem(tmp_path), **{"photon.reflectance": 0.25, "photon.noise_hz": 2.0e6,
                                                 "photon.dead_time_s": 2e-8, "flight.duration_s": 1.0})
    with_land_cover = build_scene(cfg)
    uniform = dataclasses.replace(with_land_cover, reflectance=np.full(len(with_land_cover.triangles), 0.25))
    run_value = dataclasses.replace(with_land_cover, reflectance=None)
    a, b = (_photons(cfg, scene)[2] for scene in (uniform, run_value))
    for key in ("pulse", "time_of_flight_s", "kind", "points"):
        assert np.array_equal(*(np.concatenate([getattr(c, key) for c in run]) for run in (a, b)))
    assert sum(len(c) for c in a) > 1000


def _waveform(cfg: RunConfig, scene):
    parts = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene)).run(Waveforms(), parts.append)
    (chunk,) = parts
    return chunk


def test_waveform_of_a_uniform_albedo_is_the_run_with_backscatter_rho_over_pi(device):
    """Every triangle of the 0.20 slope at ρ = 0.3: the waveform of waveform.reflectance = f = ρ/π."""
    rho = 0.3
    settings = {**SMALL_WAVEFORM, **LINK, "run.device": device}
    cfg = waveform_config("slope", **settings)
    slope = build_scene(cfg)
    per_face = _waveform(cfg, dataclasses.replace(slope, reflectance=np.full(len(slope.triangles), rho)))
    f = float(np.float32(rho)) / math.pi  # the scene holds ρ in float32
    run_value = _waveform(waveform_config("slope", **settings, **{"waveform.reflectance": f}), slope)
    assert per_face.received[0, 0] > 0.0
    np.testing.assert_allclose(per_face.received, run_value.received, rtol=1e-12)
    np.testing.assert_allclose(per_face.power_w, run_value.power_w, rtol=1e-6, atol=1e-6 * run_value.power_w.max())


def test_waveform_sums_each_subray_at_the_albedo_it_hits(tmp_path, device):
    """The nadir footprint (60 m radius from 200 km) over water west of x = 12 m and trees east of it: the
    received share is Σ_k w_k ρ_k T_A² D² η_t η_r cos θ_k /(4 r_k²) (eq. 1 with f = ρ/π), each sub-ray at its
    own half's ρ, on flat ground H below (r_k, cos θ_k from its datum point)."""
    split = 12.0
    dem, cover = _halves_dem(tmp_path, split)
    cfg = waveform_config(dem, **{**SMALL_WAVEFORM, **LINK, "run.device": device, "scene.landcover": cover,
                                  "scene.origin": [E0, N0, H0]})
    chunk = _waveform(cfg, build_scene(cfg))
    altitude = cfg.flight.altitude_m
    fp = model.footprint(system(cfg.waveform, altitude_m=altitude))  # datum points of the sub-rays [m]
    assert np.allclose(chunk.start[0], [0.0, 0.0, altitude], atol=1e-6)
    assert np.abs(fp.x_m - split).min() > 0.15  # no sub-ray within the float32 cast's reach of the boundary
    rho = np.where(fp.x_m < split, RHO[WATER], RHO[TREES])
    r = np.sqrt(fp.x_m ** 2 + fp.y_m ** 2 + altitude ** 2)
    share = fp.weight * ALBEDO_LINK * (altitude / r) / r ** 2  # each sub-ray's at ρ = 1
    expected = np.sum(share * rho)
    assert chunk.received[0, 0] == pytest.approx(expected, rel=1e-6)
    assert chunk.received[0, 1] == 0.0
    assert expected > 2.0 * RHO[WATER] * share.sum()  # the trees' part counts


@pytest.mark.parametrize("detector", ["photon", "waveform"])
def test_summary_says_where_the_reflectance_came_from(tmp_path, detector):
    dem, cover = _halves_dem(tmp_path)
    if detector == "photon":
        cfg = _photon_cfg(dem, cover, **{"flight.duration_s": 0.05})
        plain = _photon_cfg(dem, "", **{"flight.duration_s": 0.05, "photon.reflectance": 0.3})
    else:
        settings = {**SMALL_WAVEFORM, "scene.origin": [E0, N0, H0]}
        cfg = waveform_config(dem, **settings, **{"scene.landcover": cover})
        plain = waveform_config(dem, **settings, **{"waveform.reflectance": 0.3})
    got = simulate_to_directory(cfg, tmp_path / "cover")["reflectance"]
    written = json.loads((tmp_path / "cover" / "summary.json").read_text())["reflectance"]
    assert got == written == "per triangle (land cover)"
    assert simulate_to_directory(plain, tmp_path / "plain")["reflectance"] == 0.3


def test_land_cover_sets_the_reflectance_and_buildings_get_class_6s(tmp_path):
    dem, cover = _halves_dem(tmp_path)
    box = [(E0 + x, N0 + y, H0 + z) for z in (0.0, 10.0) for x, y in ((-5, -5), (5, -5), (5, 5), (-5, 5))]
    faces = "f 5 6 7 8\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\nf 1 4 3 2\n"
    (tmp_path / "box.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in box) + faces)
    scene = dem_scene(dem, None, (E0, N0, H0), 1.0, 0.0, cover, str(tmp_path / "box.obj"))
    building = scene.classification == 6
    assert building.sum() == 12 and scene.reflectance.dtype == np.float32
    assert np.all(scene.reflectance[building] == np.float32(0.35))
    assert np.array_equal(scene.reflectance, triangle_reflectance(scene))
    centroid_x = scene.vertices[scene.triangles, 0].mean(axis=1)
    ground = ~building
    assert np.all(scene.reflectance[ground & (centroid_x < 0)] == np.float32(0.05))
    assert np.all(scene.reflectance[ground & (centroid_x > 0)] == np.float32(0.45))
    assert dem_scene(dem, None, (E0, N0, H0), 1.0, buildings=str(tmp_path / "box.obj")).reflectance is None


def test_scene_cache_round_trips_the_reflectance_and_refuses_older_entries(tmp_path, monkeypatch):
    source = tmp_path / "mesh.obj"
    source.write_text("a stand-in source file\n")
    plain = plane_scene(50.0)
    rho = np.array([0.05, 0.45], dtype=np.float32)
    loads = []

    def load(scene):
        def read():
            loads.append(scene)
            return scene
        return read

    monkeypatch.setattr(cache, "CACHE_FORMAT", 1)  # an entry of the format before per-triangle reflectance
    cache.cached_scene(source, {}, load(plain), tmp_path / "c")
    monkeypatch.undo()
    with_rho = dataclasses.replace(plain, reflectance=rho)
    assert np.array_equal(cache.cached_scene(source, {}, load(with_rho), tmp_path / "c").reflectance, rho)
    again = cache.cached_scene(source, {}, load(plain), tmp_path / "c")  # from the entry just written
    assert len(loads) == 2 and again.reflectance.dtype == np.float32 and np.array_equal(again.reflectance, rho)
    other = tmp_path / "other.obj"
    other.write_text("another\n")
    cache.cached_scene(other, {}, load(plain), tmp_path / "c")
    assert cache.cached_scene(other, {}, load(with_rho), tmp_path / "c").reflectance is None  # None kept as None
    assert len(loads) == 3


@pytest.mark.parametrize("value, said", [
    ([0.0, 0.5], "0 at triangle 0"), ([0.5, 1.2], "1.2 at triangle 1"), ([0.5, float("nan")], "nan at triangle 1"),
    ([-0.1, 0.5], "-0.1 at triangle 0"), ([0.5, 1e-60], "1e-60 at triangle 1"),  # 1e-60 is 0 in float32
    ([0.5, 0.5, 0.5], "shape (3,)"), ([[0.5, 0.5]], "shape (1, 2)"), (["dark", "light"], "dark"),
])
def test_bad_per_triangle_reflectance_names_the_field(value, said):
    with pytest.raises(InputError, match="scene.reflectance") as error:
        dataclasses.replace(plane_scene(50.0), reflectance=value)
    assert said in str(error.value) and "(0, 1]" in str(error.value)
