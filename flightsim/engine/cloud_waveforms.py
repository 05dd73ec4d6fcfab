"""Large-footprint waveforms from an ALS point cloud on a Warp device (:mod:`kernels.cloud_waveform`), the GEDI
simulator's method as the float64 model states it (:mod:`flightsim.instrument.cloud_waveform_model`).

:func:`prepare_cloud` sorts the points into a horizontal grid of cells (σ_f / 2 by default) on the device, once,
with each point's weight; :func:`cloud_waveforms` launches one block per footprint, in chunks
that keep the outputs on the device within ~200 MB, and copies each chunk's waveforms back.

The histogram has ``sub`` = ⌈4 Δr / σ_r⌉ bins per sample (a bin ≤ σ_r / 4: the split between bins widens a
pulse by at most 1/64 of its variance) and ⌈PULSE_SIGMAS σ_r / bin⌉ bins of margin on each side of the window,
so that points just outside the window still add their tails; at most MAX_BINS bins per component (shared
memory: 2 × MAX_BINS × 4 B = 40 kB a block).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from flightsim.core.errors import InputError
from flightsim.core.process_map import by_pieces
from flightsim.core.warp_runtime import copy_into, resolve_device
from flightsim.instrument.cloud_waveform_model import C, COVER_SIGMAS, CloudBeam, check_request, point_weights
from flightsim.scenes.pointcloud import PointCloud
from kernels.cloud_waveform import (PULSE_SIGMAS, CloudBeamParams, CloudGrid, cloud_cells, cloud_points,
                                    cloud_waveform_kernel)

MAX_BINS = 5120
BIN_STEP = 256  # histogram sizes are rounded up to a multiple of this (one compiled kernel per size)
OUTPUT_FLOATS = 1 << 24  # floats per waveform array a chunk of footprints writes on the device
BLOCK_DIM = 256


@dataclass
class DeviceCloud:
    """A point cloud sorted into grid cells on a device, with its points' weights.

    Attributes:
        grid: the kernel's view (its arrays are kept alive by this object).
        device: the Warp device.
        key: (rho_ground, rho_canopy, normalise) the weights were made with.
        z_range: (lowest, highest) local z of the points [m].
        origin: (3,) world E, N, H [m] of the cloud's local frame.
    """

    grid: CloudGrid
    device: str
    key: tuple[float, float, bool]
    z_range: tuple[float, float]
    origin: np.ndarray


def prepare_cloud(cloud: PointCloud, rho_ground: float = 0.4, rho_canopy: float = 0.57, normalise: bool = False,
                  device: str = "cpu", cell_m: float = 2.75) -> DeviceCloud:
    """``cloud`` sorted into cells of ``cell_m`` [m] on ``device`` with its weights (the model's
    :func:`~flightsim.instrument.cloud_waveform_model.point_weights`): each point's cell found on the device, the
    points in the cells' order by Warp's stable radix sort (a cell's points in the cloud's order), each cell's first
    point by a scan of their counts."""
    if not (math.isfinite(cell_m) and cell_m > 0.0):
        raise InputError("cloud_waveform.cell_m", cell_m, "a grid cell > 0 m")
    device = resolve_device(device)
    weights = point_weights(cloud, rho_ground, rho_canopy, normalise)
    lo, hi = cloud.bounds()
    nx, ny = (int((hi[a] - lo[a]) / cell_m) + 1 for a in (0, 1))
    n, cells = len(cloud), nx * ny
    xyz = wp.array(cloud.xyz, dtype=wp.vec3d, device=device, copy=False)  # on the CPU the host's own, elsewhere a copy
    keys, order = (wp.empty(2 * n, dtype=wp.int32, device=device) for _ in range(2))  # the sort's room
    counts = wp.zeros(cells, dtype=wp.int32, device=device)
    wp.launch(cloud_cells, n, inputs=[xyz, float(lo[0]), float(lo[1]), float(cell_m), nx, ny],
              outputs=[keys, order, counts], device=device)
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=max(1, (cells - 1).bit_length()))
    signed = np.empty(n, dtype=np.float32)  # negative for a ground point

    def piece(rows: slice) -> None:
        signed[rows] = np.where(cloud.ground_of(rows), -weights[rows], weights[rows])

    by_pieces(n, piece)
    grid = CloudGrid()
    grid.points = wp.empty(n, dtype=wp.vec4f, device=device)
    wp.launch(cloud_points, n, inputs=[xyz, wp.array(signed, dtype=wp.float32, device=device, copy=False), order],
              outputs=[grid.points], device=device)
    grid.cell_start = wp.zeros(cells + 1, dtype=wp.int32, device=device)
    wp.utils.array_scan(counts, grid.cell_start[1:], inclusive=True)
    grid.x0, grid.y0, grid.cell = float(lo[0]), float(lo[1]), float(cell_m)
    grid.nx, grid.ny = nx, ny
    return DeviceCloud(grid, device, (float(rho_ground), float(rho_canopy), bool(normalise)),
                       (float(lo[2]), float(hi[2])), cloud.origin.copy())


def cloud_waveforms(cloud: PointCloud, centres_xy, z_top: float, window_start_m, dt_s: float, samples: int,
                    beam: CloudBeam = CloudBeam(), rho_ground: float = 0.4, rho_canopy: float = 0.57,
                    normalise: bool = False, device: str = "cpu", user_footprints: bool = False,
                    prepared: DeviceCloud | None = None, block_dim: int = BLOCK_DIM) -> dict[str, np.ndarray]:
    """Waveforms of the footprints centred at ``centres_xy`` (F, 2) local [m], each sampled at ranges
    ``window_start_m`` (one, or (F,)) + i c ``dt_s`` / 2, i < ``samples``, from the plane z = ``z_top`` [m]
    along ``beam`` (the model's :func:`~flightsim.instrument.cloud_waveform_model.model_waveforms`, same meaning).

    Returns: ``rx``, ``ground``, ``canopy`` (F, samples) float32 [1/m] (∫ rx dr = 1 for an echo within the
    window) and ``outside`` (F,) bool: no point within 3 σ_f of the footprint's axis (its waveforms are 0).
    With ``user_footprints`` such a footprint is an InputError naming the first. ``prepared``: the cloud
    already on the device (:func:`prepare_cloud`), made for the same reflectances and normalisation.
    """
    centres, starts = check_request(centres_xy, z_top, window_start_m, dt_s, samples, beam)
    if prepared is None:
        prepared = prepare_cloud(cloud, rho_ground, rho_canopy, normalise, device, beam.footprint_sigma_m / 2.0)
    elif prepared.key != (float(rho_ground), float(rho_canopy), bool(normalise)):
        raise ValueError(f"the prepared cloud's weights {prepared.key} are not those asked for")
    params, pulse, bins = _beam_params(prepared, beam, dt_s, samples)
    s_axis = (z_top - beam.centre_z_m) / -beam.direction()[2]  # range of each axis's point at centre_z [m]
    origin_bin = params.pad + (s_axis - starts) * params.inv_bin
    kernel = cloud_waveform_kernel(bins)
    pulse_d = wp.array(pulse, dtype=wp.float32, device=prepared.device)
    out = {name: np.empty((len(centres), samples), dtype=np.float32) for name in ("rx", "ground", "canopy")}
    near = np.empty(len(centres), dtype=np.int32)
    chunk = int(np.clip(OUTPUT_FLOATS // samples, 1, 65536))
    for first in range(0, len(centres), chunk):
        part = slice(first, min(first + chunk, len(centres)))
        _launch(kernel, prepared, params, pulse_d, centres[part], origin_bin[part], out, near, part, block_dim)
    outside = near == 0
    if user_footprints and outside.any():
        _refuse_outside(int(np.flatnonzero(outside)[0]), centres, prepared.origin, beam)
    out["outside"] = outside
    return out


def _beam_params(prepared: DeviceCloud, beam: CloudBeam, dt_s: float, samples: int):
    """(CloudBeamParams, pulse taps (2 pad + 1,) float32 [1/m], bins per histogram component)."""
    sigma_r = beam.range_sigma_m()
    sub, width, pad, needed = histogram_layout(sigma_r, dt_s, samples)
    if needed > MAX_BINS:
        most = max((MAX_BINS - 2 - 2 * pad) // sub + 1, 0)
        raise InputError("cloud_waveform.samples", samples, f"at most {most} samples of {dt_s:g} s for a pulse of "
                                                            f"σ = {beam.pulse_sigma_s:g} s (the device histogram)")
    d = beam.direction()
    radius = beam.cut_sigmas * beam.footprint_sigma_m
    ends = np.outer((beam.centre_z_m - np.array(prepared.z_range)) / -d[2], d[:2])  # axis offsets at lowest, highest z
    p = CloudBeamParams()
    p.d = wp.vec3f(*d)
    p.centre_z = float(beam.centre_z_m)
    p.inv_two_sigma2 = 1.0 / (2.0 * beam.footprint_sigma_m ** 2)
    p.cut2, p.near2 = radius ** 2, (COVER_SIGMAS * beam.footprint_sigma_m) ** 2
    p.reach = radius / -d[2]
    p.seg_lo, p.seg_hi = wp.vec2f(*ends.min(axis=0)), wp.vec2f(*ends.max(axis=0))
    p.inv_bin, p.sub, p.pad, p.samples = 1.0 / width, sub, pad, samples
    offsets = np.arange(-pad, pad + 1) * width / sigma_r
    pulse = np.exp(-0.5 * offsets ** 2) / (sigma_r * math.sqrt(2.0 * math.pi))
    return p, pulse.astype(np.float32), -(-needed // BIN_STEP) * BIN_STEP


def histogram_layout(range_sigma_m: float, dt_s: float, samples: int) -> tuple[int, float, int, int]:
    """(bins per sample, bin width [m], bins of margin before the first sample, bins needed per component) of the
    histogram of ``samples`` waveform samples of ``dt_s`` [s] for a pulse of σ_r = ``range_sigma_m`` [m]."""
    step = C * dt_s / 2.0
    sub = max(1, math.ceil(4.0 * step / range_sigma_m))
    width = step / sub
    pad = math.ceil(PULSE_SIGMAS * range_sigma_m / width)
    return sub, width, pad, 2 * pad + (samples - 1) * sub + 2


def waveform_kernels(pulse_sigma_s: float, dt_s: float, samples: int) -> list:
    """The kernel :func:`cloud_waveforms` launches for such waveforms and pulses (σ_p = ``pulse_sigma_s`` [s]), none
    where they need more than MAX_BINS bins (which it refuses), for compiling ahead."""
    *_, needed = histogram_layout(C * pulse_sigma_s / 2.0, dt_s, samples)
    return [cloud_waveform_kernel(-(-needed // BIN_STEP) * BIN_STEP)] if needed <= MAX_BINS else []


def _launch(kernel, prepared: DeviceCloud, params, pulse_d, centres, origin_bin, out, near, part, block_dim) -> None:
    """Run one chunk of footprints and copy its waveforms into ``out`` and ``near`` at ``part``."""
    device, count, samples = prepared.device, len(centres), out["rx"].shape[1]
    arrays = {name: wp.empty((count, samples), dtype=wp.float32, device=device) for name in ("rx", "ground", "canopy")}
    near_d = wp.empty(count, dtype=wp.int32, device=device)
    wp.launch_tiled(kernel, dim=[count], block_dim=block_dim, device=device,
                    inputs=[prepared.grid, params, pulse_d, wp.array(centres.astype(np.float32), dtype=wp.vec2f,
                                                                       device=device),
                            wp.array(origin_bin.astype(np.float32), dtype=wp.float32, device=device)],
                    outputs=[arrays["rx"], arrays["ground"], arrays["canopy"], near_d])
    for name, array in arrays.items():
        copy_into(out[name][part], array)
    copy_into(near[part], near_d)


def _refuse_outside(index: int, centres: np.ndarray, origin: np.ndarray, beam: CloudBeam) -> None:
    x, y = centres[index]
    raise InputError("cloud_waveform.centres_xy",
                     f"footprint {index} at local ({x:.2f}, {y:.2f}) m, world ({x + origin[0]:.2f}, "
                     f"{y + origin[1]:.2f}) m",
                     f"footprints with ALS points within {COVER_SIGMAS:g} σ_f = "
                     f"{COVER_SIGMAS * beam.footprint_sigma_m:g} m of their axis (this one has none: it lies "
                     "outside the cloud)")
