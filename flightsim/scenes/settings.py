"""The settings every scene shares (``[scene]``: which scene, its CRS and origin, its retroreflectors), and the
scene kind a name chooses (a built-in scene's name, or a file's suffix)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.core.settings import Settings, setting
from flightsim.scenes.canopy_io import SUFFIXES as CANOPY_SUFFIXES
from flightsim.scenes.scene import DEFAULT_CRS, DEFAULT_ORIGIN


@dataclass
class SceneSettings(Settings):
    """What is scanned and where it lies; the scene kind's own settings join these."""

    table = "scene"

    name: str = setting("calibration", "a built-in scene, or the path of a mesh (.obj/.ply), height grid "
                        "(.tif/.tiff/.npy) or ALS point cloud (.las/.laz, COPC too)")
    crs: str = setting(DEFAULT_CRS, "the world's projected CRS in metres (a GeoTIFF or point cloud brings its own)")
    origin: tuple[float, float, float] = setting(DEFAULT_ORIGIN, "the local frame's origin: world E, N, H", "m",
                                                 length=3, items=(-1.0e8, 1.0e8))
    margin_m: float = setting(50.0, "ground added around what the flight reaches (built-in scenes)", "m",
                              range=(0.0, 10000.0))
    ccrs: tuple = setting((), "corner-cube retroreflectors: [east, north, up] local each (photon detector)", "m",
                          points=True)
    ccr_photons: float = setting(0.0, "photo-electrons a retroreflector returns at a footprint's centre", "",
                                 range=(0.0, 1.0e6))
    canopy: str = setting("", "leaf area density voxels over the scene: a .npz, .nc (NetCDF) or .tif (GeoTIFF "
                          "stack) grid with its leaf properties (flightsim/scenes/canopy_io.py); \"\" = none")

    def check(self, context) -> None:
        if self.canopy and Path(self.canopy).suffix.lower() not in CANOPY_SUFFIXES:
            raise InputError("scene.canopy", self.canopy, "\"\" or a " + "/".join(CANOPY_SUFFIXES) + " file path")


class ScenePart:
    """A scene kind: ``build`` makes its Scene from ``[scene]`` (``self.s``: the settings every scene shares and
    the kind's own). ``sized``: its ground grows with what the flight reaches (``half_extent_m``); ``suffixes``:
    the file suffixes that choose it (a built-in scene has none and is chosen by name); ``cacheable``: whether
    the scene cache may keep a file kind's Scene (it keeps the mesh, labels and height grid, not a canopy or
    point cloud); ``use_cache``: whether ``build`` may keep what it computes in the scene cache (``run.scene_cache``,
    set by :func:`flightsim.scenes.build.build_scene`); ``device``: the run's Warp device, on which ``build`` may
    compute (``run.device``, set there too); ``cloud_leaves``: whether the run reads the leaf area a point cloud
    implies (set there too: not when it sums the cloud's points instead)."""

    sized = False
    suffixes: tuple[str, ...] = ()
    cacheable = True  # a file kind whose Scene the scene cache can hold (its mesh and labels only)
    use_cache = False
    device = "cpu"
    cloud_leaves = True

    def __init__(self, scene):
        self.s = scene

    def build(self, half_extent_m: float, seed: int):
        """The scene, in its local frame (``half_extent_m``: the half side the flight reaches [m])."""
        raise NotImplementedError

    def build_kernels(self, device: str) -> list:
        """The Warp kernels ``build`` launches for a run on ``device`` (none: it builds on the host)."""
        return []


def scene_kind(name: str) -> str | None:
    """The scene kind of ``scene.name``: a built-in scene by name, a file kind by suffix; None if neither."""
    kinds = registry.kinds("scene")
    if name in kinds and not getattr(kinds[name], "suffixes", ()):
        return name
    suffix = Path(name).suffix.lower()
    return next((kind for kind, part in kinds.items() if suffix and suffix in getattr(part, "suffixes", ())), None)


def scene_choices() -> str:
    """What scene.name accepts, in words."""
    kinds = registry.kinds("scene")
    names = [k for k, p in kinds.items() if not getattr(p, "suffixes", ())]
    files = " or ".join("a " + "/".join(p.suffixes) + " file" for p in kinds.values() if getattr(p, "suffixes", ()))
    return f"{', '.join(names)}, or the path of {files}"
