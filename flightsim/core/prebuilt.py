"""Prebuilt kernels: Warp's compiled modules of the built-in instruments' runs (each over its own scene, and the
discrete, waveform and photon ones over the procedural forest: ``PREBUILT_RUNS``), shipped with flightsim, so that
the first run on a new machine compiles nothing it ships.

``flightsim/prebuilt/warp-<version>/`` holds, per module, what Warp's kernel cache would (its ``.meta``, the CPU's
object file for x86-64 and the CUDA binary for sm_90: the H100 and H200), made by ``flightsim compile --all --ship``
on any machine (NVRTC builds sm_90 code without a GPU). At start-up (:func:`seed_kernel_cache`, from
``init_warp``) the files Warp's kernel cache lacks are copied into it: Warp then loads them as modules it compiled
itself. A module whose source changed has another hash and is compiled as usual, so a stale prebuilt set costs
only the compile it would have saved; ``tests/test_prebuilt.py`` says when the set needs remaking.
``FLIGHTSIM_PREBUILT=0`` leaves Warp's cache alone (to time the compilers).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import uuid
from pathlib import Path

import warp as wp

PREBUILT = Path(__file__).resolve().parents[1] / "prebuilt"
CUDA_ARCHS = (90,)  # sm_90: H100, H200
MANIFEST = "MANIFEST"
KEPT = (".meta", ".o", ".cubin")  # a module's files the cache needs (its generated sources are left out)


def shipped() -> Path:
    """The prebuilt modules of this Warp version (the folder may be absent)."""
    return PREBUILT / f"warp-{wp.config.version}"


def seed_kernel_cache(cache: str | os.PathLike | None = None) -> int:
    """Copy the prebuilt modules' files that Warp's kernel cache (``cache``, else Warp's) lacks into it; return how
    many were copied. Each file lands under its final name in one rename, so processes seeding one cache side by
    side (Dask workers) never see half a file; a marker named after the manifest skips the scan next time."""
    source = shipped()
    if os.environ.get("FLIGHTSIM_PREBUILT", "1") == "0" or not (source / MANIFEST).is_file():
        return 0
    target = Path(cache or wp.config.kernel_cache_dir)
    digest = hashlib.sha256((source / MANIFEST).read_bytes()).hexdigest()[:16]
    marker = target / f".flightsim-prebuilt-{digest}"
    if marker.exists():
        return 0
    copied = 0
    for module in sorted(p for p in source.iterdir() if p.is_dir()):
        for file in module.iterdir():
            final = target / module.name / file.name
            if final.exists():
                continue
            final.parent.mkdir(parents=True, exist_ok=True)
            partial = final.with_name(f".{file.name}.{uuid.uuid4().hex}")
            shutil.copyfile(file, partial)
            os.replace(partial, final)
            copied += 1
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()
    return copied


def loaded_on_cpu() -> list:
    """The Warp modules this process has loaded on the CPU."""
    return [m for m in wp._src.context.user_modules.values() if any(ctx is None for ctx, _ in m.execs)]


def build_for_cuda(modules, arch: int, cache: str | os.PathLike | None = None) -> None:
    """Compile ``modules`` for CUDA arch ``arch`` (sm_<arch>) into Warp's kernel cache (``cache``, else Warp's), as
    a run on such a GPU would (NVRTC: no GPU needed). Call it in the process that made the modules' kernels, after
    the last of them: a module's identity is the hash of what it held then."""
    target = Path(cache or wp.config.kernel_cache_dir)
    for module in modules:
        folder = target / module.get_module_identifier()
        if not (folder / f"{folder.name}.sm{arch}.cubin").is_file():
            wp.compile_aot_module(module, arch=arch, use_ptx=False, module_dir=folder)


def missing(modules) -> list[str]:
    """The modules of ``modules`` (Warp modules) the prebuilt set lacks, for the CPU or for a CUDA arch."""
    source = shipped()
    absent = []
    for module in modules:
        cpu = module.get_module_identifier(block_dim=1)  # Warp runs a CPU launch as blocks of one thread
        if not any(f.suffix == ".o" for f in (source / cpu).glob("*")):
            absent.append(f"{cpu} (cpu)")
        cuda = module.get_module_identifier()
        absent += [f"{cuda} (sm_{arch})" for arch in CUDA_ARCHS if not (source / cuda / f"{cuda}.sm{arch}.cubin").is_file()]
    return absent


def ship(cache: Path, out: Path | None = None) -> Path:
    """Make the prebuilt set from a kernel cache ``cache`` that runs filled for the CPU and for CUDA_ARCHS (each
    module's ``.meta``, ``.o`` and ``.cubin`` files; its generated sources left out), into ``out`` (this Warp
    version's folder by default), replacing what was there; returns the folder."""
    out = Path(out or shipped())
    staging = out.with_name(f".{out.name}.{uuid.uuid4().hex}")
    for folder in sorted(Path(cache).iterdir()):
        files = [f for f in folder.iterdir() if f.name.endswith(KEPT)] if folder.name.startswith("wp_") else []
        if any(not f.name.endswith(".meta") for f in files):
            (staging / folder.name).mkdir(parents=True)
            for file in files:
                shutil.copyfile(file, staging / folder.name / file.name)
    lines = [f"{hashlib.sha256(p.read_bytes()).hexdigest()}  {p.relative_to(staging).as_posix()}"
             for p in sorted(staging.rglob("*")) if p.is_file()]
    (staging / MANIFEST).write_text("\n".join(lines) + "\n")
    if out.exists():
        shutil.rmtree(out)
    os.replace(staging, out)
    return out
