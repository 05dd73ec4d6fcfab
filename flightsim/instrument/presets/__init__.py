"""Built-in instruments: a TOML config per instrument, loaded under the user's config and flags."""
from __future__ import annotations

from pathlib import Path

PRESETS = {"risley": None,  # the defaults
           "change3": Path(__file__).with_name("change3.toml"),
           "spad": Path(__file__).with_name("spad.toml"),
           "change1": Path(__file__).with_name("change1.toml"),
           "atlas": Path(__file__).with_name("atlas.toml")}


def preset_path(name: str) -> Path | None:
    """The TOML of a built-in instrument (None for the defaults); KeyError for an unknown name."""
    return PRESETS[name]
