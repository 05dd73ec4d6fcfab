"""Registers and local memory of a workload's CUDA kernels, read without a GPU.

Each kernel a workload launches (:func:`flightsim.studies.profile.build`, run once on the CPU) is compiled for
sm_90 to PTX by Warp's own NVRTC, then by ``ptxas -v`` (from NVIDIA's ``nvidia-cuda-nvcc`` wheel, or on ``PATH``)
with the register cap the kernel runs with on a GPU: its registers per thread, stack frame and spilled bytes, the
numbers ``flightsim profile`` reads from the driver on a GPU. A change that moves a trace kernel's spills can be
weighed here before a GPU is lent::

    python3 -m pip install nvidia-cuda-nvcc
    python3 -m flightsim.studies.kernel_resources risley3 spad
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import warp as wp

ARCH = 90


def ptxas() -> str | None:
    """The ptxas of the nvidia-cuda-nvcc wheel, else one on PATH; None without either."""
    try:
        import nvidia

        for root in map(Path, nvidia.__path__):
            for found in sorted(root.glob("cu*/bin/ptxas")) + sorted(root.glob("cuda_nvcc/bin/ptxas")):
                return str(found)
    except ImportError:
        pass
    return shutil.which("ptxas")


def parse_ptxas(report: str) -> dict[str, dict[str, int]]:
    """Per entry function of ``ptxas -v``'s report: registers, stack frame, spill stores and loads, static shared
    memory [bytes] (a kernel spilling to shared memory may report negative spill bytes: what it moved there)."""
    out: dict[str, dict[str, int]] = {}
    name = None
    for line in report.splitlines():
        if m := re.search(r"Function properties for (\w+)", line):
            name = m.group(1)
        elif name and (m := re.search(r"(\d+) bytes stack frame, (-?\d+) bytes spill stores, (-?\d+) bytes spill loads",
                                      line)):
            out[name] = dict(zip(("frame", "spill_stores", "spill_loads"), map(int, m.groups())))
        elif name and (m := re.search(r"Used (\d+) registers", line)):
            out.setdefault(name, {})["registers"] = int(m.group(1))
            smem = re.search(r"(\d+) bytes smem", line)  # with shared-memory spilling, the spills' share of it too
            out[name]["smem"] = int(smem.group(1)) if smem else 0
    return {k: v for k, v in out.items() if k.endswith("_cuda_kernel_forward")}


def usage(kernel, tool: str) -> dict[str, dict[str, int]]:
    """``parse_ptxas`` of one kernel's module, compiled for sm_90 with the kernel's register cap."""
    with tempfile.TemporaryDirectory() as tmp:
        wp.compile_aot_module(kernel.module, arch=ARCH, use_ptx=True, module_dir=tmp)
        ptx = Path(tmp) / "module.ptx"
        ptx.write_bytes(next(Path(tmp).glob("*.ptx")).read_bytes().replace(b"\0", b""))  # NVRTC's PTX ends in a NUL
        command = [tool, f"-arch=sm_{ARCH}", "-v", str(ptx), "-o", str(Path(tmp) / "module.cubin")]
        cap = kernel.options.get("cuda_max_registers")
        if cap:
            command.insert(1, f"--maxrregcount={cap}")
        done = subprocess.run(command, capture_output=True, text=True, check=True)
    return parse_ptxas(done.stderr)


def launched(workload: str) -> dict[str, object]:
    """The kernels (by key) a workload launches, run once at its small size on the CPU."""
    import warp._src.context as context
    from flightsim.studies.profile import build

    seen, launch = {}, wp.launch

    def spy(kernel, *args, **kwargs):
        seen.setdefault(f"{kernel.key}@{id(kernel)}", kernel)
        return launch(kernel, *args, **kwargs)

    wp.launch = context.launch = spy
    try:
        build(workload, "cpu", True).run()
    finally:
        wp.launch = context.launch = launch
    return seen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workloads", nargs="+", help="workloads of flightsim profile, e.g. risley3 spad")
    args = parser.parse_args(argv)
    tool = ptxas()
    if tool is None:
        print("kernel_resources: no ptxas (python3 -m pip install nvidia-cuda-nvcc)", file=sys.stderr)
        return 2
    print("| workload | kernel | registers | stack frame [B] | spill stores [B] | spill loads [B] | shared [B] |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for workload in args.workloads:
        for kernel in launched(workload).values():
            for name, r in usage(kernel, tool).items():
                if kernel.key.split("__")[-1] in name:
                    print(f"| {workload} | {kernel.key.split('__')[-1]} | {r['registers']} | {r['frame']} | "
                          f"{r['spill_stores']} | {r['spill_loads']} | {r['smem']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
