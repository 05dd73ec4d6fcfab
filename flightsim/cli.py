"""The `flightsim` command line (SPEC §10). Exit status: 0 success, 2 invalid input, 1 anything else."""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import sys
import time
from pathlib import Path

from flightsim.core.version import __version__
from flightsim.engine.config import RunConfig, get_value, set_value, validate
from flightsim.engine.config_io import PREBUILT_RUNS, PRESETS, load_toml, preset_config, to_toml
from flightsim.scoring import score
from flightsim.core.errors import InputError
from flightsim.core.timeline import mark
from flightsim.cli_studies import add_study_commands, set_items
from flightsim.studies.compile_targets import OWN_INSTRUMENT, TARGETS, compile_for

EXIT_INVALID = 2

# simulate flags that set a config field: (flag, dest, config key, help)
CONFIG_FLAGS = [
    ("--scene", "scene", "scene.name", "calibration (default), plane, lunar, sandbox, ellipsoid, bump, or PATH.obj / PATH.ply"),
    ("--altitude", "altitude", "flight.altitude_m", "flying height above ground [m] (default 500)"),
    ("--array", "array", "fan.array", "beams per side of the N×N array, 1–64 (default 3)"),
    ("--spacing-mrad", "spacing_mrad", "fan.spacing_mrad", "angular spacing of the sub-beams [mrad] (default 2.314)"),
    ("--duration", "duration", "flight.duration_s", "flight time per line [s] (default 10)"),
    ("--models", "models", "output.models", "georeferencing models to write: exact,nominal (default both)"),
    ("--device", "device", "run.device", "cpu (default), cuda or cuda:N"),
    ("--seed", "seed", "run.seed", "random seed for noise models (default 0)"),
    ("--trajectory", "trajectory", "flight.trajectory", "CSV trajectory to fly instead of the line plan"),
]


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad command line in one line with exit status 2."""

    def error(self, message: str):
        self.exit(EXIT_INVALID, f"{self.prog}: error: {message} (see --help)\n")


SWEEP_FLAGS = [f for f in CONFIG_FLAGS if f[0] in ("--scene", "--duration", "--models", "--device", "--seed")]
SURVEY_FLAGS = [("--scene", "scene", "scene.name", "what every scene tile holds: calibration (default) or plane")] + [
    f for f in CONFIG_FLAGS if f[0] not in ("--scene", "--duration", "--trajectory")]
SWEEP_AXES = [
    ("--altitudes", "altitudes", "flight.altitude_m", "altitudes above ground [m], e.g. 500,1000,1500"),
    ("--arrays", "arrays", "fan.array", "array sizes N, e.g. 2,3,4,5,6"),
    ("--spacings-mrad", "spacings_mrad", "fan.spacing_mrad", "sub-beam spacings [mrad], e.g. 2.314,4.628"),
]


def base_config(args: argparse.Namespace, flags=CONFIG_FLAGS) -> RunConfig:
    """Config from --config (TOML), then the flags (unvalidated)."""
    cfg = preset_config(getattr(args, "instrument", None) or "risley")
    if args.config:
        cfg = load_toml(args.config, cfg)
    for _flag, dest, key, _help in flags:
        value = getattr(args, dest)
        if value is not None:
            set_value(cfg, key, value)
    return cfg


def build_config(args: argparse.Namespace) -> RunConfig:
    """Config from --config, the flags, then --set overrides; validated and resolved."""
    cfg = base_config(args)
    for key, value in set_items(args):
        set_value(cfg, key, value)
    return validate(cfg)


def build_grid(args: argparse.Namespace):
    """The sweep grid: base config and axes from the axis flags and multi-valued --set items."""
    from flightsim.studies.sweep import SweepGrid, parse_axis

    cfg = base_config(args, SWEEP_FLAGS)
    axes = []
    for flag, dest, key, _help in SWEEP_AXES:
        if getattr(args, dest) is not None:
            axes.append((key, parse_axis(flag, getattr(args, dest))))
    for key, value in set_items(args):
        set_value(cfg, key, value.split(",")[0])  # checks the key and the first value's type
        if "," in value and not isinstance(get_value(cfg, key), tuple):
            axes.append((key, parse_axis("--set " + key, value)))
        else:
            set_value(cfg, key, value)
    grid = SweepGrid(cfg, axes)
    grid.configurations()  # validate every configuration before any work starts
    return grid


def _add_config_flags(parser: argparse.ArgumentParser, flags=CONFIG_FLAGS) -> None:
    parser.add_argument("--instrument", help="built-in instrument to start from: " + ", ".join(PRESETS)
                        + " (default risley)")
    parser.add_argument("--config", help="run config TOML over the instrument (a run.toml of an earlier run "
                                         "reproduces it)")
    for flag, dest, _key, help_text in flags:
        parser.add_argument(flag, dest=dest, help=help_text)
    parser.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="set any setting of the parts in use, e.g. --set risley.refractive_index=1.45 (repeatable; "
                             "`flightsim config` lists them)")


def _add_cluster_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workers", type=int, help="run on a local Dask cluster of N worker processes (N > 1)")
    parser.add_argument("--scheduler", help="run on the Dask cluster of this scheduler address, e.g. tcp://host:8786")
    parser.add_argument("--gpus", help="Dask workers pinned to GPUs, one per GPU (or --workers of them): all, or 0,1")


def _nothing_made(summary: dict, out) -> int:
    """A run that made nothing: say why on stderr (summary.json holds it too) and exit 2."""
    print(f"flightsim: nothing made: {summary['empty']} (summary.json in {out} records it)", file=sys.stderr)
    return EXIT_INVALID


def cmd_config(args: argparse.Namespace) -> int:
    """Print the resolved config, every setting with its meaning, unit and range."""
    print(to_toml(build_config(args), comments=True), end="")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    cfg = build_config(args)
    from flightsim.core.progress import ProgressBar
    from flightsim.engine.run import simulate_to_directory

    summary = simulate_to_directory(cfg, Path(args.out), overwrite=args.overwrite,
                                    progress=ProgressBar("simulate"))
    if "empty" in summary:
        return _nothing_made(summary, args.out)
    if "photons" in summary:
        print(f"{summary['photons']} photons ({summary['signal_photons']} signal) from {summary['pulses']} pulses "
              f"in {summary['wall_s']:.2f} s; written to {args.out}")
        return 0
    if "waveforms" in summary:
        print(f"{summary['waveforms']} waveforms ({summary['subray_returns']} sub-ray returns) from {summary['pulses']} "
              f"pulses in {summary['wall_s']:.2f} s; written to {args.out}")
        return 0
    patches = summary.get("patches")
    scored = patches or summary
    rms = ", ".join(f"{m} {v * 1000:.2f} mm" if v is not None else f"{m} n/a" for m, v in scored["rms_m"].items())
    points = ", ".join(f"{n} {m}" for m, n in summary["points"].items())
    what = f"RMS over {patches['patches']} patches of {patches['patch_m']:g} m" if patches else "plane RMS"
    print(f"{points} points from {summary['pulses']} pulses in {summary['wall_s']:.2f} s; "
          f"{what}: {rms}; written to {args.out}")
    return 0


def cmd_compile(args: argparse.Namespace) -> int:
    """Compile every kernel the runs would launch into Warp's kernel cache, so that their first start is warm; with
    ``--ship``, into flightsim's prebuilt kernels instead (:mod:`flightsim.core.prebuilt`)."""
    if args.ship:
        return _ship(args)
    target = args.target
    own = OWN_INSTRUMENT.get(target)
    if own and (args.all or (args.instrument or own) != own):
        raise InputError("--instrument", "every built-in one (--all)" if args.all else args.instrument,
                         f"{own} or nothing with --for {target}")
    names = PRESETS if args.all else [args.instrument or own or "risley"]
    configs = {}
    for name in names:
        args.instrument = name
        configs[name] = build_config(args)
    if args.cuda_arch and any(cfg.run.device != "cpu" for cfg in configs.values()):
        raise InputError("--cuda-arch", args.cuda_arch, "a compile on the CPU (--device cpu)")
    started = time.perf_counter()
    modules = compile_for(target, configs)
    import warp as wp

    if args.cuda_arch:
        from flightsim.core.prebuilt import build_for_cuda, loaded_on_cpu
        from flightsim.core.warp_runtime import compile_ahead
        from flightsim.scenes.build import scene_part

        # what the scenes build with on a GPU only (a forest's voxels) joins the modules built for it
        compile_ahead("cpu", [k for cfg in configs.values() for k in scene_part(cfg.scene).build_kernels("cuda")])
        for arch in args.cuda_arch:
            build_for_cuda(loaded_on_cpu(), arch)

    print(f"{modules} kernel modules of {', '.join(names)} ready in {time.perf_counter() - started:.1f} s "
          f"(Warp's kernel cache: {wp.config.kernel_cache_dir})")
    return 0


def _ship(args: argparse.Namespace) -> int:
    """Remake the prebuilt kernels: each built-in instrument's run compiled in a process of its own (a module's
    identity depends on what its process made before it, so as a run of that instrument would make them), on the
    CPU and for the CUDA archs of the prebuilt set, into one empty kernel cache; then shipped."""
    if not args.all or (args.device or "cpu") != "cpu":
        raise InputError("--ship", "without --all" if not args.all else f"with --device {args.device}",
                         "--all on the CPU (every built-in instrument; the GPU binaries are built without a GPU)")
    import subprocess
    import tempfile

    from flightsim.core.prebuilt import CUDA_ARCHS, ship

    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, tempfile.TemporaryDirectory() as scenes:
        env = dict(os.environ, WARP_CACHE_PATH=tmp, FLIGHTSIM_PREBUILT="0")
        for name, scene, target in PREBUILT_RUNS:
            command = [sys.executable, "-m", "flightsim", "compile", "--device", "cpu", "--instrument", name,
                       *prebuilt_scene_flags(scene, Path(scenes)),
                       "--for", target, *[f"--cuda-arch={arch}" for arch in CUDA_ARCHS]]
            subprocess.run(command, env=env, check=True, capture_output=True)
        (cache,) = [p for p in Path(tmp).iterdir() if p.is_dir()]  # Warp's version folder
        out = ship(cache)
    modules = sum(1 for p in out.iterdir() if p.is_dir())
    print(f"{modules} prebuilt kernel modules of every built-in instrument, four over the forest, GEDI over a point "
          f"cloud, a sweep, a survey, four budgets and the studies of SPAD, ATLAS and Risley (CPU and "
          f"sm_{', sm_'.join(map(str, CUDA_ARCHS))}) "
          f"in {time.perf_counter() - started:.1f} s: {out}")
    return 0


def prebuilt_scene_flags(scene: str | None, folder: Path) -> list[str]:
    """The ``--scene`` flags of a run of :data:`~flightsim.engine.config_io.PREBUILT_RUNS`: none for the instrument's
    own scene, the name of a built-in one, or for "cloud" a small synthetic ALS point cloud written into ``folder``
    (its kernels are those of any cloud: the points' grid, and the waveforms' histogram sized by the instrument)."""
    if scene != "cloud":
        return ["--scene", scene] if scene else []
    from flightsim.studies.bench_shots import WARM_POINTS, write_shots

    folder.mkdir(parents=True, exist_ok=True)
    return ["--scene", str(write_shots(folder / "cloud", WARM_POINTS, 1)[0])]


def _cluster(args: argparse.Namespace, tasks: int):
    """The Dask client of --workers / --scheduler / --gpus (None: run serially), for ``tasks`` tasks."""
    from flightsim.engine.distributed import open_client

    if args.gpus and args.device not in (None, "cuda"):
        raise InputError("--device", args.device, "cuda or nothing with --gpus (each worker runs on its own GPU)")
    if tasks <= 1:  # a single configuration runs serially, here
        return open_client()
    return open_client(args.workers, args.scheduler, args.gpus)


def cmd_sweep(args: argparse.Namespace) -> int:
    if args.gpus and args.device is None:
        args.device = "cuda"
    grid = build_grid(args)
    from flightsim.core.progress import ProgressBar
    from flightsim.studies.sweep import plot_sweep, run_sweep

    started = time.perf_counter()
    with _cluster(args, len(grid.configurations())) as client:
        table = run_sweep(grid, Path(args.out), overwrite=args.overwrite, progress=ProgressBar("sweep"), client=client,
                          batch=args.batch)
    plots = plot_sweep(table, Path(args.out))
    print(f"{len(grid.configurations())} configurations in {time.perf_counter() - started:.1f} s; "
          f"{table} and {len(plots)} plot(s) written")
    return 0


def cmd_survey(args: argparse.Namespace) -> int:
    if args.gpus and args.device is None:
        args.device = "cuda"
    cfg = base_config(args, SURVEY_FLAGS)
    for key, value in set_items(args):
        set_value(cfg, key, value)
    cfg = validate(cfg)
    from flightsim.core.progress import ProgressBar
    from flightsim.studies.survey import parts_folder, run_survey
    from flightsim.studies.survey_plan import SurveySpec, plan_survey

    spec = SurveySpec(size_km=args.size_km, tile_m=args.tile_m, sidelap=args.sidelap, lines=args.lines,
                      segment_m=args.segment_m)
    plan = plan_survey(cfg, spec)
    print(f"survey: {plan.grid.side_m / 1000:g} km × {plan.grid.side_m / 1000:g} km in {plan.grid.n ** 2} tiles, "
          f"{plan.cfg.flight.lines} lines {plan.cfg.flight.line_spacing_m:.1f} m apart, {len(plan.tasks)} tasks, "
          f"{plan.pulses * cfg.fan.array ** 2:,} beams", file=sys.stderr)
    parts = Path(args.parts) if args.parts else None
    folder = parts_folder(Path(args.out), parts)  # a bad --parts stops the command before a cluster starts
    try:
        with _cluster(args, len(plan.tasks)) as client:
            summary = run_survey(plan, Path(args.out), client=client, overwrite=args.overwrite,
                                 progress=ProgressBar("survey"), parts=parts)
    except InputError:
        raise  # refused before a task ran (such as a --out in use): the parts' folder is not this command's
    except BaseException:  # the workers are gone now: what their last tasks wrote does not stay on a RAM disk
        shutil.rmtree(folder, ignore_errors=True)
        raise
    memory = ", ".join(f"{name} {w['peak_rss_mb']:.0f} MiB" for name, w in summary["workers"].items())
    print(f"{summary['points_written']:,} points {summary['points']} in {summary['wall_s']:.1f} s "
          f"({summary['points_per_s']:,} points/s); peak RSS per worker: {memory}; written to {args.out}")
    return 0


def cmd_waveform(args: argparse.Namespace) -> int:
    from flightsim.core.warp_runtime import resolve_device
    from flightsim.studies.waveform import run_one, run_patent

    settings = dict(set_items(args))
    resolve_device(args.device)
    if args.patent:
        if args.instrument != "change1" or args.footprints:
            raise InputError("--patent", "with --instrument/--footprints", "the change1 altimeter over the patent's "
                                                                         "own footprints (no --instrument, --footprints)")
        run_patent(Path(args.out), device=args.device, **settings)
        print((Path(args.out) / "REPORT.md").read_text())
        return 0
    summary = run_one(args.scene, Path(args.out), args.device, args.config, args.overwrite, args.instrument,
                      args.footprints, **settings)
    if "empty" in summary:
        return _nothing_made(summary, args.out)
    print(f"{summary['waveforms']} waveforms ({summary['subray_returns']} sub-ray returns) in {summary['wall_s']:.2f} s; "
          f"written to {args.out}")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from flightsim.calibration.geolocation import Bias
    from flightsim.core.warp_runtime import resolve_device
    from flightsim.studies.spaceborne import run_calibration

    resolve_device(args.device)
    try:
        along, across, rng = (float(v) for v in args.truth.split(","))
    except ValueError:
        raise InputError("--truth", args.truth, "three numbers: pointing along, across track [arcsec], ranging [m]") from None
    if not all(math.isfinite(v) for v in (along, across, rng)) or max(abs(along), abs(across)) > 60 or abs(rng) > 10:
        raise InputError("--truth", args.truth, "finite biases within ±60 arcsec and ±10 m")
    run_calibration(Path(args.out), device=args.device, truth=Bias(along, across, rng))
    print((Path(args.out) / "REPORT.md").read_text())
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    import laspy
    import numpy
    import pyproj
    import warp as wp

    from flightsim.core.warp_runtime import init_warp

    init_warp()
    info = {
        "flightsim": __version__,
        "python": platform.python_version(),
        "warp": wp.__version__,
        "numpy": numpy.__version__,
        "laspy": laspy.__version__,
        "pyproj": pyproj.__version__,
        "devices": [{"name": str(d), "description": getattr(d, "name", str(d))} for d in wp.get_devices()],
        "kernel_cache": wp.config.kernel_cache_dir,
    }
    print(json.dumps(info, indent=2))
    return 0


def make_parser() -> argparse.ArgumentParser:
    """The command line's parser: one subcommand each, in the order ``flightsim --help`` lists them."""
    parser = _Parser(prog="flightsim",
                     description="GPU-first lidar simulator: instruments as parts, scenes, outputs, studies.")
    parser.add_argument("--version", action="version", version=f"flightsim {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    _add_run_commands(sub)
    score.register(sub)
    add_study_commands(sub)
    _add_instrument_commands(sub)
    return parser


def _add_run_commands(sub) -> None:
    """config, simulate, sweep and survey: runs of a config."""
    config = sub.add_parser("config", help="print the resolved config of an instrument, every setting explained "
                                           "(a file to start from: flightsim config --instrument spad > run.toml)")
    _add_config_flags(config)
    config.set_defaults(func=cmd_config)

    sim = sub.add_parser("simulate", help="simulate a flight and write LAS tiles per georeferencing model")
    _add_config_flags(sim)
    sim.add_argument("--out", required=True, help="output directory")
    sim.add_argument("--overwrite", action="store_true", help="replace the run in a non-empty --out")
    sim.set_defaults(func=cmd_simulate)

    comp = sub.add_parser("compile", help="compile the kernels a simulate of the same flags would launch (or of "
                                          "every built-in instrument: --all) into Warp's kernel cache, ahead of the run")
    _add_config_flags(comp)
    comp.add_argument("--all", action="store_true", help="every built-in instrument with its own scene")
    comp.add_argument("--cuda-arch", type=int, action="append", metavar="N",
                      help="also build the CPU run's kernels for CUDA sm_N into the kernel cache, without a GPU (a "
                           "cache to copy to a GPU machine; repeatable)")
    comp.add_argument("--for", dest="target", choices=TARGETS, default="simulate",
                      help="the kernels a run of that command with these flags launches: simulate (default; also "
                           "waveform's), sweep (also paper's), survey, budget, or a study: spad, calibrate, selfcal")
    comp.add_argument("--ship", action="store_true", help="with --all: remake flightsim's prebuilt kernels (CPU and "
                                                          "sm_90, on any machine) rather than fill the kernel cache")
    comp.set_defaults(func=cmd_compile)

    sweep = sub.add_parser("sweep", help="plane-fit RMS over a grid of configurations (no LAS written)")
    _add_config_flags(sweep, SWEEP_FLAGS)
    for flag, dest, _key, help_text in SWEEP_AXES:
        sweep.add_argument(flag, dest=dest, help=help_text)
    sweep.add_argument("--out", required=True, help="output directory (rerun the same command to resume)")
    sweep.add_argument("--overwrite", action="store_true", help="discard the finished rows in --out")
    _add_cluster_flags(sweep)
    sweep.add_argument("--batch", type=int, default=1, help="configurations per task on a cluster (default 1)")
    sweep.set_defaults(func=cmd_sweep)

    survey = sub.add_parser("survey", help="a large survey over a tiled scene, split into tasks (on a Dask cluster)")
    _add_config_flags(survey, SURVEY_FLAGS)
    survey.add_argument("--size-km", type=float, default=5.0, help="side of the square survey area [km] (default 5)")
    survey.add_argument("--tile-m", type=int, default=1000, help="side of a scene tile [m] (default 1000)")
    survey.add_argument("--sidelap", type=float, default=0.3, help="swath overlap of neighbouring lines (default 0.3)")
    survey.add_argument("--lines", type=int, default=0, help="flight lines (default 0: enough to cover the area)")
    survey.add_argument("--segment-m", type=float, default=1000.0,
                        help="along-track length of a task [m] (default 1000)")
    survey.add_argument("--out", required=True, help="output directory: <model>/<tile>.las, run.toml, survey.json")
    survey.add_argument("--parts", help="an existing folder, reached by every worker, for the tasks' part files "
                                        "(default: under --out); on one machine a RAM disk such as /dev/shm keeps "
                                        "them off the disk altogether")
    survey.add_argument("--overwrite", action="store_true", help="replace the survey in a non-empty --out")
    _add_cluster_flags(survey)
    survey.set_defaults(func=cmd_survey)


def _add_instrument_commands(sub) -> None:
    """waveform and calibrate (the altimeters' studies), and info."""
    waveform = sub.add_parser("waveform", help="full-waveform echoes of the large-footprint lunar altimeter "
                                               "(the change1 preset) or of GEDI (--instrument gedi)")
    waveform.add_argument("--scene", default="flat", help="flat (default), slope, bump, or PATH.obj / PATH.ply / "
                                                          "PATH.las / PATH.laz")
    waveform.add_argument("--instrument", default="change1", help="change1 (default) or gedi (writes l2a.h5 too)")
    waveform.add_argument("--footprints", help="CSV of footprint centres (columns x, y in the scene's CRS, optional "
                                               "delta_time): one nadir pulse at each (flight.platform = shots)")
    waveform.add_argument("--patent", action="store_true", help="the patent's Figs. 3-5 with REPORT.md")
    waveform.add_argument("--config", help="run config TOML over the instrument's preset")
    waveform.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    waveform.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a config field")
    waveform.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    waveform.add_argument("--out", required=True, help="output directory")
    waveform.set_defaults(func=cmd_waveform)

    calibrate = sub.add_parser("calibrate", help="corner-cube calibration of the spaceborne altimeter's pointing "
                                                 "and ranging on simulated passes (the atlas preset)")
    calibrate.add_argument("--truth", default="3,-2,0.25",
                           help="injected pointing along, across track [arcsec] and ranging bias [m]")
    calibrate.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    calibrate.add_argument("--out", required=True, help="directory for REPORT.md, calibration.json and figures")
    calibrate.set_defaults(func=cmd_calibrate)

    info = sub.add_parser("info", help="versions, devices and the kernel cache")
    info.set_defaults(func=cmd_info)


def main(argv: list[str] | None = None) -> int:
    args = make_parser().parse_args(argv)
    mark("cli")
    try:
        return args.func(args)
    except InputError as exc:
        print(f"flightsim: error: {exc}", file=sys.stderr)
        return EXIT_INVALID
    except KeyboardInterrupt:
        print("flightsim: interrupted", file=sys.stderr)
        return 130
