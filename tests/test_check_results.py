"""tests/check_results.py: how it finds each report's command and tells equal, round-off and differing results."""
from __future__ import annotations

import json

import pytest

import check_results


def _write(folder, files: dict) -> None:
    for name, text in files.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(text, encoding="utf-8")


def test_every_report_command_writes_into_its_own_folder():
    found = check_results.commands(None)
    assert len(found) >= 10
    for report, command in found:
        args, committed = check_results._redirected(command, check_results.ROOT / "elsewhere")
        assert args[args.index("--out") + 1].endswith("elsewhere")
        assert committed.is_dir() and report.is_relative_to(committed), (report, command)


def test_round_off_and_differences_are_told_apart(tmp_path):
    committed, written = tmp_path / "committed", tmp_path / "written"
    report = "# R\n\nRegenerate: `flightsim x --out {}` (3 s).\nσ = 1.0 m\n"
    _write(committed, {"a.json": json.dumps({"x": 1.0, "wall_s": 3.0, "command": "flightsim x --out results/r",
                                             "rows": [1.0, 2.0]}),
                       "t.csv": "k,v\na,0.5\n", "REPORT.md": report.format("results/r"), "only_here.json": "{}"})
    _write(written, {"a.json": json.dumps({"x": 1.0 + 1e-15, "wall_s": 9.0, "command": "flightsim x --out /tmp/w",
                                           "rows": [1.0, 2.0], "new": 1}),
                     "t.csv": "k,v\na,0.5\n", "REPORT.md": report.format("/tmp/w")})
    d = check_results.compare(committed, written)
    assert (d["files"], d["numbers"], d["other"], d["reports"]) == (3, 1, [], [])
    assert 1e-16 < d["max_rel"] < 1e-14
    assert d["seconds"] == [3.0, 9.0]  # the timings compared apart: 3× slower
    assert check_results._seconds({"wall_s": 1.5, "rows": [{"scan_s": 2.0, "n": 7}], "stages_s": {"a": 0.5},
                                   "draws_per_s": 1e4}) == 4.0  # durations only, not rates

    _write(written, {"t.csv": "k,v\na,0.75\n", "REPORT.md": report.format("/tmp/w").replace("1.0 m", "1.1 m")})
    d = check_results.compare(committed, written)
    assert d["max_rel"] == 0.25 / 0.75 and d["worst"].startswith("t.csv")
    assert d["reports"] == ["REPORT.md: 1 lines, the first `σ = 1.0 m` -> `σ = 1.1 m`"]

    _write(written, {"a.json": json.dumps({"x": 1.0, "rows": [1.0]})})
    d = check_results.compare(committed, written)
    assert d["other"] == ["a.json/rows: [1.0, 2.0] -> [1.0]"]


@pytest.mark.parametrize("report", ["results/budget/atlas/REPORT.md", "results/budget/change1/REPORT.md",
                                    "results/budget/spad/REPORT.md", "results/paper/budget/REPORT.md"])
def test_committed_result_is_what_its_command_writes(report):
    """The quick results (seconds each) rerun with their reports' commands: the reports' text equal (a renamed
    config key, a changed number at print precision fails), every other value equal, the numbers to round-off
    (the suite's NumPy and OpenBLAS kernels round differently from the user's run that wrote them: within 1e-11)."""
    command = dict(check_results.commands(report))[check_results.ROOT / report]
    d = check_results.rerun(command)
    assert d["returncode"] == 0, d["stderr"][-500:]
    assert d["files"] >= 2 and d["reports"] == [] and d["other"] == []
    assert d["max_rel"] <= 1e-9, d["worst"]
