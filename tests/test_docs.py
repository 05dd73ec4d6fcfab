"""The documentation builds with warnings as errors (``mkdocs build --strict``), its generated pages say what the
code says, and a broken link fails the build.

The site is built once into a temporary folder, with an examples folder holding the repository's examples and a
throwaway one. The settings each instrument page must hold are taken here from the registry and the preset,
independently of ``docs/hooks.py``, which generates them.
"""
import dataclasses
import html
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import mkdocstrings  # noqa: F401  (the docs build needs it: installed with the test extra)
import pytest
import yaml

import flightsim  # noqa: E402
from flightsim.core import registry  # noqa: E402
from flightsim.engine.products import catalog as _products  # noqa: E402,F401  (registers the products)
from flightsim.engine.readouts import catalog as _readouts  # noqa: E402,F401  (registers the readouts)
from flightsim.core.settings import toml_value  # noqa: E402
from flightsim.engine.config_io import PRESETS  # noqa: E402
from flightsim.platforms.flight import FlightSettings  # noqa: E402
from flightsim.scenes.settings import SceneSettings, scene_kind  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
THROWAWAY = '''"""Print the parts of the default instrument.

A throwaway example the documentation test writes.
"""
import flightsim

print(flightsim.load_config().instrument)
'''


def _build(config: Path, site: Path, examples: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
               NO_MKDOCS_2_WARNING="1")
    if examples is not None:
        env["FLIGHTSIM_DOCS_EXAMPLES"] = str(examples)
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site built from mkdocs.yml, with the repository's examples and a throwaway one."""
    tmp = tmp_path_factory.mktemp("docs")
    examples = tmp / "examples"
    examples.mkdir()
    for path in sorted((ROOT / "examples").glob("*.py")) if (ROOT / "examples").is_dir() else []:
        shutil.copy(path, examples / path.name)
    (examples / "zz_throwaway_example.py").write_text(THROWAWAY, encoding="utf-8")
    built = _build(ROOT / "mkdocs.yml", tmp / "site", examples)
    assert built.returncode == 0, built.stdout + built.stderr
    return tmp / "site"


def _page(site: Path, uri: str) -> str:
    return (site / uri / "index.html").read_text(encoding="utf-8")


def _plain(fragment: str) -> str:
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", fragment)).split())


def _rows_by_table(page: str) -> dict[str, dict[str, str]]:
    """{table: {setting: value cell as text}} of the settings tables under headings naming ``[table]``."""
    out: dict[str, dict[str, str]] = {}
    for part in re.split(r"<h3", page)[1:]:
        heading = re.match(r"[^>]*>(.*?)</h3>", part, re.S)
        table = re.search(r"\[(\w+)\]", _plain(heading.group(1))) if heading else None
        if table is None:
            continue
        for row in re.findall(r"<tr>(.*?)</tr>", part, re.S):
            cells = re.findall(r"<td>(.*?)</td>", row, re.S)
            if len(cells) == 5:
                out.setdefault(table.group(1), {})[_plain(cells[0])] = _plain(cells[1])
    return out


def _expected(name: str) -> dict[str, dict[str, object]]:
    """{table: {setting: value}} of every setting instrument ``name`` uses, from the registry and its preset."""
    cfg = flightsim.load_config(instrument=name)
    i = cfg.instrument
    out = {"instrument": {f.name: getattr(i, f.name) for f in dataclasses.fields(i)}}
    for role, kinds in (("emitter", [i.emitter]), ("deflector", [i.deflector]), ("detector", [i.detector]),
                        ("errors", list(i.errors))):
        for kind in kinds:
            settings = registry.kinds(role)[kind].settings
            out[kind] = {f.name: getattr(getattr(cfg, kind), f.name) for f in dataclasses.fields(settings)}
    sections = {"scene": (SceneSettings, registry.kinds("scene")[scene_kind(cfg.scene.name)].settings),
                "flight": (FlightSettings, registry.kinds("platform")[cfg.flight.platform].settings)}
    output = registry.kinds("detector")[i.detector].output
    if output is not None:
        sections["output"] = (registry.kinds("output")[output].settings,)
    for table, classes in sections.items():
        section = getattr(cfg, table)
        out[table] = {f.name: getattr(section, f.name) for cls in classes for f in dataclasses.fields(cls)}
    return out


@pytest.mark.parametrize("name", PRESETS)
def test_instrument_page_holds_every_setting_of_its_parts(site, name):
    page = _page(site, f"instruments/{name}")
    rows = _rows_by_table(page)
    expected = _expected(name)
    text = _plain(page)
    for table, settings in expected.items():
        if not settings:  # a part without settings (the discrete detector): named among the parts
            assert f"{table} [{table}]" in text, f"{name}: part {table} missing"
            continue
        assert table in rows, f"{name}: no settings table for [{table}]"
        for setting, value in settings.items():
            assert setting in rows[table], f"{name}: [{table}] {setting} missing"
            assert rows[table][setting].startswith(toml_value(value)), (name, table, setting, rows[table][setting])


def test_instrument_pages_show_their_figures(site):
    for name in PRESETS:
        page_dir = site / "instruments" / name
        images = re.findall(r'<img[^>]*src="([^"]+)"', _page(site, f"instruments/{name}"))
        assert images, name
        for src in images:
            assert (page_dir / src).resolve().is_file(), (name, src)


def test_parts_page_lists_every_kind_with_its_settings(site):
    page = _page(site, "parts")
    for role in registry.ROLES:
        for kind, part in registry.kinds(role).items():
            assert f'id="{role}-{kind}"' in page, (role, kind)
            if role in registry.ENGINE_ROLES:  # readouts and products: no settings
                continue
            for f in dataclasses.fields(part.settings):
                assert f"<code>{f.name}</code>" in page, (role, kind, f.name)


def test_api_reference_documents_the_public_api(site):
    api = _page(site, "api/api")
    for name in ("load_config", "simulate", "sweep", "budget", "Result", "Returns"):
        assert f'id="flightsim.api.{name}"' in api, name
    assert 'id="flightsim.engine.config.RunConfig"' in _page(site, "api/engine.config")
    assert 'id="flightsim.engine.config_io.to_toml"' in _page(site, "api/engine.config_io")
    assert 'id="flightsim.core.settings.setting"' in _page(site, "api/core.settings")
    assert 'id="flightsim.core.registry.register"' in _page(site, "api/core.registry")
    assert 'id="flightsim.instrument.base.Deflector"' in _page(site, "api/instrument.base")
    for page in (site / "api").rglob("index.html"):
        assert not re.search(r":(func|class|meth|mod):", page.read_text(encoding="utf-8")), page


def test_examples_are_rendered_with_their_source(site):
    index = _page(site, "examples")
    names = sorted(p.name for p in (ROOT / "examples").glob("*.py")) if (ROOT / "examples").is_dir() else []
    for name in names + ["zz_throwaway_example.py"]:
        if name.startswith("_"):
            continue
        assert name in index, name
        page = "".join(_plain(_page(site, f"examples/{Path(name).stem}")).split())
        source = (ROOT / "examples" / name).read_text(encoding="utf-8") if name in names else THROWAWAY
        for line in source.strip().splitlines()[-3:]:  # the code, highlighted token by token
            assert "".join(line.split()) in page, (name, line)


def test_a_broken_link_fails_the_build(tmp_path):
    docs = tmp_path / "docs"
    shutil.copytree(ROOT / "docs", docs, ignore=shutil.ignore_patterns("__pycache__"))
    (docs / "broken.md").write_text("# Broken\n\nSee [the missing page](no-such-page.md).\n", encoding="utf-8")
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    config["docs_dir"] = str(docs)
    config["hooks"] = [str(ROOT / hook) for hook in config["hooks"]]
    mkdocstrings = next(p["mkdocstrings"] for p in config["plugins"] if isinstance(p, dict) and "mkdocstrings" in p)
    python = mkdocstrings["handlers"]["python"]
    python["paths"] = [str(ROOT)]
    python["options"]["extensions"] = [str(ROOT / ext) for ext in python["options"]["extensions"]]
    config["nav"].append({"Broken": "broken.md"})
    (tmp_path / "mkdocs.yml").write_text(yaml.safe_dump(config, sort_keys=False), encoding="utf-8")
    built = _build(tmp_path / "mkdocs.yml", tmp_path / "site", tmp_path / "no-examples")
    assert built.returncode != 0
    warnings = [line for line in built.stderr.splitlines() if line.startswith("WARNING")]
    assert warnings and all("broken.md" in line and "no-such-page.md" in line for line in warnings), built.stderr
