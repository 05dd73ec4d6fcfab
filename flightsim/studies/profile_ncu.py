"""Nsight Compute's view of a workload's kernels, where ``ncu`` is on the machine: achieved occupancy, DRAM and SM
throughput, register spill traffic, atomics, branch divergence, how well global loads coalesce (32-byte sectors per
warp-wide load request: 4 when a warp's lanes read neighbouring 4-byte words, up to 32 when each lane's word is on a
sector of its own), L1 hits and the FP64 pipe's use, per kernel, averaged over its profiled launches.

The workload runs at the parent's size in a child ``flightsim profile`` under ``ncu``, which profiles the first
LAUNCHES launches of the workload's busiest kernels (every profiled launch is replayed once per metric group, so the
child is slow, and its own wall times mean nothing; only the counters are kept).
"""
from __future__ import annotations

import csv
import functools
import io
import shutil
import subprocess
import sys
import tempfile

from flightsim.studies.bench_common import kernel_name

METRICS = {  # our name: Nsight Compute metric
    "achieved_occupancy_pct": "sm__warps_active.avg.pct_of_peak_sustained_active",
    "dram_pct_of_peak": "dram__throughput.avg.pct_of_peak_sustained_elapsed",
    "sm_pct_of_peak": "sm__throughput.avg.pct_of_peak_sustained_elapsed",
    "dram_bytes": "dram__bytes.sum",
    "duration_ns": "gpu__time_duration.sum",
    "local_load_bytes": "l1tex__t_bytes_pipe_lsu_mem_local_op_ld.sum",
    "local_store_bytes": "l1tex__t_bytes_pipe_lsu_mem_local_op_st.sum",
    "atomic_requests": "l1tex__t_requests_pipe_lsu_mem_global_op_atom.sum",
    "reduction_requests": "l1tex__t_requests_pipe_lsu_mem_global_op_red.sum",
    "threads_per_warp_instruction": "smsp__thread_inst_executed_per_inst_executed.ratio",
    "global_load_sectors": "l1tex__t_sectors_pipe_lsu_mem_global_op_ld.sum",
    "global_load_requests": "l1tex__t_requests_pipe_lsu_mem_global_op_ld.sum",
    "l1_hit_pct": "l1tex__t_sector_hit_rate.pct",
    "fp64_pipe_pct": "sm__pipe_fp64_cycles_active.avg.pct_of_peak_sustained_active",
}
LAUNCHES = 12  # launches profiled per workload, of the kernels asked for (the warm-up run's, as large)
TOP_KERNELS = 6  # the kernels of a workload profiled: those that took the most GPU time


def available() -> bool:
    return shutil.which("ncu") is not None


def parse(text: str) -> dict[str, dict]:
    """Per kernel (our short name): launches profiled and the mean of each metric over them, from ``ncu --csv
    --page raw`` output (a header row, a units row, then one row per launch)."""
    lines = [line for line in text.splitlines() if line.startswith('"')]
    rows = list(csv.DictReader(io.StringIO("\n".join(lines))))
    by_kernel: dict[str, list[dict]] = {}
    for row in rows:
        if not row.get("ID", "").strip().isdigit():
            continue  # the units row
        raw = row["Kernel Name"].split("(")[0].removesuffix("_cuda_kernel_forward")
        by_kernel.setdefault(kernel_name(raw), []).append(row)
    out = {}
    for name, launches in by_kernel.items():
        record = {"launches": len(launches)}
        for ours, metric in METRICS.items():
            values = [_number(r.get(metric, "")) for r in launches]
            values = [v for v in values if v is not None]
            record[ours] = sum(values) / len(values) if values else None
        if record["dram_bytes"] is not None and record["duration_ns"]:
            record["dram_gb_per_s"] = record["dram_bytes"] / record["duration_ns"]
        if record["global_load_sectors"] is not None and record["global_load_requests"]:
            record["sectors_per_request"] = record["global_load_sectors"] / record["global_load_requests"]
        out[name] = record
    return out


def _number(text: str) -> float | None:
    try:
        return float(text.replace(",", ""))
    except ValueError:
        return None


def known(metrics: list[str], listing: str) -> list[str]:
    """The ``metrics`` whose base name (before the first dot) ``ncu --query-metrics`` lists in ``listing`` (all of them
    when the listing is empty: the query failed, and ncu will say which one it does not know)."""
    if not listing.strip():
        return metrics
    names = {line.split()[0] for line in listing.splitlines() if line.strip()}
    return [m for m in metrics if m.split(".")[0] in names]


@functools.cache
def _asked() -> str:
    """The METRICS this machine's ncu lists, comma-separated (asked of ncu once per process)."""
    listing = subprocess.run(["ncu", "--query-metrics"], capture_output=True, text=True).stdout
    return ",".join(known(list(METRICS.values()), listing))


def workload_counters(workload: str, device: str, kernels: list[str], quick: bool) -> dict:
    """{"kernels": parse(...)} of ``kernels`` (our short names) for ``workload`` (at its ``quick`` size or not)
    under ncu, or {"error": what went wrong}."""
    with tempfile.TemporaryDirectory() as tmp:
        command = ["ncu", "--csv", "--page", "raw", "--kernel-name", "regex:" + "|".join(kernels),
                   "--launch-count", str(LAUNCHES), "--metrics", _asked(),
                   sys.executable, "-m", "flightsim", "profile", "--device", device,
                   *(["--quick"] if quick else []), "--workloads", workload, "--out", tmp]
        done = subprocess.run(command, capture_output=True, text=True)
    kernels = parse(done.stdout)
    if not kernels:
        return {"error": (done.stderr or done.stdout)[-600:].strip() or f"ncu exit {done.returncode}"}
    return {"kernels": kernels}
