"""Paper figures (flightsim/studies/figures.py and figures_optics.py): the data they write, against closed forms
and symmetry."""
import csv
import math

import numpy as np
import pytest

from flightsim.studies import figures, figures_optics
from flightsim.instrument.risley_model import apex_for_cone
from flightsim.core.errors import InputError

DELTA = 2.314e-3  # [rad]
N_GLASS = 1.5066
CONE = math.radians(15.0)
APEX = apex_for_cone(CONE, N_GLASS)
# first-order angular magnification of the wedge in its plane of deviation (normal incidence on
# Σ1, internal incidence α on Σ2, exit angle α + θ): dθ_out/dθ_in = cos α / cos(α + θ)
MAGNIFICATION = math.cos(APEX) / math.cos(APEX + CONE)
BEAMS = [f"{i}-{j}" for i in (1, 2, 3) for j in (1, 2, 3)]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def read(path) -> tuple[list[str], dict[str, np.ndarray]]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    columns = {}
    for k, name in enumerate(header):
        values = [r[k] for r in body]
        try:
            columns[name] = np.array([float(v) for v in values])
        except ValueError:
            columns[name] = np.array(values)
    return header, columns


def assert_png(path) -> None:
    data = path.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 10_000


@pytest.fixture(scope="module")
def optics(tmp_path_factory):
    out = tmp_path_factory.mktemp("optics")
    return {"5a": figures_optics.fig5a(out), "5c": figures_optics.fig5c(out), "6b": figures_optics.fig6b(out),
            "6b2k": figures_optics.fig6b(out / "h2000", altitude_m=2000.0)}


# ---------------------------------------------------------------------------------------------
# Fig. 5(a)


def test_fig5a_writes_png_and_documented_columns(optics):
    png, path = optics["5a"]
    assert_png(png)
    header, data = read(path)
    assert header == ["phi_deg"] + [f"dA_{b}_mrad" for b in BEAMS]
    assert data["phi_deg"][0] == 0.0 and data["phi_deg"][-1] == 360.0


def test_fig5a_centre_beam_is_zero_and_beams_oscillate_about_incident_spacing(optics):
    _, data = read(optics["5a"][1])
    assert np.abs(data["dA_2-2_mrad"]).max() < 1e-9
    for names, incident in ((("1-1", "1-3", "3-1", "3-3"), math.sqrt(2) * DELTA),
                            (("1-2", "2-1", "2-3", "3-2"), DELTA)):
        for name in names:
            d_a = data[f"dA_{name}_mrad"][:-1] * 1e-3  # one turn, 360° left out
            # smallest: the offset is normal to the deviation plane, first-order magnification 1
            assert d_a.min() == pytest.approx(incident, rel=1e-4)
            # largest: in the deviation plane, magnified by cos α / cos(α + θ) (≈ 1.188) to first order
            assert d_a.max() == pytest.approx(MAGNIFICATION * incident, rel=3e-3)
            # two swings per turn: two maxima and two minima (circularly)
            rising = np.diff(np.r_[d_a, d_a[0]]) > 0
            assert np.count_nonzero(rising & ~np.roll(rising, -1)) == 2


def test_fig5a_half_turn_symmetry(optics):
    _, data = read(optics["5a"][1])
    phi = data["phi_deg"]
    first = phi < 180.0
    later = np.searchsorted(phi, phi[first] + 180.0)
    assert np.allclose(phi[later], phi[first] + 180.0)
    # rotating the prism by π and the fan by π maps A_{1-1} onto A_{3-3} and A_{1-3} onto A_{3-1}
    for a, b in (("1-1", "3-3"), ("1-3", "3-1"), ("1-2", "3-2"), ("2-1", "2-3")):
        assert np.abs(data[f"dA_{a}_mrad"][first] - data[f"dA_{b}_mrad"][later]).max() < 1e-9
    # the mirror y → −y maps φ → −φ and A_{i-j} onto A_{i-(4−j)}
    mirror = np.searchsorted(phi, (360.0 - phi[first]) % 360.0)
    assert np.abs(data["dA_1-1_mrad"][first] - data["dA_1-3_mrad"][mirror]).max() < 1e-9


# ---------------------------------------------------------------------------------------------
# Fig. 5(c)


def test_fig5c_columns_incident_grid_and_exit_angles_match_fig5a(optics):
    png, path = optics["5c"]
    assert_png(png)
    header, data = read(path)
    assert header == ["beam", "i", "j", "incident_x_mrad", "incident_y_mrad", "exit_x_mrad", "exit_y_mrad",
                      "shift_urad"]
    assert list(data["beam"]) == BEAMS
    offsets = (data["i"] - 2) * DELTA, (data["j"] - 2) * DELTA
    assert np.allclose(data["incident_x_mrad"], np.tan(offsets[0]) * 1e3, rtol=0, atol=1e-12)
    assert np.allclose(data["incident_y_mrad"], np.tan(offsets[1]) * 1e3, rtol=0, atol=1e-12)
    # gnomonic radius about the centre beam is tan ΔA: compare with Fig. 5(a)'s row at φ = 45°
    _, fig5a = read(optics["5a"][1])
    row = np.flatnonzero(fig5a["phi_deg"] == 45.0)[0]
    radius = np.hypot(data["exit_x_mrad"], data["exit_y_mrad"]) * 1e-3
    for k, name in enumerate(BEAMS):
        assert math.atan(radius[k]) * 1e3 == pytest.approx(fig5a[f"dA_{name}_mrad"][row], abs=1e-9)
    shift = np.hypot(data["exit_x_mrad"] - data["incident_x_mrad"], data["exit_y_mrad"] - data["incident_y_mrad"])
    assert np.allclose(data["shift_urad"], shift * 1e3)
    assert data["shift_urad"].max() > 100.0  # visibly distorted (paper Fig. 5c)


def test_shape_change_is_the_largest_pair_angle_change():
    # at φ = 45° the fan stretches along its (1, 1) diagonal: A_{1-1} and A_{3-3} part most,
    # each by about (M − 1)·√2Δ from the centre
    change = figures_optics.shape_change_urad(45.0)
    assert change == pytest.approx(2 * (MAGNIFICATION - 1) * math.sqrt(2) * DELTA * 1e6, rel=5e-3)


# ---------------------------------------------------------------------------------------------
# Fig. 6(b)


@pytest.mark.parametrize("key, altitude", [("6b", 500.0), ("6b2k", 2000.0)])
def test_fig6b_footprint_centres_lie_on_the_scan_circle(optics, key, altitude):
    png, path = optics[key]
    assert_png(png)
    header, data = read(path)
    assert header == ["phi_deg", "beam", "i", "j", "exact_x_m", "exact_y_m", "nominal_x_m", "nominal_y_m"]
    assert len(data["beam"]) == 8 * 9
    centre = data["beam"] == "2-2"
    assert np.array_equal(data["phi_deg"][centre], np.arange(0.0, 360.0, 45.0))
    x, y = data["exact_x_m"][centre], data["exact_y_m"][centre]
    # the on-axis beam leaves Σ2 at (0, 0, d1) at exactly 15° off the axis
    assert np.allclose(np.hypot(x, y), (altitude - 0.01) * math.tan(CONE), rtol=1e-9, atol=0)
    assert np.allclose(np.hypot(x, y), altitude * math.tan(CONE), rtol=0.01 / altitude * 1.01, atol=0)
    # and it points away from the prism's thick side: azimuth φ + 180°
    azimuth = np.degrees(np.arctan2(y, x))
    assert np.allclose((azimuth - data["phi_deg"][centre]) % 360.0, 180.0, rtol=0, atol=1e-9)
    # both models agree on the centre beam
    assert np.allclose(data["nominal_x_m"][centre], x, atol=1e-9)
    assert np.allclose(data["nominal_y_m"][centre], y, atol=1e-9)


def test_fig6b_footprint_scales_with_altitude(optics):
    _, low = read(optics["6b"][1])
    _, high = read(optics["6b2k"][1])
    spread = []
    for data in (low, high):
        centre = np.repeat(np.flatnonzero(data["beam"] == "2-2"), 9)
        spread.append(np.hypot(data["exact_x_m"] - data["exact_x_m"][centre],
                               data["exact_y_m"] - data["exact_y_m"][centre]))
    # footprint size ∝ range from the prism: (h − d1) to first order in the tiny exit-point offsets
    assert np.allclose(spread[1], spread[0] * (2000.0 - 0.01) / (500.0 - 0.01), rtol=1e-4)
    # a corner sits about one slant range × √2Δ from the centre
    assert spread[0].max() == pytest.approx(500.0 / math.cos(CONE) * math.sqrt(2) * DELTA * MAGNIFICATION
                                            / math.cos(CONE), rel=0.05)


# ---------------------------------------------------------------------------------------------
# Figs. 8–10 from synthetic tables


def write_csv(path, header, rows) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows(rows)


def test_fig8a_uses_first_configuration_roofs_and_roads(tmp_path):
    rows = []
    kinds = {1: "roof", 2: "road", 3: "ground", 4: "roof", 5: "wall", 7: "roof"}
    for altitude in (500, 1000):
        for plane_id in (7, 4, 3, 2, 1, 5):
            exact = 0.002 + 0.0001 * plane_id
            rows.append([altitude, 3, 2.314, "exact", plane_id, kinds[plane_id], 100, exact, 30.0, 90.0])
            if plane_id != 4:  # plane 4 lacks a nominal row: left out
                rows.append([altitude, 3, 2.314, "nominal", plane_id, kinds[plane_id], 100,
                             exact + 0.01 * plane_id * altitude / 500, 30.0, 90.0])
    source = tmp_path / "planes.csv"
    write_csv(source, list(figures.PLANE_COLUMNS), rows)
    png, path = figures.fig8a(source, tmp_path / "out")
    assert_png(png)
    header, data = read(path)
    assert header == ["plane_id", "kind", "rms_nominal_m", "rms_exact_m", "difference_m"]
    assert list(data["plane_id"]) == [1, 2, 7]
    assert list(data["kind"]) == ["roof", "road", "roof"]
    assert np.allclose(data["difference_m"], [0.01, 0.02, 0.07], rtol=0, atol=1e-15)
    assert np.allclose(data["rms_exact_m"], 0.002 + 0.0001 * data["plane_id"], rtol=0, atol=1e-15)


def sweep_rows():
    """Nominal RMS = 0.1 m/km · h + 0.003 m, exact 0.0004 m/km · h + 0.0005 m, plus other configurations."""
    rows = []
    for altitude in (500, 1000, 2000, 3000, 4000, 5000):
        rows.append([altitude, 3, 2.314, "nominal", 0.1 * altitude / 1000 + 0.003, 1000])
        rows.append([altitude, 3, 2.314, "exact", 0.0004 * altitude / 1000 + 0.0005, 1000])
        if altitude != 500:  # other arrays and spacings: ignored by Fig. 8(b)
            rows.append([altitude, 4, 2.314, "nominal", 9.0, 1000])
            rows.append([altitude, 3, 4.628, "nominal", 9.0, 1000])
    for array in (2, 4, 5, 6):
        for model, rms in (("nominal", 0.02 * array), ("exact", 0.001)):
            rows.append([500, array, 2.314, model, rms, 100 * array])
    for multiple in (2, 3, 4, 5):
        for model, rms in (("nominal", 0.05 * multiple), ("exact", 0.001)):
            rows.append([500, 3, 2.314 * multiple, model, rms, 200 + multiple])
    return rows


@pytest.fixture
def sweep(tmp_path):
    path = tmp_path / "sweep.csv"
    write_csv(path, list(figures.SWEEP_COLUMNS), sweep_rows())
    return path


def test_fig8b_fit_recovers_known_slope(sweep, tmp_path):
    png, path = figures.fig8b(sweep, tmp_path / "out")
    assert_png(png)
    header, data = read(path)
    assert header == ["model", "altitude_km", "rms_m", "fit_rms_m", "slope_m_per_km", "intercept_m", "r2"]
    nominal = data["model"] == "nominal"
    assert np.count_nonzero(nominal) == 6 and np.count_nonzero(~nominal) == 6
    assert np.allclose(data["slope_m_per_km"][nominal], 0.1, rtol=1e-12)
    assert np.allclose(data["intercept_m"][nominal], 0.003, rtol=1e-10)
    assert np.allclose(data["r2"][nominal], 1.0, atol=1e-12)
    assert np.allclose(data["slope_m_per_km"][~nominal], 0.0004, rtol=1e-10)
    assert np.allclose(data["fit_rms_m"], data["rms_m"], atol=1e-14)


def test_linear_fit_against_independent_formulas():
    rng = np.random.default_rng(3)
    x = np.linspace(0.5, 5.0, 10)
    y = 0.1 * x + 0.01 + rng.normal(0.0, 0.01, x.size)
    slope, intercept, r2 = figures.linear_fit(x, y)
    # normal equations solved by hand, and R² = squared Pearson correlation for a least-squares line
    n, sx, sy, sxx, sxy = x.size, x.sum(), y.sum(), (x * x).sum(), (x * y).sum()
    assert slope == pytest.approx((n * sxy - sx * sy) / (n * sxx - sx * sx), rel=1e-12)
    assert intercept == pytest.approx((sy - slope * sx) / n, rel=1e-10)
    assert r2 == pytest.approx(np.corrcoef(x, y)[0, 1] ** 2, rel=1e-12)
    assert math.isnan(figures.linear_fit([1.0, 2.0], [3.0, 3.0])[2])
    with pytest.raises(InputError):
        figures.linear_fit([1.0, 1.0], [1.0, 2.0])


def test_fig9a_rms_vs_array(sweep, tmp_path):
    png, path = figures.fig9a(sweep, tmp_path / "out")
    assert_png(png)
    header, data = read(path)
    assert header == ["model", "array", "rms_m", "points"]
    nominal = data["model"] == "nominal"
    assert list(data["array"][nominal]) == [2, 3, 4, 5, 6]
    assert np.allclose(data["rms_m"][nominal], [0.04, 0.053, 0.08, 0.1, 0.12])
    assert list(data["points"][nominal]) == [200, 1000, 400, 500, 600]


def test_fig10a_rms_vs_spacing(sweep, tmp_path):
    png, path = figures.fig10a(sweep, tmp_path / "out")
    assert_png(png)
    header, data = read(path)
    assert header == ["model", "spacing_mrad", "spacing_multiple", "rms_m", "points"]
    nominal = data["model"] == "nominal"
    assert np.allclose(data["spacing_multiple"][nominal], [1, 2, 3, 4, 5])
    assert np.allclose(data["spacing_mrad"][nominal], 2.314 * np.arange(1, 6))
    assert np.allclose(data["rms_m"][nominal], [0.053, 0.1, 0.15, 0.2, 0.25])


def test_tables_without_the_needed_columns_or_rows_are_rejected(sweep, tmp_path):
    bad = tmp_path / "bad.csv"
    write_csv(bad, ["altitude_m", "model", "rms_m"], [[500, "nominal", 0.05]])
    with pytest.raises(InputError, match="columns"):
        figures.fig8b(bad, tmp_path / "out")
    with pytest.raises(InputError, match="array = 7"):
        figures.fig8b(sweep, tmp_path / "out", array=7)
    empty = tmp_path / "empty.csv"
    write_csv(empty, list(figures.PLANE_COLUMNS), [])
    with pytest.raises(InputError, match="rows"):
        figures.fig8a(empty, tmp_path / "out")
