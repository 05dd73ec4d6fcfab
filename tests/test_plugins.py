"""Parts from outside the package: the Palmer scanner of examples/palmer_scanner.py against an independent float64
reflection and the ellipse (a circle when level) its cone draws on a plane, the same part installed as a plug-in
through the ``flightsim.parts`` entry point (a throwaway dist-info; no change to flightsim), and the plug-ins that
must be refused: one that raises on import, and kinds that clash with a built-in part's table or a section."""
import dataclasses
import importlib.util
import math
import os
import re
import shutil
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import flightsim
from flightsim.core import registry
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from kernels import trace
from kernels.frames import ROW_ORIGIN, ROW_PHI, ROW_PULSE, ROW_ROT

ROOT = Path(__file__).resolve().parent.parent
PALMER = ROOT / "examples" / "palmer_scanner.py"
NED_TO_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@pytest.fixture(scope="module")
def palmer():
    """examples/palmer_scanner.py imported as a module (registering the part); the registry restored afterwards."""
    flightsim.register_part  # noqa: B018  (the API: the built-in parts are registered first)
    saved = {role: dict(kinds) for role, kinds in registry._parts.items()}
    spec = importlib.util.spec_from_file_location("palmer_scanner", PALMER)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # as an import would (dataclasses and Warp look the module up)
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]
    for role, kinds in registry._parts.items():
        kinds.clear()
        kinds.update(saved[role])


def _config(device: str, **overrides):
    base = {"instrument.deflector": "palmer", "output.models": ["exact"], "scene.name": "plane",
            "flight.platform": "hover", "flight.altitude_m": 100.0, "run.device": device}
    return flightsim.load_config(overrides={**base, **overrides})


# ---------------------------------------------------------------------------------------------
# an independent float64 model: the docstring's geometry, written again


def _mirror_normal(phi: np.ndarray, tilt: float) -> np.ndarray:
    """The tilted normal (sin τ, 0, cos τ) turned by φ about the spin axis z: (phases, 3)."""
    tilted = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    c, s = np.cos(phi), np.sin(phi)
    rz = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1),
                   np.stack([0 * c, 0 * c, 1 + 0 * c], -1)], -2)
    return rz @ tilted


def _reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    return d - 2.0 * np.sum(d * n, axis=-1, keepdims=True) * n


def _reference_exits(emitted: np.ndarray, phi: np.ndarray, tilt: float) -> np.ndarray:
    """(phases, beams, 3): each emitted beam (emitter frame, +z the axis), mounted to fire up the spin axis
    (x, −y, −z), reflected off the mirror at each phase."""
    fired = emitted * np.array([1.0, -1.0, -1.0])
    return _reflect(fired[None, :, :], _mirror_normal(phi, tilt)[:, None, :])


def _body_to_enu(roll: float, pitch: float, heading: float) -> np.ndarray:
    """R_ENU←body of the aerospace angles (body x forward, y right, z down): NED←body = Rz(ψ) Ry(θ) Rx(φ)."""
    def rot(axis, a):
        c, s = math.cos(a), math.sin(a)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        m = np.eye(3)
        m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
        return m
    return NED_TO_ENU @ rot(2, heading) @ rot(1, pitch) @ rot(0, roll)


def _phases(cfg, t0: float, k: np.ndarray) -> np.ndarray:
    """φ_k = 2π frac(f (t0 + k/PRF) + φ0/2π), the GPS-time product reduced exactly."""
    p = cfg.palmer
    c0 = Fraction(p.rotation_hz) * Fraction(t0)
    c0 = float(c0 - math.floor(c0)) + math.radians(p.phase0_deg) / (2 * math.pi)
    cycles = c0 + k * (p.rotation_hz / p.prf_hz)
    return 2 * math.pi * (cycles - np.floor(cycles))


# ---------------------------------------------------------------------------------------------
# the part on the device


@pytest.mark.parametrize("precise", [True, False], ids=["float64", "float32"])
def test_exit_directions_are_the_reflection_of_each_beam_off_the_spinning_mirror(palmer, device, precise):
    cfg = _config(device, **{"palmer.prf_hz": 360.0, "palmer.rotation_hz": 7.0, "palmer.phase0_deg": 12.5,
                             "palmer.tilt_deg": 11.0, "flight.duration_s": 0.25, "flight.heading_deg": 30.0,
                             "flight.roll_deg": 4.0})
    scene = build_scene(cfg)
    tracer = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    table, n = tracer.first_chunk(60)
    beams = tracer.beams_per_pulse
    vec = wp.vec3d if precise else wp.vec3f
    starts, directions = (wp.empty(n, dtype=vec, device=tracer.device) for _ in range(2))
    wp.launch(trace.emit_rays_kernel(tracer.instrument.kernel, precise=precise), n, inputs=[table, tracer.scan],
              outputs=[starts, directions], device=tracer.device)
    pulses = n // beams
    t = table.numpy()[:, :pulses]
    phi, rot, origin = t[ROW_PHI], t[ROW_ROT:ROW_ROT + 9].T.reshape(-1, 3, 3), t[ROW_ORIGIN:ROW_ORIGIN + 3].T
    assert np.ptp(phi) > 5.0 and pulses == 60  # phases all round the turn (7° apart)
    assert np.allclose(phi, _phases(cfg, tracer.trajectories[0].start_time, t[ROW_PULSE]), rtol=0, atol=1e-9)
    reference = _reference_exits(tracer.instrument.emitter.directions(), phi, math.radians(cfg.palmer.tilt_deg))
    local = np.einsum("pij,pbj->pbi", rot, reference)
    got = directions.numpy().astype(np.float64).reshape(pulses, beams, 3)
    assert np.abs(got - local).max() < (1e-13 if precise else 2e-7)
    assert np.abs(starts.numpy().astype(np.float64).reshape(pulses, beams, 3) - origin[:, None]).max() < (
        1e-9 if precise else 1e-4)  # every beam leaves the mirror's centre, the sensor origin
    # the fan's centre beam leaves at 2τ from the spin axis: (sin 2τ cos φ, sin 2τ sin φ, cos 2τ)
    two_tau = 2 * math.radians(cfg.palmer.tilt_deg)
    closed = np.stack([math.sin(two_tau) * np.cos(phi), math.sin(two_tau) * np.sin(phi),
                       np.full_like(phi, math.cos(two_tau))], -1)
    assert np.abs(reference[:, beams // 2] - closed).max() < 1e-15


@pytest.mark.parametrize("attitude", [(0.0, 0.0, 0.0), (6.0, -4.0, 30.0)], ids=["level-circle", "tilted-ellipse"])
def test_ground_points_lie_on_the_cone_s_ellipse_over_a_plane(palmer, device, attitude):
    roll, pitch, heading = attitude
    cfg = _config(device, **{"fan.array": 1, "flight.duration_s": 0.1, "flight.roll_deg": roll,
                             "flight.pitch_deg": pitch, "flight.heading_deg": heading, "palmer.phase0_deg": -20.0})
    result = flightsim.simulate(cfg, with_truth=True)
    returns = result.returns
    assert len(returns.pulse) == result.stats["pulses"] == 1001  # every pulse hits the plane, two turns
    position = flight_trajectories(cfg, result.scene)[0].position[0]  # the hover [m, world]
    ground = result.scene.origin[2] + result.scene.ground_z
    axis = _body_to_enu(*np.radians([roll, pitch, heading]))
    phi = _phases(cfg, cfg.flight.start_gps_time, returns.pulse.astype(np.float64))
    u = _reference_exits(np.array([[0.0, 0.0, 1.0]]), phi, math.radians(cfg.palmer.tilt_deg))[:, 0] @ axis.T
    predicted = position + ((ground - position[2]) / u[:, 2])[:, None] * u
    for points in (returns.points["exact"], returns.true_points):
        assert np.abs(points - predicted).max() < 2e-5  # float32 kernels, ~100 m from the sensor
    # the conic: every point at 2τ from the cone's axis (the sensor's z); level, a circle of radius h tan 2τ
    ray = returns.points["exact"] - position
    cone_axis = axis[:, 2]
    angle = np.arccos(ray @ cone_axis / np.linalg.norm(ray, axis=1))
    assert np.abs(angle - 2 * math.radians(cfg.palmer.tilt_deg)).max() < 1e-6
    if attitude == (0.0, 0.0, 0.0):
        radius = np.hypot(*(ray[:, :2].T))
        assert np.abs(radius - 100.0 * math.tan(math.radians(15.0))).max() < 2e-5
    else:  # an ellipse, not a circle: the nearest and farthest points differ by metres
        radius = np.hypot(*(ray[:, :2].T))
        assert np.ptp(radius) > 2.0


def test_nominal_model_and_lut_are_refused_for_the_palmer_deflector(palmer):
    with pytest.raises(flightsim.core.errors.InputError, match=r"output\.models.*palmer deflector has no rigid"):
        flightsim.load_config(overrides={"instrument.deflector": "palmer"})
    with pytest.raises(flightsim.core.errors.InputError, match=r"run\.optics.*palmer deflector has no exit table"):
        flightsim.load_config(overrides={"instrument.deflector": "palmer", "output.models": ["exact"],
                                         "run.optics": "lut"})


# ---------------------------------------------------------------------------------------------
# kinds that clash


@pytest.mark.parametrize("kind, says", [
    ("fan", "would share its config table with the emitter fan"),
    ("scene", "would share its config table with the [scene] section"),
    ("risley", "is taken by flightsim.instrument.risley.RisleyDeflector"),
])
def test_a_kind_that_clashes_with_a_built_in_table_or_section_is_refused(palmer, kind, says):
    class Clashing(palmer.PalmerScanner):
        pass

    before = {role: dict(kinds) for role, kinds in registry._parts.items()}
    with pytest.raises(registry.KindClash, match=re.escape(says)):
        flightsim.register_part("deflector", kind)(Clashing)
    assert {role: dict(kinds) for role, kinds in registry._parts.items()} == before
    flightsim.register_part("deflector", "palmer")(palmer.PalmerScanner)  # the same class again: harmless


# ---------------------------------------------------------------------------------------------
# installed plug-ins: a throwaway dist-info on PYTHONPATH


def _install(site: Path, modules: dict[str, str], entry_points: dict[str, str]) -> dict:
    """A dist-info declaring ``entry_points`` ({name: "module:attr"}) in group flightsim.parts, beside the modules'
    sources; the environment of a subprocess that sees them (and this checkout's flightsim)."""
    site.mkdir(parents=True, exist_ok=True)
    for name, source in modules.items():
        (site / f"{name}.py").write_text(source, encoding="utf-8")
    info = site / "flightsim_test_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: flightsim-test-plugin\nVersion: 0.1\n")
    lines = "".join(f"{name} = {target}\n" for name, target in entry_points.items())
    (info / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\n{lines}", encoding="utf-8")
    paths = [str(ROOT), str(site), os.environ.get("PYTHONPATH")]   # keep where the interpreter finds Warp
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, paths)))


def _flightsim(args: list[str], env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flightsim", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.fixture(scope="module")
def installed_palmer(tmp_path_factory) -> dict:
    """examples/palmer_scanner.py installed unchanged as the module palmer_scanner, its class the entry point."""
    return _install(tmp_path_factory.mktemp("site"), {"palmer_scanner": PALMER.read_text(encoding="utf-8")},
                    {"palmer": "palmer_scanner:PalmerScanner"})


def test_an_installed_plug_in_runs_from_the_command_line(installed_palmer, tmp_path, device):
    out = tmp_path / "run"
    done = _flightsim(["simulate", "--set", "instrument.deflector=palmer", "--set", "output.models=exact",
                       "--set", "palmer.tilt_deg=10", "--scene", "plane", "--duration", "0.2", "--device", device,
                       "--out", str(out)], installed_palmer)
    assert done.returncode == 0, done.stderr
    tiles = sorted((out / "exact").glob("*.las"))
    assert tiles and not (out / "nominal").exists()
    assert "[palmer]" in (out / "run.toml").read_text() and "tilt_deg = 10.0" in (out / "run.toml").read_text()
    assert re.search(r"exact \d+", done.stdout), done.stdout


def test_flightsim_config_prints_the_plug_in_s_table_documented(installed_palmer, palmer):
    done = _flightsim(["config", "--set", "instrument.deflector=palmer", "--set", "output.models=exact"],
                      installed_palmer)
    assert done.returncode == 0, done.stderr
    table = done.stdout.split("[palmer]\n", 1)[1].split("\n\n", 1)[0]
    assert f"# deflector palmer: {palmer.PalmerSettings.__doc__}\n[palmer]\n" in done.stdout  # titled by its doc
    for f in dataclasses.fields(palmer.PalmerSettings):
        line = next(line for line in table.splitlines() if line.startswith(f"{f.name} = "))
        assert f.metadata["doc"] in line and (f.metadata["unit"] in line), line
    assert "a finite number in (0, 30] deg" in table  # the tilt's range
    # the plug-in is one of the deflectors the config offers
    done = _flightsim(["config", "--set", "instrument.deflector=nope"], installed_palmer)
    assert done.returncode == 2 and "fixed, fsm, galvo, palmer, panoramic, risley" in done.stderr


def _refused(env: dict, tmp_path: Path) -> str:
    out = tmp_path / "out"
    done = _flightsim(["simulate", "--duration", "0.1", "--out", str(out)], env)
    assert done.returncode == 2, done.stdout + done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr, done.stderr
    assert not out.exists()
    return done.stderr


def test_a_plug_in_that_raises_on_import_exits_2_naming_it(tmp_path):
    env = _install(tmp_path / "site", {"broken_part": "raise RuntimeError('no licence for the\\nscanner')\n"},
                   {"broken-scanner": "broken_part"})
    line = _refused(env, tmp_path)
    assert line.startswith("flightsim: error: invalid plug-in broken-scanner = 'broken_part': expected a module")
    assert "RuntimeError: no licence for the scanner" in line


@pytest.mark.parametrize("source, target, says", [
    ("import flightsim\nfrom palmer_scanner import PalmerScanner\n\n"
     "@flightsim.register_part('deflector', 'fan')\nclass Fan(PalmerScanner):\n    pass\n",
     "clash", "would share its config table with the emitter fan"),
    ("from palmer_scanner import PalmerScanner\n\nclass Scene(PalmerScanner):\n    role, kind = 'deflector', 'scene'\n",
     "clash:Scene", "would share its config table with the [scene] section"),
    ("from palmer_scanner import PalmerSettings\n\nclass Risley:\n    settings = PalmerSettings\n"
     "    role, kind = 'deflector', 'risley'\n", "clash:Risley", "is taken by flightsim.instrument.risley"),
], ids=["module-registers-fan", "class-named-scene", "class-named-risley"])
def test_an_installed_plug_in_whose_kind_clashes_exits_2_naming_it(tmp_path, source, target, says):
    env = _install(tmp_path / "site", {"clash": source, "palmer_scanner": PALMER.read_text(encoding="utf-8")},
                   {"clashing": target})
    line = _refused(env, tmp_path)
    assert line.startswith(f"flightsim: error: invalid plug-in clashing = '{target}': expected a part kind of its own")
    assert says in line
