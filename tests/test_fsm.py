"""The fast-steering-mirror deflector against the paper's reflection formula (eq. 2) and closed forms,
MODE-A coverage with the paper's timing, and bad input."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from flightsim.engine.config import RunConfig, validate
from flightsim.instrument import fsm_model
from flightsim.instrument.fan import FanEmitter

H = math.sqrt(0.5)


def _spad_config(**fields) -> RunConfig:
    cfg = RunConfig()
    cfg.instrument.deflector = "fsm"
    cfg.fan.array, cfg.fan.spacing_mrad = 32, 3.545  # 32 × 0.2031° = the paper's 6.5° field
    cfg.output.models = ("exact",)
    cfg.scene.name = "plane"
    cfg.flight.platform = "hover"
    cfg.flight.altitude_m = 100.0
    for key, value in fields.items():
        section, name = key.split("__")
        setattr(getattr(cfg, section), name, value)
    return validate(cfg)


def _paper_eq2(incoming, tx, ty):
    """The paper's eq. (2): the beam (l, m, n) leaving the large FSM at tilts θx, θy (FSM frame)."""
    l, m, n = incoming[..., 0], incoming[..., 1], incoming[..., 2]
    w = np.sqrt(np.tan(tx) ** 2 + np.tan(ty) ** 2 + 1)
    a, b, c = np.tan(tx) / w, np.tan(ty) / w, -1 / w
    k = l * a + m * b + n * c
    return np.stack([l - 2 * a * k, m - 2 * b * k, n - 2 * c * k], axis=-1)


def _incoming(emitted):
    """Independent float64: the mounted fan folded by the 45° mirror (normal (1, −1/√2, 1/√2)/√2)."""
    e = emitted
    s0 = np.stack([e[..., 2], H * (e[..., 0] + e[..., 1]), H * (e[..., 1] - e[..., 0])], axis=-1)
    n = np.array([1.0, -H, H]) / math.sqrt(2)
    return s0 - 2 * (s0 @ n)[..., None] * n


SENSOR = np.array([[1.0, 0.0, 0.0], [0.0, H, -H], [0.0, H, H]])


def test_at_rest_the_fan_leaves_as_emitted():
    beams = FanEmitter(_spad_config().fan).directions()
    _, direction, _ = fsm_model.trace(fsm_model.FsmGeometry(), 0.0, 0.0, beams)
    assert np.abs(direction - beams).max() < 1e-15


def test_tilts_turn_the_axis_by_the_reflection_law():
    t = np.radians(np.array([-1.0, -0.3, 0.2, 0.7]))
    axis = np.array([0.0, 0.0, 1.0])
    _, dy, _ = fsm_model.trace(fsm_model.FsmGeometry(), 0.0, t, axis)
    assert dy == pytest.approx(np.stack([0 * t, -np.sin(2 * t), np.cos(2 * t)], axis=-1), abs=1e-15)  # in plane: 2θ
    _, dx, _ = fsm_model.trace(fsm_model.FsmGeometry(), t, 0.0, axis)
    assert dx[:, 0] == pytest.approx(-H * np.sin(2 * t), abs=1e-15)  # out of the plane of incidence: sin 2θ / √2


def test_device_rays_match_the_papers_reflection_formula():
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import build_scene, flight_trajectories

    cfg = _spad_config(flight__duration_s=0.002, run__seed=3)
    scene = build_scene(cfg)
    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    pulses = 100
    _, directions = (a.numpy().astype(np.float64) for a in sim.sample_rays(pulses * 1024))
    pose = sim.poses64(1, 0, 1).numpy()[0]
    rot = np.asarray(pose["rot"], dtype=np.float64).reshape(3, 3)
    g = sim.instrument.deflector.geometry()
    tx, ty = fsm_model.scan_angles(g, np.arange(pulses))
    beams = FanEmitter(cfg.fan).directions()
    expected = _paper_eq2(_incoming(beams)[None], tx[:, None], ty[:, None]) @ SENSOR.T
    got = (directions @ rot).reshape(pulses, 1024, 3)
    assert np.linalg.norm(np.cross(got, expected), axis=-1).max() < 2e-6  # float32 rays


def test_mode_a_covers_every_cell_of_the_1100_grid_in_one_frame():
    """The paper: 43,000 pulses in 0.86 s interleave the 32 × 32 array to 1100 × 1100 over 6.5°."""
    cfg = _spad_config()
    deflector_geometry = fsm_model.FsmGeometry(mode="A", span_rad=tuple(v * 1e-3 for v in cfg.fsm.span_mrad),
                                               lines=cfg.fsm.lines, frame_pulses=round(cfg.fsm.frame_s * cfg.fsm.prf_hz))
    assert deflector_geometry.frame_pulses == 43000
    beams = FanEmitter(cfg.fan).directions()
    half, n = math.radians(3.25), 1100
    hit = np.zeros((n, n), dtype=bool)
    for first in range(0, 43000, 4300):
        tx, ty = fsm_model.scan_angles(deflector_geometry, np.arange(first, first + 4300))
        _, d, _ = fsm_model.trace(deflector_geometry, tx[:, None], ty[:, None], beams[None])
        i = np.floor((np.arctan2(d[..., 0], d[..., 2]) + half) / (2 * half) * n).astype(int)
        j = np.floor((np.arctan2(d[..., 1], d[..., 2]) + half) / (2 * half) * n).astype(int)
        inside = (i >= 0) & (i < n) & (j >= 0) & (j < n)
        hit[j[inside], i[inside]] = True
    assert hit.all(), (~hit).sum()


@pytest.mark.parametrize("setting, field", [
    ("fsm.prf_hz=50", "fsm.prf_hz"),
    ("fsm.mode=C", "fsm.mode"),
    ("fsm.span_mrad=2.6,500", "fsm.span_mrad"),
    ("fsm.aperture_mm=0.1", "fsm.aperture_mm"),
    ("risley.encoder_arcsec=5", "risley.encoder_arcsec"),
    ("fsm.zero_arcsec=1,2,3", "fsm.zero_arcsec"),
])
def test_bad_fsm_input_exits_2_naming_the_field(tmp_path, setting, field):
    args = ["--set", "instrument.deflector=fsm", "--set", "output.models=exact", "--set", setting]
    run = subprocess.run([sys.executable, "-m", "flightsim", "simulate", *args, "--out", str(tmp_path / "o")],
                         capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0], run.stderr


def test_galvo_refuses_fsm_errors(tmp_path):
    run = subprocess.run([sys.executable, "-m", "flightsim", "simulate", "--instrument", "change3", "--set",
                          "fsm.noise_arcsec=3", "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert run.returncode == 2 and "fsm.noise_arcsec" in run.stderr
