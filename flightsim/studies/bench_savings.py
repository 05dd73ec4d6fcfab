"""`flightsim bench` sections of what skipped work saves and of run time against error (each speed knob against a
float64 reference of the same pipeline)."""
from __future__ import annotations

import time

from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.config import RunConfig, copy_config, set_value, validate
from flightsim.engine.meshes import SceneMeshes
from flightsim.engine.readouts.points import Points
from flightsim.engine.readouts.statistics import run_statistics
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, edge_buffer_m, flight_trajectories
from flightsim.studies.bench_common import simulator, Sizes, timed_statistics, workload


def skipping(device: str, s: Sizes) -> list[dict]:
    """Measured savings of each kind of skipped work."""
    cfg = workload(device, 3, s.pareto_returns)
    rows = [_culling_saving(cfg), _mode_saving(cfg), _build_once_saving(cfg)]
    both = timed_statistics(simulator(cfg))[0]
    for label, settings in (("exact model only", {"output.models": "exact"}),
                            ("nominal model only", {"output.models": "nominal"}),
                            ("edge buffer off", {"scoring.edge_buffer_m": 0.0}),
                            ("range noise on (0.02 m)", {"instrument.errors": "ranging", "ranging.noise_m": 0.02})):
        wall = timed_statistics(simulator(workload(device, 3, s.pareto_returns, **settings)))[0]
        rows.append({"what": label, "baseline_s": both, "variant_s": wall, "saving": 1 - wall / both})
    return rows


def _culling_saving(cfg: RunConfig) -> dict:
    scene = build_scene(cfg)  # sized for the nominal flight
    long = _with(cfg, {"flight.duration_s": 4 * cfg.flight.duration_s})
    walls = {}
    for cull in (True, False):
        run_cfg = _with(long, {"run.cull": cull})
        sim = Tracer(run_cfg, scene, flight_trajectories(run_cfg, scene), edge_buffer_m=edge_buffer_m(run_cfg))
        walls[cull], counts = timed_statistics(sim, repeats=1)
        if cull:
            culled = counts.pulses_culled / (counts.pulses + counts.pulses_culled)
    return {"what": f"culling a line 4x longer than the scene ({100 * culled:.0f}% of pulses culled)",
            "baseline_s": walls[False], "variant_s": walls[True], "saving": 1 - walls[True] / walls[False]}


def _with(cfg: RunConfig, settings: dict) -> RunConfig:
    """A validated copy of ``cfg`` with ``settings`` ({table.field: value}) set."""
    out = copy_config(cfg)
    for key, value in settings.items():
        set_value(out, key, value)
    return validate(out)


def _mode_saving(cfg: RunConfig) -> dict:
    sim = simulator(cfg)
    sim.run(Points(), lambda chunk: None)
    started = time.perf_counter()
    counts = sim.run(Points(), lambda chunk: None)
    points_wall = time.perf_counter() - started
    stats_wall, _ = timed_statistics(sim, repeats=1)
    per_return = 8 + 4 * 4 + 4 + 12 * len(sim.models) + 4  # slot, range, face, angle, cos, edge, points, flags
    return {"what": f"statistics mode instead of points mode ({per_return} B/return to the host vs "
                    f"{len(sim.scene.planes) * 2 * 80} B per run)",
            "baseline_s": points_wall, "variant_s": stats_wall, "saving": 1 - stats_wall / points_wall,
            "returns": counts.returns}


def _build_once_saving(cfg: RunConfig, rounds: int = 2) -> dict:
    """A 5-configuration sweep with the scene, BVH and kernels built once vs per configuration: the two in turn,
    ``rounds`` times, the best of each (the first round also pays each way's first-use costs, which a single
    timing of each charged to whichever ran first)."""
    configs = [_with(cfg, {"flight.altitude_m": a}) for a in (500.0, 600.0, 700.0, 800.0, 900.0)]
    extent_cfg = configs[-1]

    def shared() -> None:
        meshes = SceneMeshes(build_scene(extent_cfg), resolve_device(cfg.run.device))
        for c in configs:
            run_statistics(simulator(c, meshes))

    def rebuilt() -> None:
        for c in configs:
            scene = build_scene(extent_cfg)
            run_statistics(Tracer(c, scene, flight_trajectories(c, scene), edge_buffer_m=edge_buffer_m(c)))

    best = {shared: float("inf"), rebuilt: float("inf")}
    for _ in range(rounds):
        for way in best:
            started = time.perf_counter()
            way()
            best[way] = min(best[way], time.perf_counter() - started)
    return {"what": f"scene + BVH built once for a 5-configuration sweep (kernels are cached per process; best of "
                    f"{rounds}, the two in turn)",
            "baseline_s": best[rebuilt], "variant_s": best[shared], "saving": 1 - best[shared] / best[rebuilt]}


def knob_variants(kind: str, quick: bool) -> list[tuple[str, str, dict]]:
    """(knob, value, config settings) for the run-time-against-error study."""
    variants = [("optics", v, {"run.optics": v}) for v in ("float64", "float32")]
    variants += [("optics", f"lut{m}", {"run.optics": "lut", "run.lut_samples": m})
                 for m in ((1024,) if quick else (256, 1024, 4096, 16384))]
    if quick:
        return variants
    constructors = ("sah", "median") + (("lbvh", "cubql") if kind == "cuda" else ())  # lbvh/cubql: GPU only
    variants += [("bvh", f"{c}/leaf{leaf or 'default'}", {"run.bvh": c, "run.bvh_leaf_size": leaf})
                 for c in constructors for leaf in (0, 1, 2, 4)]
    slots = (1 << 16, 1 << 18, 1 << 20) + ((1 << 22, 1 << 24) if kind == "cuda" else ())
    variants += [("chunk", f"{n} slots", {"run.chunk_pulses": n // 9}) for n in slots]
    variants += [("slots_per_thread", f"{n}", {"run.slots_per_thread": n}) for n in (1, 4, 16, 64, 256)]
    if kind == "cuda":  # a register cap only exists for CUDA kernels; 255 = no cap
        variants += [("max_registers", f"{n}", {"run.max_registers": n}) for n in (48, 64, 96, 255)]
    return variants


def _knob_costs(device: str, s: Sizes, settings: dict) -> dict:
    """Wall time of the throughput workload and largest errors at 0.5 and 5 km for one knob setting."""
    from flightsim.studies.accuracy import measure_errors

    cfg = workload(device, 3, s.pareto_returns, **settings)
    wall, counts = timed_statistics(simulator(cfg))
    pointing, point = 0.0, 0.0
    for altitude in (500.0, 5000.0):
        check_cfg = workload(device, 3, 5e4 if s.quick else 2e5, **{**settings, "flight.altitude_m": altitude})
        errors = measure_errors(simulator(check_cfg, with_truth=True))
        pointing = max(pointing, errors.max_pointing_rad)
        point = max([point, *errors.max_point_error_m.values()])
    return {"wall_s": wall, "returns_per_s": counts.returns / wall, "max_pointing_urad": pointing * 1e6,
            "max_point_error_mm": point * 1e3}


def pareto(device: str, s: Sizes) -> list[dict]:
    """Wall time and largest errors against the float64 reference for each knob setting."""
    rows = []
    kind = "cpu" if resolve_device(device) == "cpu" else "cuda"
    for knob, value, settings in knob_variants(kind, s.quick):
        row = {"device": resolve_device(device), "knob": knob, "value": value}
        try:
            row.update(_knob_costs(device, s, settings))
        except Exception as exc:  # an experimental constructor may be unavailable: record it and go on
            row["error"] = f"{type(exc).__name__}: {exc}"[:200]
        rows.append(row)
    return rows
