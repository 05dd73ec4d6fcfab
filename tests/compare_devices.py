"""Run the same simulations on two Warp devices and compare every point (SPEC: CPU and GPU agree
to 1 mm).

    python3 tests/compare_devices.py --out DIR [--devices cpu,cuda:0] [--quick]

Writes DIR/cpu_vs_gpu.json: the two devices (Warp name and hardware description) and, per case
and georeferencing model, the number of points on each device, how many were matched by
(flight line, pulse, beam), the returns found on one device only, and the maximum, median, 99th
and 99.9th percentile distances between matched points [m]. Without CUDA the second device is
the CPU again, so the script also runs (as a determinism check) on a machine without a GPU.
Exit status 0 when every matched point agrees within 1 mm and no return is found on one device
only, 1 otherwise.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flightsim.engine.config import RunConfig, set_value, validate  # noqa: E402
from flightsim.engine.world import build_scene, flight_trajectories  # noqa: E402
from flightsim.engine.tracer import Tracer  # noqa: E402
from flightsim.core.warp_runtime import init_warp  # noqa: E402
from flightsim.engine.readouts.points import Points

TOLERANCE_M = 1e-3
CASES = {  # name: settings; the quick set is the first two at a tenth of the duration
    "calibration_500m_3x3": {"flight.altitude_m": 500.0, "flight.duration_s": 10.0},
    "plane_5000m_3x3_far_north": {"scene.name": "plane", "scene.crs": "EPSG:32633",
                                  "scene.origin": [500000.0, 7000000.0, 120.0], "flight.altitude_m": 5000.0,
                                  "flight.duration_s": 5.0, "flight.roll_deg": 2.0, "flight.heading_deg": 30.0},
    "calibration_1000m_8x8_noise": {"flight.altitude_m": 1000.0, "fan.array": 8, "flight.duration_s": 5.0,
                                    "instrument.errors": ["ranging"], "ranging.noise_m": 0.05,
                                    "run.seed": 7},
    "calibration_500m_3x3_two_lines_float32": {"flight.lines": 2, "flight.duration_s": 5.0, "run.optics": "float32"},
}


def config(settings: dict, device: str, quick: bool) -> RunConfig:
    cfg = RunConfig()
    for key, value in settings.items():
        set_value(cfg, key, value)
    if quick:
        set_value(cfg, "flight.duration_s", cfg.flight.duration_s / 10.0)
    set_value(cfg, "run.device", device)
    return validate(cfg)


def simulate(cfg: RunConfig) -> tuple[dict[str, dict[tuple, np.ndarray]], dict]:
    """{model: {(line, pulse, beam): world point}} and the run's counts."""
    scene = build_scene(cfg)
    simulator = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    keys, points = [], {model: [] for model in simulator.models}

    def consume(chunk):
        keys.append(np.column_stack([np.full(len(chunk), chunk.line_id), chunk.pulse, chunk.beam]))
        for model in simulator.models:
            points[model].append(scene.local_to_world(chunk.points[model]))

    started = time.perf_counter()
    counts = simulator.run(Points(), consume)
    wall = time.perf_counter() - started
    keys = np.concatenate(keys) if keys else np.zeros((0, 3), dtype=np.int64)
    out = {model: (keys, np.concatenate(p) if p else np.zeros((0, 3))) for model, p in points.items()}
    return out, {"pulses": counts.pulses, "returns": counts.returns, "tir_dropped": counts.tir_dropped,
                 "misses": counts.misses, "wall_s": round(wall, 3)}


def compare(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> dict:
    """Distances between the points of two runs matched by (line, pulse, beam)."""
    (keys_a, xyz_a), (keys_b, xyz_b) = a, b
    code = lambda k: (k[:, 0].astype(np.int64) << 48) | (k[:, 1].astype(np.int64) << 12) | k[:, 2]  # noqa: E731
    _, ia, ib = np.intersect1d(code(keys_a), code(keys_b), assume_unique=True, return_indices=True)
    distance = np.linalg.norm(xyz_a[ia] - xyz_b[ib], axis=1)
    stats = {f"{name}_m": float(np.percentile(distance, q)) if len(distance) else None
             for name, q in (("p50", 50), ("p99", 99), ("p999", 99.9))}
    return {
        "points_a": len(keys_a), "points_b": len(keys_b), "matched": len(ia),
        "only_a": len(keys_a) - len(ia), "only_b": len(keys_b) - len(ib),
        "max_m": float(distance.max()) if len(distance) else None, **stats,
        "within_1mm": bool(len(ia) == len(keys_a) == len(keys_b) and (distance <= TOLERANCE_M).all()),
    }


def describe(device: str) -> dict:
    import warp as wp

    d = wp.get_device(device)
    name = platform.processor() or platform.machine() if d.is_cpu else d.name
    return {"warp": device, "hardware": name}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="output directory for cpu_vs_gpu.json")
    parser.add_argument("--devices", help="two Warp devices, comma-separated (default: cpu and cuda:0 if present)")
    parser.add_argument("--quick", action="store_true", help="the first two cases at a tenth of their duration")
    args = parser.parse_args(argv)
    init_warp()
    import warp as wp

    if args.devices:
        devices = [d.strip() for d in args.devices.split(",")]
    else:
        devices = ["cpu", "cuda:0" if wp.get_cuda_device_count() else "cpu"]
    if len(devices) != 2:
        parser.error("--devices takes exactly two devices")
    cases = list(CASES.items())[:2] if args.quick else list(CASES.items())
    report = {"devices": {"a": describe(devices[0]), "b": describe(devices[1])}, "tolerance_m": TOLERANCE_M,
              "quick": args.quick, "cases": {}}
    for name, settings in cases:
        runs = [simulate(config(settings, device, args.quick)) for device in devices]
        report["cases"][name] = {
            "settings": settings,
            "counts": {"a": runs[0][1], "b": runs[1][1]},
            "models": {model: compare(runs[0][0][model], runs[1][0][model]) for model in runs[0][0]},
        }
        print(name, {m: r["max_m"] for m, r in report["cases"][name]["models"].items()}, flush=True)
    report["within_1mm"] = all(r["within_1mm"] for case in report["cases"].values() for r in case["models"].values())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cpu_vs_gpu.json").write_text(json.dumps(report, indent=2) + "\n")
    return 0 if report["within_1mm"] else 1


if __name__ == "__main__":
    sys.exit(main())
