"""`flightsim bench` section forest, GEDI shots: the GEDI simulator's own use end to end, a list of footprint centres
over an airborne point cloud (`flightsim waveform --instrument gedi --scene CLOUD.las --footprints SHOTS.csv`), in a
fresh process as a user runs it: its wall, peak memory and stages (summary.json)."""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from flightsim.core.warp_runtime import resolve_device
from flightsim.instrument.cloud_waveform_model import synthetic_forest
from flightsim.studies.bench_common import run_measured

EDGE_M = 30.0  # footprints keep this far inside the cloud's bounding box [m] (3 σ_f is 16.5 m)
WARM_POINTS, WARM_FOOTPRINTS = 100_000, 20  # the first run's cloud (compiles the kernels, fills the caches)


def cloud_shots(device: str, points: int, footprints: int) -> dict:
    """The command over a synthetic forest of ``points`` (:func:`synthetic_forest`, written as LAS 1.4) and
    ``footprints`` random centres, ``waveform.processing = "device"``, after one over a small cloud."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        _shots_run(device, *write_shots(folder / "warm", WARM_POINTS, WARM_FOOTPRINTS)[:2], folder / "warm_out")
        cloud, shots, written = write_shots(folder / "cloud", points, footprints)
        record = _shots_run(device, cloud, shots, folder / "out")
    return {"points": written, "footprints": footprints, **record}


def write_shots(stem: Path, points: int, footprints: int, seed: int = 3) -> tuple[Path, Path, int]:
    """(``stem``.las, ``stem``.csv, the points written): a synthetic forest of about ``points`` in world coordinates
    (LAS 1.4, point format 6, 1 mm scale, the cloud's CRS) and ``footprints`` centres (x, y, delta_time) uniform
    over its box less EDGE_M."""
    import laspy

    cloud = synthetic_forest(points, seed=1)
    world = cloud.xyz + cloud.origin
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales, header.offsets = [0.001] * 3, np.floor(world.min(axis=0))
    header.add_crs(cloud.crs)
    las = laspy.LasData(header)
    las.x, las.y, las.z = world[:, 0], world[:, 1], world[:, 2]
    las.classification = cloud.classification
    las.return_number, las.number_of_returns = cloud.return_number, cloud.number_of_returns
    las.write(str(stem.with_suffix(".las")))
    low, high = world.min(axis=0)[:2] + EDGE_M, world.max(axis=0)[:2] - EDGE_M
    xy = np.random.default_rng(seed).uniform(low, high, (footprints, 2))
    rows = [f"{x!r},{y!r},{1.0e8 + 0.01 * i!r}" for i, (x, y) in enumerate(xy.tolist())]
    stem.with_suffix(".csv").write_text("x,y,delta_time\n" + "\n".join(rows) + "\n")
    return stem.with_suffix(".las"), stem.with_suffix(".csv"), len(world)


def _shots_run(device: str, cloud: Path, shots: Path, out: Path) -> dict:
    command = [sys.executable, "-m", "flightsim", "waveform", "--instrument", "gedi", "--scene", str(cloud),
               "--footprints", str(shots), "--device", resolve_device(device), "--set", "waveform.processing=device",
               "--out", str(out)]
    wall, code, peak_mib, _ = run_measured(command)
    if code != 0:
        raise RuntimeError(f"the GEDI shots benchmark run failed: {' '.join(command)}")
    summary = json.loads((out / "summary.json").read_text())
    return {"wall_s": wall, "peak_rss_mib": peak_mib, "waveforms": summary["waveforms"],
            "stages_s": summary["stages_s"], "footprints_per_s": summary["waveforms"] / wall}
