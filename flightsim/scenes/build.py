"""A scene from its settings: the kind chosen by ``scene.name`` builds it; scenes read from files go through the
scene cache (:mod:`flightsim.scenes.cache`)."""
from __future__ import annotations

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.scenes.canopy_io import read_canopy
from flightsim.scenes.scene import Scene, parse_crs
from flightsim.scenes.settings import scene_choices, scene_kind


def scene_part(scene):
    """The scene kind part for the ``[scene]`` section ``scene`` (common and kind settings)."""
    kind = scene_kind(scene.name)
    if kind is None:
        raise InputError("scene.name", scene.name, scene_choices())
    return registry.part("scene", kind)(scene)


def build_scene(scene, half_extent_m: float, seed: int = 0, use_cache: bool = True, device: str = "cpu",
                cloud_leaves: bool = True) -> Scene:
    """The scene of the ``[scene]`` section ``scene``: a built-in kind with ground of ``half_extent_m`` [m] where it
    is sized to the flight (relief from ``seed``); a file through the scene cache when ``use_cache`` (keyed on
    every scene setting and the files they name; its height grid built on ``device``), and what a built-in kind
    computes from its settings alone (a procedural forest's voxels, integrated on ``device`` unless it is the CPU)
    kept there too; with the leaf area grid of ``scene.canopy`` over it, read every time. ``cloud_leaves``: False
    for a run that reads a point cloud's points but not the leaf area they imply (a point cloud's scene then has no
    canopy)."""
    parse_crs(scene.crs, field="scene.crs")
    part = scene_part(scene)
    part.use_cache, part.device, part.cloud_leaves = use_cache, device, cloud_leaves
    if not getattr(part, "suffixes", ()) or not use_cache or not part.cacheable:
        built = part.build(half_extent_m, seed)
    else:
        from flightsim.scenes.cache import cached_scene

        built = cached_scene(scene.name, scene.values(), lambda: part.build(half_extent_m, seed), grid_device=device)
    if scene.canopy:
        if built.canopy is not None or built.cloud is not None:
            raise InputError("scene.canopy", scene.canopy, f"\"\" for the {scene_kind(scene.name)} scene: it brings "
                             "its own leaves")
        built.canopy = read_canopy(scene.canopy, built.crs, built.origin)
    return built
