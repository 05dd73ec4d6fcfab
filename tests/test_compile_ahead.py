"""The kernels a run launches are compiled in two parallel batches: those of its set-up (run.compile_setup: the
deflector's, the flight planning's, the tracer's and the product's ``setup_kernels``), exactly the modules the
set-up would load one by one, and those of its chunks before the first (Tracer.compile_ahead): in a fresh
process, no Warp module is loaded between the batches or after the second; and `flightsim compile` leaves
nothing for a run of the same flags to load. Each run is a subprocess so that modules loaded by other
tests cannot hide one the run's list leaves out."""
import json
import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import json, os, sys
    from warp._src import context
    from flightsim.engine import run as run_module, tracer as tracer_module
    from flightsim.cli import main

    # the modules first loaded in each phase: before the set-up batch, in it, after it (the rest of the set-up),
    # in compile_ahead, after compile_ahead; FLIGHTSIM_TEST_SERIAL_SETUP=1 leaves the set-up batch out
    state = {"phase": "start", "loads": {p: [] for p in ("start", "setup", "between", "ahead", "after")}}
    ahead, setup = tracer_module.Tracer.compile_ahead, run_module.compile_setup
    load = context.Module.load

    def compile_ahead(self, *parts):
        state["phase"] = "ahead"
        ahead(self, *parts)
        state["phase"] = "after"

    def compile_setup(*args):
        state["phase"] = "setup"
        if not os.environ.get("FLIGHTSIM_TEST_SERIAL_SETUP"):
            setup(*args)
        state["phase"] = "between"

    def recording_load(self, device, *args, **kwargs):
        if not any(ctx == device.context for ctx, _ in self.execs):
            state["loads"][state["phase"]].append(f"{self.name.split('__locals__')[0]} on {device}")
        return load(self, device, *args, **kwargs)

    tracer_module.Tracer.compile_ahead = compile_ahead
    run_module.compile_setup = compile_setup
    context.Module.load = recording_load
    if sys.argv[1] == "compile-then":  # flightsim compile with the flags, then the run: nothing left to load
        flags = sys.argv[3:sys.argv.index("--out")] + sys.argv[sys.argv.index("--out") + 2:]
        assert main(["compile", *flags]) == 0
        state["phase"] = "after"
        sys.argv = sys.argv[1:]
    code = main(sys.argv[1:])
    print(json.dumps({"code": code, "loads": state["loads"]}))
""")

CASES = {
    "points to LAS": ["--instrument", "risley", "--duration", "0.2"],
    "galvo points to LAS": ["--instrument", "change3", "--duration", "0.05"],
    "waveforms": ["--instrument", "change1", "--duration", "0.5"],
    "waveforms, FFT convolution": ["--instrument", "change1", "--duration", "0.5", "--set", "waveform.convolution=fft"],
    "photons, SPAD": ["--instrument", "spad", "--duration", "0.002"],
    "photons, ATLAS six beams": ["--instrument", "atlas", "--duration", "0.002"],
    "waveforms, GEDI": ["--instrument", "gedi", "--duration", "0.01"],
}


def _loads(tmp_path, *command, serial_setup: bool = False) -> dict[str, list[str]]:
    """The modules a fresh process first loaded in each phase of the run (see SCRIPT)."""
    env = dict(os.environ, PYTHONPATH=os.getcwd() + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if serial_setup:
        env["FLIGHTSIM_TEST_SERIAL_SETUP"] = "1"
    done = subprocess.run([sys.executable, "-c", SCRIPT, *command, "--device", "cpu", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["code"] == 0
    return result["loads"]


@pytest.mark.parametrize("case", sorted(CASES))
def test_no_module_loads_after_compile_ahead_or_outside_the_setup_batch(case, tmp_path):
    loads = _loads(tmp_path, "simulate", *CASES[case])
    assert loads["ahead"] and loads["after"] == []
    assert loads["setup"] and loads["between"] == []  # the set-up's own kernels were all in its batch


@pytest.mark.parametrize("case", ["points to LAS", "photons, SPAD"])
def test_setup_batch_is_what_the_set_up_would_load_one_by_one(case, tmp_path):
    batch = _loads(tmp_path / "batch", "simulate", *CASES[case])["setup"]
    serial = _loads(tmp_path / "serial", "simulate", *CASES[case], serial_setup=True)
    assert serial["setup"] == [] and sorted(serial["start"] + serial["between"]) == sorted(batch)


@pytest.mark.parametrize("case", ["points to LAS", "photons, SPAD"])
def test_compile_command_leaves_nothing_to_load(case, tmp_path):
    assert _loads(tmp_path, "compile-then", "simulate", *CASES[case])["after"] == []
