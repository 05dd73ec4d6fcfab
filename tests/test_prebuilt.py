"""The prebuilt kernels (flightsim/core/prebuilt.py): every module a built-in instrument's run loads is shipped for
the CPU and for sm_90, and seeding copies into Warp's kernel cache only what it lacks."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from flightsim.cli import main, prebuilt_scene_flags
from flightsim.core import prebuilt
from flightsim.engine.config_io import PREBUILT_RUNS

ROOT = Path(__file__).resolve().parents[1]

CHECK = """
import json, sys, threading, traceback
from warp._src import context

compiles = []  # what compiled, from which thread and call: the failure's own account of itself
_compile = context.Module._compile


def recording_compile(self, *args, **kwargs):
    did = _compile(self, *args, **kwargs)
    if did:
        compiles.append({"module": self.name, "thread": threading.current_thread().name,
                         "stack": traceback.format_stack(limit=12)})
    return did


context.Module._compile = recording_compile
from flightsim.cli import build_config, make_parser

from flightsim.core import prebuilt
from flightsim.core.warp_runtime import compile_ahead
from flightsim.scenes.build import scene_part

target, flags = sys.argv[1], sys.argv[2:]
if target == "sweep":  # a sweep as `flightsim sweep` runs it: the first configuration of a small grid, flown
    from flightsim.cli import build_grid
    from flightsim.studies.sweep import SceneCache, run_configuration

    args = make_parser().parse_args(["sweep", "--device", "cpu", "--duration", "0.05", "--altitudes", "500,1000",
                                     "--instrument", *flags, "--out", "-"])
    (labels, cfg), *others = build_grid(args).configurations()
    run_configuration(labels, cfg, SceneCache([cfg, *(c for _, c in others)]))
else:  # the rest as the command runs them, small: `flightsim budget` with two draws, a survey of one tile, the
    # SPAD study with 100 pulses a frame, a calibration pass on each platform, selfcal's quick flight
    from flightsim.studies.compile_targets import compile_for

    cfg = build_config(make_parser().parse_args(["compile", "--device", "cpu", "--instrument", *flags]))
    compile_for(target, {flags[0]: cfg})
gpu_only = scene_part(cfg.scene).build_kernels("cuda")  # what the scene builds with on a GPU (a forest's voxels)
compile_ahead("cpu", gpu_only)
loaded = prebuilt.loaded_on_cpu()
print(json.dumps({"loaded": len(loaded), "gpu_only": len(gpu_only), "missing": prebuilt.missing(loaded),
                  "compiles": compiles}))
"""


@pytest.mark.parametrize("instrument, scene, target", PREBUILT_RUNS,
                         ids=[f"{n}-{s or 'own'}{'' if t == 'simulate' else '-' + t}" for n, s, t in PREBUILT_RUNS])
def test_each_built_in_run_is_prebuilt_for_the_cpu_and_sm90(tmp_path, instrument, scene, target):
    """A run of the instrument (over its own scene, the procedural forest or a point cloud) in a process of its own
    (as `flightsim simulate` runs it; the statistics readout as `flightsim sweep` flies a configuration; a survey, a
    budget and the studies as `flightsim survey`, `budget`, `spad`, `calibrate` and `selfcal` run them) finds every
    module it loads prebuilt, for the CPU and for sm_90 (a forest's also the voxel kernel a GPU run builds its scene
    with), and compiles nothing. A kernel changed without remaking the prebuilt set fails here: run ``flightsim compile --all
    --ship``."""
    env = dict(os.environ, WARP_CACHE_PATH=str(tmp_path / "kernels"), FLIGHTSIM_CACHE=str(tmp_path / "scenes"),
               FLIGHTSIM_PREBUILT="1")
    args = [target, instrument, *prebuilt_scene_flags(scene, tmp_path / "cloud")]
    done = subprocess.run([sys.executable, "-c", CHECK, *args], env=env, capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    found = json.loads(done.stdout.strip().splitlines()[-1])
    assert found["loaded"] >= 5 and found["gpu_only"] == (1 if scene == "forest" else 0)
    assert found["missing"] == [], "remake the prebuilt kernels: flightsim compile --all --ship"
    compiled = sorted(p.parent.name for p in (tmp_path / "kernels").rglob("*.cpp"))
    assert compiled == [], f"compiled though prebuilt: {compiled}; {json.dumps(found['compiles'], indent=1)}"


def test_seeding_copies_only_what_the_cache_lacks(tmp_path, monkeypatch):
    shipped = tmp_path / "prebuilt" / "warp-test"
    (shipped / "wp_a_1234567").mkdir(parents=True)
    (shipped / "wp_a_1234567" / "wp_a_1234567.meta").write_text("{}")
    (shipped / "wp_a_1234567" / "wp_a_1234567.o").write_bytes(b"object")
    (shipped / prebuilt.MANIFEST).write_text("two files\n")
    monkeypatch.setattr(prebuilt, "shipped", lambda: shipped)
    cache = tmp_path / "cache"
    (cache / "wp_a_1234567").mkdir(parents=True)
    (cache / "wp_a_1234567" / "wp_a_1234567.o").write_bytes(b"compiled here")
    assert prebuilt.seed_kernel_cache(cache) == 1  # the meta; the object compiled here stays
    assert (cache / "wp_a_1234567" / "wp_a_1234567.o").read_bytes() == b"compiled here"
    assert (cache / "wp_a_1234567" / "wp_a_1234567.meta").read_text() == "{}"
    (cache / "wp_a_1234567" / "wp_a_1234567.meta").unlink()
    assert prebuilt.seed_kernel_cache(cache) == 0  # the manifest's marker: not scanned again
    (shipped / prebuilt.MANIFEST).write_text("remade\n")
    assert prebuilt.seed_kernel_cache(cache) == 1
    monkeypatch.setenv("FLIGHTSIM_PREBUILT", "0")
    (shipped / prebuilt.MANIFEST).write_text("remade again\n")
    assert prebuilt.seed_kernel_cache(cache) == 0


@pytest.mark.parametrize("flags", [["--instrument", "risley", "--for", "spad"], ["--all", "--for", "calibrate"],
                                   ["--instrument", "atlas", "--for", "selfcal"]])
def test_compile_refuses_another_instrument_s_study(capsys, flags):
    """`flightsim compile --for spad|calibrate|selfcal` compiles that instrument's study alone: another instrument (or
    every one) exits 2 with one line naming --instrument, before anything is compiled."""
    assert main(["compile", "--device", "cpu", *flags]) == 2
    line = capsys.readouterr().err.strip().splitlines()
    assert len(line) == 1 and "--instrument" in line[0] and "expected" in line[0] and "with --for" in line[0], line
