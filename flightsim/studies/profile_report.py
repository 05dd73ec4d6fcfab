"""profile.md from the records of :mod:`flightsim.studies.profile`: a summary per workload, then per kernel, and
the observations the numbers support (the kernel that dominates, idle time, low occupancy, spills)."""
from __future__ import annotations

LOW_OCCUPANCY = 0.5  # below this share of an SM's warp slots a memory-bound kernel hides latency poorly
HIGH_IDLE = 0.2  # share of the wall time with no GPU activity above which host work is the first target


def _fmt(value, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def _summary(records: list[dict]) -> list[str]:
    lines = ["| workload | units | rate [units/s] | bare cast [rays/s] | ratio | wall [ms] | kernels [ms] | "
             "copies [ms] | sorts and scans [ms] | idle [ms] |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in records:
        kernels = sum(k["gpu_s"] for k in r["kernels"].values())
        native = sum(s for kind, s in r["other_activity_s"].items() if kind.endswith("(CUB)"))
        copies = sum(r["other_activity_s"].values()) - native
        lines.append(f"| {r['workload']} | {r['units']:.3g} {r['unit']} | {_fmt(r['rate'])} | "
                     f"{_fmt(r['bare_rays_per_s'])} | {_fmt(r['ratio_to_bare'], 2)} | {1e3 * r['profiled_wall_s']:.1f} | "
                     f"{1e3 * kernels:.1f} | {1e3 * copies:.1f} | {1e3 * native:.1f} | {1e3 * r['idle_s']:.1f} |")
    return lines


def _kernel_table(r: dict) -> list[str]:
    lines = [f"### {r['workload']}", "", "| kernel | launches | GPU [ms] | share of wall | registers | spill [B] | "
             "shared [B] | occupancy |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, k in r["kernels"].items():
        lines.append(f"| {name} | {k['launches']} | {1e3 * k['gpu_s']:.2f} | {k['share']:.1%} | "
                     f"{_fmt(k.get('registers'))} | {_fmt(k.get('local_bytes'))} | {_fmt(k.get('shared_bytes'))} | "
                     f"{_fmt(k.get('occupancy'), 2)} |")
    copies = ", ".join(f"{kind} {1e3 * s:.2f} ms" for kind, s in r["other_activity_s"].items()) or "none"
    return lines + ["", f"Other GPU activity: {copies}; no GPU activity for {1e3 * r['idle_s']:.1f} ms "
                        f"({r['idle_s'] / r['profiled_wall_s']:.0%} of the wall).", "", *_ncu_table(r)]


def _ncu_table(r: dict) -> list[str]:
    counters = r.get("ncu")
    if not counters:
        return []
    if "error" in counters:
        return [f"Nsight Compute: {counters['error']}", ""]
    lines = ["Nsight Compute (the workload at the same size, its first launches of these kernels; means over them):", "",
             "| kernel | launches | achieved occupancy | DRAM [% of peak] | DRAM [GB/s] | SM [% of peak] | "
             "spill traffic [MB] | atomics + reductions | threads per warp instruction | global load sectors per "
             "request | L1 hits | FP64 pipe |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, k in counters["kernels"].items():
        spill = sum(k.get(key) or 0.0 for key in ("local_load_bytes", "local_store_bytes")) / 1e6
        atomics = sum(k.get(key) or 0.0 for key in ("atomic_requests", "reduction_requests"))
        lines.append(f"| {name} | {k['launches']} | {_pct(k.get('achieved_occupancy_pct'))} | "
                     f"{_pct(k.get('dram_pct_of_peak'))} | {_fmt(k.get('dram_gb_per_s'))} | "
                     f"{_pct(k.get('sm_pct_of_peak'))} | {spill:.3g} | {atomics:.3g} | "
                     f"{_fmt(k.get('threads_per_warp_instruction'))} | {_fmt(k.get('sectors_per_request'))} | "
                     f"{_pct(k.get('l1_hit_pct'))} | {_pct(k.get('fp64_pipe_pct'))} |")
    return lines + [""]


def _pct(value) -> str:
    return "–" if value is None else f"{value:.0f} %"


def observations(r: dict) -> list[str]:
    """What a workload's numbers say, one sentence each."""
    notes = []
    wall = r["profiled_wall_s"]
    if r["kernels"]:
        top, k = next(iter(r["kernels"].items()))
        notes.append(f"`{top}` takes {k['gpu_s'] / wall:.0%} of the wall time")
    if wall and r["idle_s"] / wall > HIGH_IDLE:
        notes.append(f"the GPU idles {r['idle_s'] / wall:.0%} of the wall time (host work, launch gaps, syncs)")
    for name, k in r["kernels"].items():
        if k["gpu_s"] / wall < 0.05:
            continue
        if k.get("occupancy") is not None and k["occupancy"] < LOW_OCCUPANCY:
            notes.append(f"`{name}` ({k['gpu_s'] / wall:.0%}) runs at {k['occupancy']:.0%} theoretical occupancy "
                         f"({k.get('registers')} registers/thread)")
        if k.get("local_bytes"):
            notes.append(f"`{name}` spills {k['local_bytes']} bytes/thread to local memory")
    return notes


def write_markdown(result: dict) -> str:
    """The whole profile.md."""
    records = result["workloads"]
    lines = [f"# Where the time goes ({result['gpu_name'] or result['device']}, {result['git_commit']}, "
             f"{result['date']})", "",
             f"`flightsim profile --device {result['device'].split(':')[0]}{' --quick' if result['quick'] else ''}"
             f"{' --ncu' if any('ncu' in r for r in records) else ''} --out results` (Warp's CUDA activity timing and "
             "the CUDA driver's function attributes; occupancy is the theoretical occupancy at Warp's block size; "
             "with --ncu, Nsight Compute's counters).", "", "## Summary", "",
             *_summary(records), "", "## Observations", ""]
    for r in records:
        notes = observations(r)
        if notes:
            lines.append(f"- **{r['workload']}**: " + "; ".join(notes) + ".")
    lines += ["", "## Kernels", ""]
    if result["device"] == "cpu":
        return "\n".join(lines + ["On the CPU a launch runs on the calling thread: no per-kernel timing."]) + "\n"
    for r in records:
        lines += _kernel_table(r)
    return "\n".join(lines) + "\n"
