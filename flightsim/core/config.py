"""Run configuration: dataclasses with defaults (SPEC §3–§4), validation, TOML in and out.

A run is fully described by a :class:`RunConfig`. Every numeric field carries its allowed range
and unit in its dataclass metadata; :func:`validate` checks them all and raises
:class:`~flightsim.core.errors.InputError` naming the field. ``to_toml`` / ``load_toml`` round-trip the
resolved configuration that is stored beside every output.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flightsim.core.errors import InputError

MODELS = ("exact", "nominal")
BUILTIN_SCENES = ("calibration", "plane", "lunar", "sandbox", "ellipsoid", "bump")
SCENE_FILES = (".obj", ".ply", ".tif", ".tiff", ".npy")  # meshes and height grids
SCENE_PLANES = ("auto", "none")  # how the faces of a mesh file become planes (scene.planes)
EMITTERS = ("fan", "channels")
DEFLECTORS = ("risley", "galvo", "fsm", "fixed")
DETECTORS = ("discrete", "photon", "waveform")
PLATFORMS = ("lines", "hover", "orbit")
BODIES = ("earth", "moon")
ARCSEC = math.pi / (180.0 * 3600.0)  # [rad per arcsecond]
CHANGE3_CHANNELS_MRAD = tuple(float(17 - 2 * i) for i in range(1, 17))  # θ_i = 17 − 2i (seed paper §2.3)
OPTICS = ("float32", "float64", "lut")
BVH_CONSTRUCTORS = ("auto", "sah", "median", "lbvh", "cubql")
KMH = 1.0 / 3.6  # [m/s per km/h]
MIN_ROTATION_PERIOD_S, MAX_ROTATION_PERIOD_S = 60.0, 1.0e7  # a spinning body's period: 1 min to 116 days [s]
ROTATION_PERIOD_UNIT = f"s; 0 = not rotating, else at least {MIN_ROTATION_PERIOD_S:g} s"


def _num(lo: float, hi: float, unit: str = "", *, lo_open: bool = False, integer: bool = False) -> dict:
    """Field metadata: allowed closed (or left-open) interval and unit."""
    return {"range": (lo, hi, lo_open), "unit": unit, "integer": integer}


@dataclass
class SceneConfig:
    """What is scanned: a built-in scene or a mesh file, and where it lies."""

    name: str = "calibration"  # a built-in scene, or a path to an .obj/.ply mesh or a .tif/.tiff/.npy height grid
    crs: str = "EPSG:32648"
    origin: tuple[float, float, float] = (409000.0, 3393000.0, 450.0)  # world E, N, H [m]
    slope: float = field(default=0.0, metadata=_num(-2.0, 2.0, "rise/run"))  # plane scene only
    cell_m: float = field(default=1.0, metadata=_num(0.0, 1.0e5, "m, node spacing of a .npy height grid", lo_open=True))
    simplify_m: float = field(default=0.0, metadata=_num(0.0, 1.0e4, "m, largest vertical error of a simplified height "
                                                                     "grid; 0 = two triangles per cell"))
    landcover: str = ""  # height grids: a GeoTIFF of ASPRS class codes in the grid's CRS (scenes.landcover)
    buildings: str = ""  # height grids: an .obj/.ply mesh in the grid's CRS world coordinates (scenes.buildings)
    ccrs: tuple = ()  # corner-cube retroreflectors: [east, north, up] local [m] each (photon detector)
    ccr_photons: float = field(default=0.0, metadata=_num(0.0, 1.0e6, "photo-electrons a CCR returns at a footprint's "
                                                                       "centre"))
    margin_m: float = field(default=50.0, metadata=_num(0.0, 10000.0, "m"))
    planes: str = "auto"  # mesh files: "auto" groups faces into planes; "none" keeps one label per OBJ group or PLY
    # class/plane_id (a terrain: no grouping, and no plane-fit RMS, which would measure the curvature)


@dataclass
class FlightConfig:
    """The flight plan: straight parallel lines over the scene centre, or a trajectory file."""

    altitude_m: float = field(default=500.0, metadata=_num(0.0, 1.0e6, "m above ground", lo_open=True))
    speed_kmh: float = field(default=200.0, metadata=_num(0.0, 30000.0, "km/h (to orbital ground speeds)", lo_open=True))
    duration_s: float = field(default=10.0, metadata=_num(0.0, 36000.0, "s per line", lo_open=True))
    heading_deg: float = field(default=0.0, metadata=_num(-360.0, 360.0, "deg"))
    roll_deg: float = field(default=0.0, metadata=_num(-30.0, 30.0, "deg"))
    pitch_deg: float = field(default=0.0, metadata=_num(-30.0, 30.0, "deg"))
    start_gps_time: float = field(default=450_000_000.0, metadata=_num(-1.0e9, 2.0e9, "s, adjusted standard GPS time"))
    lines: int = field(default=1, metadata=_num(1, 65535, integer=True))
    line_spacing_m: float = field(default=200.0, metadata=_num(0.0, 1.0e5, "m", lo_open=True))
    trajectory: str = ""  # CSV trajectory file; when given it replaces the line plan
    platform: str = "lines"  # "lines": flight lines (or the trajectory file); "hover": a lander or tripod over the scene centre
    descent_mps: float = field(default=0.0, metadata=_num(-100.0, 100.0, "m/s, hover platform (positive: descending)"))
    body: str = "earth"  # orbit platform: the central body, earth (WGS84) or moon (a 1737.4 km sphere)
    inclination_deg: float = field(default=92.0, metadata=_num(0.0, 180.0, "deg, orbit platform"))
    eccentricity: float = field(default=0.0, metadata=_num(0.0, 1.0, "orbit platform, below 1; altitude_m is the "
                                                                      "altitude of the pass over the scene"))
    perigee_arg_deg: float = field(default=0.0, metadata=_num(-360.0, 360.0, "deg, orbit platform: argument of "
                                                                             "perigee from the ascending node"))
    body_rotation_period_s: float = field(default=0.0, metadata=_num(0.0, MAX_ROTATION_PERIOD_S, ROTATION_PERIOD_UNIT))
    # hover platform: the scene spins about its local y axis through the local origin (platforms.rotating_body)
    terrain_following: bool = False  # planned lines keep altitude_m above the ground under the aircraft, climbing
    # and descending at most platforms.plan.MAX_CLIMB_MPS (else: altitude_m above the scene's ground height)


@dataclass
class SensorConfig:
    """The instrument as it really is: beam array, prism, scan timing, mounting."""

    array: int = field(default=3, metadata=_num(1, 64, "beams per side", integer=True))
    spacing_mrad: float = field(default=2.314, metadata=_num(0.0, 200.0, "mrad"))
    prf_hz: float = field(default=5000.0, metadata=_num(0.0, 1.0e7, "Hz", lo_open=True))
    rotation_hz: float = field(default=20.0, metadata=_num(0.0, 1000.0, "Hz"))
    phase0_deg: float = field(default=0.0, metadata=_num(-360.0, 360.0, "deg"))
    cone_half_angle_deg: float = field(default=15.0, metadata=_num(0.0, 89.0, "deg", lo_open=True))
    apex_angle_deg: float = field(default=0.0, metadata=_num(0.0, 89.0, "deg; 0 derives it from the cone angle"))
    refractive_index: float = field(default=1.5066, metadata=_num(1.0, 4.0, "", lo_open=True))
    thickness_mm: float = field(default=10.0, metadata=_num(0.0, 1000.0, "mm", lo_open=True))
    boresight_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # roll, pitch, yaw of sensor in body
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # sensor origin in the body frame
    max_range_m: float = field(default=30000.0, metadata=_num(0.0, 1.0e6, "m", lo_open=True))
    range_noise_m: float = field(default=0.0, metadata=_num(0.0, 100.0, "m, 1 sigma"))
    divergence_mrad: float = field(default=0.3, metadata=_num(0.0, 100.0, "mrad, full angle"))


@dataclass
class InstrumentConfig:
    """Which parts make the instrument (ARCHITECTURE.md, "Instruments as parts")."""

    emitter: str = "fan"  # "fan": the N×N DOE fan of [sensor]; "channels": the linear array of [channels]
    deflector: str = "risley"  # "risley": the wedge of [sensor]; "galvo": the two mirrors of [galvo];
    # "fsm": the 45° mirror and fast steering mirror of [fsm]; "fixed"
    detector: str = "discrete"  # "discrete": one return per beam; "photon": photon events of a SPAD pixel ([photon]);
    # "waveform": a full waveform per beam from sub-rays over its footprint ([waveform])


@dataclass
class ChannelsConfig:
    """A linear array of channels fanned along the emitter's y axis (a vertical fan behind a galvo)."""

    angles_mrad: tuple[float, ...] = CHANGE3_CHANNELS_MRAD  # angle of each channel from the beam axis [mrad]


@dataclass
class GalvoConfig:
    """The two-mirror galvanometer scanner (kernels.galvo) and its raster."""

    b_mm: float = field(default=50.0, metadata=_num(0.0, 1000.0, "mm, source to mirror 1", lo_open=True))
    e_mm: float = field(default=20.0, metadata=_num(0.0, 1000.0, "mm, mirror 1 to mirror 2", lo_open=True))
    aperture_mm: float = field(default=15.0, metadata=_num(0.0, 1000.0, "mm, half size of each mirror",
                                                           lo_open=True))
    field_deg: tuple[float, float] = (30.0, 30.0)  # full field of the central ray: horizontal, vertical [deg]
    strips: int = field(default=17, metadata=_num(1, 4096, "horizontal strips per frame", integer=True))
    columns: int = field(default=256, metadata=_num(1, 65536, "pulses per strip", integer=True))
    frame_s: float = field(default=0.1, metadata=_num(0.0, 3600.0, "s per frame", lo_open=True))


@dataclass
class FsmConfig:
    """The fast-steering-mirror path and its scan (kernels.fsm): MODE-A or MODE-B."""

    b2_mm: float = field(default=30.0, metadata=_num(0.0, 1000.0, "mm, grating to the 45° mirror", lo_open=True))
    d_mm: float = field(default=40.0, metadata=_num(0.0, 1000.0, "mm, 45° mirror to the FSM", lo_open=True))
    aperture_mm: float = field(default=25.0, metadata=_num(0.0, 1000.0, "mm, half size of each mirror", lo_open=True))
    mode: str = "A"  # "A": triangle-wave sweeps in x, steps in y (sub-pixel interleave); "B": a steps × steps grid
    span_mrad: tuple[float, float] = (2.62, 1.80)  # full FSM tilt span of the pattern (θx, θy) [mrad]
    lines: int = field(default=40, metadata=_num(1, 65536, "MODE-A sweeps per frame, MODE-B steps per axis",
                                                  integer=True))
    frame_s: float = field(default=0.86, metadata=_num(0.0, 3600.0, "s per frame", lo_open=True))
    prf_hz: float = field(default=50000.0, metadata=_num(0.0, 1.0e7, "Hz", lo_open=True))


@dataclass
class ErrorsConfig:
    """Error sources applied to the truth while the processing believes the nominal instrument
    (seed paper §2); all off by default."""

    b1_arcsec: float = field(default=0.0, metadata=_num(-3600.0, 3600.0, "arcsec, horizontal encoder zero error"))
    b2_arcsec: float = field(default=0.0, metadata=_num(-3600.0, 3600.0, "arcsec, collimation-axis error"))
    b3_arcsec: float = field(default=0.0, metadata=_num(-3600.0, 3600.0, "arcsec, horizontal-axis error"))
    c1_arcsec: float = field(default=0.0, metadata=_num(-3600.0, 3600.0, "arcsec, vertical encoder zero error"))
    h_noise_arcsec: float = field(default=0.0, metadata=_num(0.0, 3600.0, "arcsec, horizontal mirror angle, 1 sigma"))
    v_noise_arcsec: float = field(default=0.0, metadata=_num(0.0, 3600.0, "arcsec, vertical mirror angle, 1 sigma"))
    channel_delay_m: float = field(default=0.0, metadata=_num(0.0, 10.0, "m, 1 sigma of each channel's fixed delay"))
    range_bias_m: float = field(default=0.0, metadata=_num(-100.0, 100.0, "m, added to every range (a ranging bias)"))
    clock_drift: float = field(default=0.0, metadata=_num(-1.0e-3, 1.0e-3, "clock frequency drift e_df"))
    tdc_bin_s: float = field(default=0.0, metadata=_num(0.0, 1.0e-6, "s, TDC resolution"))
    jitter_s: float = field(default=0.0, metadata=_num(0.0, 1.0e-6, "s, rising-edge jitter of each stamp, 1 sigma"))
    rise_time_s: float = field(default=0.0, metadata=_num(0.0, 1.0e-6, "s, echo rise time (constant-fraction "
                                                                       "timing noise; 0 = off)"))
    encoder_arcsec: float = field(default=0.0, metadata=_num(-3600.0, 3600.0, "arcsec, prism-angle encoder zero "
                                                                            "error (risley)"))
    encoder_noise_arcsec: float = field(default=0.0, metadata=_num(0.0, 3600.0, "arcsec, prism angle per pulse, "
                                                                                "1 sigma (risley)"))
    fsm_zero_arcsec: tuple[float, float] = (0.0, 0.0)  # FSM encoder zero errors of θx, θy on the truth [arcsec]
    fsm_noise_arcsec: float = field(default=0.0, metadata=_num(0.0, 3600.0, "arcsec, FSM tilt noise per axis and "
                                                                            "pulse, 1 sigma"))
    boresight_arcsec: tuple[float, float, float] = (0.0, 0.0, 0.0)  # roll, pitch, yaw of the true sensor axes in
    # the believed ones (residual boresight calibration error) [arcsec]
    position_noise_m: float = field(default=0.0, metadata=_num(0.0, 100.0, "m, POS position per axis and pulse, "
                                                                           "1 sigma"))
    attitude_noise_arcsec: float = field(default=0.0, metadata=_num(0.0, 3600.0, "arcsec, POS attitude about each "
                                                                                 "sensor axis per pulse, 1 sigma"))
    cfd_fraction: float = field(default=0.3, metadata=_num(0.0, 1.0, "constant fraction k"))
    snr: float = field(default=31.0, metadata=_num(0.0, 1.0e6, "echo signal-to-noise ratio", lo_open=True))


@dataclass
class PhotonConfig:
    """The photon-counting detector (kernels.photon): one SPAD pixel with its own TDC per beam."""

    wavelength_nm: float = field(default=532.0, metadata=_num(100.0, 20000.0, "nm"))
    pulse_energy_j: float = field(default=1.0e-9, metadata=_num(0.0, 10.0, "J per beam", lo_open=True))
    aperture_m: float = field(default=0.05, metadata=_num(0.0, 10.0, "m, receiver diameter", lo_open=True))
    optics_transmission: float = field(default=0.5, metadata=_num(0.0, 1.0, "receiver optics", lo_open=True))
    pde: float = field(default=0.2, metadata=_num(0.0, 1.0, "photon detection efficiency", lo_open=True))
    pulse_fwhm_s: float = field(default=1.0e-9, metadata=_num(0.0, 1.0e-6, "s", lo_open=True))
    jitter_s: float = field(default=1.0e-10, metadata=_num(0.0, 1.0e-6, "s, timing jitter, 1 sigma"))
    tdc_bin_s: float = field(default=0.0, metadata=_num(0.0, 1.0e-6, "s, TDC resolution; 0 = exact times"))
    gate_m: tuple[float, float] = (5.0, 600.0)  # range gate, one-way [m]
    noise_hz: float = field(default=1.0e5, metadata=_num(0.0, 1.0e10, "Hz, background and dark counts per pixel"))
    dead_time_s: float = field(default=5.0e-8, metadata=_num(0.0, 1.0e-3, "s, non-paralyzable"))
    max_events: int = field(default=8, metadata=_num(1, 256, "detections per pixel and pulse", integer=True))
    reflectance: float = field(default=0.2, metadata=_num(0.0, 1.0, "Lambertian, every face unless scene.landcover "
                                                                    "sets it", lo_open=True))


@dataclass
class WaveformConfig:
    """The full-waveform detector (kernels.waveform): each beam's footprint sampled by sub-rays over its
    Gaussian profile exp(−2 tan²φ/α²), their echoes summed into one waveform per beam (seed:
    large-footprint-echo-waveform-patent.txt; defaults are the patent's Chang'e-1-like altimeter)."""

    half_divergence_rad: float = field(default=3.0e-4, metadata=_num(0.0, 0.1, "rad, α: the 1/e² half angle", lo_open=True))
    pulse_fwhm_s: float = field(default=7.0e-9, metadata=_num(0.0, 1.0e-6, "s", lo_open=True))
    peak_power_w: float = field(default=0.05, metadata=_num(0.0, 1.0e9, "W", lo_open=True))
    scheme: str = "polar"  # footprint sub-rays: polar (the patent's rings × sectors), polar_midpoint, equal_energy
    n_rings: int = field(default=60, metadata=_num(1, 4096, "rings of the footprint", integer=True))
    n_sectors: int = field(default=120, metadata=_num(1, 4096, "sectors of the footprint", integer=True))
    sample_interval_s: float = field(default=1.0e-11, metadata=_num(0.0, 1.0e-6, "s", lo_open=True))
    samples: int = field(default=32768, metadata=_num(16, 1 << 22, "samples per waveform", integer=True))
    aperture_m: float = field(default=1.0, metadata=_num(0.0, 100.0, "m, receiver diameter D", lo_open=True))
    transmitter_efficiency: float = field(default=1.0, metadata=_num(0.0, 1.0, "η_t", lo_open=True))
    receiver_efficiency: float = field(default=1.0, metadata=_num(0.0, 1.0, "η_r", lo_open=True))
    atmosphere_transmission: float = field(default=1.0, metadata=_num(0.0, 1.0, "T_A, one way", lo_open=True))
    reflectance: float = field(default=1.0, metadata=_num(0.0, 1.0, "f, backscatter of eq. 1, every face unless "
                                                                    "scene.landcover sets it", lo_open=True))
    receiver_fwhm_s: float = field(default=0.0, metadata=_num(0.0, 1.0e-6, "s, Gaussian impulse response; 0 = none"))
    shot_noise: bool = False  # Poisson photo-electrons of signal and background in every sample
    wavelength_nm: float = field(default=1064.0, metadata=_num(100.0, 20000.0, "nm"))
    quantum_efficiency: float = field(default=0.4, metadata=_num(0.0, 1.0, "of the detector", lo_open=True))
    background_w: float = field(default=0.0, metadata=_num(0.0, 1.0e3, "W, optical background at the detector"))
    thermal_noise_w: float = field(default=0.0, metadata=_num(0.0, 1.0e3, "W rms per sample, receiver noise"))
    bits: int = field(default=0, metadata=_num(0, 16, "digitiser resolution; 0 = no digitiser", integer=True))
    full_scale_w: float = field(default=0.0, metadata=_num(0.0, 1.0e9, "W, the digitiser's top code; needed with bits"))


@dataclass
class ProcessingConfig:
    """The deflector the georeferencing believes in; 0 means "the same as the sensor's"."""

    refractive_index: float = field(default=0.0, metadata=_num(0.0, 4.0, "; 0 = sensor value"))
    apex_angle_deg: float = field(default=0.0, metadata=_num(0.0, 89.0, "deg; 0 = sensor value"))
    thickness_mm: float = field(default=0.0, metadata=_num(0.0, 1000.0, "mm; 0 = sensor value"))
    b_mm: float = field(default=0.0, metadata=_num(0.0, 1000.0, "mm; 0 = galvo value"))
    e_mm: float = field(default=0.0, metadata=_num(0.0, 1000.0, "mm; 0 = galvo value"))


@dataclass
class OutputConfig:
    """What is written."""

    models: tuple[str, ...] = MODELS
    tile_size_m: int = field(default=500, metadata=_num(1, 100000, "m", integer=True))
    laz: bool = False
    position_error: bool = False
    copc: bool = False  # also one COPC file per model, <model>.copc.laz, from its tiles (outputs.copc)
    crs: str = ""  # photon runs: CRS of the photon LAS points, "" = the scene's (flightsim.outputs.photon_las)


@dataclass
class ScoringConfig:
    """How plane fits are scored (SPEC §9)."""

    edge_buffer_m: float = field(default=-1.0, metadata=_num(-1.0, 1000.0, "m; -1 = automatic"))
    patch_m: float = field(default=0.0, metadata=_num(0.0, 100000.0, "m, side of the square patches a LAS run "
                                                      "fits; 0 = 25 m on a curved scene, none on a planar one"))


@dataclass
class RunSettings:
    """How the run executes."""

    device: str = "cpu"
    seed: int = field(default=0, metadata=_num(0, 2**31 - 1, integer=True))
    chunk_pulses: int = field(default=0, metadata=_num(0, 2**24, "pulses; 0 = automatic", integer=True))
    cull: bool = True  # skip pulses whose beams cannot reach the scene
    optics: str = "float64"  # per-beam arithmetic: float64, float32, or lut (float32, exit rays tabulated over φ)
    lut_samples: int = field(default=4096, metadata=_num(8, 1 << 22, "prism angles per turn", integer=True))
    bvh: str = "auto"  # BVH constructor: auto (sah on the CPU, cubql on a GPU), sah, median, lbvh, cubql
    bvh_leaf_size: int = field(default=0, metadata=_num(0, 64, "triangles; 0 = Warp's default", integer=True))
    slots_per_thread: int = field(default=0, metadata=_num(0, 4096, "statistics mode; 0 = automatic",
                                                                integer=True))
    sum_replicas: int = field(default=0, metadata=_num(0, 4096, "statistics mode on a GPU: copies of the sums; "
                                                       "0 = automatic", integer=True))
    max_registers: int = field(default=0, metadata=_num(0, 255, "registers per thread of the CUDA trace kernels; "
                                                         "0 = automatic", integer=True))
    scene_cache: bool = True  # keep scenes read from files in $FLIGHTSIM_CACHE (~/.cache/flightsim/scenes) as .npz


@dataclass
class RunConfig:
    """Everything that defines a run."""

    scene: SceneConfig = field(default_factory=SceneConfig)
    flight: FlightConfig = field(default_factory=FlightConfig)
    instrument: InstrumentConfig = field(default_factory=InstrumentConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    channels: ChannelsConfig = field(default_factory=ChannelsConfig)
    galvo: GalvoConfig = field(default_factory=GalvoConfig)
    fsm: FsmConfig = field(default_factory=FsmConfig)
    errors: ErrorsConfig = field(default_factory=ErrorsConfig)
    photon: PhotonConfig = field(default_factory=PhotonConfig)
    waveform: WaveformConfig = field(default_factory=WaveformConfig)
    processing: ProcessingConfig = field(default_factory=ProcessingConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    scoring: ScoringConfig = field(default_factory=ScoringConfig)
    run: RunSettings = field(default_factory=RunSettings)


# ---------------------------------------------------------------------------------------------
# derived optics


def apex_for_cone(cone_half_angle: float, n_glass: float) -> float:
    """Apex angle α [rad] whose on-axis deviation is the cone half-angle θ [rad].

    The on-axis beam crosses Σ1 undeviated and meets Σ2 at incidence α, leaving at asin(n sin α),
    so θ = asin(n sin α) − α, i.e. tan α = sin θ / (n − cos θ).
    """
    return math.atan2(math.sin(cone_half_angle), n_glass - math.cos(cone_half_angle))


def cone_for_apex(apex: float, n_glass: float) -> float:
    """On-axis deviation θ [rad] of a wedge of apex α [rad]; NaN on total internal reflection."""
    s = n_glass * math.sin(apex)
    return math.asin(s) - apex if s < 1.0 else math.nan


def resolved_apex_deg(sensor: SensorConfig) -> float:
    """The sensor's apex angle [deg]: given, or derived from the cone half-angle."""
    if sensor.apex_angle_deg > 0.0:
        return sensor.apex_angle_deg
    return math.degrees(apex_for_cone(math.radians(sensor.cone_half_angle_deg), sensor.refractive_index))


def copy_config(cfg: RunConfig) -> RunConfig:
    """An independent copy (every section copied; field values are immutable)."""
    return RunConfig(**{f.name: dataclasses.replace(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)})


def resolve(config: RunConfig) -> RunConfig:
    """Fill derived values (apex angle, cone angle, believed prism) so the config stands alone."""
    cfg = copy_config(config)
    s, p = cfg.sensor, cfg.processing
    if s.apex_angle_deg > 0.0:
        cone = math.degrees(cone_for_apex(math.radians(s.apex_angle_deg), s.refractive_index))
        if abs(cone - s.cone_half_angle_deg) > 1e-9:  # keep a stated cone that the apex already implies
            s.cone_half_angle_deg = cone
    else:
        s.apex_angle_deg = resolved_apex_deg(s)
    p.refractive_index = p.refractive_index or s.refractive_index
    p.apex_angle_deg = p.apex_angle_deg or s.apex_angle_deg
    p.thickness_mm = p.thickness_mm or s.thickness_mm
    p.b_mm = p.b_mm or cfg.galvo.b_mm
    p.e_mm = p.e_mm or cfg.galvo.e_mm
    return cfg


# ---------------------------------------------------------------------------------------------
# validation


def _check_number(name: str, value: Any, meta: dict) -> None:
    lo, hi, lo_open = meta["range"]
    unit = f" {meta['unit']}" if meta["unit"] else ""
    if meta["integer"]:
        allowed = f"an integer in [{lo}, {hi}]{unit}"
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise InputError(name, value, allowed)
        return
    allowed = f"a finite number in {'(' if lo_open else '['}{lo:g}, {hi:g}]{unit}"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(name, value, allowed)
    if value < lo or value > hi or (lo_open and value == lo):
        raise InputError(name, value, allowed)


def _check_vector(name: str, value: Any, limit: float, unit: str) -> None:
    allowed = f"three finite numbers each within ±{limit:g} {unit}"
    if not isinstance(value, (tuple, list)) or len(value) != 3:
        raise InputError(name, value, allowed)
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > limit:
            raise InputError(name, value, allowed)


def check_fields(section_name: str, section: Any) -> None:
    """Range-check every numeric field that declares a range in its metadata."""
    for f in dataclasses.fields(section):
        if "range" in f.metadata:
            _check_number(f"{section_name}.{f.name}", getattr(section, f.name), f.metadata)


def _check_optics(cfg: RunConfig) -> None:
    """The wedge's optics (the default fan and prism are checked whichever parts a run uses)."""
    s = cfg.sensor
    critical = math.degrees(math.asin(1.0 / s.refractive_index))
    if s.apex_angle_deg > 0.0 and s.apex_angle_deg >= critical:
        raise InputError("sensor.apex_angle_deg", s.apex_angle_deg,
                         f"an angle below {critical:.3f} deg (total internal reflection of the on-axis beam)")
    max_cone = 90.0 - critical
    if s.apex_angle_deg == 0.0 and s.cone_half_angle_deg >= max_cone:
        raise InputError("sensor.cone_half_angle_deg", s.cone_half_angle_deg,
                         f"an angle in (0, {max_cone:.3f}) deg for refractive index {s.refractive_index:g}")
    half_fan = (s.array - 1) / 2 * s.spacing_mrad * 1e-3
    if half_fan >= math.radians(80.0):
        limit = math.radians(80.0) / max((s.array - 1) / 2, 0.5) * 1e3
        raise InputError("sensor.spacing_mrad", s.spacing_mrad,
                         f"a spacing below {limit:.3f} mrad for a {s.array}x{s.array} array (fan within ±80 deg)")
    p = cfg.processing
    if 0.0 < p.refractive_index <= 1.0:
        raise InputError("processing.refractive_index", p.refractive_index, "0 (sensor value) or a number in (1, 4]")
    n_believed = p.refractive_index or s.refractive_index
    if p.apex_angle_deg > 0.0 and math.sin(math.radians(p.apex_angle_deg)) * n_believed >= 1.0:
        raise InputError("processing.apex_angle_deg", p.apex_angle_deg,
                         f"an angle below {math.degrees(math.asin(1.0 / n_believed)):.3f} deg")


def _check_choices(cfg: RunConfig) -> None:
    models = tuple(cfg.output.models)
    if not models or any(m not in MODELS for m in models) or len(set(models)) != len(models):
        raise InputError("output.models", ",".join(map(str, models)), "a non-empty subset of exact,nominal")
    if cfg.output.copc and cfg.instrument.detector in ("photon", "waveform"):
        raise InputError("output.copc", True, f"false with instrument.detector = {cfg.instrument.detector} "
                                              "(COPC is made from the discrete-return tiles)")
    scenes = f"{', '.join(BUILTIN_SCENES)}, or a path to an .obj/.ply mesh or a .tif/.tiff/.npy height grid"
    if not isinstance(cfg.scene.name, str) or not cfg.scene.name:
        raise InputError("scene.name", cfg.scene.name, scenes)
    if cfg.scene.name not in BUILTIN_SCENES and Path(cfg.scene.name).suffix.lower() not in SCENE_FILES:
        raise InputError("scene.name", cfg.scene.name, scenes)
    if cfg.flight.platform in ("hover", "orbit") and cfg.flight.trajectory:
        raise InputError("flight.trajectory", cfg.flight.trajectory,
                         f"empty with flight.platform = {cfg.flight.platform}")
    choices = (("run.optics", cfg.run.optics, OPTICS), ("run.bvh", cfg.run.bvh, BVH_CONSTRUCTORS),
               ("scene.planes", cfg.scene.planes, SCENE_PLANES),
               ("instrument.emitter", cfg.instrument.emitter, EMITTERS),
               ("instrument.deflector", cfg.instrument.deflector, DEFLECTORS),
               ("instrument.detector", cfg.instrument.detector, DETECTORS),
               ("flight.platform", cfg.flight.platform, PLATFORMS), ("flight.body", cfg.flight.body, BODIES))
    for name, value, allowed in choices:
        if value not in allowed:
            raise InputError(name, value, "one of " + ", ".join(allowed))
    device = cfg.run.device
    if device != "cpu" and device != "cuda" and not (device.startswith("cuda:") and device[5:].isdigit()):
        raise InputError("run.device", device, "cpu, cuda or cuda:N")
    _check_vector("scene.origin", cfg.scene.origin, 1.0e8, "m")
    _check_vector("sensor.boresight_deg", cfg.sensor.boresight_deg, 10.0, "deg")
    _check_vector("sensor.lever_arm_m", cfg.sensor.lever_arm_m, 100.0, "m")
    _check_vector("errors.boresight_arcsec", cfg.errors.boresight_arcsec, 3600.0, "arcsec")


def _check_rotation(cfg: RunConfig) -> None:
    """flight.body_rotation_period_s (already in [0, MAX]) is 0, or at least MIN under a hover (a hover
    already refuses a trajectory file, so a rotating body never flies one)."""
    f = cfg.flight
    period = f.body_rotation_period_s
    if period == 0.0:
        return
    if period < MIN_ROTATION_PERIOD_S:  # the same words as the range check of the field's metadata
        raise InputError("flight.body_rotation_period_s", period,
                         f"a finite number in [0, {MAX_ROTATION_PERIOD_S:g}] {ROTATION_PERIOD_UNIT}")
    if f.platform != "hover":
        raise InputError("flight.body_rotation_period_s", period,
                         f"0 with flight.platform = {f.platform} (a rotating body needs flight.platform = hover)")


def _check_ccrs(cfg: RunConfig) -> None:
    """scene.ccrs: each retroreflector three finite local coordinates [m]."""
    for ccr in cfg.scene.ccrs:
        ok = isinstance(ccr, (list, tuple)) and len(ccr) == 3 and all(  # as converted by _to_points
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in ccr)
        if not ok:
            raise InputError("scene.ccrs", ccr, "[east, north, up] local coordinates [m], three finite numbers each")


def _check_output_crs(cfg: RunConfig) -> None:
    """output.crs: "" or, for a photon run from the Earth, a projected CRS in metres with a WKT1 form (the LAS
    tiles'; latitude and longitude are in atl03.h5)."""
    value = cfg.output.crs
    if not value:
        return
    if cfg.instrument.detector != "photon" or (cfg.flight.platform == "orbit" and cfg.flight.body != "earth"):
        raise InputError("output.crs", value, "\"\" (the scene's CRS) unless instrument.detector = photon over "
                                              "the Earth")
    from flightsim.scenes.scene import parse_crs

    parse_crs(value, field="output.crs")


def _check_terrain(cfg: RunConfig) -> None:
    """scene.simplify_m, scene.landcover and scene.buildings go with a height grid (scenes.dem) only."""
    s = cfg.scene
    grid = "a .tif/.tiff/.npy height grid as scene.name"
    is_grid = Path(s.name).suffix.lower() in (".tif", ".tiff", ".npy")
    if s.simplify_m > 0.0 and not is_grid:
        raise InputError("scene.simplify_m", s.simplify_m, f"0 unless scene.name is {grid}")
    for name, value, suffixes in (("scene.landcover", s.landcover, (".tif", ".tiff")),
                                  ("scene.buildings", s.buildings, (".obj", ".ply"))):
        if value and (not is_grid or Path(value).suffix.lower() not in suffixes):
            raise InputError(name, value, f"\"\" or a {'/'.join(suffixes)} file path, with {grid}")


def validate(cfg: RunConfig) -> RunConfig:
    """Check every field; return the resolved config or raise InputError naming the field."""
    for section in dataclasses.fields(cfg):
        check_fields(section.name, getattr(cfg, section.name))
    _check_choices(cfg)
    _check_rotation(cfg)
    _check_ccrs(cfg)
    _check_output_crs(cfg)
    _check_optics(cfg)
    resolved = resolve(cfg)
    from flightsim.instrument.parts import HostInstrument  # the parts check their own sections

    _check_terrain(cfg)
    HostInstrument(resolved).check()
    return resolved


# ---------------------------------------------------------------------------------------------
# TOML and overrides


def _to_bool(value: Any) -> bool:
    if isinstance(value, str) and value.lower() in ("true", "false"):
        return value.lower() == "true"
    if isinstance(value, bool):
        return value
    raise ValueError(value)


def _to_int(value: Any) -> int:
    if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
        raise ValueError(value)
    return int(value)


def _to_tuple(value: Any, like: tuple) -> tuple:
    items = value.split(",") if isinstance(value, str) else list(value)
    if like and isinstance(like[0], float):
        return tuple(float(v) for v in items)
    return tuple(str(v).strip() for v in items if str(v).strip())


POINT_LISTS = ("scene.ccrs",)  # fields holding lists of points: TOML arrays of arrays, or "[[x, y, z], ...]"


def _to_points(name: str, value: Any) -> tuple:
    """A list of points from TOML (arrays of numbers) or the command line (the same, as text)."""
    import json

    try:
        items = json.loads(value) if isinstance(value, str) else value
        return tuple(tuple(float(v) for v in point) if isinstance(point, (list, tuple)) else (point,)
                     for point in items)
    except (TypeError, ValueError):
        raise InputError(name, value, "a list of points such as [[0, 0, 1], [5, 0, 1]]") from None


def _coerce(name: str, current: Any, value: Any) -> Any:
    """Convert a TOML or command-line value to the type of the field it replaces."""
    if canonical_key(name) in POINT_LISTS:
        return _to_points(name, value)
    convert = {bool: _to_bool, int: _to_int, float: float, str: str}.get(type(current))
    try:
        return _to_tuple(value, current) if isinstance(current, tuple) else convert(value)
    except (TypeError, ValueError):
        raise InputError(name, value, f"a value of type {type(current).__name__}") from None


ALIASES = {"prism": "sensor"}  # section names users may say instead ("prism.refractive_index")


def canonical_key(dotted: str) -> str:
    """``section.field`` with a section alias replaced by the real section name."""
    section_name, sep, name = dotted.partition(".")
    return ALIASES.get(section_name, section_name) + sep + name


def get_value(cfg: RunConfig, dotted: str) -> Any:
    """The value of ``section.field`` (aliases allowed)."""
    section_name, _, name = canonical_key(dotted).partition(".")
    return getattr(getattr(cfg, section_name), name)


def set_value(cfg: RunConfig, dotted: str, value: Any) -> None:
    """Set ``section.field`` from a string or TOML value, converting to the field's type."""
    section_name, _, name = canonical_key(dotted).partition(".")
    section = getattr(cfg, section_name, None)
    if section is None or not dataclasses.is_dataclass(section) or name not in {f.name for f in dataclasses.fields(section)}:
        known = ", ".join(f"{s.name}.<field>" for s in dataclasses.fields(cfg))
        raise InputError(dotted, value, f"a known setting ({known}; see `flightsim simulate --help`)")
    setattr(section, name, _coerce(dotted, getattr(section, name), value))


def from_dict(data: dict, base: RunConfig | None = None) -> RunConfig:
    """Build a config from nested tables (as read from TOML) over ``base`` (default: the defaults);
    unknown keys are errors."""
    cfg = copy_config(base) if base is not None else RunConfig()
    for section_name, table in data.items():
        if not isinstance(table, dict):
            raise InputError(section_name, table, "a table of settings")
        for key, value in table.items():
            set_value(cfg, f"{section_name}.{key}", value)
    return cfg


def load_toml(path: str | Path, base: RunConfig | None = None) -> RunConfig:
    """Read a run config from a TOML file over ``base`` (unvalidated; call :func:`validate`)."""
    try:
        with open(path, "rb") as fh:
            return from_dict(tomllib.load(fh), base)
    except OSError as exc:
        raise InputError("--config", str(path), f"a readable TOML file ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError("--config", str(path), f"valid TOML ({exc})") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


PART_SECTIONS = {"channels": ("emitter", "channels"), "galvo": ("deflector", "galvo"),  # written when chosen
                 "fsm": ("deflector", "fsm"),
                 "photon": ("detector", "photon"), "waveform": ("detector", "waveform")}


def to_toml(cfg: RunConfig) -> str:
    """The config as TOML text; floats are written with full precision (``repr``). The sections of
    parts the instrument does not use are left out."""
    lines = []
    for section in dataclasses.fields(cfg):
        part = PART_SECTIONS.get(section.name)
        if part and getattr(cfg.instrument, part[0]) != part[1]:
            continue
        lines.append(f"[{section.name}]")
        for f in dataclasses.fields(getattr(cfg, section.name)):
            lines.append(f"{f.name} = {_toml_value(getattr(getattr(cfg, section.name), f.name))}")
        lines.append("")
    return "\n".join(lines)


def preset_config(name: str) -> RunConfig:
    """The config of a built-in instrument (``flightsim.instrument.presets``), unvalidated."""
    from flightsim.instrument.presets import PRESETS, preset_path

    if name not in PRESETS:
        raise InputError("--instrument", name, "one of " + ", ".join(PRESETS))
    path = preset_path(name)
    return load_toml(path) if path else RunConfig()
