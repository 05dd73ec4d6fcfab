"""The run config: the instrument's composition, the settings of the parts in use, the scene, the flight, the
outputs and the run options (ARCHITECTURE.md, "A part owns its settings").

A :class:`RunConfig` has fixed sections (``[instrument]``, ``[scene]``, ``[flight]``, ``[output]``, ``[scoring]``,
``[run]``) and one table per instrument part in use, named by the part's kind (``[fan]``, ``[risley]``,
``[photon]``, ``[ranging]``, ...). ``[scene]``, ``[flight]`` and ``[output]`` are :class:`Section` s: the settings
every kind shares plus those of the kind in use (the scene kind ``scene.name`` chooses, the platform of
``flight.platform``, the output of the detector). A setting of a part or kind the run does not use is refused
by :func:`validate`, naming the part and the parts in use. TOML in and out, presets and the documented TOML
are in :mod:`flightsim.engine.config_io`.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.core.registry import Context
from flightsim.core.settings import Settings, check_settings, coerce, field_names, setting
from flightsim.instrument import catalog as _instrument_catalog  # noqa: F401  (registers the built-in parts)
from flightsim.outputs import catalog as _output_catalog  # noqa: F401
from flightsim.platforms import catalog as _platform_catalog  # noqa: F401
from flightsim.platforms.flight import FlightSettings
from flightsim.scenes import catalog as _scene_catalog  # noqa: F401
from flightsim.scenes.settings import SceneSettings, scene_choices, scene_kind
from flightsim.scoring.settings import ScoringSettings

OPTICS = ("float32", "float64", "lut")
BVH_CONSTRUCTORS = ("auto", "sah", "median", "lbvh", "cubql")
ALIASES = {"prism": "risley"}  # tables users may name instead ("prism.refractive_index")


@dataclass
class InstrumentSettings(Settings):
    """Which parts make the instrument, and how it is mounted on the platform."""

    table = "instrument"

    emitter: str = setting("fan", "the beams of a pulse (its settings: the table of that name)",
                           choices=lambda: tuple(sorted(registry.kinds("emitter"))))
    deflector: str = setting("risley", "what turns the beams into the scan (its settings: the table of that name)",
                             choices=lambda: tuple(sorted(registry.kinds("deflector"))))
    detector: str = setting("discrete", "what a beam that hits becomes (its settings: the table of that name)",
                            choices=lambda: tuple(sorted(registry.kinds("detector"))))
    errors: tuple[str, ...] = setting((), "error models on the truth (their settings: the tables of those names)",
                                      item=str, choices=lambda: tuple(sorted(registry.kinds("errors"))))
    max_range_m: float = setting(30000.0, "longest range a beam is traced", "m", range=(0.0, 1.0e6), lo_open=True)
    boresight_deg: tuple[float, float, float] = setting((0.0, 0.0, 0.0), "roll, pitch, yaw of the sensor in the "
                                                        "body frame", "deg", length=3, items=(-10.0, 10.0))
    lever_arm_m: tuple[float, float, float] = setting((0.0, 0.0, 0.0), "the sensor origin in the body frame", "m",
                                                      length=3, items=(-100.0, 100.0))


@dataclass
class RunSettings(Settings):
    """How the run executes (none of it changes the physics)."""

    table = "run"

    device: str = setting("cpu", "cpu, cuda or cuda:N")
    seed: int = setting(0, "seed of every random draw", range=(0, 2 ** 31 - 1))
    chunk_pulses: int = setting(0, "pulses per launch; 0 = automatic", "pulses", range=(0, 2 ** 24))
    cull: bool = setting(True, "skip pulses whose beams cannot reach the scene")
    optics: str = setting("float64", "per-beam arithmetic: float64, float32, or lut (float32, exit rays tabulated "
                          "over the prism angle)", choices=OPTICS)
    lut_samples: int = setting(4096, "prism angles per turn of the lut optics", "angles", range=(8, 1 << 22))
    bvh: str = setting("auto", "BVH constructor: auto (sah on the CPU, cubql with 2 triangles a leaf on a GPU), sah, "
                       "median, lbvh, cubql", choices=BVH_CONSTRUCTORS)
    bvh_leaf_size: int = setting(0, "triangles per BVH leaf; 0 = the automatic BVH's, else Warp's default",
                                 "triangles", range=(0, 64))
    slots_per_thread: int = setting(0, "statistics mode: consecutive slots per reducing thread; 0 = automatic",
                                    "slots", range=(0, 4096))
    sum_replicas: int = setting(0, "statistics mode on a GPU: copies of the per-plane sums; 0 = automatic",
                                "copies", range=(0, 4096))
    max_registers: int = setting(0, "registers per thread of the CUDA trace kernels; 0 = automatic", "registers",
                                 range=(0, 255))
    host_photons: int = setting(1 << 20, "photon runs: detections brought to the host and handed to the products at a "
                                "time (parts of whole pulses); larger parts keep more of the host's cores busy and "
                                "hold more memory", "photons", range=(1 << 10, 1 << 26))
    scene_cache: bool = setting(True, "keep scenes read from files, procedural forests' voxels and an Earth "
                                "orbit's IERS table in $FLIGHTSIM_CACHE (~/.cache/flightsim/scenes)")

    def check(self, context) -> None:
        d = self.device
        if d != "cpu" and d != "cuda" and not (d.startswith("cuda:") and d[5:].isdigit()):
            raise InputError("run.device", d, "cpu, cuda or cuda:N")


# ---------------------------------------------------------------------------------------------
# sections made of common settings and a kind's


def changed_field(settings: Settings, baseline: Settings | None) -> str | None:
    """The first field of ``settings`` that differs from ``baseline`` (default: the class's defaults), or None."""
    reference = baseline if baseline is not None else type(settings)()
    return next((f.name for f in dataclasses.fields(settings) if getattr(settings, f.name) != getattr(reference, f.name)),
                None)


def _platform(cfg: "RunConfig") -> str:
    return cfg.flight.common_settings.platform


def _scene(cfg: "RunConfig") -> str | None:
    return scene_kind(cfg.scene.common_settings.name)


def _output(cfg: "RunConfig") -> str | None:
    detector = registry.kinds("detector").get(cfg.instrument.detector)
    return getattr(detector, "output", None) if detector is not None else None


@dataclass
class _Touched:
    """A section field set while the kind in use did not declare it: for the kinds that do."""

    name: str
    value: Any
    kinds: tuple[str, ...]


_SECTION_STATE = ("_name", "_common", "_role", "_kind_of", "_owner", "_kinds", "_touched", "_baseline")


class Section:
    """A config section whose fields are the common settings' and those of the kind in use (e.g. ``[flight]``:
    the altitude for every platform, ``descent_mps`` for the hover platform only). Attribute access reaches
    both; a kind's settings are made on first use and kept when the kind changes and back."""

    def __init__(self, name: str, common: Settings | None, role: str, kind_of: Callable[["RunConfig"], str | None],
                 owner: "RunConfig"):
        state = {"_name": name, "_common": common, "_role": role, "_kind_of": kind_of, "_owner": owner,
                 "_kinds": {}, "_touched": [], "_baseline": {}}
        for key, value in state.items():
            object.__setattr__(self, key, value)

    @property
    def common_settings(self) -> Settings | None:
        """The settings every kind shares (None for a section made of the kind's alone)."""
        return self._common

    def mark_baseline(self) -> None:
        """Take the kinds' present settings as given by the instrument, not the user (a preset's): a kind not in
        use may keep them without complaint."""
        self._touched.clear()
        object.__setattr__(self, "_baseline", copy.deepcopy(self._kinds))

    @property
    def kind(self) -> str | None:
        """The kind in use (None when there is none, or the selector names no kind)."""
        return self._kind_of(self._owner)

    def kind_settings(self, kind: str | None = None) -> Settings | None:
        """The settings of ``kind`` (default: the kind in use), made with their defaults on first use."""
        kind = self.kind if kind is None else kind
        if kind is None or kind not in registry.kinds(self._role):
            return None
        if kind not in self._kinds:
            self._kinds[kind] = registry.part(self._role, kind).settings()
        return self._kinds[kind]

    def _holder(self, name: str) -> Settings | None:
        if self._common is not None and name in field_names(self._common):
            return self._common
        own = self.kind_settings()
        return own if own is not None and name in field_names(own) else None

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") or name in _SECTION_STATE:
            raise AttributeError(name)
        holder = self._holder(name)
        if holder is None:
            raise AttributeError(f"{self._name}.{name} is not a setting of {self._in_use()}")
        return getattr(holder, name)

    def __setattr__(self, name: str, value: Any) -> None:
        holder = self._holder(name)
        if holder is None:
            raise AttributeError(f"{self._name}.{name} is not a setting of {self._in_use()}")
        setattr(holder, name, value)

    def _in_use(self) -> str:
        kind = self.kind
        return f"the {kind} {self._role}" if kind else f"this [{self._name}]"

    def declaring(self, name: str) -> tuple[str, ...]:
        """The kinds of this section's role that declare ``name``."""
        return tuple(k for k, part in registry.kinds(self._role).items() if name in field_names(part.settings))

    def set(self, name: str, value: Any) -> None:
        """Set ``name`` from a TOML or command-line value: on the common settings or the kind in use, else on
        every kind that declares it (refused by :func:`validate` unless the run comes to use one of them)."""
        dotted = f"{self._name}.{name}"
        holder = self._holder(name)
        if holder is not None:
            field = next(f for f in dataclasses.fields(holder) if f.name == name)
            setattr(holder, name, coerce(dotted, field, value))
            return
        kinds = self.declaring(name)
        if not kinds:
            raise InputError(dotted, value, f"a setting of [{self._name}] ({', '.join(self.names())}"
                                            f"{'; other kinds have more' if self._kind_of else ''})")
        for kind in kinds:
            settings = self.kind_settings(kind)
            field = next(f for f in dataclasses.fields(settings) if f.name == name)
            setattr(settings, name, coerce(dotted, field, value))
        self._touched.append(_Touched(name, getattr(settings, name), kinds))

    def get(self, name: str) -> Any:
        """The value of ``name``: in use, else the default or the value set for the kinds that declare it."""
        holder = self._holder(name)
        if holder is not None:
            return getattr(holder, name)
        kinds = self.declaring(name)
        if not kinds:
            raise InputError(f"{self._name}.{name}", "?", f"a setting of [{self._name}] ({', '.join(self.names())})")
        return getattr(self.kind_settings(kinds[0]), name)

    def names(self) -> tuple[str, ...]:
        """The settings in use: common, then the kind's."""
        own = self.kind_settings()
        return (field_names(self._common) if self._common is not None else ()) + (
            field_names(own) if own is not None else ())

    def entries(self) -> list[tuple[dataclasses.Field, Any]]:
        """(field, value) of every setting in use, common first."""
        parts = [s for s in (self._common, self.kind_settings()) if s is not None]
        return [(f, getattr(s, f.name)) for s in parts for f in dataclasses.fields(s)]

    def values(self) -> dict[str, Any]:
        """{name: value} of every setting in use."""
        return {f.name: value for f, value in self.entries()}

    def check(self, context: Context) -> None:
        """Refuse settings given for a kind not in use, then check the common and the kind's settings."""
        kind = self.kind
        given = [(t.name, t.value, t.kinds) for t in self._touched]
        for other, settings in self._kinds.items():
            if other != kind:
                changed = changed_field(settings, self._baseline.get(other))
                given += [(changed, getattr(settings, changed), (other,))] if changed else []
        for name, value, kinds in given:
            if kind not in kinds:
                raise InputError(f"{self._name}.{name}", value,
                                 f"no value here: it is a setting of the {' or '.join(kinds)} {self._role}, and this "
                                 f"run's {self._role} is {kind or 'none'} (its settings: {', '.join(self.names())})")
        for settings in (self._common, self.kind_settings()):
            if settings is not None:
                check_settings(self._name, settings, context)

    def __deepcopy__(self, memo):
        copied = Section.__new__(Section)
        memo[id(self)] = copied
        for key in _SECTION_STATE:
            value = object.__getattribute__(self, key)
            object.__setattr__(copied, key, value if key in ("_kind_of", "_role", "_name") else copy.deepcopy(value, memo))
        return copied

    def __getstate__(self):
        return {key: object.__getattribute__(self, key) for key in _SECTION_STATE}

    def __setstate__(self, state):
        for key, value in state.items():
            object.__setattr__(self, key, value)


# ---------------------------------------------------------------------------------------------
# the run config


class RunConfig:
    """Everything that defines a run (the defaults are the airborne Risley instrument's)."""

    SECTIONS = registry.SECTIONS

    def __init__(self):
        self.instrument = InstrumentSettings()
        self.scene = Section("scene", SceneSettings(), "scene", _scene, self)
        self.flight = Section("flight", FlightSettings(), "platform", _platform, self)
        self.output = Section("output", None, "output", _output, self)
        self.scoring = ScoringSettings()
        self.run = RunSettings()
        self.parts: dict[str, Settings] = {}  # instrument parts' settings by table (kind), made on first use
        self.touched: dict[str, str] = {}  # instrument part tables given a value: table -> first field set
        self.baseline: dict[str, Settings] = {}  # part tables as the preset gave them (mark_baseline)

    def __getattr__(self, name: str) -> Settings:
        """The settings of the instrument part ``name`` (``cfg.risley``, ``cfg.photon``), made on first use."""
        if name.startswith("_") or name in ("instrument", "parts", "touched", "baseline"):
            raise AttributeError(name)
        part = registry.instrument_part(name)
        if part is None:
            raise AttributeError(f"'RunConfig' has no section or part table {name!r}")
        if name not in self.parts:
            self.parts[name] = part.settings()
        return self.parts[name]

    def mark_baseline(self) -> None:
        """Take the present settings as the instrument's (a preset's), not the user's: a part or kind the user later
        stops using may keep them without complaint."""
        self.touched.clear()
        self.baseline = copy.deepcopy(self.parts)
        for section in (self.scene, self.flight, self.output):
            section.mark_baseline()

    def given_unused(self) -> tuple[str, str] | None:
        """(table, field) of a setting given to an instrument part the run does not use: set from a file or
        the command line, or changed from the preset's (or default) value; None when there is none."""
        used = self.parts_in_use()
        for table, name in self.touched.items():
            if table not in used:
                return table, name
        for table, settings in self.parts.items():
            changed = changed_field(settings, self.baseline.get(table)) if table not in used else None
            if changed:
                return table, changed
        return None

    def parts_in_use(self) -> dict[str, str]:
        """{table: role} of the instrument's parts: emitter, deflector, detector, then the error models."""
        i = self.instrument
        used = {i.emitter: "emitter", i.deflector: "deflector", i.detector: "detector"}
        used.update({kind: "errors" for kind in i.errors})
        return used

    def error_model(self, kind: str) -> Settings | None:
        """The settings of error model ``kind`` when the instrument uses it, else None."""
        return getattr(self, kind) if kind in self.instrument.errors else None

    @property
    def detector_part(self) -> type:
        """The detector's part class."""
        return registry.part("detector", self.instrument.detector, "instrument.detector")

    def tables(self) -> list[tuple[str, list[tuple[dataclasses.Field, Any]]]]:
        """Every table the run uses, in TOML order: [instrument], the parts', [scene], [flight], [output],
        [scoring] (discrete-return runs), [run]."""
        def plain(s: Settings):
            return [(f, getattr(s, f.name)) for f in dataclasses.fields(s)]

        out = [("instrument", plain(self.instrument))]
        out += [(kind, plain(getattr(self, kind))) for kind in self.parts_in_use() if field_names(getattr(self, kind))]
        out += [("scene", self.scene.entries()), ("flight", self.flight.entries())]
        if self.output.kind_settings() is not None and field_names(self.output.kind_settings()):
            out.append(("output", self.output.entries()))
        if getattr(self.detector_part, "scored", False):
            out.append(("scoring", plain(self.scoring)))
        return out + [("run", plain(self.run))]

    def __eq__(self, other) -> bool:
        return isinstance(other, RunConfig) and self.tables() == other.tables()


def copy_config(cfg: RunConfig) -> RunConfig:
    """An independent copy."""
    return copy.deepcopy(cfg)


def _table(dotted: str) -> tuple[str, str]:
    table, _, name = dotted.partition(".")
    return ALIASES.get(table, table), name


def canonical_key(dotted: str) -> str:
    """``table.field`` with a table alias replaced by the part's table (``prism.x`` → ``risley.x``)."""
    table, name = _table(dotted)
    return f"{table}.{name}"


def config_dict(cfg: RunConfig) -> dict[str, dict[str, Any]]:
    """The tables the run uses as nested dicts ({table: {setting: value}}), as TOML would read them back."""
    return {table: {f.name: list(v) if isinstance(v, tuple) else v for f, v in entries} for table, entries in cfg.tables()}


def set_value(cfg: RunConfig, dotted: str, value: Any) -> None:
    """Set ``table.field`` from a TOML or command-line value, converted to the field's type."""
    from flightsim.engine.legacy import moved

    table, name = _table(dotted)
    if table in ("scene", "flight", "output"):
        getattr(cfg, table).set(name, value)
        return
    if table in ("instrument", "scoring", "run") or registry.instrument_part(table) is not None:
        settings = getattr(cfg, table)
        fields = {f.name: f for f in dataclasses.fields(settings)}
        if name not in fields:
            raise InputError(dotted, value, f"a setting of [{table}] ({', '.join(fields)})")
        setattr(settings, name, coerce(dotted, fields[name], value))
        if table not in registry.SECTIONS:
            cfg.touched.setdefault(table, name)
        return
    raise InputError(dotted, value, moved(dotted) or f"a known table.setting: a section ({', '.join(registry.SECTIONS)})"
                     f" or a part's table ({', '.join(_part_tables())}); `flightsim config` lists them")


def get_value(cfg: RunConfig, dotted: str) -> Any:
    """The value of ``table.field`` (aliases allowed)."""
    table, name = _table(dotted)
    if table in ("scene", "flight", "output"):
        return getattr(cfg, table).get(name)
    settings = getattr(cfg, table, None) if table in registry.SECTIONS or registry.instrument_part(table) else None
    if settings is None or name not in field_names(settings):
        set_value(cfg, dotted, None)  # raises the error naming what is known
    return getattr(settings, name)


def _part_tables() -> list[str]:
    return [kind for role in registry.INSTRUMENT_ROLES for kind in registry.kinds(role)]


# ---------------------------------------------------------------------------------------------
# validation


def context(cfg: RunConfig) -> Context:
    """The composition as the parts' checks see it."""
    tables = {kind: getattr(cfg, kind) for kind in cfg.parts_in_use()}
    tables.update(instrument=cfg.instrument, scene=cfg.scene, flight=cfg.flight, output=cfg.output,
                  scoring=cfg.scoring, run=cfg.run)
    models = tuple(cfg.output.models) if "models" in cfg.output.names() else ()
    i = cfg.instrument
    return Context(emitter=i.emitter, deflector=i.deflector, detector=i.detector, errors=tuple(i.errors),
                   platform=cfg.flight.platform, models=models, optics=cfg.run.optics, tables=tables)


def _check_composition(cfg: RunConfig) -> None:
    i = cfg.instrument
    check_settings("instrument", i)
    for role in ("emitter", "deflector", "detector"):
        registry.part(role, getattr(i, role), f"instrument.{role}")
    for kind in i.errors:
        registry.part("errors", kind, "instrument.errors")
    if len(set(i.errors)) != len(i.errors):
        raise InputError("instrument.errors", ",".join(i.errors), "each error model once")
    registry.part("platform", cfg.flight.platform, "flight.platform")
    if scene_kind(cfg.scene.name) is None:
        raise InputError("scene.name", cfg.scene.name, scene_choices())
    unused = cfg.given_unused()
    if unused is not None:
        table, name = unused
        role = registry.instrument_part(table).role
        what = "an error model" if role == "errors" else f"a{'n' if role[0] in 'aeiou' else ''} {role}"
        raise InputError(f"{table}.{name}", getattr(getattr(cfg, table), name),
                         f"no value here: [{table}] is {what} this instrument does not use (it uses "
                         f"{', '.join(cfg.parts_in_use())}; set instrument.{role} to use it)")


def _check_deflector(cfg: RunConfig, ctx: Context) -> None:
    """The engine's side of the deflector protocol: the nominal model needs a deflector with a rigid-array model
    (``rigid_nominal``), the lut optics one with an exit table (``exit_table``); a deflector's own check may say so
    first. Without this a deflector lacking them (a plug-in's, the fixed one) would get points from rows it never
    wrote."""
    deflector = registry.part("deflector", cfg.instrument.deflector)
    if "nominal" in ctx.models and not deflector.rigid_nominal:
        raise InputError("output.models", ",".join(ctx.models),
                         f"exact (the {deflector.kind} deflector has no rigid-array nominal model)")
    if ctx.optics == "lut" and not hasattr(deflector, "exit_table"):
        raise InputError("run.optics", ctx.optics, f"float32 or float64 (the {deflector.kind} deflector has no "
                                                   f"exit table for lut)")


def validate(cfg: RunConfig) -> RunConfig:
    """Check every setting of the parts in use; return the resolved config (derived values filled in) or raise
    InputError naming the field."""
    _check_composition(cfg)
    ctx = context(cfg)
    for section in (cfg.scene, cfg.flight, cfg.output):
        section.check(ctx)
    check_settings("scoring", cfg.scoring, ctx)
    check_settings("run", cfg.run, ctx)
    for kind in cfg.parts_in_use():
        check_settings(kind, getattr(cfg, kind), ctx)
    _check_deflector(cfg, ctx)
    resolved = copy_config(cfg)
    for kind in resolved.parts_in_use():
        resolved.parts[kind] = getattr(resolved, kind).resolved()
    return resolved
