"""Writing benchmark results: bench.json (one entry per device kind), bench.md, pareto.csv and .png."""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from flightsim.core.atomic import save_figure, write_atomic
from flightsim.studies import bench_gpus, bench_photon_runs

TARGETS = {  # (returns/s, ratio) the issue sets per device kind
    "cuda": (1e9, 0.4),
    "cpu": (1e6, 0.5),
}
PARETO_COLUMNS = ["device", "knob", "value", "wall_s", "returns_per_s", "max_pointing_urad", "max_point_error_mm",
                  "error"]


def merge_and_write(out: Path, kind: str, results: dict) -> None:
    """Replace this device kind's sections in out/bench.json (keeping the others) and rewrite the reports."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "bench.json"
    merged = json.loads(path.read_text()) if path.exists() else {}
    entry = merged.get(kind, {})
    per_section = {key: {**entry.get(key, {}), **results.get(key, {})} for key in ("section_wall_s", "section_measured")}
    entry.update(results)
    entry.update(per_section)  # the sections of earlier runs keep their wall times and commits
    merged[kind] = entry
    write_atomic(path, json.dumps(merged, indent=2) + "\n")
    write_atomic(out / "bench.md", markdown(merged))
    rows = [row for k in sorted(merged) for row in merged[k].get("pareto", [])]
    if rows:
        write_atomic(out / "pareto.csv", _csv(rows))
        plot_pareto(rows, out / "pareto.png")


def _csv(rows: list[dict]) -> str:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=PARETO_COLUMNS, lineterminator="\n", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue()


def _fmt(value: float) -> str:
    return f"{value:.3g}"


def markdown(merged: dict) -> str:
    """bench.md: every section of every device kind as tables."""
    lines = ["# flightsim benchmarks", "", "Regenerate: `flightsim bench --device cpu --out results` "
             "(and `--device cuda` on a GPU machine). Ratios compare numbers measured in the same run.", ""]
    for kind in sorted(merged):
        r = merged[kind]
        lines += [f"## {kind}: last run on {r['gpu_name']} ({r['device']}, {r.get('cpu_count')} CPU cores, commit "
                  f"{r['git_commit']}, {r['date']}{', quick' if r.get('quick') else ''})", ""]
        if r.get("section_measured"):
            lines += ["Sections measured at (commit, date, and the GPU or cores where named): " + ", ".join(
                f"{name} {when}" for name, when in r["section_measured"].items()) + ".", ""]
        lines += (_throughput(r, kind) + _stages(r) + _study(r) + _las(r) + _skip(r) + _pareto(r) + _galvo(r)
                  + _spad(r) + _waveform(r) + _scale(r) + _reduce(r) + _survey(r) + bench_gpus.markdown(r) + _forest(r)
                  + _startup(r) + _ranging(r) + bench_photon_runs.markdown(r))
    return "\n".join(lines) + "\n"


def _throughput(r: dict, kind: str) -> list[str]:
    if "throughput" not in r:
        return []
    rate_target, ratio_target = TARGETS[kind]
    lines = ["### Throughput: calibration field, 500 m, both models, per-plane statistics", "",
             f"Targets: ≥ {rate_target:.0e} returns/s and ratio ≥ {ratio_target} (end-to-end ÷ bare ray cast "
             "on the same rays with the same processes).", "",
             "| array | processes | optics | returns | wall [s] | returns/s | bare ray cast returns/s | ratio |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {t['array']}×{t['array']} | {t['processes']} | {t['optics']} | {t['returns']:.3g} | {_fmt(t['wall_s'])} "
              f"| {_fmt(t['returns_per_s'])} | {_fmt(t['raycast_returns_per_s'])} | {t['ratio']:.2f} |"
              for t in r["throughput"]]
    return lines + [""]


def _galvo(r: dict) -> list[str]:
    if "galvo" not in r:
        return []
    records, b = r["galvo"]["throughput"], r["galvo"]["budget"]
    rows = [f"| {t['scene']} | {t['triangles']:,} | {t['returns']:,} | {t['wall_s']:.3f} | {_fmt(t['returns_per_s'])} | "
            f"{_fmt(t['raycast_returns_per_s'])} | {t['ratio']:.2f} |" for t in records]
    return ["", "### Chang'e-3 galvo imager (statistics mode, ranging errors on, hovering at 100 m)", "",
            "| scene | triangles | returns | wall [s] | returns/s | bare ray cast returns/s | ratio |",
            "| --- | --- | --- | --- | --- | --- | --- |", *rows, "",
            f"Monte Carlo budget: {b['draws']} draws of a full frame ({b['slots_per_draw']:,} beams each) in "
            f"{b['wall_s']:.2f} s ({b['draws_per_s']:.1f} draws/s), compile excluded.", ""]


def _spad(r: dict) -> list[str]:
    if "spad" not in r:
        return []
    f = r["spad"]
    sliced = f["pulses"] != f["frame_pulses"]
    part = f" (measured on {f['pulses']:,} of its {f['frame_pulses']:,} pulses, scaled)" if sliced else ""
    return ["", "### SPAD lidar: one MODE-A frame (photon sampling, gridding into 1100 × 1100 points on the device)", "",
            "Target: ≥ 50× faster than the instrument's 0.86 s frame (≥ 20× before). \"trace and photons\": the frame "
            "without its gridding.", "",
            "| pulses | beams | photons | points | wall [s] | trace and photons [s] | frame [s] | × instrument | "
            "beams/s | bare ray cast rays/s | ratio |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            f"| {f['pulses']:,} | {f['beams']:,} | {f['photons']:,} | {f['points']:,} | {f['wall_s']:.4f} | "
            f"{f['trace_and_photons_s']:.4f} | {f['frame_wall_s']:.4f} | {_fmt(f['faster_than_instrument'])} | "
            f"{_fmt(f['beams_per_s'])} | {_fmt(f['raycast_rays_per_s'])} | {f['ratio']:.2f} |", "",
            f"One frame takes {f['frame_wall_s']:.3g} s{part}: {_fmt(f['faster_than_instrument'])}× faster than the "
            f"instrument records it.", ""] + _spad_traffic(f.get("traffic"))


def _spad_traffic(t: dict | None) -> list[str]:
    """The SPAD frame's memory traffic (flightsim/studies/spad_traffic.py) against the device's copy bandwidth."""
    if not t or not t.get("copy_bandwidth_Bps"):
        return []
    stages = ", ".join(f"{name} {b / 1e9:.2f}" for name, b in t["stages_bytes"].items())
    return [f"Its memory traffic (logical bytes, flightsim/studies/spad_traffic.py): {t['total_bytes'] / 1e9:.2f} GB "
            f"({stages} GB; sort keys of {t['key_bits']} bits); at the device's copy bandwidth of "
            f"{t['copy_bandwidth_Bps'] / 1e12:.2f} TB/s that alone takes {1e3 * t['memory_floor_s']:.2f} ms, "
            f"{100 * t['floor_over_wall']:.0f} % of the frame's wall.", ""]


def _convolution_ms(kernels: dict) -> str:
    """GPU time of the pulse convolution [ms]: the direct sums and, with waveform.convolution = fft, the FFTs and
    the split of the spans between them ('n/a' where a record holds none of them: the CPU's)."""
    parts = [t for name, t in kernels.items() if name.startswith("convolve") or name == "split_spans"]
    return f"{1e3 * sum(parts):.1f}" if parts else "n/a"


def _waveform(r: dict) -> list[str]:
    if not r.get("waveform"):
        return []
    rows = [f"| {w['scene']} | {w['shots']:,} | {w['subrays']:,} | {w['samples']:,} | {w['wall_s']:.3f} | "
            f"{_fmt(w['subray_returns_per_s'])} | "
            f"{_fmt(w['accumulation_returns_per_s']) if w.get('accumulation_returns_per_s') else 'n/a'} | "
            f"{_fmt(w['raycast_returns_per_s'])} | {w['ratio']:.2f} | {_of_accumulation(w)} | "
            f"{_convolution_ms(w.get('kernels_s', {}))} |"
            for w in r["waveform"]]
    return ["", "### Waveform altimeter (change1: sub-rays summed into waveforms on the device)", "",
            "Target (H100): ≥ 1e9 sub-ray returns/s with the waveform accumulation. End to end: pilot ray, "
            "deposit and convolution with the pulse, wall time; accumulation: the GPU time of the kernels that "
            "cast and deposit the sub-rays (emit_rays, pilot, deposit); ratio: end to end ÷ bare ray cast of "
            "the same sub-rays; ÷ accumulation: end to end ÷ accumulation (target ≥ 0.5); convolution: direct "
            "sums, FFTs and the split between them (waveform.convolution).", "",
            "| footprint | shots | sub-rays | samples per waveform | wall [s] | sub-ray returns/s, end to end | "
            "accumulation | bare ray cast returns/s | ratio | ÷ accumulation | convolution [ms] |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |", *rows, ""]


def _of_accumulation(w: dict) -> str:
    """End-to-end sub-ray returns/s ÷ the accumulation's ('n/a' without the kernels' times: the CPU)."""
    rate = w.get("accumulation_returns_per_s")
    return f"{w['subray_returns_per_s'] / rate:.2f}" if rate else "n/a"


def _ranging(r: dict) -> list[str]:
    if not r.get("ranging"):
        return []
    rows = [f"| {w['case']} | {w['samples']:,} | {w['waveforms']:,} | {w['device_s']:.3f} | "
            f"{_fmt(w['device_waveforms_per_s'])} | {_fmt(w['host_waveforms_per_s'])} | {w['speedup']:.0f} |"
            for w in r["ranging"]]
    return ["", "### Waveform ranging (waveforms.h5: measures and Gaussian decomposition, waveform.processing)", "",
            "Synthetic sums of 1-4 Gaussians with noise; device: flightsim.instrument.waveform_batch.process end to "
            "end (host arrays in and out); host: waveform_model.measure + decompose, one waveform at a time.", "",
            "| waveforms | samples | count | device [s] | device waveforms/s | host waveforms/s | speed-up |",
            "| --- | --- | --- | --- | --- | --- | --- |", *rows, ""]


def _forest(r: dict) -> list[str]:
    if "forest" not in r:
        return []
    c, v, a = r["forest"]["cloud"], r["forest"]["voxels"], r["forest"]["als"]
    return ["", "### Forests", "",
            "Targets (H100): ≥ 1e5 point-cloud waveforms/s from ≥ 1e7 points; ≥ 1e9 ray-voxel steps/s; discrete ALS "
            "over a 1 km² voxel forest at ≥ 0.5 of the throughput over its bare ground.", "",
            "| point-cloud waveforms (GEDI method) | points | footprints | device [s] | footprints/s | NumPy float64 "
            "footprints/s | speed-up | least correlation with NumPy |", "| --- | --- | --- | --- | --- | --- | --- | --- |",
            f"| {c['samples']} samples of 1 ns | {c['points']:,} | {c['footprints']:,} | {c['device_s']:.3f} | "
            f"{_fmt(c['footprints_per_s'])} | {_fmt(c['numpy_footprints_per_s'])} | {_fmt(c['speedup'])} | "
            f"{c['min_correlation']:.6f} |", "",
            f"Device: end to end (the waveforms copied to the host), the cloud sorted once beforehand in "
            f"{c['prepare_s']:.2f} s; NumPy: {c['numpy_footprints']} footprints, its KD-tree built in the call.", "",
            *_forest_shots(r["forest"].get("shots")),
            f"Leaf voxel walk: {v['rays']:,} rays through a {'×'.join(map(str, v['grid']))} grid, {v['steps']:,} "
            f"steps in {v['wall_s']:.4f} s: {_fmt(v['steps_per_s'])} steps/s.", "", *_forest_scene(r["forest"]),
            "| discrete ALS, points readout on the device | beams | returns | wall [s] | beams/s |",
            "| --- | --- | --- | --- | --- |",
            *[f"| {name} ({a['forest_size_m']:g} m square) | {x['beams']:,} | {x['returns']:,} | {x['wall_s']:.3f} | "
              f"{_fmt(x['beams_per_s'])} |" for name, x in (("forest, LAI 3", a["forest"]), ("bare ground", a["bare"]))],
            "", f"Forest ÷ bare ground: {a['ratio']:.2f}.", ""]


def _forest_shots(x: dict | None) -> list[str]:
    """GEDI shots over a point cloud end to end, where the section measured them."""
    if x is None:
        return []
    stages = ", ".join(f"{name} {seconds:.2f}" for name, seconds in x["stages_s"].items())
    return [f"GEDI shots end to end (`flightsim waveform --instrument gedi --scene CLOUD.las --footprints SHOTS.csv "
            f"--set waveform.processing=device` in a fresh process, after one over a small cloud; "
            f"`flightsim/studies/bench_shots.py`): {x['footprints']:,} footprints over {x['points']:,} points in "
            f"{x['wall_s']:.1f} s ({_fmt(x['footprints_per_s'])} footprints/s), peak {x['peak_rss_mib']:.0f} MiB; "
            f"stages [s]: {stages}.", ""]


def _forest_scene(f: dict) -> list[str]:
    """The forest scene's build, where the section measured it."""
    if "scene" not in f:
        return []
    b = f["scene"]
    lines = [f"Forest scene ({b['forest_size_m']:g} m square, LAI 3, {'×'.join(map(str, b['voxels']))} voxels, on the "
             f"host in {b['threads']} threads): {b['computed_s']:.1f} s with its voxels computed, "
             f"{b['stored_s']:.1f} s computed and stored in the scene cache, {b['cached_s']:.2f} s from it."]
    if "device" in b:
        d = b["device"]
        lines.append(f"The same scene for a run on the GPU, its voxels integrated there: {d['computed_s']:.2f} s; "
                     f"{d['voxels_differing']:,} of the voxels differ from the host's, by at most "
                     f"{d['max_difference']:.1e} m²/m³ (densities up to {d['max_lad']:.2f}).")
    return lines + [""]


def _startup(r: dict) -> list[str]:
    if not r.get("startup"):
        return []
    runs = [x for x in r["startup"] if "cli_s" in x]
    every = [x for x in r["startup"] if "cli_s" not in x]
    return ["", "### Start-up", "", f"`{runs[0]['command']}`, timed from before the process starts "
            "(cold: an empty Warp kernel cache, into which flightsim's prebuilt kernels are copied at start-up; "
            "cold, nothing prebuilt: the same with FLIGHTSIM_PREBUILT=0, the run compiling its set-up's modules in "
            "one parallel batch and its chunks' in another before its first chunk; warm: the cache the cold run "
            "left; compiled ahead: `flightsim compile` of the same flags first, in an empty cache, nothing "
            "prebuilt). " + ("Every process reads Python's bytecode, as an installed package's are (a first, untimed "
                             "run writes it). " if runs[0].get("bytecode") else "")
            + (f"Each row: the median of {runs[0]['runs']} runs (each cold one in an empty cache of its own). "
               if runs[0].get("runs", 1) > 1 else "")
            + "Targets: first result <= 3 s cold, <= 1 s warm.", "",
            "| kernel cache | command line parsed [s] | first trace launch [s] | first LAS tile [s] | exit [s] | "
            "modules compiled | flightsim compile [s] |", "| --- | --- | --- | --- | --- | --- | --- |",
            *[f"| {x['cache']} | {x['cli_s']:.2f} | {x['first_ray_s']:.2f} | {_fmt(x['first_file_s'])} | "
              f"{x['exit_s']:.2f} | {x['modules_compiled']} | {_optional(x, 'compile_s', '.1f')} |" for x in runs], "",
            *[f"`flightsim compile --all` (every built-in instrument, its own scene) in an empty cache, nothing prebuilt: "
              f"{x['compile_s']:.1f} s." for x in every], ""]


def _stages(r: dict) -> list[str]:
    if not r.get("stages"):
        return []
    lines = ["### Where the time goes (GPU time per kernel, same workload at a quarter of the size)", "",
             "| array | stage | time [s] | ns per beam slot | share of wall |", "| --- | --- | --- | --- | --- |"]
    for x in r["stages"]:
        rows = sorted(((name.split("__")[-1], t) for name, t in x["kernels_s"].items()), key=lambda kv: -kv[1])
        rows.append(("host work and gaps (wall − kernels)", x["wall_s"] - sum(x["kernels_s"].values())))
        rows.append(("wall", x["wall_s"]))
        rows.append(("for scale: bare ray cast of as many rays", x["bare_raycast_s"]))
        lines += [f"| {x['array']}×{x['array']} | {name} | {_fmt(t)} | {1e9 * t / x['slots']:.3f} "
                  f"| {100 * t / x['wall_s']:.0f}% |" for name, t in rows]
    return lines + [""]


def _study(r: dict) -> list[str]:
    if "study" not in r:
        return []
    s = r["study"]
    return ["### The seed paper's study over the calibration field", "",
            f"{s['configurations']} configurations × both models ({s['rows']} rows) in **{s['wall_s']:.1f} s** "
            f"in a fresh process from an empty kernel cache (into which flightsim copies its prebuilt kernels where "
            f"the measured version has them; the rest compiled in the run): `flightsim {s['command']}`.", ""]


def _las(r: dict) -> list[str]:
    if "las" not in r:
        return []
    lines = ["### LAS output path (`flightsim simulate`, plane scene, 8×8 array, both models)", "",
             "| points written | wall [s] | points/s | CLI start-up [s] | points/s after start-up | peak RSS [MiB] |",
             "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {x['points_written']:.3g} | {x['wall_s']:.1f} | {_fmt(x['points_per_s'])} | "
              f"{_optional(x, 'startup_s', '.1f')} | {_optional(x, 'points_per_s_after_startup', '.3g')} | "
              f"{x['peak_rss_mib']:.0f} |" for x in r["las"]]
    return lines + ["", "Wall: the whole command in a fresh process. Start-up: the same command flying 0.01 s "
                        "(interpreter, Warp, scene, kernels, output). Memory is bounded by the chunk size and open "
                        "tiles, not by the run length.", ""]


def _optional(record: dict, key: str, spec: str) -> str:
    """A record's value formatted by ``spec``, or – where an older record lacks it."""
    value = record.get(key)
    return "–" if value is None else format(value, spec)


def _scale(r: dict) -> list[str]:
    if "scale" not in r:
        return []
    x = r["scale"]
    disk = x["disk_write_bytes_per_s"]
    lines = [f"### Scale: terrain meshes (testdem GeoTIFF, 3 km square, 8×8 array at 500 m; disk writes "
             f"{disk / 1e6:.0f} MB/s)", "",
             "| triangles | read [s] | plan [s] | per line [ms] | BVH [s] | ready [s] | from cache: read / ready [s] | "
             "statistics returns/s | bare ray cast /s | ratio | LAS points/s | LAS MB/s | disk MB/s | of disk | "
             "LAS ÷ statistics | device MiB |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for e in x["scenes"]:
        memory = "–" if e["device_memory_mib"] is None else f"{e['device_memory_mib']:.0f}"
        at = f" (at {e['git_commit']})" if "git_commit" in e else ""
        lines.append(f"| {e['triangles']:.3g}{at} | {_optional(e, 'load_s', '.2f')} | {_optional(e, 'plan_s', '.2f')} | "
                     f"{_optional(e, 'plan_ms_per_line', '.2f')} | {e['bvh_build_s']:.2f} | "
                     f"{_optional(e, 'ready_s', '.2f')} | {_optional(e, 'cached_load_s', '.2f')} / "
                     f"{_optional(e, 'ready_cached_s', '.2f')} | "
                     f"{_fmt(e['stats_returns_per_s'])} | {_fmt(e['raycast_returns_per_s'])} | {e['stats_ratio']:.2f} | "
                     f"{_fmt(e['las_points_per_s'])} | {e['las_bytes_per_s'] / 1e6:.0f} | "
                     f"{_row_disk(e, disk) / 1e6:.0f} | {e['las_fraction_of_disk']:.2f} | "
                     f"{e['las_fraction_of_stats']:.2f} | {memory} |")
    return lines + ["", "Ready: the GeoTIFF read into a scene without the scene cache, the flight lines planned "
                        "(plan: the scene's height grid built, then each line's clearance checked over it; per line: "
                        "a second plan over the built grid) and the BVHs built; from cache: the same with the scene "
                        "read from the scene cache. LAS: both models, records packed on the device, one writer "
                        "thread per model; its wall runs until every tile is closed. Ratio: statistics-mode "
                        "returns/s ÷ bare ray cast of the same rays. Disk: the disk's sequential write rate probed "
                        "right before the row's LAS run, both on an idle disk (what earlier steps wrote synced first); "
                        "'of disk' is the LAS rate against it. A row measured at another commit than the section "
                        "says so.", ""]


def _row_disk(e: dict, section_disk: float) -> float:
    """The disk rate a scale row's 'of disk' compares with: its own probe (rows before it had one: the section's)."""
    return e.get("disk_write_bytes_per_s", section_disk)


def _reduce(r: dict) -> list[str]:
    if not r.get("reduce"):
        return []
    knobs = [(x["sum_replicas"], x["slots_per_thread"]) for x in r["reduce"][0]["ratios"]]
    lines = ["### Statistics reduction: copies of the sums × slots per reducing thread", "",
             "Statistics-mode returns/s ÷ bare ray cast of the same rays (`run.sum_replicas`, "
             "`run.slots_per_thread`; each case's scene and BVH built once, best of three).", "",
             "| case | triangles | planes | bare ray cast /s | " + " | ".join(
                 f"R {rep}, {spt} slots" for rep, spt in knobs) + " |", "| --- " * (4 + len(knobs)) + "|"]
    for x in r["reduce"]:
        lines.append(f"| {x['case']} | {x['triangles']:.3g} | {x['planes']} | {_fmt(x['raycast_returns_per_s'])} | "
                     + " | ".join(_reduce_cell(k) for k in x["ratios"]) + " |")
    return lines + [""]


def _reduce_cell(k: dict) -> str:
    """A ratio, with the copies of the sums actually used where device memory capped them."""
    capped = k["replicas_used"] != k["sum_replicas"]
    return f"{k['ratio']:.3f}" + (f" (R {k['replicas_used']})" if capped else "")


def _survey(r: dict) -> list[str]:
    if "survey" not in r:
        return []
    x = r["survey"]
    return [f"### Survey: {x['area_km2']:g} km² at 500 m, both models to LAZ", "",
            "| area [km²] | DEM pixel [m] | lines | beams | points written | LAZ GB | wall [s] | points/s | "
            "peak RSS [MiB] |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            f"| {x['area_km2']:g} | {x['dem_cell_m']:g} | {x['lines']} × {x['line_km']:g} km | {x['beams']:.3g} | "
            f"{x['points_written']:.3g} | {x['laz_bytes'] / 1e9:.2f} | {x['wall_s']:.1f} | {_fmt(x['points_per_s'])} | "
            f"{x['peak_rss_mib']:.0f} |", "", *_survey_stages(x),
            "`flightsim simulate` in a fresh process over the testdem terrain (fractal relief, river, land cover, "
            "town) with terrain following, lines spaced as `flightsim survey` spaces them; wall: the whole "
            "command, scene read (no scene cache) to the last LAZ tile closed. Peak RSS: the flightsim process, "
            "with the shared-memory rings (64 MB each) through which it hands records to its LAZ worker processes "
            "(from 4 cores up, per model one per 2 cores, at most 8); the workers' own interpreters add about "
            "90 MB each.", ""]


def _survey_stages(x: dict) -> list[str]:
    """Where the survey's time went (summary.json ``stages_s``), when the record has it."""
    stages = x.get("stages_s")
    if not stages:
        return []
    start_up = x["wall_s"] - sum(stages.values())
    return ["| start-up | " + " | ".join(stages) + " |", "| --- " * (len(stages) + 1) + "|",
            f"| {start_up:.1f} | " + " | ".join(f"{v:.1f}" for v in stages.values()) + " |", "",
            "(seconds; start-up: the process until the config is read, and leaving it)", ""]


def _skip(r: dict) -> list[str]:
    if "skip" not in r:
        return []
    lines = ["### Work skipped and what it saves", "", "| what | without [s] | with [s] | saving |",
             "| --- | --- | --- | --- |"]
    lines += [f"| {x['what']} | {_fmt(x['baseline_s'])} | {_fmt(x['variant_s'])} | {100 * x['saving']:.0f}% |"
              for x in r["skip"]]
    return lines + ["", "(For the feature rows, 'without' is the default run and 'with' the variant; a negative "
                    "saving is the variant's cost.)", ""]


def _pareto(r: dict) -> list[str]:
    if "pareto" not in r:
        return []
    lines = ["### Run time against error (float64 reference of the same pipeline)", "",
             "| knob | value | wall [s] | returns/s | max pointing error [µrad] | max point error [mm] |",
             "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {x['knob']} | {x['value']} | {_fmt(x['wall_s'])} | {_fmt(x['returns_per_s'])} "
              f"| {_fmt(x['max_pointing_urad'])} | {_fmt(x['max_point_error_mm'])} |" if "error" not in x else
              f"| {x['knob']} | {x['value']} | not available here: {x['error']} | | | |" for x in r["pareto"]]
    return lines + [""]


def plot_pareto(rows: list[dict], path: Path) -> None:
    """Wall time against largest pointing and point error, one colour per device, one marker per knob."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if not r.get("error")]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    markers = {"optics": "o", "bvh": "s", "chunk": "^", "slots_per_thread": "D", "max_registers": "v"}
    for device in sorted({r["device"] for r in rows}):
        for knob, marker in markers.items():
            sel = [r for r in rows if r["device"] == device and r["knob"] == knob]
            for ax, key in zip(axes, ("max_pointing_urad", "max_point_error_mm")):
                ax.scatter([float(r[key]) for r in sel], [float(r["wall_s"]) for r in sel], marker=marker,
                           label=f"{device} {knob}")
                for r in sel:
                    if knob == "optics":
                        ax.annotate(r["value"], (float(r[key]), float(r["wall_s"])), fontsize=7)
    for ax, label in zip(axes, ("max pointing error [µrad]", "max point error [mm]")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("wall time of the throughput run [s]")
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7)
    fig.suptitle("Run time against error of each speed knob (lower left is better)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)
