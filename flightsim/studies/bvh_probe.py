"""Bare ray casts (the pipeline's :func:`kernels.mesh_cast.closest_hit`, nothing else) per BVH constructor and leaf
size, over the scenes and rays of the workloads that cast against large meshes: the SPAD's 32×32 fans over the
sandbox, the galvo imager's cone over the lunar scene, the Risley's cone over the calibration field and over the
scale section's terrain (:func:`flightsim.scenes.testdem.terrain`, 3 km square). Rays/s of each (constructor, leaf
size), the same with Warp's own ``wp.mesh_query_ray`` and how many rays the two cast to another face or t, the
BVH's build time, and how many rays hit another face than the first variant's::

    python3 -m flightsim.studies.bvh_probe --device cuda --rays 4194304

(profile-experiments.md section 32 chose the GPU's automatic BVH with it; section 41 measured closest_hit.)
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from flightsim.core.warp_runtime import init_warp, resolve_device
from kernels.trace import cast_rays, cast_rays_warp

VARIANTS = (("cubql", None), ("cubql", 1), ("cubql", 2), ("cubql", 4), ("cubql", 8), ("sah", 1), ("sah", 2),
            ("sah", 4), ("lbvh", 1))
MAX_RANGE_M = 5000.0


def cone(origin, half_rad: float, n: int, rng: np.random.Generator, jitter_m: float = 0.0):
    """(starts, unit directions) of n rays down from ``origin`` (± jitter_m in x and y) within ±half_rad."""
    starts = np.tile(np.asarray(origin, dtype=np.float64), (n, 1))
    starts[:, :2] += rng.uniform(-jitter_m, jitter_m, (n, 2))
    a = rng.uniform(-half_rad, half_rad, (n, 2))
    d = np.column_stack([np.tan(a), -np.ones(n)])
    return starts, d / np.linalg.norm(d, axis=1, keepdims=True)


def fans(origin, half_rad: float, n: int, rng: np.random.Generator, k: int = 32):
    """The rays of n / k² pulses of a k × k fan (the SPAD's beam order), each pulse pointed ±1.5 mrad off."""
    u = np.linspace(-half_rad, half_rad, k)
    a, b = np.meshgrid(u, u, indexing="ij")
    pointing = rng.uniform(-0.0015, 0.0015, (max(1, n // (k * k)), 1, 2))
    angles = (np.stack([a.ravel(), b.ravel()], -1)[None] + pointing).reshape(-1, 2)
    d = np.column_stack([np.tan(angles), -np.ones(len(angles))])
    return np.tile(np.asarray(origin, dtype=np.float64), (len(d), 1)), d / np.linalg.norm(d, axis=1, keepdims=True)


def cases(rays: int, dem_triangles: tuple[int, ...], rng: np.random.Generator):
    """(label, scene, starts, directions) of each measured set."""
    from flightsim.scenes.calibration import calibration_scene
    from flightsim.scenes.lunar import lunar_scene
    from flightsim.scenes.smallbody import sandbox_scene
    from flightsim.scenes.testdem import terrain

    yield "sandbox, SPAD fans from 100 m", sandbox_scene(), *fans([0.0, 0.0, 100.0], 0.0567, rays, rng)
    yield "lunar, ±0.3 rad from 100 m", lunar_scene(), *cone([0.0, 0.0, 100.0], 0.3, rays, rng)
    yield "calibration field, ±0.35 rad from 500 m", calibration_scene(400.0), *cone([0.0, 0.0, 500.0], 0.35, rays,
                                                                                       rng, 150.0)
    for triangles in dem_triangles:
        yield (f"terrain of {triangles:.0e} triangles, ±0.35 rad from 500 m", terrain(triangles),
               *cone([0.0, 0.0, 500.0], 0.35, rays, rng, 1000.0))


def casts(mesh: wp.Mesh, starts: wp.array, directions: wp.array, repeats: int = 5,
          kernel=cast_rays) -> tuple[float, np.ndarray]:
    """(rays/s, best of ``repeats``, after one untimed cast; the faces hit, −1 for none) of ``kernel``."""
    n, device = len(starts), starts.device
    faces = wp.empty(n, dtype=wp.int32, device=device)
    args = dict(dim=n, inputs=[mesh.id, starts, directions, MAX_RANGE_M], outputs=[faces], device=device)
    wp.launch(kernel, **args)
    best = float("inf")
    for _ in range(repeats):
        wp.synchronize_device(device)
        started = time.perf_counter()
        wp.launch(kernel, **args)
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - started)
    return n / best, faces.numpy()


def probe(device: str, rays: int, dem_triangles: tuple[int, ...] = (10**6, 8 * 10**6), seed: int = 1) -> list[dict]:
    """One record per (set, constructor, leaf size): rays/s (closest_hit and Warp's query), faces differing between
    the two, build [s], faces differing from the first variant."""
    d = resolve_device(device)
    records = []
    for label, scene, s, v in cases(rays, dem_triangles, np.random.default_rng(seed)):
        points = wp.array(scene.vertices.astype(np.float32), dtype=wp.vec3f, device=d)
        indices = wp.array(scene.triangles.astype(np.int32).ravel(), dtype=wp.int32, device=d)
        starts = wp.array(s.astype(np.float32), dtype=wp.vec3f, device=d)
        directions = wp.array(v.astype(np.float32), dtype=wp.vec3f, device=d)
        first = None
        for constructor, leaf in VARIANTS:
            if constructor == "lbvh" and wp.get_device(d).is_cpu:
                continue  # a CPU tree has no LBVH (Warp falls back to SAH)
            started = time.perf_counter()
            mesh = wp.Mesh(points=points, indices=indices, bvh_constructor=constructor, bvh_leaf_size=leaf)
            wp.synchronize_device(d)
            build = time.perf_counter() - started
            rate, faces = casts(mesh, starts, directions)
            warp_rate, warp_faces = casts(mesh, starts, directions, kernel=cast_rays_warp)
            first = faces if first is None else first
            records.append({"set": label, "triangles": len(scene.triangles), "constructor": constructor,
                            "leaf": leaf or "default", "rays_per_s": rate, "warp_rays_per_s": warp_rate,
                            "differ_from_warp": int((faces != warp_faces).sum()), "build_s": build,
                            "faces_differ": int((faces != first).sum())})
    return records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    parser.add_argument("--rays", type=int, default=1 << 22, help="rays a set (default 4194304)")
    parser.add_argument("--terrain", default="1e6,8e6", help="triangles of each terrain (default 1e6,8e6)")
    args = parser.parse_args(argv)
    init_warp()
    triangles = tuple(int(float(x)) for x in args.terrain.split(",") if x)
    print("| set | triangles | BVH | leaf | rays/s | Warp's mesh query [rays/s] | faces differing from it | "
          "build [s] | faces differing from the first BVH |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in probe(args.device, args.rays, triangles):
        print(f"| {r['set']} | {r['triangles']} | {r['constructor']} | {r['leaf']} | {r['rays_per_s']:.3g} | "
              f"{r['warp_rays_per_s']:.3g} | {r['differ_from_warp']} | {r['build_s']:.2f} | {r['faces_differ']} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
