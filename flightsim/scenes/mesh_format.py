"""What the mesh readers share: the error they raise for a malformed file, and the ASPRS classes that
group and plane names stand for ("ground" → 2, "road" → 11, "roof"/"wall"/"building" → 6, else 1)."""
from __future__ import annotations

from flightsim.scenes.scene import CLASS_BUILDING, CLASS_GROUND, CLASS_ROAD, CLASS_UNCLASSIFIED

NAME_CLASSES = (("ground", CLASS_GROUND), ("road", CLASS_ROAD), ("roof", CLASS_BUILDING),
                ("wall", CLASS_BUILDING), ("building", CLASS_BUILDING))
"""(word, ASPRS class): a name holding the word (any case) stands for the class; the first match counts."""


class MeshFormatError(Exception):
    """What is wrong with a mesh file; :func:`~flightsim.scenes.meshio.load_mesh` turns it into an InputError."""


def class_from_name(name: str) -> int:
    """ASPRS class of a group or plane name (:data:`NAME_CLASSES`; unclassified, 1, if none matches)."""
    lowered = name.lower()
    for word, classification in NAME_CLASSES:
        if word in lowered:
            return classification
    return CLASS_UNCLASSIFIED


def kind_from_class(classification: int) -> str:
    """Plane kind of a class that is not a building: "ground", "road" or "surface"."""
    return {CLASS_GROUND: "ground", CLASS_ROAD: "road"}.get(int(classification), "surface")
