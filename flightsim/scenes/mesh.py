"""Mesh scenes (``scene.name`` a path to an .obj or .ply file), read by :mod:`flightsim.scenes.meshio`."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from flightsim.core.errors import InputError
from flightsim.core.registry import register
from flightsim.core.settings import Settings, setting
from flightsim.scenes.meshio import load_mesh
from flightsim.scenes.scene import Scene
from flightsim.scenes.settings import ScenePart

MESH_SUFFIXES = (".obj", ".ply")


@dataclass
class MeshSettings(Settings):
    """How a mesh file's faces become planes."""

    planes: str = setting("auto", "auto: faces grouped into planes; none: one label per OBJ group or PLY class/"
                          "plane_id (a terrain: no plane-fit RMS, which would measure its curvature)",
                          choices=("auto", "none"))


@register("scene", "mesh")
class MeshScene(ScenePart):
    """The mesh file named by ``scene.name``."""

    settings = MeshSettings
    suffixes = MESH_SUFFIXES

    def build(self, half_extent_m: float, seed: int) -> Scene:
        if not Path(self.s.name).is_file():
            raise InputError("scene.name", self.s.name, "the path of an existing .obj/.ply mesh")
        return load_mesh(self.s.name, self.s.crs, self.s.origin, planes=self.s.planes)
