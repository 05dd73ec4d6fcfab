"""The study commands of the command line: paper, selfcal, bench, profile, budget, spad and forest (the studies
that reproduce a paper, measure the simulator or give a scene's truth); :mod:`flightsim.cli` adds them."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from flightsim.core.errors import InputError


def set_items(args: argparse.Namespace) -> list[tuple[str, str]]:
    """The ``--set KEY=VALUE`` pairs of a command line, each split and stripped."""
    items = []
    for item in args.set or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise InputError("--set", item, "KEY=VALUE, e.g. risley.refractive_index=1.45")
        items.append((key.strip(), value.strip()))
    return items


def cmd_paper(args: argparse.Namespace) -> int:
    from flightsim.studies.paper import reproduce
    from flightsim.core.warp_runtime import resolve_device

    resolve_device(args.device)
    report = reproduce(Path(args.out), device=args.device, overwrite=args.overwrite)
    print(report.read_text())
    return 0


def cmd_selfcal(args: argparse.Namespace) -> int:
    from flightsim.studies.selfcal_report import run_selfcal
    from flightsim.core.warp_runtime import resolve_device

    resolve_device(args.device)
    results = run_selfcal(Path(args.out), device=args.device, quick=args.quick, progress=lambda r: print(
        f"{r['array']}×{r['array']} at {r['altitude_m'] / 1000:g} km from the {r['start']} values: RMS {r['rms_m']['nominal_believed']:.4f} → "
        f"{r['rms_m']['exact_selfcal']:.4f} m ({r['wall_s']:.0f} s)", file=sys.stderr))
    print(f"self-calibration report in {args.out}/REPORT.md ({results['wall_s']:.0f} s)")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from flightsim.studies.bench import SECTIONS, run_bench
    from flightsim.core.warp_runtime import resolve_device

    resolve_device(args.device)
    sections = tuple(args.sections.split(",")) if args.sections else SECTIONS
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        raise InputError("--sections", args.sections, "a comma-separated subset of " + ",".join(SECTIONS))
    run_bench(args.device, args.quick, Path(args.out), sections)
    print((Path(args.out) / "bench.md").read_text())
    return 0


def cmd_profile(args: argparse.Namespace) -> int:
    from flightsim.studies.profile import WORKLOADS, run_profile

    names = tuple(args.workloads.split(",")) if args.workloads else WORKLOADS
    if set(names) - set(WORKLOADS):
        raise InputError("--workloads", args.workloads, "a comma-separated subset of " + ",".join(WORKLOADS))
    run_profile(args.device, args.quick, Path(args.out), names, ncu=args.ncu)
    print((Path(args.out) / "profile.md").read_text())
    return 0


def cmd_budget(args: argparse.Namespace) -> int:
    from flightsim.core.warp_runtime import resolve_device
    from flightsim.studies.budget_catalog import run_any

    resolve_device(args.device)
    run_any(args.instrument, Path(args.out), args.device, args.draws, args.columns, args.seed, args.sources)
    print((Path(args.out) / "REPORT.md").read_text())
    return 0


def cmd_spad(args: argparse.Namespace) -> int:
    from flightsim.core.warp_runtime import resolve_device
    from flightsim.studies.spad import run_spad

    resolve_device(args.device)
    if args.pulses is not None and not 100 <= args.pulses <= 43000:
        raise InputError("--pulses", args.pulses, "an integer in [100, 43000]")
    if args.reference == "tls":
        from flightsim.studies.spad_tls_run import run_tls

        run_tls(Path(args.out), device=args.device, pulses=args.pulses)
        print((Path(args.out) / "tls" / "REPORT.md").read_text())
        return 0
    run_spad(Path(args.out), device=args.device, pulses=args.pulses)
    print((Path(args.out) / "REPORT.md").read_text())
    return 0


def cmd_forest(args: argparse.Namespace) -> int:
    if args.report:
        from flightsim.studies.forest_report import run_forest_report

        results = run_forest_report(Path(args.out), args.device)
        print(f"forest report in {args.out}/REPORT.md ({results['wall_s']:.0f} s)")
        return 0
    from flightsim.studies.forest_truth import run_forest

    summary = run_forest(Path(args.out), set_items(args), seed=args.seed, chm_cell_m=args.chm_cell_m,
                         device=args.device)
    print(f"{summary['stems']} trees, LAI {summary['lai_achieved']:.3f} (target {summary['lai_target']:g}), "
          f"canopy cover {summary['canopy_cover']:.3f}; {', '.join(summary['files'])} written to {args.out}")
    return 0


def add_study_commands(sub) -> None:
    """paper, spad, forest and selfcal (the studies that reproduce a paper or give a scene's truth), then bench,
    profile and budget (those that measure the simulator or an instrument)."""
    _add_measurement_commands(sub)
    paper = sub.add_parser("paper", help="reproduce the seed paper's study: sweeps, figures and a report")
    paper.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    paper.add_argument("--out", required=True, help="output directory (e.g. results/paper)")
    paper.add_argument("--overwrite", action="store_true", help="recompute finished sweeps")
    paper.set_defaults(func=cmd_paper)

    spad = sub.add_parser("spad", help="the small-body SPAD lidar's experiments: MODE-A, MODE-B, laser power")
    spad.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    spad.add_argument("--pulses", type=int, help="pulses per frame (default: the paper's 43,000; fewer for a quick run)")
    spad.add_argument("--reference", choices=("mesh", "tls"), default="mesh",
                      help="mesh (default): score against the true surface; tls: against a simulated VZ-2000 scan "
                           "registered by total station, as the paper did (writes OUT/tls/)")
    spad.add_argument("--out", required=True, help="directory for REPORT.md and spad.json")
    spad.set_defaults(func=cmd_spad)

    forest = sub.add_parser("forest", help="truth of a procedural forest stand: canopy height model, trees, leaf "
                                           "area voxels (chm.tif, trees.csv, canopy.npz, forest.json)")
    forest.add_argument("--set", action="append", metavar="KEY=VALUE",
                        help="a [scene] setting of the forest, e.g. --set scene.forest_lai=4 (repeatable)")
    forest.add_argument("--seed", type=int, help="random seed of the stand (default 0)")
    forest.add_argument("--chm-cell-m", type=float, default=1.0, help="cell of the canopy height model [m] (default 1)")
    forest.add_argument("--report", action="store_true", help="check the forests against closed forms, a float64 "
                        "implementation and the stand's truth instead: REPORT.md, forest_report.json, a figure")
    forest.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N: where the leaf voxels are "
                        "integrated (as a flight on it does, so the two share them), or the report's runs")
    forest.add_argument("--out", required=True, help="directory for the four files (or the report)")
    forest.set_defaults(func=cmd_forest)
    selfcal = sub.add_parser("selfcal", help="Risley self-calibration (n, apex, encoder offset, boresight) from blind "
                                             "planes: RMS before and after, recovered parameters (REPORT.md, JSON)")
    selfcal.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    selfcal.add_argument("--quick", action="store_true", help="one configuration (3×3 at 1 km) instead of the grid")
    selfcal.add_argument("--out", required=True, help="output directory (e.g. results/paper/selfcal)")
    selfcal.set_defaults(func=cmd_selfcal)


def _add_measurement_commands(sub) -> None:
    """bench, profile and budget."""
    bench = sub.add_parser("bench", help="measure throughput, run time against error, and savings")
    bench.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    bench.add_argument("--quick", action="store_true", help="small sizes (under a minute on a CPU)")
    bench.add_argument("--sections", help="comma-separated subset of throughput,stages,study,las,skip,pareto,galvo,"
                       "spad,waveform,scale,reduce,survey,forest,startup,ranging,gpus,photons (default: all)")
    bench.add_argument("--out", required=True, help="directory for bench.json, bench.md, pareto.csv/png")
    bench.set_defaults(func=cmd_bench)

    profile = sub.add_parser("profile", help="where each workload's device time goes: per kernel GPU time, "
                                             "registers, occupancy, idle time")
    profile.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    profile.add_argument("--quick", action="store_true", help="small sizes")
    profile.add_argument("--workloads", help="comma-separated subset (default: all)")
    profile.add_argument("--ncu", action="store_true", help="also Nsight Compute's counters (ncu on the PATH)")
    profile.add_argument("--out", required=True, help="directory for profile.json and profile.md (records of other workloads there are kept)")
    profile.set_defaults(func=cmd_profile)

    budget = sub.add_parser("budget", help="full-link error budget of an instrument: change3 (the galvo imager, "
                                           "seed paper §2-§3) or risley (the airborne DOE-array instrument)")
    budget.add_argument("--instrument", default="change3", help="change3 (default), risley, spad, change1 or atlas")
    budget.add_argument("--sources", help="spad, change1, atlas: a comma-separated subset of the error sources")
    budget.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    budget.add_argument("--draws", type=int, help="Monte Carlo draws (change3, risley: default 200) or shots per "
                        "source (spad 256, change1 100, atlas 20000)")
    budget.add_argument("--columns", type=int, help="pulses per strip (default: the instrument's 256)")
    budget.add_argument("--seed", type=int, default=0, help="random seed of the draws (default 0)")
    budget.add_argument("--out", required=True, help="directory for REPORT.md, budget.json, deviation_maps.png")
    budget.set_defaults(func=cmd_budget)
