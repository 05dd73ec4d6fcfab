"""Registers and local memory of a workload's CUDA kernels, read without a GPU.

Each kernel a workload launches (:func:`flightsim.studies.profile.build`, run once on the CPU) is compiled for
sm_90 to PTX by Warp's own NVRTC, then by ``ptxas -v`` (from NVIDIA's ``nvidia-cuda-nvcc`` wheel, or on ``PATH``)
with the register cap the kernel runs with on a GPU: its registers per thread, stack frame and spilled bytes, the
numbers ``flightsim profile`` reads from the driver on a GPU. With ``cuobjdump`` (NVIDIA's ``nvidia-cuda-cuobjdump``
wheel, or on ``PATH``) also its machine code's size: SASS instructions, of them selects (``SEL``, ``FSEL``: where
Warp's code in static single assignment merges the values a branch may have changed) and local-memory loads and
stores. A change that moves a trace kernel's spills or instructions can be weighed here before a GPU is lent::

    python3 -m pip install nvidia-cuda-nvcc nvidia-cuda-cuobjdump
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


def tool(name: str) -> str | None:
    """CUDA tool ``name`` (ptxas, cuobjdump) from NVIDIA's wheels (nvidia-cuda-nvcc, nvidia-cuda-cuobjdump), else one on
    PATH; None without either."""
    try:
        import nvidia

        for root in map(Path, nvidia.__path__):
            for found in sorted(root.glob(f"cu*/bin/{name}")) + sorted(root.glob(f"cuda_*/bin/{name}")):
                return str(found)
    except ImportError:
        pass
    return shutil.which(name)


def ptxas() -> str | None:
    return tool("ptxas")


_SASS_LINE = re.compile(r"/\*[0-9a-f]{4,}\*/\s+(?:@!?U?P[T0-9]+\s+)?([A-Z][A-Z0-9_]*)")


def parse_sass(listing: str) -> dict[str, dict[str, int]]:
    """Per function of ``cuobjdump -sass``'s listing: its instructions, of them selects (SEL, FSEL, USEL) and
    local-memory loads and stores (LDL, STL)."""
    out: dict[str, dict[str, int]] = {}
    counts = None
    for line in listing.splitlines():
        if m := re.search(r"Function : (\w+)", line):
            counts = out.setdefault(m.group(1), {"instructions": 0, "selects": 0, "local": 0})
        elif counts is not None and (m := _SASS_LINE.search(line)):
            opcode = m.group(1)
            counts["instructions"] += 1
            counts["selects"] += opcode in ("SEL", "FSEL", "USEL")
            counts["local"] += opcode in ("LDL", "STL")
    return out


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


def usage(kernel, compiler: str) -> dict[str, dict[str, int]]:
    """``parse_ptxas`` of one kernel's module, compiled for sm_90 by ``compiler`` (a ptxas) with the kernel's register
    cap, with ``parse_sass``'s counts where a cuobjdump is found."""
    with tempfile.TemporaryDirectory() as tmp:
        wp.compile_aot_module(kernel.module, arch=ARCH, use_ptx=True, module_dir=tmp)
        ptx = Path(tmp) / "module.ptx"
        ptx.write_bytes(next(Path(tmp).glob("*.ptx")).read_bytes().replace(b"\0", b""))  # NVRTC's PTX ends in a NUL
        command = [compiler, f"-arch=sm_{ARCH}", "-v", str(ptx), "-o", str(Path(tmp) / "module.cubin")]
        cap = kernel.options.get("cuda_max_registers")
        if cap:
            command.insert(1, f"--maxrregcount={cap}")
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        found = parse_ptxas(done.stderr)
        disassembler = tool("cuobjdump")
        if disassembler:
            listing = subprocess.run([disassembler, "-sass", str(Path(tmp) / "module.cubin")], capture_output=True,
                                     text=True, check=True).stdout
            for name, sass in parse_sass(listing).items():
                if name in found:
                    found[name].update(sass)
    return found


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
    compiler = ptxas()
    if compiler is None:
        print("kernel_resources: no ptxas (python3 -m pip install nvidia-cuda-nvcc)", file=sys.stderr)
        return 2
    sass = ["instructions", "selects", "local"] if tool("cuobjdump") else []
    print("| workload | kernel | registers | stack frame [B] | spill stores [B] | spill loads [B] | shared [B] |"
          + "".join(f" SASS {column} |" for column in sass))
    print("| --- " * (7 + len(sass)) + "|")
    for workload in args.workloads:
        for kernel in launched(workload).values():
            for name, r in usage(kernel, compiler).items():
                if kernel.key.split("__")[-1] in name:
                    print(f"| {workload} | {kernel.key.split('__')[-1]} | {r['registers']} | {r['frame']} | "
                          f"{r['spill_stores']} | {r['spill_loads']} | {r['smem']} |"
                          + "".join(f" {r.get(column, '–')} |" for column in sass))
    return 0


if __name__ == "__main__":
    sys.exit(main())
