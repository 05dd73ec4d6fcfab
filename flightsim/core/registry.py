"""The registry of part kinds: every emitter, deflector, detector, error model, platform, scene kind and
output registers here under its role and name, and a run config is composed from them.

A part is a class with a ``settings`` attribute (a :class:`flightsim.core.settings.Settings` dataclass;
an empty one when it has none); the engine's readouts (what a detector makes of the traced beams) and products
(what a run writes from a readout) have none. Built-in parts register when their package's ``catalog`` module is
imported; parts installed from outside register through the entry-point group ``flightsim.parts``
(``[project.entry-points."flightsim.parts"] my_scanner = "my_package.scanner:MyScanner"``: the object is
a part class carrying ``role`` and ``kind``, or a module that calls :func:`register` when imported),
or by calling :func:`register` before the config is loaded.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Mapping

from flightsim.core.errors import InputError

ROLES = ("emitter", "deflector", "detector", "errors", "platform", "scene", "output", "readout", "product")
ENGINE_ROLES = ("readout", "product")  # the engine's parts: no settings of their own
INSTRUMENT_ROLES = ("emitter", "deflector", "detector", "errors")  # parts with a table of their own
SECTIONS = ("instrument", "scene", "flight", "output", "scoring", "run")  # the config's fixed tables
ENTRY_POINT_GROUP = "flightsim.parts"

_parts: dict[str, dict[str, type]] = {role: {} for role in ROLES}
_plugins_loaded = False


class KindClash(ValueError):
    """A part kind that another part already has, or that would share a config table with another part or a
    section."""


def register(role: str, kind: str, part: type | None = None):
    """Register ``part`` as ``kind`` of ``role`` (usable as a class decorator: ``@register("deflector",
    "palmer")``). A kind is taken once per role (registering the same class again is harmless), and an
    instrument part's kind names its config table, so it must be unique among the instrument roles and differ
    from the config's sections; a clash raises :class:`KindClash`."""
    if role not in ROLES:
        raise ValueError(f"unknown part role {role!r}: one of {', '.join(ROLES)}")
    if not isinstance(kind, str) or not re.fullmatch(r"[A-Za-z0-9_-]+", kind):
        raise ValueError(f"part kind {kind!r}: letters, digits, _ and - only (it names a config table or choice)")

    def add(cls: type) -> type:
        if role not in ENGINE_ROLES and not hasattr(cls, "settings"):
            raise TypeError(f"part {kind!r} ({cls.__qualname__}) has no 'settings' class")
        taken = _parts[role].get(kind)
        if taken is not None and taken is not cls:
            raise KindClash(f"{role} kind {kind!r} is taken by {taken.__module__}.{taken.__qualname__}")
        if role in INSTRUMENT_ROLES:
            clash = [r for r in INSTRUMENT_ROLES if r != role and kind in _parts[r]]
            if clash or kind in SECTIONS:
                raise KindClash(f"{role} kind {kind!r} would share its config table with "
                                f"{'the ' + clash[0] + ' ' + kind if clash else 'the [' + kind + '] section'}")
        cls.role, cls.kind = role, kind
        _parts[role][kind] = cls
        return cls

    return add(part) if part is not None else add


def _plugin_error(ep, exc: Exception, importing: bool) -> InputError:
    """One line naming the plug-in (its entry point) and what went wrong."""
    expected = ("a part kind of its own" if isinstance(exc, KindClash) else
                "a module that imports" if importing else "a part class with a role and a kind")
    return InputError(f"plug-in {ep.name}", ep.value,
                      f"{expected} ({type(exc).__name__}: {' '.join(str(exc).split())})")


def load_plugins() -> None:
    """Import the parts installed under the entry-point group (once): each entry point names a part class
    (carrying ``role`` and ``kind``) or a module that registers its parts on import. A plug-in that fails to load,
    or whose kind clashes, is an InputError naming it."""
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            loaded = ep.load()
        except Exception as exc:  # a broken plug-in must not take the command line down with a traceback
            raise _plugin_error(ep, exc, importing=True) from None
        if isinstance(loaded, type):  # a part class (a module registered its parts as it was imported)
            try:
                register(getattr(loaded, "role", None), getattr(loaded, "kind", None), loaded)
            except (ValueError, TypeError) as exc:
                raise _plugin_error(ep, exc, importing=False) from None


def kinds(role: str) -> dict[str, type]:
    """The registered kinds of a role, by name (plug-ins included)."""
    load_plugins()
    return dict(_parts[role])


def part(role: str, kind: str, field_name: str | None = None) -> type:
    """The part class of ``kind``; InputError naming ``field_name`` (default ``role``) when there is none."""
    found = kinds(role).get(kind)
    if found is None:
        raise InputError(field_name or role, kind, "one of " + ", ".join(sorted(kinds(role))))
    return found


def instrument_part(kind: str) -> type | None:
    """The instrument part (emitter, deflector, detector or error model) whose table is ``kind``, or None."""
    for role in INSTRUMENT_ROLES:
        if kind in kinds(role):
            return kinds(role)[kind]
    return None


@dataclass(frozen=True)
class Context:
    """The composition a part's settings are checked in: the kinds in use and every table's settings.

    ``tables`` maps a part's table (``fan``, ``risley``, ...) and the sections' names to their settings;
    ``models`` are the georeferencing models asked for, ``optics`` the per-beam arithmetic.
    """

    emitter: str
    deflector: str
    detector: str
    errors: tuple[str, ...]
    platform: str
    models: tuple[str, ...] = ()
    optics: str = "float64"
    tables: Mapping[str, Any] = field(default_factory=dict)

    def settings(self, kind: str) -> Any:
        """The settings of the part ``kind`` in use (KeyError otherwise)."""
        return self.tables[kind]

    @property
    def parts(self) -> tuple[str, ...]:
        """The instrument's parts in use: emitter, deflector, detector, then the error models."""
        return (self.emitter, self.deflector, self.detector, *self.errors)
