"""Typed settings of a part: fields with a default, a unit, an allowed range and a one-line meaning.

Every part (an emitter, a deflector, a detector, an error model, a platform, a scene kind, an output)
declares its settings as a dataclass whose fields are made by :func:`setting`, and subclasses
:class:`Settings`. This module checks them (:func:`check_settings`: ranges, choices, lengths, types;
then the class's own :meth:`Settings.check`), converts TOML and command-line values to the field's
type (:func:`coerce`) and writes them as TOML, with a comment per field when asked
(:func:`table_toml`). It knows nothing of any particular part.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any, ClassVar

from flightsim.core.errors import InputError


def setting(default: Any, doc: str, unit: str = "", *, range: tuple[float, float] | None = None,
            lo_open: bool = False, choices: tuple[str, ...] | None = None, length: int | None = None,
            items: tuple[float, float] | None = None, item: type | None = None, points: bool = False):
    """A settings field.

    default: the value (a float, int, bool, str, or a tuple of floats or strings);
    doc: what it means, one line; unit: e.g. "m", "Hz", "deg" ("" for a pure number);
    range: (lo, hi) allowed for a number, closed (left-open with ``lo_open``);
    choices: allowed strings (for a str, or for each item of a tuple of strings), or a function giving them
    (kinds that plug-ins may add);
    length: the number of items of a tuple (None: any number of at least one item, or none if the
    default is empty); items: (lo, hi) allowed for each number of a tuple; item: the item type of a
    tuple whose default is empty; points: a list of [x, y, z] points.
    """
    if isinstance(default, list):
        default = tuple(default)
    item_type = item or (type(default[0]) if isinstance(default, tuple) and default else None)
    meta = {"doc": doc, "unit": unit, "range": range, "lo_open": lo_open, "choices": choices, "length": length,
            "items": items, "item": item_type, "points": points}
    return dataclasses.field(default=default, metadata=meta)


@dataclass
class Settings:
    """Base of every part's settings. ``doc`` of the class is the table's one-line description."""

    table: ClassVar[str] = ""  # the TOML table (or section) the settings are written under

    def check(self, context: Any) -> None:
        """Cross-field checks beyond each field's range (raise InputError naming the field); ``context`` is
        the composition (:class:`flightsim.core.registry.Context`)."""

    def resolved(self) -> "Settings":
        """A copy with derived values filled in (default: itself, copied)."""
        return dataclasses.replace(self)


def fields(settings: Settings | type) -> tuple[dataclasses.Field, ...]:
    return dataclasses.fields(settings)


def field_names(settings: Settings | type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(settings))


# ---------------------------------------------------------------------------------------------
# checks


def _choices(meta: dict) -> tuple[str, ...] | None:
    choices = meta["choices"]
    return tuple(choices()) if callable(choices) else choices


def _interval(meta: dict) -> str:
    lo, hi = meta["range"]
    return f"{'(' if meta['lo_open'] else '['}{lo:g}, {hi:g}]"


def allowed_text(meta: dict, default: Any) -> str:
    """What a field accepts, as the error message and the TOML comment say it."""
    unit = f" {meta['unit']}" if meta["unit"] else ""
    if meta["points"]:
        return "a list of points such as [[0, 0, 1], [5, 0, 1]] [m]"
    if isinstance(default, bool):
        return "true or false"
    if isinstance(default, tuple):
        what = "strings" if meta["item"] is str else "finite numbers"
        count = f"{meta['length']} " if meta["length"] else ""
        if meta["choices"]:
            return f"a list of {count}items from {', '.join(_choices(meta))}"
        if meta["items"]:
            lo, hi = meta["items"]
            return f"{count or 'a list of '}{what} each in [{lo:g}, {hi:g}]{unit}"
        return f"{count or 'a list of '}{what}{unit}"
    if meta["choices"]:
        return "one of " + ", ".join(_choices(meta))
    if isinstance(default, int):
        lo, hi = meta["range"]
        return f"an integer in [{lo}, {hi}]{unit}"
    if isinstance(default, float) and meta["range"]:
        return f"a finite number in {_interval(meta)}{unit}"
    if isinstance(default, float):
        return f"a finite number{unit}"
    return "a string"


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _check_value(name: str, value: Any, meta: dict, default: Any) -> None:
    allowed = allowed_text(meta, default)
    if meta["points"]:
        ok = all(isinstance(p, (list, tuple)) and len(p) == 3 and all(_is_number(v) for v in p) for p in value)
        if not ok:
            raise InputError(name, value, "[east, north, up] local coordinates [m], three finite numbers each")
        return
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise InputError(name, value, allowed)
    elif isinstance(default, tuple):
        _check_items(name, value, meta, allowed)
    elif isinstance(default, int):
        lo, hi = meta["range"]
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise InputError(name, value, allowed)
    elif isinstance(default, float):
        if not _is_number(value):
            raise InputError(name, value, allowed)
        if meta["range"]:
            lo, hi = meta["range"]
            if value < lo or value > hi or (meta["lo_open"] and value == lo):
                raise InputError(name, value, allowed)
    elif not isinstance(value, str) or (meta["choices"] and value not in _choices(meta)):
        raise InputError(name, value, allowed)


def _check_items(name: str, value: Any, meta: dict, allowed: str) -> None:
    if not isinstance(value, (tuple, list)) or (meta["length"] and len(value) != meta["length"]):
        raise InputError(name, value, allowed)
    for v in value:
        if meta["item"] is str:
            if not isinstance(v, str) or (meta["choices"] and v not in _choices(meta)):
                raise InputError(name, ",".join(map(str, value)), allowed)
        elif not _is_number(v) or (meta["items"] and not meta["items"][0] <= v <= meta["items"][1]):
            raise InputError(name, value, allowed)


def check_settings(table: str, settings: Settings, context: Any = None) -> None:
    """Check every field of ``settings`` against its declaration, then the class's own :meth:`Settings.check`;
    raise InputError naming ``table.field``."""
    for f in dataclasses.fields(settings):
        _check_value(f"{table}.{f.name}", getattr(settings, f.name), f.metadata, f.default)
    settings.check(context)


# ---------------------------------------------------------------------------------------------
# values from TOML and the command line


def _to_bool(value: Any) -> bool:
    if isinstance(value, str) and value.lower() in ("true", "false"):
        return value.lower() == "true"
    if isinstance(value, bool):
        return value
    raise ValueError(value)


def _to_int(value: Any) -> int:
    if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
        raise ValueError(value)
    return int(value)


def _to_tuple(value: Any, item: type | None) -> tuple:
    items = value.split(",") if isinstance(value, str) else list(value)
    if item is str:
        return tuple(str(v).strip() for v in items if str(v).strip())
    return tuple(float(v) for v in items)


def _to_points(name: str, value: Any) -> tuple:
    try:
        items = json.loads(value) if isinstance(value, str) else value
        return tuple(tuple(float(v) for v in point) if isinstance(point, (list, tuple)) else (point,)
                     for point in items)
    except (TypeError, ValueError):
        raise InputError(name, value, "a list of points such as [[0, 0, 1], [5, 0, 1]]") from None


def coerce(name: str, field: dataclasses.Field, value: Any) -> Any:
    """A TOML or command-line value converted to the type of ``field`` (InputError naming ``name``)."""
    meta, default = field.metadata, field.default
    if meta.get("points"):
        return _to_points(name, value)
    try:
        if isinstance(default, tuple):
            return _to_tuple(value, meta.get("item"))
        convert = {bool: _to_bool, int: _to_int, float: float, str: str}[type(default)]
        return convert(value)
    except (TypeError, ValueError):
        raise InputError(name, value, allowed_text(meta, default)) from None


# ---------------------------------------------------------------------------------------------
# TOML out


def toml_value(value: Any) -> str:
    """A value as TOML; floats with full precision (``repr``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def describe(field: dataclasses.Field) -> str:
    """A field's comment: its meaning, then what it accepts (range and unit)."""
    return f"{field.metadata['doc']}; {allowed_text(field.metadata, field.default)}"


def table_toml(table: str, entries: list[tuple[dataclasses.Field, Any]], comments: bool = False,
               title: str = "") -> str:
    """``[table]`` with one ``name = value`` line per (field, value); with ``comments`` each line carries
    the field's meaning and range, and ``title`` heads the table."""
    lines = ([f"# {title}"] if comments and title else []) + [f"[{table}]"]
    for f, value in entries:
        text = f"{f.name} = {toml_value(value)}"
        lines.append(f"{text:<40}  # {describe(f)}" if comments else text)
    return "\n".join(lines) + "\n"
