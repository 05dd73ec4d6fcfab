"""Running the TLS-reference experiment of :mod:`flightsim.studies.spad_tls`: the 18 MODE-A power levels at 100 m
and the six MODE-B distances, each frame's points against the registered VZ-2000 cloud (C2C and local plane, with
the registration chain and with a perfect one) and against the true surface; a sensitivity table of the unknowns
the paper does not give (marker baseline, TLS spacing); tls.json and REPORT.md into ``out``/tls."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from flightsim.core.atomic import write_atomic
from flightsim.studies import cloud_compare as cc
from flightsim.studies import spad_tls as st

CPU_SHARES = 3  # processes the MODE-A series is split over on the CPU (MODE-B runs in one more)
SEED = 2028  # the registration noise (total station, TLS targets): one draw per test case


class Reference:
    """A test case's TLS cloud, its KD-tree and its registration (one draw)."""

    def __init__(self, distance_m: float, device: str, scene, lidar_pose, rng: np.random.Generator):
        started = time.perf_counter()
        self.scan = st.tls_scan(st.tls_config(distance_m, device), scene)
        self.tree = cKDTree(self.scan.points)
        self.scan_s = time.perf_counter() - started
        self.controls = st.control_points(scene)
        self.lidar_pose = lidar_pose
        self.ground_z, self.rng = scene.ground_z, rng
        self.transform = self.chain(st.MARKER_BASELINE_M)

    def chain(self, baseline_m: float, rng: np.random.Generator | None = None):
        origin, rot = self.lidar_pose
        return st.registration(self.scan, origin, rot, self.controls, self.ground_z, rng or self.rng, baseline_m)

    def compare(self, points: np.ndarray, transform=None, reference=None, tree=None) -> dict:
        """C2C and plane statistics of ``points`` against the reference moved by ``transform`` (R, t): the points
        are moved by its inverse instead (a rigid motion keeps every distance)."""
        if transform is not None:
            rot, trans = transform
            points = (points - trans) @ rot
        reference = self.scan.points if reference is None else reference
        tree = tree or self.tree
        return {"c2c": cc.stats_cm(cc.c2c_distances(points, tree)),
                "plane": cc.stats_cm(cc.plane_distances(points, reference, tree))}


def lidar_frame(cfg, scene, grid: int):
    """(points local [m], lidar (origin, R_local←sensor), wall [s], photons per shot) of one simulated frame."""
    from flightsim.engine.tracer import Tracer
    from flightsim.engine.world import flight_trajectories
    from flightsim.studies.spad import photon_frame, simulate_frame

    sim = Tracer(cfg, scene, flight_trajectories(cfg, scene))
    counts, result, wall = simulate_frame(sim, photon_frame(sim, grid))
    pose = sim.poses64(1, 0, 1).numpy()[0]
    lidar = (np.asarray(pose["origin"], np.float64), np.asarray(pose["rot"], np.float64).reshape(3, 3))
    return np.array(result.points, dtype=np.float64), lidar, wall, result.signal_photons / max(counts.beams_fired, 1)


def score_frame(label: str, points: np.ndarray, ref: Reference, scene, device: str, extra: dict) -> dict:
    """A frame's statistics: against the true surface (signed), the TLS with the chain and with a perfect
    registration."""
    from flightsim.scoring.surface import signed_distances

    started = time.perf_counter()
    mesh = cc.stats_cm(signed_distances(scene, points, device=device))
    row = {"label": label, "points": len(points), "mesh": mesh, "tls": ref.compare(points, ref.transform),
           "tls_perfect": ref.compare(points), **extra}
    row["score_s"] = time.perf_counter() - started
    return row


def sensitivity(points: np.ndarray, ref: Reference) -> list[dict]:
    """3σ and RMSE (C2C and plane) of one frame over the marker baselines and the TLS spacings, with the
    closed-form registration error at the sandbox's centre for each baseline."""
    rows = []
    rng = np.random.default_rng([SEED, 100])  # one draw per baseline, for every spacing
    transforms = {b: ref.chain(b, rng) for b in st.MARKER_BASELINES}
    for m in st.SPACINGS:
        reference = ref.scan.points if m == 1 else st.decimated(ref.scan, m)
        tree = ref.tree if m == 1 else cKDTree(reference)
        for baseline in (*st.MARKER_BASELINES, None):
            transform = transforms.get(baseline)
            reach = float(np.linalg.norm(ref.lidar_pose[0] - np.array([st.STATION_M[0], st.STATION_M[1], 0.0])))
            sigma = st.ts_sigma_m(reach)
            centre = np.array([0.0, 0.0, float(ref.lidar_pose[0][2])])  # the sandbox, straight below the lidar
            expected = 100.0 * np.sqrt(cc.rigid_fit_error(st.markers(baseline), sigma, centre)) if baseline else 0.0
            rows.append({"spacing_mm": 1e3 * st.TLS_SPACING_M * m, "marker_baseline_m": baseline,
                         "expected_registration_cm": float(expected),
                         **ref.compare(points, transform, reference, tree)})
    return rows


def mode_a_series(device: str, pulses: int | None, levels: int, figure: Path, share: tuple[int, int] = (0, 1)) -> dict:
    """The MODE-A power series at 100 m against one TLS setup (its own registration draw: the same in every
    share), the sensitivity table on its middle level, and the figure of its TLS cloud; with ``share`` = (k, n)
    only the levels k, k + n, … (the first share writes the figure)."""
    from flightsim.engine.world import build_scene
    from flightsim.studies.spad import PAPER as SPAD_PAPER, frame_config
    from flightsim.studies.spad_tls_report import write_figure

    base = frame_config(100.0, "A", device, pulses)
    scene = build_scene(base)
    rows, sens, ref = [], [], None
    for i, (photons, energy) in list(enumerate(st.power_energies(base, levels)))[share[0]::share[1]]:
        cfg = frame_config(100.0, "A", device, pulses, energy)
        points, lidar, wall, per_shot = lidar_frame(cfg, scene, SPAD_PAPER["mode_a"]["grid"])
        ref = ref or Reference(100.0, device, scene, lidar, np.random.default_rng([SEED, 0]))
        rows.append(score_frame(f"MODE-A power {i + 1}", points, ref, scene, device,
                                {"level": i, "photons_per_shot_set": photons, "signal_per_shot": per_shot,
                                 "wall_s": wall}))
        if i == levels // 2:
            sens = sensitivity(points, ref)
        print(f"{rows[-1]['label']}: {json.dumps(rows[-1]['tls']['plane'])}", flush=True)
    if share[0] == 0:
        write_figure(figure, ref.scan)
    return {"tls_mode_a": {"points": len(ref.scan.points), "scan_s": ref.scan_s}, "mode_a": rows, "sensitivity": sens}


def _merge(parts: list[dict]) -> dict:
    """One result of the MODE-A shares and the MODE-B series."""
    a = [p for p in parts if "mode_a" in p]
    return {"tls_mode_a": a[0]["tls_mode_a"], "mode_a": sorted((r for p in a for r in p["mode_a"]),
                                                              key=lambda r: r["level"]),
            "sensitivity": next((p["sensitivity"] for p in a if p["sensitivity"]), []),
            "mode_b": next(p["mode_b"] for p in parts if "mode_b" in p)}


def mode_b_series(device: str, pulses: int | None) -> dict:
    """The six MODE-B distances, each against its own TLS setup and registration draw."""
    from flightsim.engine.world import build_scene
    from flightsim.studies.spad import MODE_B_STEPS, PAPER as SPAD_PAPER, frame_config

    rows, scene = [], None
    for i, d in enumerate(SPAD_PAPER["mode_b"]["distances_m"]):
        cfg = frame_config(d, "B", device, pulses)
        scene = scene or build_scene(cfg)
        points, lidar, wall, per_shot = lidar_frame(cfg, scene, 32 * MODE_B_STEPS)
        ref = Reference(d, device, scene, lidar, np.random.default_rng([SEED, 1 + i]))
        rows.append(score_frame(f"MODE-B {d:g} m", points, ref, scene, device,
                                {"distance_m": d, "signal_per_shot": per_shot, "wall_s": wall,
                                 "tls_points": len(ref.scan.points), "tls_scan_s": ref.scan_s}))
        print(f"{rows[-1]['label']}: {json.dumps(rows[-1]['tls']['plane'])}", flush=True)
    return {"mode_b": rows}


def run_tls(out: Path, device: str = "cpu", pulses: int | None = None, levels: int = st.POWER_LEVELS) -> dict:
    """The whole experiment into ``out``/tls (tls.json, REPORT.md, vz2000_sandbox.png). On the CPU the MODE-A
    and MODE-B series run in separate processes (each case draws its own registration noise, so the numbers do not
    depend on the order); MODE-A is shared over CPU_SHARES processes."""
    from flightsim.studies.spad import PAPER as SPAD_PAPER
    from flightsim.studies.spad_tls_report import report

    out = Path(out) / "tls"
    out.mkdir(parents=True, exist_ok=True)
    figure = out / "vz2000_sandbox.png"
    if device == "cpu":
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(1 + CPU_SHARES, mp_context=multiprocessing.get_context("spawn")) as pool:
            jobs = [pool.submit(mode_a_series, device, pulses, levels, figure, (k, CPU_SHARES))
                    for k in range(CPU_SHARES)] + [pool.submit(mode_b_series, device, pulses)]
            parts = _merge([j.result() for j in jobs])
    else:
        parts = _merge([mode_a_series(device, pulses, levels, figure), mode_b_series(device, pulses)])
    numbers = {"device": device, "pulses_per_frame": pulses or SPAD_PAPER["mode_a"]["pulses"], "paper": st.PAPER,
               **parts, "summary": summary(parts["mode_a"], parts["mode_b"])}
    write_atomic(out / "tls.json", json.dumps(numbers, indent=2) + "\n")
    write_atomic(out / "REPORT.md", report(numbers))
    return numbers


def summary(mode_a: list[dict], mode_b: list[dict]) -> dict:
    """Means over the MODE-A power levels and the MODE-B distances of each metric's 3σ and RMSE [cm]."""
    def mean(rows, *keys):
        values = []
        for r in rows:
            v = r
            for k in keys:
                v = v[k]
            values.append(v)
        return float(np.mean(values))

    out = {}
    for name, rows in (("mode_a", mode_a), ("mode_b", mode_b)):
        for metric in (("mesh",), ("tls", "c2c"), ("tls", "plane"), ("tls_perfect", "c2c"), ("tls_perfect", "plane")):
            key = "_".join(metric)
            out[f"{name}_{key}_three_sigma_cm"] = mean(rows, *metric, "three_sigma_cm")
            out[f"{name}_{key}_rmse_cm"] = mean(rows, *metric, "rmse_cm")
    return out
