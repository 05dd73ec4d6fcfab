"""`flightsim forest --report`: the forest scenes and detectors checked against closed forms, an independent float64
implementation and the procedural forest's truth, into ``REPORT.md`` and ``forest_report.json``.

1. A homogeneous turbid layer of leaf area index L over flat ground: the fraction of 10⁶ photons that reach the
   ground through the device's voxel walk against exp(−G L / cos θ), and the mean height of their first interactions
   against the closed form top − μ (1/κ − D e^{−κD} / (1 − e^{−κD})) (κ = G u, D = H / μ the slant depth), at nadir
   and 20°, spherical and planophile leaves.
2. Large-footprint waveforms from a point cloud on the device against the float64 NumPy model of the same method
   (the GEDI simulator's) at 200 footprints of a synthetic forest: correlation, rh50, rh98, ground.
3. The procedural forest (default stand, seed 0): discrete first returns from the canopy against its true canopy
   cover; GEDI rh98 against the true top height under each footprint; ATL08 h_canopy against the CHM under each
   100 m segment.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import warp as wp

from flightsim.core.atomic import replaced_atomically, write_atomic
from flightsim.core.warp_runtime import resolve_device
from flightsim.engine.config import set_value, validate
from flightsim.engine.config_io import preset_config
from flightsim.engine.readouts.points import Points
from flightsim.engine.tracer import Tracer
from flightsim.engine.world import build_scene, flight_trajectories
from flightsim.instrument.pairs import SINGLE_BEAM
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.leaf_angles import g_function
from kernels import canopy as kc

LAYER = {"bottom_m": 5.0, "top_m": 25.0, "lai": 3.0}  # the homogeneous layer of section 1
MC_PHOTONS = 1_000_000


def turbid_layer(device: str, seed: int = 0) -> list[dict]:
    """Section 1: per (zenith, leaf angles), the transmitted fraction and the mean interaction height of
    ``MC_PHOTONS`` photons through the layer on the device, beside their closed forms."""
    d = resolve_device(device)
    bottom, top, lai = LAYER["bottom_m"], LAYER["top_m"], LAYER["lai"]
    lad = np.zeros((1, 1, int(top)), np.float32)
    lad[:, :, int(bottom):int(top)] = lai / (top - bottom)
    rows, rng = [], np.random.default_rng(seed)
    for leaves in ("spherical", "planophile"):
        canopy = VoxelCanopy(lad, np.array([-1e6, -1e6, 0.0]), np.array([2e6, 2e6, 1.0]), leaf_angles=leaves)
        for zenith in (0.0, 20.0):
            mu = math.cos(math.radians(zenith))
            direction = np.array([math.sin(math.radians(zenith)), 0.0, -mu])
            start = np.array([0.0, 0.0, top + 1.0]) - 0.0 * direction
            hits = _interactions(canopy.to_device(d), start, direction, (top + 1.0) / mu, rng, d)
            g = float(g_function(leaves, np.array([mu]))[0])
            kappa, depth = g * lai / (top - bottom), (top - bottom) / mu
            through = math.exp(-kappa * depth)
            heights = (top + 1.0) - hits[np.isfinite(hits)] * mu
            mean_depth = 1.0 / kappa - depth * through / (1.0 - through)
            fraction = float(np.mean(~np.isfinite(hits)))
            rows.append({"leaf_angles": leaves, "zenith_deg": zenith, "G": g, "photons": len(hits),
                         "transmitted": fraction, "exp(-GL/mu)": through,
                         "relative_error": fraction / through - 1.0,
                         "binomial_sigma": math.sqrt(through * (1.0 - through) / len(hits)) / through,
                         "mean_height_m": float(heights.mean()), "closed_form_height_m": top - mean_depth * mu,
                         "height_sigma_m": float(heights.std() / math.sqrt(len(heights)))})
    return rows


def _interactions(canopy, start: np.ndarray, direction: np.ndarray, t_end: float, rng, device: str) -> np.ndarray:
    n = MC_PHOTONS
    starts = wp.array(np.tile(start, (n, 1)), dtype=wp.vec3d, device=device)
    directions = wp.array(np.tile(direction, (n, 1)), dtype=wp.vec3d, device=device)
    xi = wp.array(rng.random(n), dtype=wp.float64, device=device)
    out = wp.empty(n, dtype=wp.float64, device=device)
    wp.launch(kc.interactions, n, inputs=[canopy, starts, directions, t_end, xi], outputs=[out], device=device)
    return out.numpy()


def cloud_waveforms_against_model(device: str, footprints: int = 200) -> dict:
    """Section 2: the device's point-cloud waveforms against the float64 model at ``footprints`` footprints of a
    synthetic forest of 2e5 points."""
    from flightsim.engine.cloud_waveforms import cloud_waveforms
    from flightsim.instrument.cloud_waveform_model import (CloudBeam, model_waveforms, synthetic_forest,
                                                            waveform_metrics)

    cloud = synthetic_forest(200_000, seed=2)
    low, high = cloud.bounds()
    centres = np.random.default_rng(5).uniform(low[:2] + 15.0, high[:2] - 15.0, (footprints, 2))
    z_top, beam, dt, samples = float(high[2]) + 5.0, CloudBeam(), 1.0e-9, 600
    args = (cloud, centres, z_top, 0.0, dt, samples, beam)
    started = time.perf_counter()
    ours = cloud_waveforms(*args, device=device)
    ours_s = time.perf_counter() - started
    started = time.perf_counter()
    ref = model_waveforms(*args)
    ref_s = time.perf_counter() - started
    heights = z_top - (np.arange(samples) + 0.5) * dt * 299792458.0 / 2.0  # nadir: height of each sample
    m_ours = waveform_metrics(ours["rx"], ours["ground"], heights)
    m_ref = waveform_metrics(ref["rx"], ref["ground"], heights)
    corr = [np.corrcoef(a, b)[0, 1] for a, b in zip(ours["rx"].astype(np.float64), ref["rx"]) if b.any()]
    return {"footprints": footprints, "points": len(cloud), "min_correlation": float(min(corr)),
            **{f"max_abs_{k}_m": float(np.nanmax(np.abs(m_ours[k] - m_ref[k]))) for k in ("rh50", "rh98", "ground_z")},
            "device_s": ours_s, "numpy_s": ref_s}


def first_return_cover(device: str, seed: int = 0, voxel_m: float = 1.0) -> dict:
    """Section 3a: the share of first returns that come from the crowns (leaves, or stems) against the stand's true
    canopy cover (the union of its crowns' vertical projections) and against the cover of its leaf voxels (the share
    of those first returns' positions whose voxel column holds leaves), over beams landing inside the stand: a
    nadir-looking discrete profiler flown in 20 lines 10 m apart over the default procedural forest, its crowns in
    voxels of ``voxel_m``."""
    from flightsim.scenes.forest_scene import stand
    from flightsim.studies.forest_truth import canopy_cover

    cfg = preset_config("risley")
    for key, value in {"scene.name": "forest", "scene.forest_voxel_m": voxel_m, "instrument.deflector": "fixed",
                       "fan.array": 1, "fixed.prf_hz": 2000.0, "flight.duration_s": 4.0, "flight.lines": 20,
                       "flight.line_spacing_m": 10.0, "run.seed": seed, "output.models": ["exact"],
                       "run.device": device}.items():
        set_value(cfg, key, value)
    cfg = validate(cfg)
    scene = build_scene(cfg)
    chunks = []
    Tracer(cfg, scene, flight_trajectories(cfg, scene), with_truth=True).run(Points(), consume=chunks.append)
    trees, leaves = stand(cfg.scene, seed), scene.canopy
    first = np.concatenate([c.return_number for c in chunks]) == 1
    local = np.concatenate([c.true_points for c in chunks])[first]
    inside = np.all(np.abs(local[:, :2]) < trees.size_m / 2.0, axis=1)
    crown = local[inside, 2] > 0.5  # above the flat ground: leaves or stems
    column = np.floor((local[inside, :2] - leaves.lower[:2]) / leaves.cell[:2]).astype(int)
    leafy = leaves.leaf_area_index()[column[:, 0], column[:, 1]] > 0.0
    n, cover = int(inside.sum()), canopy_cover(trees)
    return {"voxel_m": voxel_m, "first_returns": n, "canopy_fraction": float(crown.mean()), "canopy_cover": cover,
            "voxel_cover": float(leafy.mean()), "bias": float(crown.mean()) - cover,
            "bias_to_voxels": float(crown.mean() - leafy.mean()), "binomial_sigma": math.sqrt(cover * (1 - cover) / n)}


def _forest_config(instrument: str, items: dict):
    """A validated config of ``instrument`` over the procedural forest with ``items`` set."""
    cfg = preset_config(instrument)
    for key, value in {"scene.name": "forest", **items}.items():
        set_value(cfg, key, value)
    return validate(cfg)


def _top_height(chm: tuple, xy: np.ndarray, radius: float, quantile: float | None = None) -> np.ndarray:
    """The truth CHM (``canopy_height_model``'s (heights, west, north) at 1 m) under each point of ``xy`` (local
    [m]) within ``radius``: the highest cell, or its ``quantile`` (0-1)."""
    heights, west, north = chm
    rows, cols = heights.shape
    x = west + (np.arange(cols) + 0.5)
    y = north - (np.arange(rows) + 0.5)
    out = np.full(len(xy), np.nan)
    for i, (px, py) in enumerate(xy):
        near = ((x[None, :] - px) ** 2 + (y[:, None] - py) ** 2) <= radius ** 2
        if near.any():
            values = heights[near]
            out[i] = values.max() if quantile is None else np.quantile(values, quantile)
    return out


def gedi_over_forest(device: str, directory: Path, seed: int = 0) -> dict:
    """Section 3b: GEDI (the ``gedi`` preset from the ISS, its L2A) at a 7 × 7 grid of footprints 25 m apart over
    the default stand, rh98 against the highest true crown top within each footprint's 1/e² radius (2σ_f)."""
    from flightsim.engine.run import simulate_to_directory
    from flightsim.scenes.forest_scene import stand
    from flightsim.studies.forest_truth import canopy_height_model

    grid = np.arange(-75.0, 76.0, 25.0)
    local = np.array([(x, y) for y in grid for x in grid])
    probe = _forest_config("gedi", {"run.seed": seed})
    world = local + np.asarray(probe.scene.origin)[:2]
    directory.mkdir(parents=True, exist_ok=True)
    footprints = directory / "footprints.csv"
    write_atomic(footprints, "x,y\n" + "".join(f"{x:.3f},{y:.3f}\n" for x, y in world))
    cfg = _forest_config("gedi", {"run.seed": seed, "flight.platform": "shots", "flight.footprints": str(footprints),
                                  "run.device": device})
    simulate_to_directory(cfg, directory / "gedi", overwrite=True)
    import h5py

    with h5py.File(directory / "gedi" / "l2a.h5") as f:
        rh98 = f["BEAM0000/rh"][:, 98].astype(np.float64)
        flag = f["BEAM0000/quality_flag"][:]
        sigma_f = float(f["BEAM0000"].attrs["footprint_sigma_m"])
    chm = canopy_height_model(stand(cfg.scene, seed), 1.0)
    truth, core = (_top_height(chm, local, k * sigma_f) for k in (2.0, 1.0))
    good = (flag == 1) & np.isfinite(truth)
    error, inner = rh98[good] - truth[good], rh98[good] - core[good]
    return {"footprints": len(local), "quality": int(good.sum()), "footprint_sigma_m": sigma_f,
            "bias_m": float(error.mean()), "rmse_m": float(np.sqrt(np.mean(error ** 2))),
            "bias_within_sigma_m": float(inner.mean()), "rmse_within_sigma_m": float(np.sqrt(np.mean(inner ** 2))),
            "rh98": rh98.tolist(), "true_top": truth.tolist()}


def atl08_over_forest(device: str, directory: Path, seed: int = 0) -> dict:
    """Section 3c: ATLAS from orbit over a 600 m stand: each 100 m ATL08 segment's h_canopy against the 98th
    percentile of the true CHM within 6 m (the 12 m footprint's radius) of the segment's footprint centres."""
    import h5py
    import pyproj

    from flightsim.engine.run import simulate_to_directory
    from flightsim.scenes.forest_scene import stand
    from flightsim.studies.forest_truth import canopy_height_model

    cfg = _forest_config("atlas", {**SINGLE_BEAM, "scene.forest_size_m": 600.0, "flight.duration_s": 0.08,
                                   "run.seed": seed,
                                   "photon.gate_m": [499900.0, 500100.0], "run.device": device})
    simulate_to_directory(cfg, directory / "atlas", overwrite=True)
    with h5py.File(directory / "atlas" / "atl08.h5") as f:
        seg = f["gt1/land_segments"]
        lat, lon, h_canopy = seg["latitude"][:], seg["longitude"][:], seg["canopy/h_canopy"][:]
        h_te, first = seg["terrain/h_te_mean"][:].astype(np.float64), seg["segment_id_beg"][:]
    with h5py.File(directory / "atlas" / "atl03.h5") as f:
        shot_lat = f["gt1/footprint/lat"][:]
        shot_lon = f["gt1/footprint/lon"][:]
    crs = pyproj.CRS.from_user_input(cfg.scene.crs)
    to_local = pyproj.Transformer.from_crs(crs.geodetic_crs, crs, always_xy=True)
    origin = np.asarray(cfg.scene.origin)
    centres = np.column_stack(to_local.transform(lon, lat)) - origin[:2]
    shots = np.column_stack(to_local.transform(shot_lon, shot_lat)) - origin[:2]
    trees = stand(cfg.scene, seed)
    chm = canopy_height_model(trees, 1.0)
    half = trees.size_m / 2.0
    rows, photons = [], _photon_truth(directory / "atlas" / "atl03.h5", (first - 1) * 20.0)
    for centre, value, te, (ground, leaves) in zip(centres, h_canopy, h_te, photons):
        mine = shots[np.hypot(*(shots - centre).T) <= 50.0]
        if not len(mine) or np.any(np.abs(centre) > half - 50.0) or not value < 1e30:
            continue
        under = _top_height(chm, mine, 6.0)  # each footprint's top: the canopy photons see crowns within it
        rows.append((float(value), float(np.percentile(under[np.isfinite(under)], 98)), leaves,
                     te - ground if te < 1e30 else np.nan))
    got, truth, leaves, ground_error = np.array(rows).T if rows else (np.array([]),) * 4
    error = got - truth
    return {"segments": len(rows), "h_canopy": got.tolist(), "true_p98": truth.tolist(),
            "bias_m": float(error.mean()) if len(rows) else None,
            "rmse_m": float(np.sqrt(np.mean(error ** 2))) if len(rows) else None,
            "leaf_photon_p98": leaves.tolist(), "bias_to_leaf_photons_m": float(np.mean(got - leaves))
            if len(rows) else None, "h_te_error_m": ground_error.tolist()}


def _photon_truth(path: Path, starts: np.ndarray) -> list[tuple[float, float]]:
    """Per 100 m segment starting ``starts`` [m along track]: the mean height of its photons from the ground
    (truth_kind 1, their ranging noise averages out) and the 98th percentile of its leaf photons' (truth_kind 3)
    heights above that: what ATL08's h_te_mean and h_canopy would be with every photon classified by its truth."""
    import h5py

    with h5py.File(path) as f:
        g = f["gt1/heights"]
        along, h, kind = g["x_atc"][:], g["h_ph"][:].astype(np.float64), g["truth_kind"][:]
    out = []
    for start in starts:
        inside = (along >= start) & (along < start + 100.0)
        ground = h[inside & (kind == 1)].mean() if np.any(inside & (kind == 1)) else np.nan
        leaves = h[inside & (kind == 3)] - ground
        out.append((float(ground), float(np.percentile(leaves, 98)) if len(leaves) else np.nan))
    return out


def write_report(out: Path, results: dict) -> None:
    """REPORT.md and forest_report.json in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "forest_report.json", json.dumps(results, indent=2) + "\n")
    write_atomic(out / "REPORT.md", "\n".join(report_lines(results)) + "\n")


def report_lines(r: dict) -> list[str]:
    lines = ["# Forests: the canopy checked", "", f"Regenerate: `flightsim forest --report --device "
             f"{r['device']} --out results/forest` ({r['device']}, {r['wall_s']:.0f} s).", "",
             "## 1. A homogeneous turbid layer", "",
             f"Leaf area index {LAYER['lai']:g} between {LAYER['bottom_m']:g} m and {LAYER['top_m']:g} m over flat "
             f"ground; {MC_PHOTONS:,} photons per case through the device's voxel walk (first interaction drawn "
             "from the optical depth), against exp(−G L / cos θ) and the closed-form mean interaction height.", "",
             "| leaves | zenith | G | transmitted | exp(−GL/μ) | relative error (1σ binomial) | mean height [m] | "
             "closed form [m] |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for x in r["turbid_layer"]:
        lines.append(f"| {x['leaf_angles']} | {x['zenith_deg']:g}° | {x['G']:.4f} | {x['transmitted']:.5f} | "
                     f"{x['exp(-GL/mu)']:.5f} | {x['relative_error']:+.2%} ({x['binomial_sigma']:.2%}) | "
                     f"{x['mean_height_m']:.3f} ± {x['height_sigma_m']:.3f} | {x['closed_form_height_m']:.3f} |")
    c = r["cloud"]
    lines += ["", "## 2. Point-cloud waveforms against the float64 model", "",
              f"{c['footprints']} GEDI footprints (σ_f 5.5 m, 1 ns samples) over a synthetic forest of "
              f"{c['points']:,} points: the device kernel against the NumPy float64 implementation of the same "
              "method (flightsim/instrument/cloud_waveform_model.py). Targets: correlation ≥ 0.999, rh50, rh98 and "
              "ground within 0.1 m. Against Hancock's gediRat itself on real plots: `gedi_peer.md`.", "",
              f"Least correlation {c['min_correlation']:.6f}; largest |Δ rh50| {c['max_abs_rh50_m']:.4f} m, |Δ rh98| "
              f"{c['max_abs_rh98_m']:.4f} m, |Δ ground| {c['max_abs_ground_z_m']:.4f} m.", ""]
    lines += ["## 3. The procedural forest", "", "### Discrete first returns against canopy cover", "",
              "A nadir-looking profiler (one beam, 2 kHz) in 20 lines 10 m apart over the default stand (seed 0). "
              "Canopy cover: the union of the crowns' vertical projections; voxel cover: the share of the same "
              "first returns whose voxel column holds leaves.", "",
              "| voxel | first returns | from crowns | canopy cover | voxel cover | bias to cover | bias to voxel cover |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for f in r["first_returns"]:
        lines.append(f"| {f['voxel_m']:g} m | {f['first_returns']:,} | {f['canopy_fraction']:.3f} | {f['canopy_cover']:.3f} | "
                     f"{f['voxel_cover']:.3f} | {f['bias']:+.3f} | {f['bias_to_voxels']:+.3f} |")
    lines += ["", "A crown in voxels reaches to the edges of every voxel it touches (with that voxel's share of its leaf "
              "area), so the voxels' cover exceeds the crowns' by about the crowns' perimeter times half a voxel; it "
              "shrinks with the voxel. Against the voxels' own cover the first returns fall short where a beam crosses "
              "too little leaf area to reach the detector's threshold (discrete.threshold): a thin crown edge "
              "returns from the ground.", ""]
    g, a = r["gedi"], r["atl08"]
    lines += ["### GEDI over the forest", "",
              f"The `gedi` preset from the ISS (`shots` platform) at {g['footprints']} footprints 25 m apart over the "
              f"default stand; L2A rh98 against the highest true crown top within each footprint's 1/e² radius "
              f"(2σ_f = {2 * g['footprint_sigma_m']:.1f} m): {g['quality']} shots of quality 1, bias "
              f"{g['bias_m']:+.2f} m, RMSE {g['rmse_m']:.2f} m; against the highest within σ_f: bias "
              f"{g['bias_within_sigma_m']:+.2f} m, RMSE {g['rmse_within_sigma_m']:.2f} m. A crown at the footprint's "
              "edge holds e⁻² of the centre's weight per unit area: its top adds little energy above rh98, and the "
              "leaves' echo starts where the beam has met leaves, below the crowns' surface.", "",
              "### ATL08 over the forest", "",
              f"The `atlas` preset from orbit over a 600 m stand: {a['segments']} 100 m segments inside it, h_canopy "
              f"against the 98th percentile of the true crown tops under the segment's footprints (within 6 m of "
              f"each centre): bias {a['bias_m']:+.2f} m, RMSE {a['rmse_m']:.2f} m." if a["segments"] else
              "### ATL08 over the forest: no segment inside the stand", "", *_atl08_lines(a),
              "![GEDI rh98 and ATL08 h_canopy against the truth](forest_checks.png)", "",
              "Hancock et al. (2019, Earth and Space Science 6:294) found the GEDI simulator's waveforms from real ALS "
              "within 0.22 m mean bias and 5.7 m RMSE of the metrics of real LVIS waveforms: a simulator against an "
              "instrument, over real forests. Here the simulator is measured against its own scene's truth, so the "
              "bias and RMSE above are those of the detectors' and the products' algorithms (the leading edge of a "
              "canopy echo, the L2A and ATL08 algorithms' thresholds, the footprint's Gaussian weighting of the crowns "
              "it holds), with no instrument or geolocation error in them.", ""]
    return lines


def _atl08_lines(a: dict) -> list[str]:
    """What the ATL08 difference is made of: its ground against the ground photons, its h_canopy against the leaf
    photons' own 98th percentile."""
    if not a["segments"]:
        return []
    te = np.abs(np.array(a["h_te_error_m"], dtype=np.float64))
    leaves = np.array(a["leaf_photon_p98"])
    ground = (f"h_te_mean lies within {np.nanmax(te):.2f} m of the mean height of the segment's photons from the "
              "ground (the simulator's truth_kind 1)" if np.isfinite(te).any() else "no segment has a terrain height")
    return [f"Its ground: {ground}. With every photon classified by its truth, the leaf photons' 98th percentile "
            f"above that ground is {leaves.min():.1f}–{leaves.max():.1f} m, and h_canopy lies "
            f"{a['bias_to_leaf_photons_m']:+.2f} m from it on average: the classification is not what remains. The "
            f"{a['bias_m']:+.2f} m to the crown tops is where leaf photons come from: each from the first leaves it "
            "meets, a Beer–Lambert depth below the crowns' surface (mean 1/(G·LAD), metres in these crowns), and a "
            "crown top near a footprint's edge gets little of the Gaussian footprint's energy, while the truth takes "
            "the highest crown top within 6 m of each footprint centre. (Before the ground finder looked for the "
            "lowest dense surface, it took a low percentile of each 10 m window: under this closed stand with its "
            "dim ground that put the ground 0.4–10.8 m up in the canopy of the pass's six segments, and h_canopy "
            "was 7.46 m low, RMSE 8.38 m.)",
            ""]


def run_forest_report(out: Path, device: str = "cpu") -> dict:
    """Every section; writes REPORT.md, forest_report.json and forest_checks.png into ``out`` (the runs of section 3
    into ``out/runs``) and returns the results."""
    out, started = Path(out), time.perf_counter()
    results = {"device": device, "turbid_layer": turbid_layer(device),
               "cloud": cloud_waveforms_against_model(device),
               "first_returns": [first_return_cover(device, voxel_m=v) for v in (1.0, 0.5)],
               "gedi": gedi_over_forest(device, out / "runs"), "atl08": atl08_over_forest(device, out / "runs")}
    results["wall_s"] = time.perf_counter() - started
    write_report(out, results)
    plot_checks(out / "forest_checks.png", results)
    return results


def plot_checks(path: Path, r: dict) -> None:
    """GEDI rh98 and ATL08 h_canopy against their truths, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.2))
    for ax, (x, y, title) in zip(axes, ((r["gedi"]["true_top"], r["gedi"]["rh98"], "GEDI rh98, 49 footprints"),
                                        (r["atl08"]["true_p98"], r["atl08"]["h_canopy"], "ATL08 h_canopy, 100 m"))):
        ax.plot(x, y, "o", ms=4)
        low, high = 0.0, max([*x, *y, 1.0]) * 1.05
        ax.plot([low, high], [low, high], "k-", lw=0.8)
        ax.set(xlim=(low, high), ylim=(low, high), xlabel="truth [m]", ylabel="simulated [m]", title=title)
    fig.tight_layout()
    with replaced_atomically(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
