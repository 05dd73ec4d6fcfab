"""Part-scoped settings: run.toml holds the tables of the parts in use only, a setting of a part the run does not
use is refused naming it, presets document themselves, and run.toml files of the first format are read."""
from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from flightsim.cli import main
from flightsim.core import registry
from flightsim.core.errors import InputError
from flightsim.engine.config import RunConfig, set_value, validate
from flightsim.engine.config_io import PRESETS, load_toml, preset_config, to_toml
from flightsim.instrument.pairs import SINGLE_BEAM

LEGACY = Path(__file__).parent / "data" / "legacy"  # run.toml of each preset as the first format wrote it
TABLES = {
    "risley": {"instrument", "fan", "risley", "discrete", "scene", "flight", "output", "scoring", "run"},
    "change3": {"instrument", "channels", "galvo", "discrete", "ranging", "scene", "flight", "output", "scoring", "run"},
    "spad": {"instrument", "fan", "fsm", "photon", "scene", "flight", "output", "run"},
    "change1": {"instrument", "fan", "fixed", "waveform", "scene", "flight", "run"},
    "atlas": {"instrument", "pairs", "fixed", "photon", "scene", "flight", "output", "run"},
    "gedi": {"instrument", "fan", "fixed", "waveform", "scene", "flight", "run"},
    "vz2000": {"instrument", "fan", "panoramic", "discrete", "ranging", "scene", "flight", "output", "scoring", "run"},
}


def _error(args: list[str], capsys) -> str:
    assert main(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


@pytest.mark.parametrize("name", PRESETS)
def test_run_toml_holds_the_tables_of_the_parts_in_use_only(name):
    assert set(tomllib.loads(to_toml(validate(preset_config(name))))) == TABLES[name]


def test_a_waveform_run_has_no_prism_galvo_fsm_or_error_tables():
    text = to_toml(validate(preset_config("change1")))
    for absent in ("[risley]", "[galvo]", "[fsm]", "[ranging]", "[pose]", "apex_angle_deg", "b1_arcsec",
                   "believed_"):
        assert absent not in text


@pytest.mark.parametrize("name", [p for p in PRESETS if (LEGACY / f"{p}.toml").exists()])  # gedi came later
def test_first_format_run_toml_reads_as_the_preset(name):
    old = validate(load_toml(LEGACY / f"{name}.toml"))
    preset = preset_config(name)
    if name == "atlas":  # the first format's atlas flew the one nadir beam the preset now flies as SINGLE_BEAM
        for key, value in SINGLE_BEAM.items():
            set_value(preset, key, value)
    assert to_toml(old) == to_toml(validate(preset))


def test_first_format_value_of_a_part_not_in_use_is_refused_naming_it(tmp_path):
    text = (LEGACY / "change1.toml").read_text().replace("b1_arcsec = 0.0", "b1_arcsec = 3.0")
    (tmp_path / "old.toml").write_text(text)
    with pytest.raises(InputError, match=r"errors\.b1_arcsec.*galvo.*fan, fixed, waveform"):
        load_toml(tmp_path / "old.toml")


def test_first_format_errors_turn_on_their_error_models(tmp_path):
    text = (LEGACY / "risley.toml").read_text().replace("range_noise_m = 0.0", "range_noise_m = 0.02")
    text = text.replace("boresight_arcsec = [0.0, 0.0, 0.0]", "boresight_arcsec = [1.0, 0.0, 0.0]")
    (tmp_path / "old.toml").write_text(text)
    cfg = validate(load_toml(tmp_path / "old.toml"))
    assert set(cfg.instrument.errors) == {"ranging", "pose"}
    assert cfg.ranging.noise_m == 0.02 and cfg.pose.boresight_arcsec == (1.0, 0.0, 0.0)


def test_set_on_a_part_the_instrument_does_not_use_exits_2_naming_it(tmp_path, capsys):
    out = tmp_path / "w"
    line = _error(["simulate", "--instrument", "change1", "--set", "galvo.b1_arcsec=3", "--out", str(out)], capsys)
    assert "galvo.b1_arcsec" in line and "[galvo] is a deflector" in line and "fan, fixed, waveform" in line
    assert not out.exists()


@pytest.mark.parametrize("setting, named, owner", [
    ("flight.descent_mps=1", "flight.descent_mps", "hover platform"),
    ("flight.inclination_deg=98", "flight.inclination_deg", "orbit platform"),
    ("scene.cell_m=2", "scene.cell_m", "dem scene"),
    ("scene.planes=none", "scene.planes", "mesh scene"),
    ("output.crs=EPSG:32633", "output.crs", "photons output"),
])
def test_setting_of_another_kind_exits_2_naming_the_kind_in_use(tmp_path, capsys, setting, named, owner):
    line = _error(["simulate", "--set", setting, "--out", str(tmp_path / "o")], capsys)
    assert named in line and owner in line


@pytest.mark.parametrize("setting, named, allowed", [
    ("instrument.deflector=palmer", "instrument.deflector", "one of fixed, fsm, galvo, panoramic, risley"),
    ("instrument.errors=wind", "instrument.errors", "pose, ranging"),
    ("risley.colour=red", "risley.colour", "a setting of [risley] (prf_hz"),
    ("sensor.array=4", "sensor.array", "fan.array (this setting moved)"),
    ("errors.jitter_s=1e-9", "errors.jitter_s", "ranging.jitter_s"),
    ("processing.refractive_index=1.5", "processing.refractive_index", "risley.believed_refractive_index"),
    ("flight.platform=balloon", "flight.platform", "one of"),
])
def test_unknown_kinds_and_settings_say_what_is_allowed(tmp_path, capsys, setting, named, allowed):
    line = _error(["simulate", "--set", setting, "--out", str(tmp_path / "o")], capsys)
    assert named in line and allowed in line


def test_a_config_file_missing_a_part_table_gets_its_defaults_and_the_composition_checked(tmp_path, capsys):
    (tmp_path / "galvo.toml").write_text('[instrument]\ndeflector = "galvo"\n')
    line = _error(["simulate", "--config", str(tmp_path / "galvo.toml"), "--out", str(tmp_path / "o")], capsys)
    assert "instrument.emitter" in line and "channels with the galvo deflector" in line
    (tmp_path / "galvo.toml").write_text('[instrument]\nemitter = "channels"\ndeflector = "galvo"\n'
                                         '[output]\nmodels = ["exact"]\n')
    cfg = validate(load_toml(tmp_path / "galvo.toml"))
    assert dataclasses.astuple(cfg.galvo.resolved()) == dataclasses.astuple(type(cfg.galvo)().resolved())


def _preset_without(tmp_path, monkeypatch, table: str | None, text: str | None = None) -> None:
    """The built-in presets in tmp_path, spad.toml without one of its tables (or replaced by text)."""
    from flightsim.engine import config_io

    for name in PRESETS:
        source = config_io.preset_path(name).read_text(encoding="utf-8")
        if name == "spad":
            blocks = re.split(r"(?m)^(?=\[)", source)  # the preamble, then one block per table
            source = text if text is not None else "".join(b for b in blocks if not b.startswith(f"[{table}]"))
            assert text is not None or tomllib.loads(source).keys() == tomllib.loads(
                config_io.preset_path(name).read_text(encoding="utf-8")).keys() - {table}
        (tmp_path / f"{name}.toml").write_text(source, encoding="utf-8")
    monkeypatch.setattr(config_io, "PRESET_DIR", tmp_path)


def test_a_preset_file_missing_a_part_table_flies_that_part_s_defaults(tmp_path, monkeypatch):
    _preset_without(tmp_path, monkeypatch, "fsm")
    cfg = validate(preset_config("spad"))
    assert cfg.instrument.deflector == "fsm"
    assert dataclasses.astuple(cfg.fsm.resolved()) == dataclasses.astuple(type(cfg.fsm)().resolved())


def test_a_preset_file_missing_its_instrument_table_exits_2_naming_the_orphan_table(tmp_path, monkeypatch, capsys):
    _preset_without(tmp_path, monkeypatch, "instrument")  # the default composition: fan, risley, discrete
    line = _error(["config", "--instrument", "spad"], capsys)
    assert "fsm" in line and "risley" in line, line


def test_an_unreadable_preset_file_exits_2_naming_it(tmp_path, monkeypatch, capsys):
    _preset_without(tmp_path, monkeypatch, None, text="[instrument\nemitter = 'fan'\n")
    line = _error(["config", "--instrument", "spad"], capsys)
    assert "--instrument" in line and "spad.toml" in line, line


def test_a_preset_s_tables_do_not_follow_a_part_the_user_replaces():
    cfg = preset_config("spad")  # its [photon] values are the preset's, not the user's
    for key, value in (("instrument.detector", "discrete"), ("output.models", "exact")):
        set_value(cfg, key, value)
    assert validate(cfg).instrument.detector == "discrete"


def test_a_value_given_to_a_part_by_attribute_is_refused_when_the_part_is_not_used():
    cfg = RunConfig()
    cfg.waveform.n_rings = 10
    with pytest.raises(InputError, match=r"waveform\.n_rings.*\[waveform\] is a detector"):
        validate(cfg)


@pytest.mark.parametrize("name", PRESETS)
def test_config_command_prints_a_self_documenting_file_that_reproduces_the_preset(tmp_path, capsys, name):
    assert main(["config", "--instrument", name]) == 0
    text = capsys.readouterr().out
    settings = [line for line in text.splitlines() if "=" in line and not line.startswith("#")]
    assert settings and all("  # " in line for line in settings)
    (tmp_path / "run.toml").write_text(text)
    assert to_toml(validate(load_toml(tmp_path / "run.toml"))) == to_toml(validate(preset_config(name)))


def test_every_part_setting_is_declared_with_a_meaning_and_numbers_with_a_range():
    for role in registry.ROLES:
        if role in registry.ENGINE_ROLES:  # readouts and products have no settings
            continue
        for kind, part in registry.kinds(role).items():
            for f in dataclasses.fields(part.settings):
                assert f.metadata.get("doc"), (role, kind, f.name)
                if isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
                    assert f.metadata["range"] is not None, (role, kind, f.name)


def test_config_command_is_quick_to_fail_on_bad_input():
    run = subprocess.run([sys.executable, "-m", "flightsim", "config", "--set", "fan.array=0"], capture_output=True,
                         text=True)
    assert run.returncode == 2 and run.stderr.startswith("flightsim: error: invalid fan.array = 0")
