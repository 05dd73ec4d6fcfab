"""The kernels a run launches are compiled together before its first chunk (Tracer.compile_ahead): in a fresh
process, no Warp module is loaded on the run's device after compile_ahead returned; and `flightsim compile`
leaves nothing for a run of the same flags to load. Each run is a subprocess so that modules loaded by other
tests cannot hide one the run's list leaves out."""
import json
import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import json, sys
    from warp._src import context
    from flightsim.engine import tracer as tracer_module
    from flightsim.cli import main

    state = {"after": None, "late": []}
    ahead = tracer_module.Tracer.compile_ahead
    load = context.Module.load

    def compile_ahead(self, *parts):
        ahead(self, *parts)
        state["after"] = True

    def recording_load(self, device, *args, **kwargs):
        new = (device.context, kwargs.get("block_dim")) not in self.execs and not any(
            ctx == device.context for ctx, _ in self.execs)
        if state["after"] and new:
            state["late"].append(self.name)
        return load(self, device, *args, **kwargs)

    tracer_module.Tracer.compile_ahead = compile_ahead
    context.Module.load = recording_load
    if sys.argv[1] == "compile-then":  # flightsim compile with the flags, then the run: nothing left to load
        flags = sys.argv[3:sys.argv.index("--out")] + sys.argv[sys.argv.index("--out") + 2:]
        assert main(["compile", *flags]) == 0
        state["after"] = True
        sys.argv = sys.argv[1:]
    code = main(sys.argv[1:])
    print(json.dumps({"code": code, "compiled_ahead": state["after"], "late": state["late"]}))
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


def _late_loads(tmp_path, *command) -> list[str]:
    """The modules a fresh process loaded after compile_ahead (or `flightsim compile`) returned."""
    env = dict(os.environ, PYTHONPATH=os.getcwd() + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = subprocess.run([sys.executable, "-c", SCRIPT, *command, "--device", "cpu", "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["code"] == 0 and result["compiled_ahead"]
    return result["late"]


@pytest.mark.parametrize("case", sorted(CASES))
def test_no_module_loads_after_compile_ahead(case, tmp_path):
    assert _late_loads(tmp_path, "simulate", *CASES[case]) == []


@pytest.mark.parametrize("case", ["points to LAS", "photons, SPAD"])
def test_compile_command_leaves_nothing_to_load(case, tmp_path):
    assert _late_loads(tmp_path, "compile-then", "simulate", *CASES[case]) == []
