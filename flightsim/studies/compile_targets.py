"""What `flightsim compile --for COMMAND` compiles: the kernels a run of that command launches, each loaded into Warp's
kernel cache (or from it) by the command's own code run once and small, or by listing them without flying. The
prebuilt set (:data:`~flightsim.engine.config_io.PREBUILT_RUNS`) names its runs by these commands."""
from __future__ import annotations

import tempfile
from pathlib import Path

from flightsim.engine.config import RunConfig

TARGETS = ("simulate", "sweep", "survey", "budget", "spad", "calibrate", "selfcal")
"""The commands `flightsim compile --for` knows: a run's product (simulate, and waveform), a sweep's configuration
(sweep, paper), a survey's tasks, an instrument's error budget and the studies of SPAD, ATLAS and Risley."""
OWN_INSTRUMENT = {"spad": "spad", "calibrate": "atlas", "selfcal": "risley"}  # the studies of one instrument


def compile_for(target: str, configs: dict[str, RunConfig]) -> int:
    """Load the kernels of ``target``'s runs of ``configs`` (instrument name → its config, on one device) into
    Warp's kernel cache, compiling what it lacks; returns the kernel modules loaded or listed."""
    if target == "simulate":
        from flightsim.engine.run import compile_kernels

        return compile_kernels(list(configs.values()))
    if target == "sweep":
        from flightsim.studies.sweep import compile_configuration

        return sum(map(compile_configuration, configs.values()))
    return max(_compile_one(target, name, cfg) for name, cfg in configs.items())


def _compile_one(target: str, name: str, cfg: RunConfig) -> int:
    device = cfg.run.device
    if target == "survey":
        return compile_survey(cfg)
    if target == "budget":
        from flightsim.studies.budget_catalog import compile_budget

        return compile_budget(name, device)
    if target == "spad":
        from flightsim.studies.spad import compile_study

        return compile_study(device)
    if target == "calibrate":
        from flightsim.studies.spaceborne import compile_calibration

        return compile_calibration(device)
    from flightsim.studies.selfcal_flight import compile_selfcal

    return compile_selfcal(device)


def compile_survey(cfg: RunConfig) -> int:
    """The kernels `flightsim survey` launches with ``cfg``: a survey of one tile flown once in a scratch directory
    (its tasks' kernels are a large survey's); returns the modules loaded."""
    from flightsim.core.warp_runtime import loaded_modules
    from flightsim.studies.survey import run_survey
    from flightsim.studies.survey_plan import SurveySpec, plan_survey

    plan = plan_survey(cfg, SurveySpec(size_km=1.0))
    with tempfile.TemporaryDirectory() as tmp:
        run_survey(plan, Path(tmp) / "survey")
    return loaded_modules()
