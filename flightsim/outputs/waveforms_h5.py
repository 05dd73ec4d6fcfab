"""Waveforms to HDF5 (h5py), laid out like a GEDI L1B product: per beam a group ``BEAMbbbb`` with one
row per shot and the waveforms concatenated (``rxwaveform[rx_sample_start_index − 1 :][: rx_sample_count]``,
1-based as GEDI). ``waveforms.h5``:

BEAMbbbb/shot_number            uint64   line_id · 2³² + pulse
BEAMbbbb/line_id, pulse         int32, int64
BEAMbbbb/delta_time             float64  adjusted standard GPS time of the shot [s]
BEAMbbbb/rxwaveform             float32  received power [W], samples of every shot one after another
BEAMbbbb/rx_sample_start_index  uint64   1-based start of each shot's samples in rxwaveform
BEAMbbbb/rx_sample_count        uint32
BEAMbbbb/rx_window_start_s      float64  two-way time of flight of each shot's sample 0 [s]
BEAMbbbb/txwaveform, tx_sample_start_index, tx_sample_count: the transmitted power P(t) [W] at the
                                         same interval, sample 0 at tx_window_start_s after emission
BEAMbbbb/geolocation/{x,y,z}_bin0, {x,y,z}_lastbin      float64  world E, N, H (scene CRS) of the first
                                         and last sample on the beam's line of sight, at range c(t − τ/2)/2
BEAMbbbb/geolocation/latitude_bin0, longitude_bin0, latitude_lastbin, longitude_lastbin  [deg] in the
                                         scene CRS's geodetic CRS
BEAMbbbb/ranging/range_halfpower_m, range_centroid_m, range_peak_m, fwhm_s, rms_width_s, n_components,
                 component_range_m, component_amplitude_w, component_sigma_s (MAX_COMPONENTS columns,
                 NaN-padded): half-power leading edge, centroid, peak and Gaussian decomposition
                 (flightsim.instrument.waveform_model); with the receiver's noise, of each waveform less
                 its noise mean (taken from its ends, as l2a.h5's), the centroid and RMS width over the
                 samples from the first to the last above the noise floor (waveform_model.window_noise),
                 the components from the smoothed maxima above that floor (scaled to the smoothing)
BEAMbbbb/truth/nadir_range_m    float64  the beam's central ray to the scene [m]
BEAMbbbb/truth/mean_height_m    float64  footprint-weighted mean height (world H) [m]
BEAMbbbb/truth/received_in_window  float64  share of the received energy inside the window

Attributes: ``sample_interval_s``, ``config_toml``, ``crs_wkt``, ``flightsim``; each ``BEAMbbbb`` group's
attributes are the beam's (``pulse_sigma_s``, ``footprint_sigma_m``, and where they apply ``rho_ground``,
``rho_canopy``: :class:`WaveformWriter`). Written under a temporary name and renamed when complete.

With an :class:`L2AProduct` the writer hands it every beam's waveforms as it writes them: their GEDI L2A metrics
(:func:`flightsim.outputs.l2a.l2a_metrics`) go into ``l2a.h5`` beside (:func:`flightsim.outputs.l2a_h5.write_l2a`),
worked out on a thread of the product's own while the writer goes on with the next batch (one batch at a time), with
the truth: ``elev_ground``, the elevation where the beam's central ray meets the scene (truth/nadir_range_m
along the beam), and ``rh``, :func:`flightsim.outputs.l2a.truth_rh` of the waveform before the receiver's noise and
digitiser.

Beside it, ``returns.las``: every Gaussian component of every waveform as a discrete return (LAS 1.4,
PDRF 6, the scene's CRS), placed on its beam at the component's range c(t − τ/2)/2, at the shot's GPS time.
"""
from __future__ import annotations

import contextlib
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyproj

from flightsim.core.process_map import ProcessMap, map_rows, row_chunks, usable_cores
from flightsim.instrument import waveform_model as model
from flightsim.outputs.h5_product import H5Product
from flightsim.outputs.l2a import L2ASettings, l2a_metrics, truth_rh

MAX_COMPONENTS = 4
FLUSH_BYTES = 32 << 20  # waveforms [B] the writer gathers from line parts before it processes and writes them
PARALLEL_ROWS = 512  # a beam's shots in one batch from which the per-shot work goes to worker processes
MAX_WORKERS = 32  # the most worker processes a writer starts


def _reference_ranging(system: model.WaveformSystem, times: np.ndarray, echoes: np.ndarray, noise) -> tuple[list, list]:
    """(measures, components) of each waveform ``echoes`` (S, N) [W] at ``times`` (S, N) [s] by the float64
    reference model; ``noise``: ((S,) means, (S,) floors) [W] or None (a module-level function: a worker process
    runs it on a chunk of shots)."""
    per_row = [None] * len(echoes) if noise is None else list(zip(*noise))
    rows = [echo.astype(np.float64) for echo in echoes]
    return ([model.measure(system, times[i], echo, per_row[i]) for i, echo in enumerate(rows)],
            [model.decompose(system, times[i], echo, noise=per_row[i]) for i, echo in enumerate(rows)])


@dataclass
class Shots:
    """Line parts of waveforms (:class:`~flightsim.engine.readouts.waveforms.WaveformChunk`) joined: their rows
    one after another, each with its line's ``line_id`` and ``start_time`` [s] and ``part``, the index of the part
    it came from; the other fields are the parts' (same names, units and row shapes)."""

    line_id: np.ndarray
    start_time: np.ndarray
    part: np.ndarray
    pulse: np.ndarray
    beam: np.ndarray
    window_start_s: np.ndarray
    power_w: np.ndarray
    received: np.ndarray
    start: np.ndarray
    direction: np.ndarray
    clean_w: np.ndarray | None

    def __len__(self) -> int:
        return len(self.pulse)

    @classmethod
    def join(cls, parts: list) -> "Shots":
        """The parts' rows one after another (a single part's arrays as they are, not copied)."""
        sizes = [len(p) for p in parts]
        per_row = lambda values: np.repeat(np.asarray(values), sizes)  # noqa: E731
        rows = lambda name: (getattr(parts[0], name) if len(parts) == 1  # noqa: E731
                             else np.concatenate([getattr(p, name) for p in parts]))
        joined = {name: rows(name) for name in ("pulse", "beam", "window_start_s", "power_w", "received", "start",
                                                 "direction")}
        clean = None if parts[0].clean_w is None else rows("clean_w")
        return cls(per_row([p.line_id for p in parts]).astype(np.int64),
                   per_row([p.start_time for p in parts]).astype(np.float64), per_row(np.arange(len(parts))),
                   clean_w=clean, **joined)


class L2AProduct:
    """GEDI L2A metrics of a run's waveforms, beam by beam as they come, into ``path`` (l2a.h5) at :meth:`close`.

    ``dt_s``: sample interval [s]; ``pulse_sigma_s``: σ of the pulse in the waveforms [s]; ``footprint_sigma_m``: the
    footprint's σ_f [m] (the sensitivity's ground width); ``beam_attrs``: each beam group's attributes
    (:data:`flightsim.outputs.l2a_h5.BEAM_ATTRS`); ``attrs``: the file's.
    """

    def __init__(self, path: Path, dt_s: float, pulse_sigma_s: float, footprint_sigma_m: float, beam_attrs: dict,
                 attrs: dict):
        self.path, self.dt, self.pulse_sigma = path, dt_s, pulse_sigma_s
        self.settings = L2ASettings(footprint_sigma_m=footprint_sigma_m)
        self.beam_attrs, self.attrs = beam_attrs, attrs
        self.beams: dict[int, list[dict]] = {}
        self.truth: dict[int, list[dict]] = {}
        self._thread: ThreadPoolExecutor | None = None
        self._running: Future | None = None

    def add(self, beam: int, columns: dict[str, np.ndarray], rx: np.ndarray, clean: np.ndarray,
            ground: np.ndarray, workers: ProcessMap | None = None) -> None:
        """One beam's shots: their waveforms ``rx`` after the receiver and ``clean`` before it (S, N) [W],
        ``columns`` as waveforms.h5 has them, ``ground`` (S,) the true ground elevation [m] (none of them changed
        afterwards), spread over ``workers`` by rows when given. Their metrics are worked out on the product's thread
        while the caller goes on, once the batch before is done (its error raised here)."""
        self.settle()
        if self._thread is None:
            self._thread = ThreadPoolExecutor(1, thread_name_prefix="l2a")
        self._running = self._thread.submit(self._metrics, beam, columns, rx, clean, ground, workers)

    def settle(self) -> None:
        """Wait for the batch being worked out; raise its error."""
        running, self._running = self._running, None
        if running is not None:
            running.result()

    def _metrics(self, beam: int, columns: dict[str, np.ndarray], rx: np.ndarray, clean: np.ndarray,
                 ground: np.ndarray, workers: ProcessMap | None) -> None:
        geo = {f"{q}_{tag}": columns[f"geolocation/{name}_{tag}"] for tag in ("bin0", "lastbin")
               for q, name in (("elevation", "z"), ("latitude", "latitude"), ("longitude", "longitude"))}
        metrics = l2a_metrics(rx, self.dt, pulse_sigma_s=self.pulse_sigma, settings=self.settings, workers=workers,
                              **geo)
        metrics.update(shot_number=columns["shot_number"], delta_time=columns["delta_time"])
        self.beams.setdefault(beam, []).append(metrics)
        rh = truth_rh(np.asarray(clean, dtype=np.float64) * self.dt, geo["elevation_bin0"], geo["elevation_lastbin"],
                      ground)
        self.truth.setdefault(beam, []).append({"elev_ground": ground, "rh": rh})

    def abort(self) -> None:
        """Wait for the batch being worked out (its error dropped: the run is failing already) and end the thread."""
        with contextlib.suppress(Exception):
            self.settle()
        self._end_thread()

    def _end_thread(self) -> None:
        if self._thread is not None:
            self._thread.shutdown()
            self._thread = None

    def close(self) -> tuple[str, dict[str, int]]:
        """Write l2a.h5 once the last batch is worked out; (its name, {"shots": shots, "quality_flag": shots
        flagged 1})."""
        from flightsim.outputs.l2a_h5 import write_l2a

        try:
            self.settle()
        finally:
            self._end_thread()
        beams = {b: {**_joined(parts), **self.beam_attrs} for b, parts in self.beams.items()}
        truth = {b: _joined(parts) for b, parts in self.truth.items()}
        write_l2a(self.path, beams, truth, self.attrs)
        flags = np.concatenate([b["quality_flag"] for b in beams.values()])
        return self.path.name, {"shots": int(len(flags)), "quality_flag": int(np.count_nonzero(flags == 1))}


def _joined(parts: list[dict]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


class WaveformWriter:
    """Appends WaveformChunks to ``directory/waveforms.h5``; ``close()`` renames it into place. ``beam_attrs`` are
    written on every beam group; ``l2a`` (or None) gets every beam's waveforms too."""

    def __init__(self, directory: Path, cfg_text: str, system: model.WaveformSystem, prf_hz: float, scene,
                 tx: tuple[np.ndarray, float], beam_attrs: dict | None = None, l2a: L2AProduct | None = None,
                 device: str | None = None):
        self.product = H5Product(directory / "waveforms.h5", config_toml=cfg_text, crs_wkt=scene.crs.to_wkt(),
                                 sample_interval_s=system.sample_interval_s)
        self.beam_attrs, self.l2a = beam_attrs or {}, l2a
        self.device = device  # where the ranging is computed (waveform.processing = "device"); None: the host
        self.system, self.prf_hz, self.scene = system, prf_hz, scene
        self.tx, self.tx_start = tx
        geodetic = scene.crs.geodetic_crs
        self.to_geodetic = pyproj.Transformer.from_crs(scene.crs, geodetic, always_xy=True) if geodetic else None
        self.shots = 0
        self.directory = directory
        self.returns: list[np.ndarray] = []
        self.return_times: list[np.ndarray] = []
        self.pending: list = []  # line parts taken and not yet written
        self.workers: ProcessMap | None = None
        self.pending_bytes = 0

    def __call__(self, chunk) -> None:
        """Take a flight line's part of a chunk (:class:`~flightsim.engine.readouts.waveforms.WaveformChunk`); the
        parts are processed and written together once they hold FLUSH_BYTES of waveforms (a run of the shots
        platform hands over one shot per line), and at :meth:`flush`."""
        self.pending.append(chunk)
        self.pending_bytes += chunk.power_w.nbytes
        if self.pending_bytes >= FLUSH_BYTES:
            self.flush()

    def flush(self) -> None:
        """Process and write the parts taken so far: each beam's shots of all of them at once, in the order they
        came; returns.las gets their components part by part, beam by beam, as each part alone would give them."""
        if not self.pending:
            return
        shots = Shots.join(self.pending)
        self.pending, self.pending_bytes = [], 0
        ranges = np.full((len(shots), MAX_COMPONENTS), np.nan)
        for beam in np.unique(shots.beam):
            rows = np.flatnonzero(shots.beam == beam)
            head, tail = self._shot_columns(shots, rows)
            # l2a.h5's metrics go on on their thread over the worker processes: set going before a ranging on the
            # device (which needs neither them nor the workers), after one on the host (which maps over the workers)
            columns = self._ranged(shots, rows, head, tail) if self.device is None else None
            if self.l2a is not None:
                clean = shots.power_w if shots.clean_w is None else shots.clean_w
                self.l2a.add(int(beam), head | tail, shots.power_w[rows], clean[rows],
                             self._ground(shots, rows, tail), self._workers(len(rows)))
            if columns is None:
                columns = self._ranged(shots, rows, head, tail)
            ranges[rows] = columns["ranging/component_range_m"]
            self._append(f"BEAM{int(beam):04d}", columns, shots.power_w[rows].ravel())
            self.shots += len(rows)
        self._keep_returns(shots, np.lexsort((shots.beam, shots.part)), ranges)

    def _ground(self, shots, rows: np.ndarray, columns: dict[str, np.ndarray]) -> np.ndarray:
        """World elevation where each shot's central ray meets the scene (its nadir range along the beam) [m]."""
        local = shots.start[rows] + columns["truth/nadir_range_m"][:, None] * shots.direction[rows]
        return local[:, 2] + self.scene.origin[2]

    def _shot_columns(self, shots, rows: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The columns of the shots ``rows`` that come before the ranging/ ones and after them (ids, times and
        windows; truth and geolocation): all but the ranging."""
        s, n = self.system, len(rows)
        samples = shots.power_w.shape[1]
        t0 = shots.window_start_s[rows]
        received = shots.received[rows]
        line = shots.line_id[rows]
        head = {
            "shot_number": (line.astype(np.uint64) << np.uint64(32)) + shots.pulse[rows].astype(np.uint64),
            "line_id": line.astype(np.int32), "pulse": shots.pulse[rows],
            "delta_time": shots.start_time[rows] + shots.pulse[rows] / self.prf_hz,
            "rx_window_start_s": t0, "rx_sample_count": np.full(n, samples, np.uint32),
            "tx_window_start_s": np.full(n, self.tx_start), "tx_sample_count": np.full(n, len(self.tx), np.uint32),
        }
        tail = {
            "truth/nadir_range_m": 0.5 * model.C * t0 + 0.5 * samples * s.sample_interval_s * 0.5 * model.C,
            "truth/mean_height_m": received[:, 2] / np.where(received[:, 3] > 0, received[:, 3], np.nan)
                                   + self.scene.origin[2],
            "truth/received_in_window": received[:, 0] / np.maximum(received[:, 0] + received[:, 1], 1e-300),
        }
        tail.update(self._geolocation(shots, rows, t0, samples))
        as_arrays = lambda columns: {name: np.asarray(v) for name, v in columns.items()}  # noqa: E731
        return as_arrays(head), as_arrays(tail)

    def _ranged(self, shots, rows: np.ndarray, head: dict, tail: dict) -> dict[str, np.ndarray]:
        """The shots' columns in the file's order: ``head``, their ranging/ measures and components, ``tail``."""
        noise = None if shots.clean_w is None else model.window_noise(shots.power_w[rows])  # the receiver's
        ranging, comp = (self._ranging_host if self.device is None else self._ranging_device)(
            shots, rows, head["rx_window_start_s"], noise)
        return {**head, **{name: np.asarray(v) for name, v in ranging.items()},
                "ranging/component_range_m": comp[:, 0], "ranging/component_amplitude_w": comp[:, 1],
                "ranging/component_sigma_s": comp[:, 2], **tail}

    def _ranging_host(self, shots, rows: np.ndarray, t0: np.ndarray, noise) -> tuple[dict, np.ndarray]:
        """The ranging/ measures of each shot and its components (n, 3, MAX_COMPONENTS: range [m], amplitude [W],
        σ [s], NaN-padded) by the float64 reference model, one waveform at a time (over the writer's worker
        processes when it has them); ``noise``: the shots' receiver noise (mean, floor) [W], or None."""
        s, workers = self.system, self._workers(len(rows))
        times = t0[:, None] + s.sample_interval_s * np.arange(shots.power_w.shape[1])[None, :]
        chunks = [(s, times[c], shots.power_w[rows[c]], None if noise is None else (noise[0][c], noise[1][c]))
                  for c in row_chunks(len(rows), workers)]
        results = map_rows(_reference_ranging, chunks, workers)
        measures = [m for chunk_measures, _ in results for m in chunk_measures]
        parts = [p for _, chunk_parts in results for p in chunk_parts]
        comp = np.full((len(rows), 3, MAX_COMPONENTS), np.nan)
        for i, gs in enumerate(parts):
            for j, g in enumerate(gs[:MAX_COMPONENTS]):
                comp[i, :, j] = (0.5 * model.C * (g.time_s - 0.5 * s.pulse_fwhm_s), g.amplitude_w, g.sigma_s)
        return {"ranging/range_halfpower_m": [m.half_power_range_m for m in measures],
                "ranging/range_centroid_m": [m.centroid_range_m for m in measures],
                "ranging/range_peak_m": [m.peak_range_m for m in measures],
                "ranging/fwhm_s": [m.fwhm_s for m in measures], "ranging/rms_width_s": [m.rms_width_s for m in measures],
                "ranging/n_components": np.array([len(p) for p in parts], np.int32)}, comp

    def _ranging_device(self, shots, rows: np.ndarray, t0: np.ndarray, noise) -> tuple[dict, np.ndarray]:
        """:meth:`_ranging_host`'s columns computed for all the rows at once on ``self.device``
        (:func:`flightsim.instrument.waveform_batch.process`)."""
        from flightsim.instrument.waveform_batch import process

        s = self.system
        b = process(s, t0, shots.power_w[rows], self.device, noise=noise)
        ranges = b.ranges_m(s)
        k = min(MAX_COMPONENTS, b.time_s.shape[1])
        comp = np.full((len(rows), 3, MAX_COMPONENTS), np.nan)
        comp[:, 0, :k] = 0.5 * model.C * (b.time_s[:, :k] - 0.5 * s.pulse_fwhm_s)
        comp[:, 1, :k], comp[:, 2, :k] = b.amplitude_w[:, :k], b.sigma_s[:, :k]
        return {"ranging/range_halfpower_m": ranges["half_power_range_m"],
                "ranging/range_centroid_m": ranges["centroid_range_m"], "ranging/range_peak_m": ranges["peak_range_m"],
                "ranging/fwhm_s": b.measures["fwhm_s"], "ranging/rms_width_s": b.measures["rms_width_s"],
                "ranging/n_components": b.count.astype(np.int32)}, comp

    def _workers(self, rows: int) -> ProcessMap | None:
        """The writer's worker processes for per-shot fits, started when a batch first has PARALLEL_ROWS rows and
        this process may run on more than one core; None before and on one core."""
        cores = usable_cores()
        if self.workers is None and rows >= PARALLEL_ROWS and cores > 1:
            self.workers = ProcessMap(min(cores, MAX_WORKERS))
        return self.workers

    def _keep_returns(self, shots: Shots, order: np.ndarray, ranges: np.ndarray) -> None:
        """Each component (range [m] per shot and column, NaN-padded) as a world point with its shot's time, the
        shots taken in ``order``."""
        shot, column = np.nonzero(np.isfinite(ranges[order]))
        shot = order[shot]
        r = ranges[shot, column]
        local = shots.start[shot] + r[:, None] * shots.direction[shot]
        self.returns.append(self.scene.local_to_world(local))
        self.return_times.append(shots.start_time[shot] + shots.pulse[shot] / self.prf_hz)

    def _geolocation(self, shots, rows, t0, samples) -> dict[str, np.ndarray]:
        s = self.system
        out = {}
        for tag, t in (("bin0", t0), ("lastbin", t0 + (samples - 1) * s.sample_interval_s)):
            r = 0.5 * model.C * (t - 0.5 * s.pulse_fwhm_s)
            world = self.scene.local_to_world(shots.start[rows] + r[:, None] * shots.direction[rows])
            out.update({f"geolocation/{a}_{tag}": world[:, k] for k, a in enumerate("xyz")})
            if self.to_geodetic is not None:
                lon, lat = self.to_geodetic.transform(world[:, 0], world[:, 1])
                out.update({f"geolocation/latitude_{tag}": lat, f"geolocation/longitude_{tag}": lon})
        return out

    def _append(self, group: str, columns: dict[str, np.ndarray], rx: np.ndarray) -> None:
        """A beam's shots: their waveforms (gzip: mostly zeros outside the echo) and their columns."""
        n = len(columns["pulse"])
        tx = np.tile(self.tx.astype(np.float32), n)
        rx_before = self.product.append(group, {"rxwaveform": rx.astype(np.float32)}, compress=True)
        tx_before = self.product.append(group, {"txwaveform": tx}, compress=True)
        columns["rx_sample_start_index"] = (rx_before + 1 + np.arange(n) * columns["rx_sample_count"][0]).astype(np.uint64)
        columns["tx_sample_start_index"] = (tx_before + 1 + np.arange(n) * len(self.tx)).astype(np.uint64)
        self.product.append(group, columns)
        self.product.file[group].attrs.update(self.beam_attrs)

    def close(self) -> list[str]:
        """Finish waveforms.h5 and write returns.las (when any waveform held a return); their names. (l2a.h5 is
        the caller's to close: :meth:`L2AProduct.close`.)"""
        from flightsim.outputs.grid_products import write_points_las

        self.flush()
        if self.l2a is not None:  # its last batch done on the workers before they stop
            self.l2a.settle()
        self._stop_workers()
        names = [self.product.close()]
        if self.returns and sum(len(r) for r in self.returns):
            write_points_las(self.directory / "returns.las", np.concatenate(self.returns), self.scene.crs,
                             gps_time=np.concatenate(self.return_times))
            names.append("returns.las")
        return names

    def abort(self) -> None:
        try:
            if self.l2a is not None:  # its batch finishes on the workers before they stop (a second ^C: at once)
                self.l2a.abort()
        finally:
            self._stop_workers()
            self.product.abort()

    def _stop_workers(self) -> None:
        if self.workers is not None:
            self.workers.stop()
