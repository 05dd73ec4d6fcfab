"""Device side of flightsim: every Warp kernel and function that runs per pulse or per beam.

On an x86-64 machine with the x86-64-v3 instructions (AVX2, FMA: every x86-64 CPU since 2013-2015) the CPU kernels
are compiled for that level rather than for the host's own (Warp's ``-march=native``): the same object code on every
such machine, so that flightsim's prebuilt CPU kernels (:mod:`flightsim.core.prebuilt`), whose file names Warp keys
by the target, load on any of them, and a CPU run gives the same bits on each.
"""
import warp as wp

X86_64_V3 = frozenset({"avx", "avx2", "bmi1", "bmi2", "f16c", "fma", "abm", "movbe", "xsave"})
"""The x86-64-v3 level's instructions, as Linux's /proc/cpuinfo names them (abm: LZCNT)."""


def _cpu_flags() -> frozenset[str]:
    """The host CPU's instruction-set flags from /proc/cpuinfo (empty where there is none: not Linux)."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def _portable_cpu_target() -> None:
    """Warp's CPU compiler flags with ``-target-cpu x86-64-v3`` (the form its compiler takes) for its default
    ``-march=native``, where the host has that level (elsewhere, and where the flags were set otherwise, they stay as
    they are)."""
    flags = wp.config.cpu_compiler_flags
    if flags and flags.startswith("-march=native") and X86_64_V3 <= _cpu_flags():
        wp.config.cpu_compiler_flags = flags.replace("-march=native", "-target-cpu x86-64-v3", 1)


_portable_cpu_target()
