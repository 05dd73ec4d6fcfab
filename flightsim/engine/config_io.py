"""Run configs in and out of TOML, the built-in instruments (presets) and the documented TOML of
``flightsim config``.

``run.toml`` (:func:`to_toml`) holds the tables of the parts in use only, floats with full precision, so that
``--config DIR/run.toml`` reproduces a run byte for byte. Files of the first format are read through
:mod:`flightsim.engine.legacy` (which moves each setting to its part's table), then the settings of kinds the
run does not use are dropped here.
"""
from __future__ import annotations

import tomllib
from pathlib import Path

from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.core.settings import table_toml
from flightsim.engine import legacy
from flightsim.engine.config import RunConfig, copy_config, set_value

PRESET_DIR = Path(__file__).resolve().parent.parent / "instrument" / "presets"
PRESETS = ("risley", "change3", "spad", "change1", "atlas", "gedi", "vz2000")
PREBUILT_RUNS = (tuple((name, None, "simulate") for name in PRESETS)
                 + tuple((name, "forest", "simulate") for name in ("risley", "gedi", "atlas", "vz2000"))
                 + (("gedi", "cloud", "simulate"), ("risley", None, "sweep"), ("risley", None, "survey"),
                    ("spad", None, "spad"), ("atlas", None, "calibrate"), ("risley", None, "selfcal"))
                 + tuple((name, None, "budget") for name in ("change3", "risley", "spad", "atlas")))
"""(instrument, scene, command) of each run whose kernels ship prebuilt (:mod:`flightsim.core.prebuilt`;
``flightsim compile --for`` the command, :mod:`flightsim.studies.compile_targets`): every built-in instrument over
its own scene (None) writing its product, the discrete (airborne and terrestrial), waveform and photon detectors over
the procedural forest (and so over a point cloud's leaves), GEDI over an ALS point cloud ("cloud": a small synthetic
one, :func:`flightsim.cli.prebuilt_scene_flags`), a sweep's configuration (`flightsim sweep`, `flightsim paper`), a
survey's tasks, the studies of SPAD (`flightsim spad`), ATLAS (the corner-cube calibration, `flightsim calibrate`) and
Risley (its self-calibration, `flightsim selfcal`) and the error budgets that compile kernels of their own (`flightsim
budget`; change1's are its product's)."""
SELECTORS = {"scene": ("name",), "flight": ("platform",)}  # applied before the other settings of their table


def _ordered(data: dict) -> list[str]:
    first = [t for t in ("instrument", "flight", "scene", "output") if t in data]
    return first + [t for t in data if t not in first]


def from_dict(data: dict, base: RunConfig | None = None) -> RunConfig:
    """A config from nested tables (as read from TOML) over ``base`` (default: the built-in defaults); unknown
    settings are errors, first-format tables are moved to where their settings live now."""
    cfg = copy_config(base) if base is not None else RunConfig()
    if legacy.is_legacy(data):
        data = _drop_idle_kind_settings(legacy.migrate(data))
    for table in _ordered(data):
        values = data[table]
        if not isinstance(values, dict):
            raise InputError(table, values, "a table of settings")
        keys = sorted(values, key=lambda k: k not in SELECTORS.get(table, ()))
        for key in keys:
            set_value(cfg, f"{table}.{key}", values[key])
    return cfg


def _drop_idle_kind_settings(data: dict) -> dict:
    """The first format wrote every flight, scene, output and scoring setting; those of kinds not in use keep
    their defaults and are dropped here (the config refuses a value given to a kind it does not use)."""
    probe = RunConfig()
    for key in ("instrument", "flight", "scene"):
        for name, value in data.get(key, {}).items():
            if key == "instrument" or name in ("platform", "name"):
                set_value(probe, f"{key}.{name}", value)
    detector = getattr(probe.detector_part, "scored", True)
    for table in ("scene", "flight", "output", "scoring"):
        values = data.get(table, {})
        section = getattr(probe, table)
        in_use = set(section.names()) if table != "scoring" else (set(values) if detector else set())
        for name in list(values):
            never_used = f"{table}.{name}" == "output.models"  # only discrete runs georeference by models
            if name not in in_use and (never_used or legacy.holds_old_default(f"{table}.{name}", values[name])):
                del values[name]
    return data


def load_toml(path: str | Path, base: RunConfig | None = None) -> RunConfig:
    """A run config from a TOML file over ``base`` (unvalidated; call :func:`flightsim.engine.config.validate`)."""
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except OSError as exc:
        raise InputError("--config", str(path), f"a readable TOML file ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError("--config", str(path), f"valid TOML ({exc})") from None
    return from_dict(data, base)


def preset_path(name: str) -> Path:
    """The TOML of a built-in instrument."""
    if name not in PRESETS:
        raise InputError("--instrument", name, "one of " + ", ".join(PRESETS))
    return PRESET_DIR / f"{name}.toml"


def preset_config(name: str) -> RunConfig:
    """The config of a built-in instrument (unvalidated). Its tables are the instrument's, not the user's: a
    later change of a part drops them without complaint."""
    path = preset_path(name)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise InputError("--instrument", name, f"a readable preset ({path}: {exc})") from None
    cfg = from_dict(data)
    orphan = cfg.given_unused()
    if orphan is not None:
        raise InputError("--instrument", name, f"a preset whose part tables are its parts' ({path} has "
                         f"[{orphan[0]}], which its instrument ({', '.join(cfg.parts_in_use())}) does not use)")
    cfg.mark_baseline()
    return cfg


def _title(table: str, cfg: RunConfig) -> str:
    """A table's heading comment: what it is (the part's settings' first docstring line)."""
    if table in ("scene", "flight", "output"):
        section = getattr(cfg, table)
        own = section.kind_settings()
        doc = _sentence(own or section.common_settings)
        return f"{doc} ({section.kind})" if own is not None else doc
    part = registry.instrument_part(table)
    doc = _sentence(getattr(cfg, table))
    return f"{part.role} {table}: {doc}" if part is not None else doc


def _sentence(settings) -> str:
    """The first sentence of a settings class's docstring, on one line."""
    text = " ".join(type(settings).__doc__.split())
    return text.split(". ")[0].rstrip(".") + "."


def to_toml(cfg: RunConfig, comments: bool = False) -> str:
    """The config as TOML: the tables of the parts in use; with ``comments`` each setting carries its meaning,
    unit and range, and each table what it is."""
    head = "# flightsim run config: `flightsim config --instrument NAME` prints a preset with every setting explained\n\n"
    body = "\n".join(table_toml(table, entries, comments, _title(table, cfg)) for table, entries in cfg.tables())
    return (head if comments else "") + body
