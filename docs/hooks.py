"""MkDocs hooks: the parts of the documentation made from the code at build time.

- Markers ``<!-- flightsim: NAME [ARG] -->`` in a page are replaced by Markdown made from the part registry
  (:mod:`flightsim.core.registry`) and the built-in instruments (:mod:`flightsim.engine.config_io`):

  ============================  ===========================================================================
  ``presets``                   the built-in instruments and the parts each is composed of
  ``instrument-parts NAME``     the parts of instrument NAME, linked to their entries on the parts page
  ``instrument-settings NAME``  every table instrument NAME uses, one row per setting: its value in the
                                instrument (as ``flightsim config --instrument NAME`` prints it), the part's
                                default where that differs, unit, allowed values and meaning
  ``preset-toml NAME``          the preset file of instrument NAME, with its comments
  ``parts``                     every registered part kind, by role, with its settings
  ``part-settings KIND``        the settings of instrument part KIND (its table), with their defaults
  ``section TABLE``             the settings of a fixed table (instrument, scene, flight, scoring, run) that
                                every kind shares
  ``kinds ROLE``                the kinds of a role (scene, platform, output) that add settings to a section
  ============================  ===========================================================================

- ``results/`` (reports, figures, tables) is copied into the site at build time, so pages link to
  ``results/...`` and the PNGs are not duplicated under ``docs/``; the reports join the navigation under
  Results.
- Every ``examples/*.py`` that exists at build time (``$FLIGHTSIM_DOCS_EXAMPLES`` names another directory)
  becomes a page with its docstring and source, listed under Examples; no directory or an empty one gives
  an index saying so.
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import html
import os
import re
import sys
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent  # the repository the docs describe
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from flightsim.core import registry  # noqa: E402
from flightsim.core.settings import Settings, allowed_text, toml_value  # noqa: E402
from flightsim.engine import config as config_module  # noqa: E402  (imports register the built-in parts)
from flightsim.engine.config_io import PRESETS, preset_config, preset_path  # noqa: E402
from flightsim.engine.products import catalog as _products  # noqa: E402,F401  (registers the products)
from flightsim.engine.readouts import catalog as _readouts  # noqa: E402,F401  (registers the readouts)
from flightsim.platforms.flight import FlightSettings  # noqa: E402
from flightsim.scenes.settings import SceneSettings  # noqa: E402
from flightsim.scoring.settings import ScoringSettings  # noqa: E402

MARKER = re.compile(r"<!--\s*flightsim:\s*([\w-]+)(?:\s+([\w-]+))?\s*-->")
RESULT_SUFFIXES = (".md", ".png", ".csv", ".json", ".toml")
ROLE_TITLES = {"emitter": "Emitters", "deflector": "Deflectors", "detector": "Detectors", "errors": "Error models",
               "platform": "Platforms", "scene": "Scene kinds", "output": "Outputs", "readout": "Readouts",
               "product": "Products"}
SETTINGS_ROLES = tuple(role for role in registry.ROLES if role not in registry.ENGINE_ROLES)
SECTION_SETTINGS = {"instrument": config_module.InstrumentSettings, "scene": SceneSettings,
                    "flight": FlightSettings, "scoring": ScoringSettings, "run": config_module.RunSettings}
SECTION_OF_ROLE = {"scene": "scene", "platform": "flight", "output": "output"}
ROLE_OF_SECTION = {table: role for role, table in SECTION_OF_ROLE.items()}


# ---------------------------------------------------------------------------------------------
# Markdown of settings


def _text(text: str) -> str:
    """Plain text for a Markdown table cell: HTML and Markdown's own characters escaped."""
    text = html.escape(" ".join(text.split()), quote=False)
    return re.sub(r"([\\`*_\[\]|])", r"\\\1", text)


def _code(value) -> str:
    text = toml_value(value)
    return f"`{text}`" if text else "`\"\"`"


def _doc(cls: type) -> str:
    return " ".join((cls.__doc__ or "").split())


def _allowed(field: dataclasses.Field) -> str:
    """What a field accepts (as error messages and ``flightsim config`` say it), without the unit."""
    text = allowed_text(field.metadata, field.default)
    unit = field.metadata["unit"]
    return text[: -len(unit) - 1] if unit and text.endswith(" " + unit) else text


def settings_table(settings: Settings | type) -> str:
    """One row per setting: name, default (of a class) or value (of an instance, the default noted where it
    differs), unit, allowed values, meaning."""
    fields = dataclasses.fields(settings)
    if not fields:
        return "No settings of its own.\n"
    instance = settings if isinstance(settings, Settings) else None
    rows = [f"| setting | {'value' if instance is not None else 'default'} | unit | allowed | meaning |",
            "| --- | --- | --- | --- | --- |"]
    for f in fields:
        value = _code(getattr(instance, f.name) if instance is not None else f.default)
        if instance is not None and getattr(instance, f.name) != f.default:
            value += f"<br>(default {_code(f.default)})"
        unit = _text(f.metadata["unit"]) or ""
        rows.append(f"| `{f.name}` | {value} | {unit} | {_text(_allowed(f))} | {_text(f.metadata['doc'])} |")
    return "\n".join(rows) + "\n"


def _selected_by(role: str, kind: str, part: type) -> str:
    """How a run comes to use ``kind``."""
    if role in registry.INSTRUMENT_ROLES:
        if role == "errors":
            return f'`instrument.errors = ["{kind}"]`; settings in `[{kind}]`'
        return f'`instrument.{role} = "{kind}"`; settings in `[{kind}]`'
    if role == "platform":
        return f'`flight.platform = "{kind}"`; settings join `[flight]`'
    if role == "scene":
        suffixes = getattr(part, "suffixes", ())
        how = (f"`scene.name` = a path ending in {', '.join(f'`{s}`' for s in suffixes)}" if suffixes
               else f'`scene.name = "{kind}"`')
        return f"{how}; settings join `[scene]`"
    detectors = [k for k, d in registry.kinds("detector").items() if getattr(d, "output", None) == kind]
    return f"runs of the {' or '.join(f'`{d}`' for d in detectors) or 'no'} detector; settings in `[output]`"


def _autoref(path: str) -> str:
    """An optional cross-reference: a link where the API reference documents ``path``, plain code elsewhere."""
    return f'<autoref identifier="{path}" optional>`{path}`</autoref>'


def anchor(role: str, kind: str) -> str:
    return f"{role}-{kind}"


# ---------------------------------------------------------------------------------------------
# the built-in instruments


@functools.cache
def preset(name: str):
    """The resolved config of a built-in instrument, as ``flightsim config --instrument NAME`` prints it."""
    if name not in PRESETS:
        raise PluginError(f"flightsim docs: no built-in instrument {name!r} (one of {', '.join(PRESETS)})")
    return config_module.validate(preset_config(name))


def composition(name: str) -> list[tuple[str, str, str]]:
    """(role, kind, table) of every part instrument NAME uses, the section kinds included."""
    cfg = preset(name)
    out = [(role, kind, kind) for kind, role in cfg.parts_in_use().items()]
    out.append(("platform", cfg.flight.kind, "flight"))
    out.append(("scene", cfg.scene.kind, "scene"))
    if cfg.output.kind is not None:
        out.append(("output", cfg.output.kind, "output"))
    return out


def presets_table(page_dir: str) -> str:
    prefix = "" if page_dir == "instruments" else "instruments/"
    rows = ["| instrument | emitter | deflector | detector | error models | platform | scene |",
            "| --- | --- | --- | --- | --- | --- | --- |"]
    for name in PRESETS:
        cfg = preset(name)
        i = cfg.instrument
        errors = ", ".join(f"`{e}`" for e in i.errors) or "—"
        rows.append(f"| [{name}]({prefix}{name}.md) | `{i.emitter}` | `{i.deflector}` | `{i.detector}` | {errors} "
                    f"| `{cfg.flight.kind}` | `{cfg.scene.name}` |")
    return "\n".join(rows) + "\n"


def instrument_parts(name: str) -> str:
    rows = ["| role | kind | settings | what it is |", "| --- | --- | --- | --- |"]
    for role, kind, table in composition(name):
        part = registry.part(role, kind)
        rows.append(f"| {role} | [`{kind}`](../parts.md#{anchor(role, kind)}) | `[{table}]` "
                    f"| {_text(_doc(part.settings))} |")
    return "\n".join(rows) + "\n"


def instrument_settings(name: str) -> str:
    cfg = preset(name)
    blocks = []
    for table, _ in cfg.tables():
        if table in ("scene", "flight", "output"):
            section = getattr(cfg, table)
            role = ROLE_OF_SECTION[table]
            if section.common_settings is not None:
                blocks.append((f"`[{table}]`: every {role}", section.common_settings))
            own = section.kind_settings()
            if own is not None and dataclasses.fields(own):
                blocks.append((f"`[{table}]`: the `{section.kind}` {role}", own))
        elif table in SECTION_SETTINGS:
            blocks.append((f"`[{table}]`", getattr(cfg, table)))
        else:
            part = registry.instrument_part(table)
            blocks.append((f"`[{table}]`: the `{table}` {'error model' if part.role == 'errors' else part.role}",
                           getattr(cfg, table)))
    lead = (f"Every table a run of `{name}` uses, as `flightsim config --instrument {name}` prints it: the value "
            f"the instrument gives each setting (with the default where they differ), its unit, what it accepts "
            f"and what it means.\n\n")
    return lead + "\n".join(f"### {title}\n\n{_text(_doc(type(s)))}\n\n{settings_table(s)}" for title, s in blocks)


def preset_toml(name: str) -> str:
    preset(name)
    text = preset_path(name).read_text(encoding="utf-8")
    return f'```toml title="flightsim/instrument/presets/{name}.toml"\n{text.rstrip()}\n```\n'


# ---------------------------------------------------------------------------------------------
# every part kind; the sections


def parts_page() -> str:
    used: dict[tuple[str, str], list[str]] = {}
    for name in PRESETS:
        for role, kind, _ in composition(name):
            used.setdefault((role, kind), []).append(name)
    out = []
    for role in SETTINGS_ROLES:
        out.append(f"## {ROLE_TITLES[role]}\n")
        for kind, part in registry.kinds(role).items():
            users = ", ".join(f"[{n}](instruments/{n}.md)" for n in used.get((role, kind), [])) or "none"
            out.append(f"### `{kind}` {{#{anchor(role, kind)}}}\n\n{_text(_doc(part.settings))}\n\n"
                       f"- chosen by {_selected_by(role, kind, part)}\n"
                       f"- host class {_autoref(part.__module__ + '.' + part.__qualname__)}, settings "
                       f"{_autoref(part.settings.__module__ + '.' + part.settings.__qualname__)}\n"
                       f"- built-in instruments using it: {users}\n\n{settings_table(part.settings)}")
    return "\n".join(out + engine_parts())


def engine_parts() -> list[str]:
    """The engine's parts, which have no settings: the readouts (named by the detectors that provide them) and the
    products a run to files writes from them."""
    out = []
    for role in registry.ENGINE_ROLES:
        out.append(f"## {ROLE_TITLES[role]}\n")
        for kind, part in registry.kinds(role).items():
            owners = [k for k, d in registry.kinds("detector").items() if kind in getattr(d, "readouts", ())]
            out.append(f"### `{kind}` {{#{anchor(role, kind)}}}\n\n{_text(_doc(part))}\n\n"
                       f"- detectors: {', '.join(f'`{o}`' for o in owners) or 'none'}\n"
                       f"- class {_autoref(part.__module__ + '.' + part.__qualname__)}\n")
    return out


def part_settings(kind: str) -> str:
    part = registry.instrument_part(kind)
    if part is None:
        raise PluginError(f"flightsim docs: no instrument part {kind!r}")
    return settings_table(part.settings)


def section_table(table: str) -> str:
    if table not in SECTION_SETTINGS:
        raise PluginError(f"flightsim docs: no section {table!r} (one of {', '.join(SECTION_SETTINGS)})")
    return settings_table(SECTION_SETTINGS[table])


def kinds_table(role: str) -> str:
    if role not in SECTION_OF_ROLE:
        raise PluginError(f"flightsim docs: no section kinds for {role!r} (one of {', '.join(SECTION_OF_ROLE)})")
    rows = [f"| {role} kind | chosen by | its own settings |", "| --- | --- | --- |"]
    for kind, part in registry.kinds(role).items():
        names = ", ".join(f"`{f.name}`" for f in dataclasses.fields(part.settings)) or "—"
        rows.append(f"| [`{kind}`](parts.md#{anchor(role, kind)}) | {_selected_by(role, kind, part)} | {names} |")
    return "\n".join(rows) + "\n"


def api_parts_page() -> str:
    """The API reference of every registered part's host class, by role (mkdocstrings directives)."""
    out = ["# Part classes\n", "The host class of every registered part kind, by role: what the engine builds from the part's "
           "settings (the [parts page](../parts.md) lists the settings; "
           "[`flightsim.instrument.base`](instrument.base.md) the protocols).\n"]
    for role in registry.ROLES:
        out.append(f"## {ROLE_TITLES[role]}\n")
        for kind, part in registry.kinds(role).items():
            out.append(f"::: {part.__module__}.{part.__qualname__}\n    options:\n      heading_level: 3\n")
    return "\n".join(out)


def expand(kind: str, arg: str | None, page_dir: str) -> str:
    """The Markdown of one marker."""
    makers = {"presets": lambda: presets_table(page_dir), "parts": parts_page,
              "instrument-parts": lambda: instrument_parts(arg), "instrument-settings": lambda: instrument_settings(arg),
              "preset-toml": lambda: preset_toml(arg), "section": lambda: section_table(arg),
              "kinds": lambda: kinds_table(arg), "part-settings": lambda: part_settings(arg)}
    if kind not in makers:
        raise PluginError(f"flightsim docs: unknown marker {kind!r} (one of {', '.join(makers)})")
    return makers[kind]()


# ---------------------------------------------------------------------------------------------
# results and examples


def result_files() -> list[Path]:
    results = ROOT / "results"
    return sorted(p for p in results.rglob("*") if p.is_file() and p.suffix in RESULT_SUFFIXES)


def _report_title(path: Path) -> str:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    return str(path.relative_to(ROOT))


def examples_dir() -> Path:
    return Path(os.environ.get("FLIGHTSIM_DOCS_EXAMPLES") or ROOT / "examples")


def examples() -> list[Path]:
    folder = examples_dir()
    return sorted(p for p in folder.glob("*.py") if not p.name.startswith("_")) if folder.is_dir() else []


def example_uri(path: Path) -> str:
    """The page of an example (``examples/index.md`` would take the Examples index's address)."""
    return f"examples/{path.stem}{'_' if path.stem == 'index' else ''}.md"


def _docstring(source: str) -> str:
    try:
        return ast.get_docstring(ast.parse(source)) or ""
    except SyntaxError:
        return ""


def example_page(path: Path) -> str:
    source = path.read_text(encoding="utf-8")
    fence = "`" * max(3, 1 + max((len(run) for run in re.findall(r"`+", source)), default=0))
    doc = _docstring(source)
    return (f"# `{path.name}`\n\n{doc}\n\nRun it from the repository root: `python3 examples/{path.name}`\n\n"
            f'{fence}python title="examples/{path.name}"\n{source.rstrip()}\n{fence}\n')


def examples_index(paths: list[Path]) -> str:
    text = ("# Examples\n\nScripts in `examples/` that use the [Python API](api/index.md); each page shows one "
            "with its source. Run them from the repository root.\n\n")
    if not paths:
        return text + "No examples yet: `examples/` holds no scripts in this checkout.\n"
    rows = ["| example | what it does |", "| --- | --- |"]
    for p in paths:
        first = _docstring(p.read_text(encoding="utf-8")).strip().split("\n\n")[0]
        rows.append(f"| [`{p.name}`]({example_uri(p)}) | {_text(first)} |")
    return text + "\n".join(rows) + "\n"


# ---------------------------------------------------------------------------------------------
# the hooks


def _replace_nav(nav: list, title: str, entries: list) -> None:
    for i, item in enumerate(nav):
        if isinstance(item, dict) and title in item:
            nav[i] = {title: entries}
            return
    raise PluginError(f"flightsim docs: mkdocs.yml's nav has no {title!r} entry")


def on_config(config):
    """The nav's Examples and Results sections: their index pages, then one page per example and report."""
    nav = config.nav
    _replace_nav(nav, "Examples", ["examples.md"] + [{p.name: example_uri(p)} for p in examples()])
    reports = [p for p in result_files() if p.suffix == ".md"]
    _replace_nav(nav, "Results", ["results.md"] + [{_report_title(p): str(p.relative_to(ROOT))} for p in reports])
    return config


def on_files(files: Files, config) -> Files:
    """Add results/, the API page of the part classes and the example pages to the site's files."""
    for path in result_files():
        files.append(File.generated(config, str(path.relative_to(ROOT)), abs_src_path=str(path)))
    paths = examples()
    files.append(File.generated(config, "api/parts.md", content=api_parts_page()))
    files.append(File.generated(config, "examples.md", content=examples_index(paths)))
    for path in paths:
        files.append(File.generated(config, example_uri(path), content=example_page(path)))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    """Replace the markers with the Markdown made from the registry and the presets."""
    page_dir = os.path.dirname(page.file.src_uri)
    return MARKER.sub(lambda m: expand(m.group(1), m.group(2), page_dir), markdown)
