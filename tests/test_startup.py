"""The command line's start (flightsim/entry.py): the CUDA device a command line names is started on a thread
while the modules import, and it is the context Warp then uses."""
import json
import os
import subprocess
import sys

import pytest

from flightsim.entry import cuda_ordinal, start_cuda


@pytest.mark.parametrize("argv, ordinal", [
    (["simulate", "--device", "cuda", "--out", "x"], 0),
    (["simulate", "--device=cuda:1"], 1),
    (["sweep", "--device", "cuda:12"], 12),
    (["simulate", "--device", "cpu"], None),
    (["simulate", "--device"], None),
    (["simulate", "--device", "cudax"], None),
    (["simulate", "--device=cuda:"], None),
    (["simulate", "--out", "cuda"], None),
    (["simulate", "--set", "run.device=cuda"], None),  # a config field: the run starts CUDA itself
])
def test_the_device_a_command_line_names(argv, ordinal):
    assert cuda_ordinal(argv) == ordinal


def test_the_context_started_is_the_one_warp_uses(device):
    if not device.startswith("cuda"):
        pytest.skip("a CUDA device only")
    import warp as wp

    ordinal = int(device.split(":")[1])
    context = start_cuda(ordinal)
    assert context is not None and context == wp.get_device(device).context  # an int (ctypes c_void_p)


def test_no_such_device_starts_nothing():
    assert start_cuda(1 << 20) is None


def test_source_trees_are_timed_side_by_side():
    from pathlib import Path

    from flightsim.studies.startup_ab import compare, table

    tree = Path(__file__).resolve().parents[1]
    records = compare("cpu", 1, [tree])
    (run,) = records[tree]
    assert 0.0 < run["cli_s"] < run["first_ray_s"] < run["first_file_s"] <= run["exit_s"] < 60.0
    assert run["modules_compiled"] == 0  # the first, untimed run filled the kernel cache
    assert table(records).splitlines()[2].startswith(f"| {tree} | 1 | {run['cli_s']:.3f} / ")


def test_a_command_that_ends_at_once_waits_for_the_driver_start(monkeypatch):
    import time

    from flightsim import entry

    started = []
    monkeypatch.setattr(entry, "start_cuda", lambda ordinal: (time.sleep(0.5), started.append(ordinal)))
    with pytest.raises(SystemExit) as ended:
        entry.main(["simulate", "--device", "cuda:1", "--no-such-flag"])
    assert ended.value.code == 2 and started == [1]  # the process would exit only now


UNFLOWN_KERNELS = ("kernels.canopy", "kernels.canopy_returns", "kernels.canopy_photons", "kernels.photon",
                   "kernels.photon_frame", "kernels.photon_grid", "kernels.waveform", "kernels.waveform_fft",
                   "kernels.fsm", "kernels.galvo", "kernels.panoramic", "kernels.fixed", "kernels.wedges")


def test_a_risley_run_loads_no_other_parts_kernels(tmp_path):
    """The default run (Risley, points to LAS) in a fresh process: the kernels modules of the parts it does not fly
    (canopy, photons, waveforms, other deflectors) are never imported (flightsim/core/lazy.py), while the ones it
    flies are."""
    script = ("import json, sys\nfrom flightsim.entry import main\n"
              f"code = main(['simulate', '--device', 'cpu', '--duration', '0.02', '--out', {str(tmp_path)!r}])\n"
              "print(json.dumps([code, sorted(m for m in sys.modules if m.startswith('kernels.'))]))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=os.environ, check=True)
    code, loaded = json.loads(done.stdout.strip().splitlines()[-1])
    assert code == 0
    assert {"kernels.trace", "kernels.wedge", "kernels.las_records"} <= set(loaded)
    assert not set(loaded) & set(UNFLOWN_KERNELS), sorted(set(loaded) & set(UNFLOWN_KERNELS))


def test_a_photon_run_off_orbit_imports_neither_atl03_nor_scipy(tmp_path):
    """A SPAD run (photons, off orbit) in a fresh process: atl03.h5's writer and its signal finder, and with them
    SciPy (~0.3 s of a run's start), are never imported; an ATLAS run (from orbit) imports the writer."""
    def loaded(args: list[str], out) -> set[str]:
        script = ("import json, sys\nfrom flightsim.entry import main\n"
                  f"code = main(['simulate', '--device', 'cpu', *{args!r}, '--out', {str(out)!r}])\n"
                  "tops = ('scipy', 'flightsim')\n"
                  "print(json.dumps([code, sorted(m for m in sys.modules if m.split('.')[0] in tops)]))\n")
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=os.environ,
                              check=True)
        code, modules = json.loads(done.stdout.strip().splitlines()[-1])
        assert code == 0
        return set(modules)

    spad = loaded(["--instrument", "spad", "--duration", "0.0005"], tmp_path / "spad")
    assert "flightsim.outputs.photons_h5" in spad
    assert not {m for m in spad if m.startswith("scipy") or m == "flightsim.outputs.atl03_h5"}
    atlas = loaded(["--instrument", "atlas", "--duration", "0.0002"], tmp_path / "atlas")
    assert "flightsim.outputs.atl03_h5" in atlas


def test_warp_names_its_cpu_objects_before_any_parallel_load():
    """init_warp has Warp work out the LLVM version and target of its CPU objects' names on one thread: Warp's native
    call for the version can return an empty string when several module loads ask at once, and a module then
    misses its prebuilt object and compiles (seen as an intermittent compile in tests/test_prebuilt.py)."""
    script = ("from warp._src import context\nfrom flightsim.core.warp_runtime import init_warp\ninit_warp()\n"
              "print(repr(context._cpu_toolchain_version_cache), repr(context.runtime.get_llvm_version()))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=os.environ, check=True)
    cached, version = done.stdout.split()
    assert version not in ("''", "'unknown'") and cached == version


def test_gedi_shots_over_a_cloud_import_no_raster_library(tmp_path):
    """GEDI shots over an ALS cloud write HDF5 and returns.las, no raster: rasterio (~0.2 s of a run's start, with
    its cloud sessions) is never imported; writing a GeoTIFF imports it."""
    from flightsim.studies.bench_shots import write_shots

    cloud, shots, _ = write_shots(tmp_path / "cloud", 100_000, 4)
    script = ("import json, sys\nfrom flightsim.entry import main\n"
              f"code = main(['waveform', '--instrument', 'gedi', '--device', 'cpu', '--scene', {str(cloud)!r}, "
              f"'--footprints', {str(shots)!r}, '--out', {str(tmp_path / 'out')!r}])\n"
              "print(json.dumps([code, 'rasterio' in sys.modules]))\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=os.environ, check=True)
    assert json.loads(done.stdout.strip().splitlines()[-1]) == [0, False]
    assert (tmp_path / "out" / "returns.las").is_file()
    script = ("import sys, numpy as np, pyproj\nfrom flightsim.outputs.grid_products import write_geotiff\n"
              "assert 'rasterio' not in sys.modules\n"
              f"write_geotiff({str(tmp_path / 'h.tif')!r}, np.zeros((2, 2)), (0.0, 2.0), 1.0, pyproj.CRS(32633))\n"
              "print('rasterio' in sys.modules)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=os.environ, check=True)
    assert done.stdout.strip().splitlines()[-1] == "True"
