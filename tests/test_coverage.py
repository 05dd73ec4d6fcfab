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


def test_every_lines_windows_planned_together_are_each_line_planned_alone():
    """Lines of 2-40 samples at random attitudes passing near, over and far from a 200 m square scene: the windows
    of all of them worked out at once (as a run plans them) are those of each line alone, line by line; some lines
    are culled whole and some in part."""
    from flightsim.engine.coverage import pulse_windows
    from trajectories import PulseTiming, Trajectory, rotation

    rng = np.random.default_rng(12)
    lines, positions = [], []
    for k in range(400):
        n = int(rng.integers(2, 40))
        t = 1.0e8 + 7.0 * k + np.cumsum(rng.uniform(0.01, 0.3, n))
        start, heading = rng.uniform(-900.0, 900.0, 2), rng.uniform(-np.pi, np.pi)
        along = np.cumsum(rng.uniform(5.0, 40.0, n))
        xyz = np.column_stack([start[0] + along * np.sin(heading), start[1] + along * np.cos(heading),
                               rng.uniform(300.0, 600.0, n)])
        attitude = np.column_stack([rng.normal(0.0, 0.2, n), rng.normal(0.0, 0.2, n), np.full(n, heading)])
        lines.append(Trajectory(t, xyz, attitude, line_id=k))
        positions.append(xyz)
    bounds = (np.array([-100.0, -100.0, 0.0]), np.array([100.0, 100.0, 20.0]))
    timing = PulseTiming(prf_hz=50.0)
    boresight = rotation.normalize(np.array([0.01, -0.02, 0.003, 1.0]))
    together = pulse_windows(lines, positions, bounds, timing, 0.05, boresight)
    alone = [pulse_windows([line], [xyz], bounds, timing, 0.05, boresight)[0] for line, xyz in zip(lines, positions)]
    assert together == alone
    counts = [timing.pulse_count(line.start_time, line.end_time) for line in lines]
    whole = sum(w == [(0, c)] for w, c in zip(together, counts))
    assert sum(w == [] for w in together) > 50 and whole > 5 and len(lines) - whole - sum(w == [] for w in together) > 5


def test_the_lines_with_one_segment_near_the_scene_get_the_windows_of_the_loop_over_segments():
    """_lone_windows (every line with one near segment at once) against _windows (a line's segments in turn), over
    lines of 2-6 samples, half of them at whole pulse periods (k0, k1 at the floor's edges), with one, none or
    several segments near."""
    from flightsim.engine.coverage import _lone_windows, _windows
    from trajectories import PulseTiming, Trajectory

    rng = np.random.default_rng(13)
    timing = PulseTiming(prf_hz=50.0)
    lines, flags = [], []
    for k in range(600):
        n = int(rng.integers(2, 7))
        steps = rng.integers(1, 40, n - 1) / 50.0 if k % 2 else rng.uniform(0.001, 0.8, n - 1)
        t = 1.0e8 + 3.0 * k + np.concatenate([[0.0], np.cumsum(steps)])
        lines.append(Trajectory(t, np.zeros((n, 3)), np.zeros((n, 3)), line_id=k))
        flags.append(np.append(rng.random(n - 1) < rng.choice([0.0, 0.3, 1.0 / (n - 1), 1.0]), False))
    sizes = np.array([len(line.gps_time) for line in lines])
    first = np.cumsum(sizes) - sizes
    near = np.concatenate(flags)[:-1]  # one segment a sample but the last: the segment to the next line is False
    rel = np.concatenate([line.gps_time - line.start_time for line in lines])
    counts = [timing.pulse_count(line.start_time, line.end_time) for line in lines]
    got = _lone_windows(near, first, rel, np.array(counts), timing.prf_hz)
    lone = [i for i in range(len(lines)) if near[first[i]:first[i] + sizes[i] - 1].sum() == 1]
    assert len(lone) > 100 and set(got) <= set(lone)
    for i in lone:
        assert got.get(i, []) == _windows(lines[i], near[first[i]:first[i] + sizes[i] - 1], counts[i], timing.prf_hz)
