"""Run configs of the first format (``[sensor]``, ``[errors]``, ``[processing]`` holding every part's settings),
read into the present one: each setting moves to the table of the part that owns it.

A setting of a part the run does not use (a prism value in a waveform altimeter's file) was ignored by the
first format; it is dropped when it holds the first format's default (or, for the prism, the value the
defaults derive), and refused otherwise, naming the setting, where it belongs and that the instrument does
not use it. A ranging or pose error that is set turns on the ``ranging`` or ``pose`` error model.

Plain tables in, plain tables out: this module uses no config, so the config modules call it
(:mod:`flightsim.engine.config_io` reads files through it, ``config.set_value`` asks it where an old key moved).
"""
from __future__ import annotations

import math
from typing import Any

from flightsim.core.errors import InputError
from flightsim.instrument.risley_model import apex_for_cone

LEGACY_TABLES = ("sensor", "errors", "processing")

# the first format's defaults of the settings that moved or that a part may not use
OLD_DEFAULTS: dict[str, Any] = {
    "sensor.array": 3, "sensor.spacing_mrad": 2.314, "sensor.prf_hz": 5000.0, "sensor.rotation_hz": 20.0,
    "sensor.phase0_deg": 0.0, "sensor.cone_half_angle_deg": 15.0, "sensor.apex_angle_deg": 0.0,
    "sensor.refractive_index": 1.5066, "sensor.thickness_mm": 10.0, "sensor.range_noise_m": 0.0,
    "sensor.divergence_mrad": 0.3,
    **{f"errors.{k}": 0.0 for k in ("b1_arcsec", "b2_arcsec", "b3_arcsec", "c1_arcsec", "h_noise_arcsec",
                                    "v_noise_arcsec", "channel_delay_m", "range_bias_m", "clock_drift", "tdc_bin_s",
                                    "jitter_s", "rise_time_s", "encoder_arcsec", "encoder_noise_arcsec",
                                    "fsm_noise_arcsec", "position_noise_m", "attitude_noise_arcsec")},
    "errors.cfd_fraction": 0.3, "errors.snr": 31.0, "errors.fsm_zero_arcsec": (0.0, 0.0),
    "errors.boresight_arcsec": (0.0, 0.0, 0.0),
    **{f"processing.{k}": 0.0 for k in ("refractive_index", "apex_angle_deg", "thickness_mm", "b_mm", "e_mm")},
    "channels.angles_mrad": tuple(float(17 - 2 * i) for i in range(1, 17)),
    "galvo.b_mm": 50.0, "galvo.e_mm": 20.0, "galvo.aperture_mm": 15.0, "galvo.field_deg": (30.0, 30.0),
    "galvo.strips": 17, "galvo.columns": 256, "galvo.frame_s": 0.1,
    "fsm.b2_mm": 30.0, "fsm.d_mm": 40.0, "fsm.aperture_mm": 25.0, "fsm.mode": "A", "fsm.span_mrad": (2.62, 1.80),
    "fsm.lines": 40, "fsm.frame_s": 0.86, "fsm.prf_hz": 50000.0,
    "photon.wavelength_nm": 532.0, "photon.pulse_energy_j": 1.0e-9, "photon.aperture_m": 0.05,
    "photon.optics_transmission": 0.5, "photon.pde": 0.2, "photon.pulse_fwhm_s": 1.0e-9, "photon.jitter_s": 1.0e-10,
    "photon.tdc_bin_s": 0.0, "photon.gate_m": (5.0, 600.0), "photon.noise_hz": 1.0e5, "photon.dead_time_s": 5.0e-8,
    "photon.max_events": 8, "photon.reflectance": 0.2,
    "scene.slope": 0.0, "scene.cell_m": 1.0, "scene.simplify_m": 0.0, "scene.landcover": "", "scene.buildings": "",
    "scene.planes": "auto",
    "flight.speed_kmh": 200.0, "flight.heading_deg": 0.0, "flight.roll_deg": 0.0, "flight.pitch_deg": 0.0,
    "flight.lines": 1, "flight.line_spacing_m": 200.0, "flight.trajectory": "", "flight.descent_mps": 0.0,
    "flight.body": "earth", "flight.inclination_deg": 92.0, "flight.eccentricity": 0.0, "flight.perigee_arg_deg": 0.0,
    "flight.body_rotation_period_s": 0.0, "flight.terrain_following": False,
    "output.models": ("exact", "nominal"), "output.tile_size_m": 500, "output.laz": False,
    "output.position_error": False, "output.copc": False, "output.crs": "",
    "scoring.edge_buffer_m": -1.0, "scoring.patch_m": 0.0,
}

RISLEY = ("rotation_hz", "phase0_deg", "cone_half_angle_deg", "apex_angle_deg", "refractive_index", "thickness_mm")
RANGING = {"sensor.range_noise_m": "noise_m", **{f"errors.{k}": k for k in (
    "channel_delay_m", "range_bias_m", "clock_drift", "tdc_bin_s", "jitter_s", "rise_time_s", "cfd_fraction", "snr")}}
POSE = ("boresight_arcsec", "position_noise_m", "attitude_noise_arcsec")
GALVO_ERRORS = ("b1_arcsec", "b2_arcsec", "b3_arcsec", "c1_arcsec", "h_noise_arcsec", "v_noise_arcsec")


def is_legacy(data: dict) -> bool:
    """Whether a config's tables are of the first format."""
    return any(table in data for table in LEGACY_TABLES)


def _target(old: str, emitter: str, deflector: str) -> tuple[str, str] | None:
    """Where a first-format setting lives now: (table, field); None for a table that kept its name."""
    table, _, name = old.partition(".")
    if table == "sensor":
        if name in ("array", "spacing_mrad"):
            return "fan", name
        if name == "divergence_mrad":
            return emitter, name
        if name == "prf_hz":
            return ("fixed" if deflector == "fixed" else "risley"), name
        if name in RISLEY:
            return "risley", name
        if name in ("boresight_deg", "lever_arm_m", "max_range_m"):
            return "instrument", name
    if old in RANGING:
        return "ranging", RANGING[old]
    if table == "errors":
        if name in GALVO_ERRORS:
            return "galvo", name
        if name in ("encoder_arcsec", "encoder_noise_arcsec"):
            return "risley", name
        if name == "fsm_zero_arcsec":
            return "fsm", "zero_arcsec"
        if name == "fsm_noise_arcsec":
            return "fsm", "noise_arcsec"
        if name in POSE:
            return "pose", name
    if table == "processing":
        return ("galvo" if name in ("b_mm", "e_mm") else "risley"), f"believed_{name}"
    if table in LEGACY_TABLES:
        raise InputError(old, "?", "a setting of the first config format")  # no such setting ever existed
    return None


def _same(value: Any, default: Any) -> bool:
    if isinstance(default, tuple):
        return isinstance(value, (list, tuple)) and len(value) == len(default) and all(
            math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=0.0) if not isinstance(b, str) else a == b
            for a, b in zip(value, default))
    if isinstance(default, float) and isinstance(value, (int, float)) and not isinstance(value, bool):
        return math.isclose(float(value), default, rel_tol=1e-12)
    return value == default


def _idle(old: str, value: Any, sensor: dict) -> bool:
    """Whether a setting of a part the run does not use holds what the first format's defaults gave it."""
    if old in OLD_DEFAULTS and _same(value, OLD_DEFAULTS[old]):
        return True
    n = float(sensor.get("refractive_index", OLD_DEFAULTS["sensor.refractive_index"]))
    cone = float(sensor.get("cone_half_angle_deg", OLD_DEFAULTS["sensor.cone_half_angle_deg"]))
    derived = {"sensor.apex_angle_deg": math.degrees(apex_for_cone(math.radians(cone), n))}
    derived.update({f"processing.{k}": sensor.get(k, derived.get(f"sensor.{k}", OLD_DEFAULTS.get(f"sensor.{k}")))
                    for k in ("refractive_index", "apex_angle_deg", "thickness_mm")})
    derived.update({"processing.b_mm": OLD_DEFAULTS["galvo.b_mm"], "processing.e_mm": OLD_DEFAULTS["galvo.e_mm"]})
    return old in derived and derived[old] is not None and _same(value, float(derived[old]))


def migrate(data: dict) -> dict:
    """The tables of a first-format config in the present format (InputError naming a setting that cannot move).

    Every flight, scene, output and scoring setting is kept: dropping those of kinds the run does not use
    needs the config itself (:func:`flightsim.engine.config_io.from_dict` does it)."""
    instrument = dict(data.get("instrument", {}))
    emitter, deflector = instrument.get("emitter", "fan"), instrument.get("deflector", "risley")
    detector = instrument.get("detector", "discrete")
    used = {emitter, deflector, detector}
    sensor = data.get("sensor", {})
    out: dict[str, dict] = {"instrument": instrument}
    errors: list[str] = list(instrument.get("errors", []))
    for table, values in data.items():
        if not isinstance(values, dict):
            raise InputError(table, values, "a table of settings")
        for name, value in values.items():
            old = f"{table}.{name}"
            target = _target(old, emitter, deflector)
            if target is None:
                if table in ("galvo", "fsm", "channels", "photon", "waveform") and table not in used:
                    if _idle(old, value, sensor):
                        continue
                    raise InputError(old, value, f"no value here: [{table}] is a part this instrument does not use")
                out.setdefault(table, {})[name] = value
                continue
            new_table, new_name = target
            if new_table in ("ranging", "pose"):
                if _idle(old, value, sensor):
                    continue
                if new_table not in errors:
                    errors.append(new_table)
            elif new_table not in used | {"instrument"}:
                if _idle(old, value, sensor):
                    continue
                raise InputError(old, value, f"no value here: it is now {new_table}.{new_name}, and [{new_table}] is "
                                             f"a part this instrument ({emitter}, {deflector}, {detector}) does not use")
            out.setdefault(new_table, {})[new_name] = value
    if errors:
        instrument["errors"] = errors
    return out


def holds_old_default(dotted: str, value: Any) -> bool:
    """Whether ``table.field`` holds the value the first format wrote for it by default (False for a setting
    the first format gave no default)."""
    return _same(value, OLD_DEFAULTS.get(dotted, object()))


def moved(dotted: str) -> str | None:
    """For a first-format setting named on the command line: where it is now, in words (None if it never was)."""
    try:
        target = _target(dotted, "fan", "risley")
    except InputError:
        return None
    if target is None:
        return None
    table, name = target
    if dotted == "sensor.prf_hz":
        return "the deflector's table: risley.prf_hz, fixed.prf_hz, fsm.prf_hz (this setting moved)"
    if dotted == "sensor.divergence_mrad":
        return "the emitter's table: fan.divergence_mrad or channels.divergence_mrad (this setting moved)"
    extra = " (and instrument.errors listing it)" if table in ("ranging", "pose") else ""
    return f"{table}.{name}{extra} (this setting moved)"
