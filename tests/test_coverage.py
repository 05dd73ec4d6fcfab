"""Host-side culling: pulses that cannot reach the scene are never launched, and nothing is lost."""
import numpy as np

from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.run import simulate_to_directory


def pad_config(tmp_path, cull: bool, **settings):
    mesh = tmp_path / "pad.obj"  # a 60 m pad with a 10 m box on it, under the middle of a 1.1 km line
    mesh.write_text("\n".join([
        "v -30 -30 0", "v 30 -30 0", "v 30 30 0", "v -30 30 0",
        "v -5 -5 10", "v 5 -5 10", "v 5 5 10", "v -5 5 10",
        "g ground", "f 1 2 3 4", "g roof", "f 5 6 7 8", ""]))
    cfg = RunConfig()
    for key, value in {"scene.name": str(mesh), "flight.duration_s": 20.0, "run.cull": cull, **settings}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def test_culling_skips_pulses_out_of_reach_without_changing_any_point(tmp_path):
    culled = simulate_to_directory(pad_config(tmp_path, True), tmp_path / "culled")
    full = simulate_to_directory(pad_config(tmp_path, False), tmp_path / "full")
    assert full["pulses_culled"] == 0
    assert culled["pulses"] + culled["pulses_culled"] == full["pulses"]
    # the scan circle (r = 134 m) touches the 60 m pad during ~330 m of the 1111 m line
    assert 0.55 < culled["pulses_culled"] / full["pulses"] < 0.75
    assert culled["points"] == full["points"]
    for model in ("exact", "nominal"):  # equal up to the order of float64 summation over chunks
        assert np.isclose(culled["rms_m"][model], full["rms_m"][model], rtol=1e-12, atol=0)
    for name in full["tiles"]["nominal"]:
        assert (tmp_path / "culled/nominal" / name).read_bytes() == (tmp_path / "full/nominal" / name).read_bytes()


def test_culling_is_conservative_for_a_banked_and_boresighted_sensor(tmp_path):
    settings = {"flight.roll_deg": 12.0, "instrument.boresight_deg": "3,-2,1", "flight.heading_deg": 30.0}
    culled = simulate_to_directory(pad_config(tmp_path, True, **settings), tmp_path / "culled")
    full = simulate_to_directory(pad_config(tmp_path, False, **settings), tmp_path / "full")
    assert culled["pulses_culled"] > 0
    assert culled["points"] == full["points"] and np.isclose(culled["rms_m"]["nominal"], full["rms_m"]["nominal"])
