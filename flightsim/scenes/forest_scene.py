"""The procedural forest scene (``scene.name = "forest"``): a stand of trees (:mod:`flightsim.scenes.forest`) on
flat or sloped ground, its crowns as turbid leaf voxels (:mod:`flightsim.scenes.forest_voxels`, the default) or
as opaque surfaces (:mod:`flightsim.scenes.forest_mesh`, for discrete-return tests).

The scene's mesh is the ground (a square under the stand and the flight, class 2, plane id 0), every tree's
stem (class 5, plane id 1 + i) and, with ``forest_crowns = "mesh"``, every crown (class 5, plane id 1 + n + i);
it is not planar (a LAS run scores patches, not planes). With voxel crowns the scene's ``canopy`` is a
:class:`flightsim.scenes.canopy.VoxelCanopy` of the stand's leaf area density (None when the stand has no leaf).
The trees come from the run's seed alone: :func:`stand` gives the same trees for the truth products
(:mod:`flightsim.studies.forest_truth`) as :meth:`ForestScene.build` for the flight.
"""
from __future__ import annotations

import importlib.util
import math
import sys
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, check_settings, field_names, setting
from flightsim.scenes import forest, forest_voxels
from flightsim.scenes.cache import cached_arrays
from flightsim.scenes.canopy import VoxelCanopy
from flightsim.scenes.forest import CROWN_SHAPES, MAX_PACKING, PlaneGround, StandSpec, Trees, grow_stand
from flightsim.scenes.forest_mesh import CLASS_CROWN, CLASS_STEM, ground_mesh, join, stand_mesh
from flightsim.scenes.forest_voxels import stand_voxels
from flightsim.scenes.leaf_angles import DISTRIBUTIONS
from flightsim.scenes.scene import CLASS_GROUND, PlaneInfo, Scene, check_half_extent, parse_crs, plane_info
from flightsim.scenes.settings import ScenePart

MAX_TREES = 1_000_000  # expected stems in a stand at most


@dataclass
class ForestSettings(Settings):
    """A procedural forest stand: hard-core tree positions, truncated-normal heights, crowns of leaf area."""

    forest_size_m: float = setting(200.0, "side of the square stand, centred on the local origin", "m",
                                   range=(1.0, 10000.0))
    forest_stems_per_ha: float = setting(400.0, "mean stem density (the count is Poisson)", "stems/ha",
                                         range=(0.0, 10000.0), lo_open=True)
    forest_min_spacing_m: float = setting(3.0, "no two stems closer than this (hard core)", "m", range=(0.0, 50.0))
    forest_height_m: float = setting(20.0, "mean tree height (normal, truncated to [2, 80] m)", "m",
                                     range=(2.0, 80.0))
    forest_height_sd_m: float = setting(4.0, "standard deviation of the tree heights", "m", range=(0.0, 40.0))
    forest_crown_shape: str = setting("ellipsoid", "crown solid about the stem", choices=CROWN_SHAPES)
    forest_crown_ratio_radius: float = setting(0.15, "crown radius / tree height", "", range=(0.0, 1.0),
                                               lo_open=True)
    forest_crown_length_ratio: float = setting(0.5, "crown length / tree height (the crown reaches the top)", "",
                                               range=(0.0, 1.0), lo_open=True)
    forest_lai: float = setting(3.0, "stand leaf area index: the trees' leaf area / stand area", "m²/m²",
                                range=(0.0, 15.0))
    forest_slope: float = setting(0.0, "rise/run of the ground, descending towards grid north", "rise/run",
                                  range=(-2.0, 2.0))
    forest_crowns: str = setting("voxels", "crowns as turbid leaf voxels or as opaque surfaces", choices=("voxels",
                                                                                                          "mesh"))
    forest_voxel_m: float = setting(1.0, "side of the leaf area voxels", "m", range=(0.05, 20.0))
    forest_segments: int = setting(12, "sides around a stem or a mesh crown", range=(4, 64))
    forest_leaf_angles: str = setting("spherical", "leaf inclination distribution (de Wit) of the crowns",
                                      choices=DISTRIBUTIONS)
    forest_leaf_reflectance: float = setting(0.45, "leaf hemispherical reflectance at the laser's wavelength", "",
                                             range=(0.0, 1.0))
    forest_leaf_transmittance: float = setting(0.45, "leaf hemispherical transmittance at the laser's wavelength",
                                               "", range=(0.0, 1.0))

    def check(self, context) -> None:
        density = self.forest_stems_per_ha / 1.0e4
        packing = density * math.pi * (self.forest_min_spacing_m / 2.0) ** 2
        if packing > MAX_PACKING:
            most = 2.0 * math.sqrt(MAX_PACKING / (math.pi * density))
            raise InputError("scene.forest_min_spacing_m", self.forest_min_spacing_m,
                             f"at most {most:.3g} m at {self.forest_stems_per_ha:g} stems/ha (the stems must fit)")
        if density * self.forest_size_m ** 2 > MAX_TREES:
            raise InputError("scene.forest_stems_per_ha", self.forest_stems_per_ha,
                             f"at most {MAX_TREES:.0e} trees: {MAX_TREES * 1.0e4 / self.forest_size_m ** 2:.4g} "
                             f"stems/ha in a {self.forest_size_m:g} m stand")
        if self.forest_leaf_reflectance + self.forest_leaf_transmittance > 1.0:
            raise InputError("scene.forest_leaf_transmittance", self.forest_leaf_transmittance,
                             f"at most 1 − forest_leaf_reflectance = {1.0 - self.forest_leaf_reflectance:g}")


@register("scene", "forest")
class ForestScene(ScenePart):
    """The forest of ``[scene]`` (common and forest settings); its ground grows with the flight."""

    settings = ForestSettings
    sized = True

    def build(self, half_extent_m: float, seed: int) -> Scene:
        return forest_scene(self.s, half_extent_m, seed, self.use_cache, voxel_device(self.device))

    def build_kernels(self, device: str) -> list:
        if voxel_device(device) is None or self.s.forest_crowns != "voxels":
            return []
        from kernels import crown_voxels

        return [crown_voxels.column_lad]


def forest_settings(settings) -> ForestSettings:
    """The forest settings of ``settings`` (a ``[scene]`` section or anything with the ``forest_*`` fields),
    checked (InputError naming the field)."""
    own = ForestSettings(**{name: getattr(settings, name) for name in field_names(ForestSettings)})
    check_settings("scene", own)
    return own


def forest_ground(s: ForestSettings) -> PlaneGround:
    """The ground the stand stands on: a plane of ``forest_slope`` (a DEM's ground, with the same methods, would
    be chosen here)."""
    return PlaneGround(s.forest_slope)


def stand(settings, seed: int) -> Trees:
    """The trees of ``settings``' forest from ``seed``: the same for the same settings and seed."""
    s = forest_settings(settings)
    spec = StandSpec(**{name: getattr(s, "forest_" + name) for name in field_names(StandSpec)})
    return grow_stand(spec, seed, forest_ground(s))


def forest_scene(settings, half_extent_m: float, seed: int, use_cache: bool = False,
                 device: str | None = None) -> Scene:
    """The forest of ``settings`` (its ``[scene]``: crs, origin, margin_m and the forest's) from ``seed``; ground
    of half side ``half_extent_m`` [m] or the stand's half side plus the margin, whichever is larger. With
    ``use_cache`` the crowns' voxels come from the scene cache when this code made them for these settings and seed
    (:func:`flightsim.scenes.cache.cached_arrays`), and are kept there when it did not; ``device``: where they are
    integrated (:func:`crown_voxels`)."""
    s = forest_settings(settings)
    trees = stand(s, seed)
    ground = forest_ground(s)
    half = max(check_half_extent(half_extent_m, 0.0), s.forest_size_m / 2.0 + settings.margin_m)
    mesh = join(ground_mesh(ground, half),
                stand_mesh(trees, s.forest_segments, crowns=s.forest_crowns == "mesh", ground=ground))
    return Scene(name="forest", crs=parse_crs(settings.crs), origin=settings.origin, vertices=mesh.vertices,
                 triangles=mesh.triangles, plane_id=mesh.part, classification=mesh.classification,
                 planes=_planes(trees, s.forest_slope, s.forest_crowns == "mesh"), ground_z=0.0, planar=False,
                 canopy=_canopy(trees, s, seed, use_cache, device))


def _planes(trees: Trees, slope: float, crowns: bool) -> list[PlaneInfo]:
    """Plane 0 the ground; 1 + i the stem of tree i; 1 + n + i its crown when the crowns are meshed (the kind
    "surface", normal up, through the tree's foot)."""
    up = np.array([0.0, 0.0, 1.0])
    feet = np.column_stack([trees.x, trees.y, trees.base_z])
    parts = [(1, CLASS_STEM)] + ([(1 + len(trees), CLASS_CROWN)] if crowns else [])
    return [plane_info(0, "ground", CLASS_GROUND, (0.0, slope, 1.0), (0.0, 0.0, 0.0))] + [
        PlaneInfo(id=first + i, kind="surface", classification=cls, normal=up, point=feet[i], pitch_deg=0.0,
                  azimuth_deg=float("nan")) for first, cls in parts for i in range(len(trees))]


def _canopy(trees: Trees, s: ForestSettings, seed: int, use_cache: bool, device: str | None):
    """The crowns' leaf area as a VoxelCanopy (voxel crowns with leaves), else None."""
    if s.forest_crowns != "voxels" or len(trees) == 0 or trees.lad <= 0.0:
        return None
    lad, lower, cell = crown_voxels(trees, s, seed, use_cache, device)
    return VoxelCanopy(lad=lad, lower=lower, cell=cell, leaf_angles=s.forest_leaf_angles,
                       leaf_reflectance=s.forest_leaf_reflectance, leaf_transmittance=s.forest_leaf_transmittance)


def crown_voxels(trees: Trees, settings, seed: int, use_cache: bool, device: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`~flightsim.scenes.forest_voxels.stand_voxels` of ``trees``, the stand of ``settings``' forest from
    ``seed``, on its ``forest_voxel_m`` grid, integrated on the host (``device`` None) or on that Warp device; with
    ``use_cache`` from the scene cache when this code made them for these settings and seed on the same kind of
    device (the two agree to a few float64 ulps, not bit for bit), and kept there when it did not (keyed on every
    forest setting, the seed, the device kind and the source that grows and voxelises the stand)."""
    s = forest_settings(settings)
    if not use_cache:
        return stand_voxels(trees, s.forest_voxel_m, device)

    def voxels() -> dict[str, np.ndarray]:
        return dict(zip(("lad", "lower", "cell"), stand_voxels(trees, s.forest_voxel_m, device)))

    inputs = {"settings": {name: getattr(s, name) for name in field_names(ForestSettings)}, "seed": seed,
              "integrated": "host" if device is None else "cuda"}
    code = (forest, forest_voxels, sys.modules[__name__]) + (() if device is None else (_crown_kernels(),))
    arrays = cached_arrays("forest", inputs, code, voxels)
    return arrays["lad"], arrays["lower"], arrays["cell"]


def voxel_device(run_device: str) -> str | None:
    """Where a run on Warp device ``run_device`` integrates a stand's voxels: None (the host's NumPy, in threads,
    faster there than a CPU kernel's one thread) for "cpu", else that device."""
    return None if run_device == "cpu" else run_device


def _crown_kernels() -> SimpleNamespace:
    """The device integration's module (:mod:`kernels.crown_voxels`) as its source file, for the cache key."""
    return SimpleNamespace(__file__=importlib.util.find_spec("kernels.crown_voxels").origin)
