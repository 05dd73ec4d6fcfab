"""GEDI as an instrument: the ``gedi`` preset, l2a.h5 of its runs against closed forms (flat ground: the smoothed
Gaussian echo's threshold crossings and its centre; a homogeneous leaf layer: the ground and the layer's top), the
shots platform's footprints over an ALS point cloud against the float64 GEDI-method model, and bad footprints."""
from __future__ import annotations

import math
from pathlib import Path

import h5py
import numpy as np
import pytest

from flightsim.cli import main
from flightsim.engine.config import validate
from flightsim.engine.config_io import preset_config

C = 299_792_458.0
DATA = Path(__file__).parent / "data"
CLOUD = DATA / "cloud_plot.laz"  # 35 m × 35 m from (409000, 3393000), EPSG:32648 (tests/test_pointcloud.py)
GROUND_Z = 450.0  # the plane scene's ground: the default origin's height [m]
SIGMA_P = 15e-9 / (2.0 * math.sqrt(2.0 * math.log(2.0)))  # the preset's pulse σ [s]
SHORT = ["--set", "flight.duration_s=0.01"]  # 3 shots at 242 Hz


def _error(args: list[str], capsys) -> str:
    assert main(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def _beam(path: Path) -> h5py.Group:
    return h5py.File(path)["BEAM0000"]


def test_the_preset_is_one_gedi_beam_from_the_iss(capsys):
    cfg = validate(preset_config("gedi"))
    w = cfg.waveform
    assert (cfg.flight.platform, cfg.flight.altitude_m, cfg.fixed.prf_hz) == ("orbit", 420e3, 242.0)
    assert w.half_divergence_rad * cfg.flight.altitude_m / 2.0 == pytest.approx(5.5, rel=1e-12)  # σ_f = H α / 2
    assert math.sqrt(2.0 * math.pi) * SIGMA_P * w.peak_power_w == pytest.approx(0.010, rel=1e-12)  # 10 mJ
    assert (w.sample_interval_s, w.samples, w.aperture_m, w.l2a) == (1e-9, 1000, 0.8, True)
    assert cfg.detector_part(w).receiver() is None  # noise-free, as the GEDI simulator's waveforms
    assert main(["config", "--instrument", "gedi"]) == 0
    assert "l2a = true" in capsys.readouterr().out


def _flat(tmp_path, name: str, *extra: str) -> Path:
    out = tmp_path / name
    assert main(["simulate", "--instrument", "gedi", *SHORT, *extra, "--out", str(out)]) == 0
    return out


def _smoothed_extent(samples: int, centre: float, sigma: float, floor: float = 1e-6) -> float:
    """(last − first) fractional sample where a Gaussian echo (centre, σ in samples), smoothed by L2A's Gaussian of
    the pulse σ (scipy's kernel: truncated at 4 σ, normalised), crosses ``floor`` of its smoothed peak, each
    crossing interpolated linearly between samples."""
    i = np.arange(samples, dtype=np.float64)
    echo = np.exp(-0.5 * ((i - centre) / sigma) ** 2)
    k = np.arange(-int(4.0 * sigma + 0.5), int(4.0 * sigma + 0.5) + 1)
    kernel = np.exp(-0.5 * (k / sigma) ** 2)
    smooth = np.convolve(echo, kernel / kernel.sum(), mode="same")
    level = floor * smooth.max()
    above = np.flatnonzero(smooth > level)
    a, b = above[0], above[-1]
    start = a - 1 + (level - smooth[a - 1]) / (smooth[a] - smooth[a - 1])
    end = b + (smooth[b] - level) / (smooth[b] - smooth[b + 1])
    return end - start


def test_l2a_of_flat_ground_matches_the_smoothed_pulse_and_the_ground(tmp_path):
    out = _flat(tmp_path, "flat")
    l2a, wave = _beam(out / "l2a.h5"), _beam(out / "waveforms.h5")
    dt, n = 1e-9, 1000
    # the echo of flat ground at nadir: the pulse, σ_p, peaking τ/2 after the window's middle (the pilot's delay)
    extent = _smoothed_extent(n, n / 2 + 7.5, SIGMA_P / dt) * C * dt / 2.0
    rh = l2a["rh"][:]
    assert np.allclose(rh[:, 100] - rh[:, 0], extent, atol=0.01)
    assert extent == pytest.approx(14.01, abs=0.01)  # 2·5.26·√2 σ_r = 14.20 m, less the kernel's truncation
    assert np.allclose(l2a["elev_lowestmode"][:], GROUND_Z, atol=0.01)
    assert (l2a["num_detectedmodes"][:] == 1).all() and (l2a["quality_flag"][:] == 1).all()
    assert np.allclose(l2a["truth/elev_ground"][:], GROUND_Z, atol=1e-6)
    assert np.allclose(l2a["truth/rh"][:, 50], 0.0, atol=0.01)  # a symmetric echo: half its energy below the centre
    for g in (l2a, wave):  # the beam's attributes
        assert g.attrs["pulse_sigma_s"] == pytest.approx(SIGMA_P, rel=1e-12)
        assert g.attrs["footprint_sigma_m"] == pytest.approx(5.5, rel=1e-12)
        assert g.attrs["rho_ground"] == pytest.approx(0.4, rel=1e-12) and "rho_canopy" not in g.attrs
    summary = (out / "summary.json").read_text()
    assert '"l2a": {\n    "shots": 3,\n    "quality_flag": 3\n  }' in summary


def test_l2a_truth_is_the_waveform_before_the_receiver_noise(tmp_path):
    clean = _flat(tmp_path, "clean")
    noisy = _flat(tmp_path, "noisy", "--set", "waveform.thermal_noise_w=2e-9")  # ~1 % of the echo's peak
    a, b = _beam(clean / "l2a.h5"), _beam(noisy / "l2a.h5")
    assert np.array_equal(a["truth/rh"][:], b["truth/rh"][:])
    rx_a, rx_b = _beam(clean / "waveforms.h5")["rxwaveform"][:], _beam(noisy / "waveforms.h5")["rxwaveform"][:]
    assert np.std(rx_b - rx_a) == pytest.approx(2e-9, rel=0.1)
    assert np.allclose(b["elev_lowestmode"][:], GROUND_Z, atol=0.05)


def test_waveforms_ranging_under_receiver_noise_and_background_is_the_noise_free_echos(tmp_path):
    """waveforms.h5's ranging/ of a noisy run (receiver noise ~1 % of the echo's peak, a background of ~4 %) against
    the same shots without either: over the whole window the centroid moved by up to a metre and the RMS width came
    out NaN; measured above the noise floor, the ranges agree to centimetres and the RMS width is the echo's, less
    the tails below the floor (at 1 % noise the floor, 4.26 σ of the noise, cuts the echo at ±2.6 of its σ: 0.96 of
    its RMS width is left). The Gaussian components, fitted to the waveforms less their noise mean, are the noise-free
    ones within the fit's noise (25 shots: amplitudes 0.996-1.007, σ 0.991-1.007 of theirs, ranges within 6 mm; with
    the background left in the fit they came out 2.6-3.7 % higher and 5.7-7.3 % wider)."""
    clean = _beam(_flat(tmp_path, "clean") / "waveforms.h5")["ranging"]
    noisy = _beam(_flat(tmp_path, "noisy", "--set", "waveform.thermal_noise_w=2e-9", "--set",
                        "waveform.background_w=1e-8") / "waveforms.h5")["ranging"]
    for name, tolerance in (("range_centroid_m", 0.05), ("range_halfpower_m", 0.05), ("range_peak_m", 0.15)):
        assert np.abs(noisy[name][()] - clean[name][()]).max() < tolerance, name
    ratio = noisy["rms_width_s"][()] / clean["rms_width_s"][()]
    assert np.all((ratio > 0.85) & (ratio < 1.0)), ratio
    assert (noisy["n_components"][()] == clean["n_components"][()]).all()
    assert np.abs(noisy["component_range_m"][:, 0] - clean["component_range_m"][:, 0]).max() < 0.02
    for name in ("component_amplitude_w", "component_sigma_s"):
        assert np.abs(noisy[name][:, 0] / clean[name][:, 0] - 1.0).max() < 0.02, name


@pytest.mark.parametrize("processing", ["host", "device"])
def test_a_run_under_heavy_noise_and_background_ranges_what_stands_out_and_nothing_else(tmp_path, processing):
    """Stress: receiver noise of ~10 % of the echo's peak on a background of ~4 times it. The run completes on either
    processing path; each shot has at most the one echo's component (none where the noise hides it), every counted
    component finite and positive, and its range near the noise-free shot's (within 4 cm in these three shots; with
    the background left in the fit, 0.8-1.5 m off)."""
    clean = _beam(_flat(tmp_path, "clean") / "waveforms.h5")["ranging"]
    noisy = _beam(_flat(tmp_path, "noisy", "--set", "waveform.thermal_noise_w=2e-8", "--set",
                        "waveform.background_w=1e-6", "--set", f"waveform.processing={processing}")
                  / "waveforms.h5")["ranging"]
    k = noisy["n_components"][()]
    assert ((k >= 0) & (k <= 1)).all() and k.sum() >= 1
    for name in ("component_range_m", "component_amplitude_w", "component_sigma_s"):
        held = noisy[name][()][:, 0][k == 1]
        assert np.isfinite(held).all() and (held > 0).all(), name
    assert np.abs(noisy["component_range_m"][:, 0] - clean["component_range_m"][:, 0])[k == 1].max() < 0.5


def test_l2a_under_a_leaf_layer_finds_the_ground_and_the_layer_top(tmp_path):
    from flightsim.scenes.canopy import VoxelCanopy
    from flightsim.scenes.canopy_io import write_canopy_npz

    bottom, top = 10, 20  # a homogeneous layer of leaf area density 0.1 m²/m³: LAI 1 [m]
    grid = np.zeros((20, 20, 24), np.float32)
    grid[:, :, bottom:top] = 0.1
    layer = VoxelCanopy(grid, np.array([-100.0, -100.0, 0.0]), np.array([10.0, 10.0, 1.0]),
                        leaf_angles="spherical", leaf_reflectance=0.57)
    path = write_canopy_npz(tmp_path / "layer.npz", layer, "EPSG:32648", np.array([409000.0, 3393000.0, GROUND_Z]))
    out = _flat(tmp_path, "layer", "--set", f"scene.canopy={path}")
    l2a = _beam(out / "l2a.h5")
    ground = l2a["truth/elev_ground"][:]
    assert np.allclose(ground, GROUND_Z, atol=1e-6)
    assert np.abs(l2a["elev_lowestmode"][:] - ground).max() < 0.3
    assert np.abs(l2a["rh"][:, 98] - top).max() < 1.0
    assert (l2a["num_detectedmodes"][:] == 2).all()
    assert l2a.attrs["rho_canopy"] == pytest.approx(0.57)


def _footprints(tmp_path, rows: list[tuple[float, ...]], header: str = "x,y,delta_time") -> Path:
    path = tmp_path / "footprints.csv"
    path.write_text(header + "\n" + "".join(",".join(map(repr, r)) + "\n" for r in rows))
    return path


CENTRES = [(409017.5, 3393017.5, 1.0e8), (409012.0, 3393021.0, 1.0e8 + 0.5), (409023.0, 3393013.0, 1.0e8 + 1.0)]


@pytest.fixture
def canopies_made(monkeypatch) -> list:
    """The leaf areas made from a point cloud (``pointcloud.cloud_canopy``'s calls) during the test."""
    from flightsim.scenes import pointcloud

    made, original = [], pointcloud.cloud_canopy
    monkeypatch.setattr(pointcloud, "cloud_canopy", lambda *a, **k: made.append(original(*a, **k)) or made[-1])
    return made


def test_footprints_over_a_point_cloud_are_the_gedi_method_at_those_centres(tmp_path, canopies_made):
    from flightsim.instrument.cloud_waveform_model import CloudBeam, model_waveforms
    from flightsim.scenes.pointcloud import read_point_cloud

    csv, out = _footprints(tmp_path, CENTRES), tmp_path / "cloud"
    assert main(["waveform", "--instrument", "gedi", "--scene", str(CLOUD), "--footprints", str(csv),
                 "--out", str(out)]) == 0
    assert canopies_made == []  # the points are summed: no leaf area is made from them
    g = _beam(out / "waveforms.h5")
    n = int(g["rx_sample_count"][0])
    rx = g["rxwaveform"][:].reshape(-1, n).astype(np.float64)
    assert list(g["line_id"][:]) == [0, 1, 2] and np.array_equal(g["delta_time"][:], [c[2] for c in CENTRES])
    centres = np.array([c[:2] for c in CENTRES])
    assert np.allclose(np.column_stack([g["geolocation/x_bin0"][:], g["geolocation/y_bin0"][:]]), centres, atol=1e-6)
    cloud = read_point_cloud(CLOUD)
    z_bin0 = g["geolocation/z_bin0"][:] - cloud.origin[2]  # the nadir windows' first samples, local [m]
    model = model_waveforms(cloud, centres - cloud.origin[:2], 100.0, 100.0 - z_bin0, 1e-9, n,
                            CloudBeam(footprint_sigma_m=5.5, pulse_sigma_s=SIGMA_P))
    for ours, theirs in zip(rx, model["rx"]):
        assert np.corrcoef(ours, theirs)[0, 1] >= 0.999
    # energy: E_t ρ̄ D²/(4 r²), ρ̄ = 1/(s_g/0.4 + s_c/0.57) from the model's ground and canopy shares of the echo
    share = model["ground"].sum(axis=1) / model["rx"].sum(axis=1)
    rho = 1.0 / (share / 0.4 + (1.0 - share) / 0.57)
    inside = model["rx"].sum(axis=1) * C * 1e-9 / 2.0
    assert np.allclose(rx.sum(axis=1) * 1e-9, 0.010 * rho * 0.8 ** 2 / (4.0 * 420e3 ** 2) * inside, rtol=2e-3)
    assert (g.attrs["rho_ground"], g.attrs["rho_canopy"], g.attrs["footprint_sigma_m"]) == (0.4, 0.57, 5.5)
    assert list(_beam(out / "l2a.h5")["quality_flag"][:]) == [1, 1, 1]


def test_footprints_over_a_point_cloud_can_be_ray_traced_instead(tmp_path, canopies_made):
    csv, out = _footprints(tmp_path, CENTRES[:1]), tmp_path / "rays"
    assert main(["waveform", "--instrument", "gedi", "--scene", str(CLOUD), "--footprints", str(csv),
                 "--set", "waveform.cloud_method=rays", "--out", str(out)]) == 0
    assert len(canopies_made) == 1 and canopies_made[0].lad.max() > 0.0  # the rays cross the cloud's leaves
    summary = (out / "summary.json").read_text()
    assert '"cloud_method": "rays"' in summary and '"subray_returns": 3200' in summary


@pytest.mark.parametrize("rows, header, named", [
    (CENTRES[:2] + [(409123.0, 3393013.0, 0.0)], "x,y,delta_time", "footprint 2 (line 4) at x = 409123.000"),
    ([(409017.5, 3393017.5)], "x,z", "it has x, z"),
    ([(409017.5, 3393017.5), (409012.0, math.nan)], "x,y", "row 1 (line 3"),
    ([], "x,y", "at least one footprint row"),
])
def test_bad_footprints_exit_2_naming_the_row(tmp_path, capsys, rows, header, named):
    csv, out = _footprints(tmp_path, rows, header), tmp_path / "bad"
    line = _error(["waveform", "--instrument", "gedi", "--scene", str(CLOUD), "--footprints", str(csv),
                   "--out", str(out)], capsys)
    assert "flight.footprints" in line and named in line, line
    assert not out.exists()
