"""The simulated world's non-image error sources, their profiles and their recorded draws.

What a robot believes differs from the truth the way it does on a real vehicle:

=============  ==========================================================================
source         what is drawn (σ per parameter; units in the field names)
=============  ==========================================================================
calibration    per camera: recorded K (fx, fy, cx, cy) and D (k1, k2, p1, p2) = true + δ;
               recorded extrinsic ``T_parent_cam``: rotation ``R_rec = Exp(δφ)·R_true``
               (δφ in the parent frame, left as in :mod:`agvviz.conventions`),
               translation ``t_rec = t_true + δt``. Truth and rendering use the true camera.
map            per marker: true pose = mapped pose moved by δ — position ``p_true = p_map +
               (δx, δy, δz)`` (parent frame), rotation ``R_true = R_map·Rz(yaw)·Rx(tilt_x)·
               Ry(tilt_y)`` (marker frame: yaw about the code's normal, tilts = not flat);
               printed side ``side_true = side_map·(1 + scale)``. The map (and a QR payload)
               carry the mapped values; rendering uses the true ones.
timing         per camera and frame: delay ``d = latency_s + jitter_sigma_s·n`` (ns): the
               image stamped t shows the world at t − d; dropped frames (probability).
bumps          floor unevenness: the AGV's true pitch θ and roll γ are smooth random fields
               of its floor position (correlation length in m), ``R_true = Rz(ψ)·Rx(θ)·Ry(γ)``.
slip           wheel slip: each odometry step's distance is scaled by ``1 + fraction + σ·n``.
imaging        image formation and print (:mod:`agvviz.sim.imaging`, :class:`ImagingErrors`):
               defocus, motion blur, rolling shutter, vignetting, illumination, shot and read
               noise, JPEG; ink spread, paper warp and texture, glare, dirt, occlusion. Each
               effect of :data:`IMAGING_EFFECTS` can be switched off on its own
               (``realism_off=imaging.defocus``); off means the ``ideal`` profile's value.
=============  ==========================================================================

Every source draws from its own generator :func:`source_rng` (seed, source name), and every
draw is a standard normal (or uniform) scaled by its σ afterwards, so switching one source or
one parameter off leaves every other draw unchanged — the exact counterfactual an error budget
needs. :class:`Draws` keeps what was drawn (JSON, :func:`metadata_values`: the scenario writes it as the
recording's ``agvviz.realism`` metadata record; :func:`agvviz.recording.mcap_stream.realism_draws`
reads it back). Numpy only: no files, no I/O.
Longer than 600 lines because the six error sources' parameters and their draws are one
vocabulary (each draw reads its source's parameters); scenarios and tests address both here.
"""

from __future__ import annotations

import dataclasses
import json
import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from agvviz.geometry import se3, so3
from agvviz.geometry.camera import PinholeCamera
from agvviz.geometry.euler import Rx, Ry, Rz
from agvviz.sim import imaging as im
from agvviz.sim.render import FloorCode  # "agvviz.realism", key "draws"

#: Error sources, each switchable on its own (``realism_off``) and each with its own generator
#: (``imaging``: the per-effect streams of :func:`agvviz.sim.imaging.source_rngs`).
SOURCES = ("calibration", "map", "timing", "bumps", "slip", "imaging")
#: Image-formation effects switchable on their own (``realism_off=imaging.<effect>``): the
#: :class:`~agvviz.sim.imaging.ImagingErrors` fields each resets to the ``ideal`` profile's value.
IMAGING_EFFECTS = {
    "ink_spread": ("ink_spread_modules",),
    "paper_warp": ("paper_warp_m",),
    "paper_texture": ("paper_texture_sigma",),
    "glare": ("glare_peak_dn",),
    "dirt": ("dirt_spots_per_label",),
    "occlusion": ("occlusion_probability",),
    "motion_blur": ("exposure_s",),
    "rolling_shutter": ("line_delay_s",),
    "pixel_aperture": ("pixel_aperture",),
    "illumination": ("illumination_sigma",),
    "vignetting": ("vignetting_strength",),
    "defocus": ("defocus_radius_px",),
    "lens_blur": ("blur_sigma_px",),
    "shot_noise": ("shot_gain_e_per_dn",),
    "read_noise": ("read_noise_dn",),
    "jpeg": ("jpeg_quality",),
}
#: Components of the random-Fourier-feature field of a bump angle.
BUMP_COMPONENTS = 64


@dataclass(frozen=True)
class CalibrationErrors:
    """σ of the recorded calibration's error, per camera (recorded − true)."""

    fx_sigma_px: float = 0.0
    fy_sigma_px: float = 0.0
    cx_sigma_px: float = 0.0
    cy_sigma_px: float = 0.0
    k1_sigma: float = 0.0
    k2_sigma: float = 0.0
    p1_sigma: float = 0.0
    p2_sigma: float = 0.0
    extrinsic_rotation_sigma_deg: float = 0.0  # per axis
    extrinsic_translation_sigma_m: float = 0.0  # per axis


@dataclass(frozen=True)
class MapErrors:
    """σ of each marker's placement and print (true − mapped)."""

    position_sigma_m: float = 0.0  # x and y each
    height_sigma_m: float = 0.0  # z
    yaw_sigma_deg: float = 0.0  # about the code's normal
    tilt_sigma_deg: float = 0.0  # about the code's x and y axes each: not flat
    print_scale_sigma: float = 0.0  # fraction of the side


@dataclass(frozen=True)
class TimingErrors:
    """Camera-to-truth timing: constant latency, per-frame jitter, dropped frames."""

    latency_s: float = 0.0
    jitter_sigma_s: float = 0.0
    drop_probability: float = 0.0


@dataclass(frozen=True)
class BumpErrors:
    """Floor bumps: σ of the AGV's pitch and roll, correlation length along the floor."""

    pitch_sigma_deg: float = 0.0
    roll_sigma_deg: float = 0.0
    correlation_m: float = 0.5


@dataclass(frozen=True)
class SlipErrors:
    """Wheel slip in the odometry: per-step distance error, mean and σ (fractions)."""

    fraction: float = 0.0
    sigma: float = 0.0


@dataclass(frozen=True)
class Realism:
    """One profile: every source's parameters."""

    name: str = "ideal"
    calibration: CalibrationErrors = field(default_factory=CalibrationErrors)
    map: MapErrors = field(default_factory=MapErrors)
    timing: TimingErrors = field(default_factory=TimingErrors)
    bumps: BumpErrors = field(default_factory=BumpErrors)
    slip: SlipErrors = field(default_factory=SlipErrors)
    #: ``ideal``: :data:`agvviz.sim.imaging.IDEAL_IMAGING` — Gaussian blur 0.8 px, read noise
    #: 2 DN, ``jpeg_quality`` 0 = the scenario's own ``jpeg_quality`` option (see
    #: :func:`scenario_imaging` for how a scenario's ``blur_sigma_px``/``noise_sigma_dn``/
    #: ``jpeg_quality`` options combine with the profile).
    imaging: im.ImagingErrors = im.IDEAL_IMAGING

    @property
    def is_ideal(self) -> bool:
        """No source draws anything (then scenarios write no ``agvviz.realism`` record)."""
        return self.parameters() == PROFILES["ideal"].parameters()

    def parameters(self) -> dict:
        """``{source: {parameter: value}}``, plain data."""
        return {source: dataclasses.asdict(getattr(self, source)) for source in SOURCES}


#: ``typical``: a carefully calibrated and surveyed AGV (see the report of issue 14 for the
#: figures it gives); ``harsh``: a hastily set-up one, ≈4–6× ``typical``.
PROFILES: dict[str, Realism] = {
    "ideal": Realism("ideal"),
    "typical": Realism(
        "typical",
        CalibrationErrors(
            # fx, fy: a good target calibration (sub-0.1 % focal length) at 1280×1024.
            fx_sigma_px=0.1, fy_sigma_px=0.1,
            # cx, cy: principal point of a many-view calibration, a tenth of a pixel.
            cx_sigma_px=0.1, cy_sigma_px=0.1,
            # Distortion: residual of a well-fitted plumb_bob model (≈0.1 px at the corners).
            k1_sigma=0.00025, k2_sigma=0.0001, p1_sigma=0.00003, p2_sigma=0.00003,
            # Extrinsic rotation: surveyed/hand-eye mount, 0.02°/axis = 0.35 mm per m of range.
            extrinsic_rotation_sigma_deg=0.02,
            # Extrinsic translation: camera centre measured to 0.1 mm per axis.
            extrinsic_translation_sigma_m=0.0001,
        ),
        # Map: codes surveyed to 0.1 mm, yaw and tilt of a flat-laid label, print scale 0.015 %.
        MapErrors(position_sigma_m=0.0001, height_sigma_m=0.0001, yaw_sigma_deg=0.007,
                  tilt_sigma_deg=0.015, print_scale_sigma=0.00015),
        # Timing: hardware-triggered global-shutter camera with PTP-synced stamps (0.1 ms).
        TimingErrors(latency_s=0.0001, jitter_sigma_s=0.0001, drop_probability=0.01),
        # Bumps: an ordinary industrial floor (a mm or two over the wheelbase): 0.25° pitch/roll.
        BumpErrors(pitch_sigma_deg=0.25, roll_sigma_deg=0.25, correlation_m=0.3),
        # Slip: unchanged (odometry only; neither target uses it): 0.2 % mean, 0.5 % per step.
        SlipErrors(fraction=0.002, sigma=0.005),
        # The photo-calibrated camera and print with whole-pixel apertures: TYPICAL_IMAGING's
        # 0.25 stands for the phone photos' decimation to 640×480; an AGV camera read out at
        # its native resolution integrates over (nearly) the whole pixel. And a global shutter:
        # an industrial AGV camera (paper 000: ±2 mm at 0.5–2.5 m/s, impossible with a 15 ms
        # rolling read-out — at 1 m/s it alone costs ≈8 mm RMSE in default qr_floor).
        dataclasses.replace(im.TYPICAL_IMAGING, pixel_aperture=1.0, line_delay_s=0.0),
    ),
    "harsh": Realism(
        "harsh",
        CalibrationErrors(
            fx_sigma_px=3.0, fy_sigma_px=3.0, cx_sigma_px=4.0, cy_sigma_px=4.0,
            k1_sigma=0.005, k2_sigma=0.002, p1_sigma=0.0005, p2_sigma=0.0005,
            extrinsic_rotation_sigma_deg=0.15, extrinsic_translation_sigma_m=0.002,
        ),
        MapErrors(position_sigma_m=0.002, height_sigma_m=0.001, yaw_sigma_deg=0.2,
                  tilt_sigma_deg=0.3, print_scale_sigma=0.003),
        TimingErrors(latency_s=0.003, jitter_sigma_s=0.001, drop_probability=0.05),
        BumpErrors(pitch_sigma_deg=0.5, roll_sigma_deg=0.5, correlation_m=0.2),
        SlipErrors(fraction=0.01, sigma=0.02),
        dataclasses.replace(im.HARSH_IMAGING, pixel_aperture=1.0),  # native read-out, as typical
    ),
}
PROFILE_NAMES = tuple(PROFILES)

#: Help lines of the three scenario options every scenario declares (``realism``,
#: ``realism_off``, ``realism_set``), passed to :func:`make_realism`.
HELP_PROFILE = "error sources' profile (agvviz/sim/realism.py): ideal, typical or harsh"
HELP_OFF = ("error sources switched off, comma-separated: calibration,map,timing,bumps,slip,imaging "
            "or one imaging effect, e.g. imaging.defocus (names in agvviz/sim/realism.py IMAGING_EFFECTS)")
HELP_SET = ("profile parameters overridden, comma-separated, e.g. "
            "calibration.fx_sigma_px=0.5,timing.latency_s=0.002,imaging.defocus_radius_px=1 "
            "(names in agvviz/sim/realism.py and agvviz/sim/imaging.py ImagingErrors)")

_CLASSES = {
    "calibration": CalibrationErrors, "map": MapErrors, "timing": TimingErrors,
    "bumps": BumpErrors, "slip": SlipErrors, "imaging": im.ImagingErrors,
}
#: Allowed range of each parameter (inclusive unless noted in :func:`_check`).
_BOUNDS = {
    "timing.latency_s": (-1.0, 1.0),
    "timing.drop_probability": (0.0, 0.99),
    "bumps.correlation_m": (1e-3, 1e3),
    "slip.fraction": (-0.5, 0.5),
}
_SIGMA_MAX = {"_px": 100.0, "_deg": 10.0, "_m": 1.0, "_s": 1.0}


def parameter_names() -> tuple[str, ...]:
    """Every ``source.parameter`` name :func:`make_realism` accepts in ``overrides``."""
    return tuple(f"{s}.{f.name}" for s in SOURCES for f in dataclasses.fields(_CLASSES[s]))


def _check(name: str, value: float) -> None:
    if name.startswith("imaging."):  # the imaging module's own ranges, one field at a time
        field_name = name.split(".", 1)[1]
        if field_name == "jpeg_quality" and value != int(value):
            raise ValueError(f"realism parameter {name} must be an integer 0..100 (0: the scenario's jpeg_quality), got {value:g}")
        try:
            im.check_imaging_errors(dataclasses.replace(im.ImagingErrors(), **{field_name: value}))
        except ValueError as exc:
            raise ValueError(f"realism parameter {name}: {exc}") from None
        return
    if not math.isfinite(value):
        raise ValueError(f"realism parameter {name} must be a finite number, got {value}")
    lo, hi = _BOUNDS.get(name, (0.0, next((v for k, v in _SIGMA_MAX.items() if name.endswith(k)), 0.5)))
    if not lo <= value <= hi:
        raise ValueError(f"realism parameter {name} must lie in {lo:g}..{hi:g}, got {value:g}")


def make_realism(profile: str, off: str = "", overrides: str = "") -> Realism:
    """The profile ``profile`` with the sources in ``off`` (comma-separated names of
    :data:`SOURCES`, or ``imaging.<effect>`` of :data:`IMAGING_EFFECTS`) switched off — set to
    the ``ideal`` profile's values — and ``overrides`` applied (``"calibration.fx_sigma_px=0.5,
    timing.latency_s=0.002,imaging.defocus_radius_px=1"``; names from :func:`parameter_names`).
    ``off`` wins over ``overrides``.

    Raises ``ValueError`` with a one-line message for an unknown profile, source or parameter
    and for a value out of its range.
    """
    if profile not in PROFILES:
        raise ValueError(f"realism={profile!r} is not one of: {', '.join(PROFILE_NAMES)}")
    realism = PROFILES[profile]
    groups = {s: dataclasses.asdict(getattr(realism, s)) for s in SOURCES}
    for item in (p.strip() for p in overrides.split(",") if p.strip()):
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in parameter_names():
            raise ValueError(
                f"realism_set: {item!r} is not name=value with a name among: {', '.join(parameter_names())}"
            )
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"realism_set: {key}={text!r} is not a number") from None
        _check(key, value)
        source, name = key.split(".")
        groups[source][name] = int(value) if name == "jpeg_quality" else value
    ideal = PROFILES["ideal"]
    for source in (s.strip() for s in off.split(",") if s.strip()):
        group, _, effect = source.partition(".")
        if group == "imaging" and effect in IMAGING_EFFECTS:
            for name in IMAGING_EFFECTS[effect]:
                groups["imaging"][name] = getattr(ideal.imaging, name)
        elif source not in SOURCES:
            raise ValueError(
                f"realism_off: {source!r} is not one of: {', '.join(SOURCES)}, "
                f"{', '.join('imaging.' + e for e in IMAGING_EFFECTS)}"
            )
        else:
            groups[source] = dataclasses.asdict(getattr(ideal, source))
    name = profile if (not off.strip() and not overrides.strip()) else f"{profile}*"
    return Realism(name, **{s: _CLASSES[s](**groups[s]) for s in SOURCES})


def check_timing(timing: TimingErrors, frame_period_s: float) -> None:
    """``ValueError`` unless |latency_s| + 5·jitter_sigma_s < half a frame period (a frame's
    capture time must stay between its neighbours' stamps)."""
    reach_s = abs(timing.latency_s) + 5.0 * timing.jitter_sigma_s
    if reach_s >= frame_period_s / 2.0:
        raise ValueError(
            f"realism timing: |latency_s| + 5·jitter_sigma_s = {reach_s:g} s must be < half the frame "
            f"period ({frame_period_s / 2.0:g} s); lower them or the frame rate"
        )


# -- imaging ------------------------------------------------------------------------------------
#: Scenario options that set an imaging parameter (option → :class:`ImagingErrors` field).
IMAGING_OPTIONS = {"blur_sigma_px": "blur_sigma_px", "noise_sigma_dn": "read_noise_dn", "jpeg_quality": "jpeg_quality"}
#: Key of :func:`agvviz.sim.imaging.source_rngs` of the print (then the code index) and of the
#: frames (then the frame index, and the camera index where a scenario has several cameras).
PRINT_KEY, FRAME_KEY = 0, 1


def scenario_imaging(realism: Realism, options) -> tuple[im.ImagingErrors, int]:
    """The image-formation errors a scenario renders with (``jpeg_quality`` 0: the scenario
    encodes the frame itself) and the JPEG quality it encodes at.

    The profile's :attr:`Realism.imaging`, except that a scenario option of
    :data:`IMAGING_OPTIONS` set to other than its default overrides it (so under ``ideal`` —
    whose blur 0.8 px and read noise 2 DN are those options' defaults — they keep their meaning
    exactly); a profile ``jpeg_quality`` of 0 stands for the option's value.
    """
    defaults = type(options)()
    values = {
        name: getattr(options, option)
        for option, name in IMAGING_OPTIONS.items()
        if hasattr(options, option) and getattr(options, option) != getattr(defaults, option)
    }
    errors = dataclasses.replace(realism.imaging, **values)
    quality = int(errors.jpeg_quality or options.jpeg_quality)
    return dataclasses.replace(errors, jpeg_quality=0), quality


def exposure_start_s(errors: im.ImagingErrors, height_px: int, t_capture_s: float) -> float:
    """When row 0 starts its exposure in a frame captured at ``t_capture_s`` (its stamp minus
    the timing delay): the capture instant is the middle of the middle row's exposure — what a
    driver stamping the frame's centre reports, and where the truth is recorded — so neither
    exposure nor rolling shutter adds a latency, only blur and skew. ``t_capture_s`` itself
    without exposure and line delay."""
    if errors.exposure_s == 0 and errors.line_delay_s == 0:
        return t_capture_s
    return t_capture_s - 0.5 * (height_px - 1) * errors.line_delay_s - 0.5 * errors.exposure_s


def imaging_record(errors: im.ImagingErrors, jpeg_quality: int, time_samples: int, rows_per_band: int) -> dict:
    """The ``imaging`` entry of :class:`Draws`: the parameters rendered with and where every
    draw comes from (the draws themselves are images: they are re-drawn from the streams)."""
    return {
        "errors": {**dataclasses.asdict(errors), "jpeg_quality": int(jpeg_quality)},
        "time_samples": int(time_samples), "rows_per_band": int(rows_per_band),
        "streams": (f"print: imaging.source_rngs(seed, {PRINT_KEY}, code index); frame k: "
                    f"imaging.source_rngs(seed, {FRAME_KEY}, k[, camera index]) but read_noise: the scenario's generator"),
        "capture_instant": "middle of the middle row's exposure",
    }


def source_rng(seed: int, source: str) -> np.random.Generator:
    """The generator of one error source: ``default_rng([seed mod 2⁶⁴, crc32(source)])`` —
    independent of every other source's and of the scenario's own ``default_rng(seed)``."""
    return np.random.default_rng([int(seed) % 2**64, zlib.crc32(source.encode())])


# -- calibration ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraDraw:
    """One camera's true and recorded calibration and extrinsic ``T_parent_cam``."""

    true_camera: PinholeCamera
    recorded_camera: PinholeCamera
    T_parent_cam_true: np.ndarray
    T_parent_cam_recorded: np.ndarray
    delta: dict  # fx_px … p2, rotation_deg (3,), translation_m (3,)

    def to_json(self) -> dict:
        def cam(c: PinholeCamera) -> dict:
            return {"K": c.K.tolist(), "D": c.dist.tolist(), "width_px": c.width_px, "height_px": c.height_px}

        return {
            "true": {**cam(self.true_camera), "T_parent_cam": self.T_parent_cam_true.tolist()},
            "recorded": {**cam(self.recorded_camera), "T_parent_cam": self.T_parent_cam_recorded.tolist()},
            "delta": self.delta,
        }


def draw_calibration(
    errors: CalibrationErrors, rng: np.random.Generator, cameras: Mapping[str, tuple[PinholeCamera, np.ndarray]]
) -> dict[str, CameraDraw]:
    """Recorded calibrations of ``cameras`` (name → (true camera, true ``T_parent_cam``)),
    in the mapping's order; 14 standard normals per camera (module docstring)."""
    out = {}
    e = errors
    for name, (camera, T_true) in cameras.items():
        z = rng.standard_normal(14)
        d_fx, d_fy, d_cx, d_cy = z[:4] * [e.fx_sigma_px, e.fy_sigma_px, e.cx_sigma_px, e.cy_sigma_px]
        d_dist = z[4:8] * [e.k1_sigma, e.k2_sigma, e.p1_sigma, e.p2_sigma]
        d_rot_deg = z[8:11] * e.extrinsic_rotation_sigma_deg
        d_t_m = z[11:14] * e.extrinsic_translation_sigma_m
        K = camera.K.copy()
        K[0, 0] += d_fx
        K[1, 1] += d_fy
        K[0, 2] += d_cx
        K[1, 2] += d_cy
        dist = camera.dist.copy()
        dist[:4] += d_dist
        recorded = PinholeCamera(K, dist, camera.width_px, camera.height_px)
        T_true = np.asarray(T_true, dtype=float)
        T_rec = T_true.copy()  # untouched where nothing was drawn (keeps −0.0 entries bit-exact)
        if np.any(d_rot_deg != 0.0):
            T_rec[:3, :3] = so3.exp(np.radians(d_rot_deg)) @ T_true[:3, :3]
        if np.any(d_t_m != 0.0):
            T_rec[:3, 3] = T_true[:3, 3] + d_t_m
        delta = {
            "fx_px": float(d_fx), "fy_px": float(d_fy), "cx_px": float(d_cx), "cy_px": float(d_cy),
            "k1": float(d_dist[0]), "k2": float(d_dist[1]), "p1": float(d_dist[2]), "p2": float(d_dist[3]),
            "rotation_deg": d_rot_deg.tolist(), "translation_m": d_t_m.tolist(),
        }
        out[name] = CameraDraw(camera, recorded, T_true, T_rec, delta)
    return out


# -- marker map ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class MarkerDraw:
    """One marker's mapped and true pose (in its parent frame) and printed side."""

    marker_id: str
    T_parent_marker_mapped: np.ndarray
    T_parent_marker_true: np.ndarray
    side_mapped_m: float
    side_true_m: float
    delta: dict  # position_m (3,), yaw_deg, tilt_x_deg, tilt_y_deg, scale

    def to_json(self) -> dict:
        return {
            "id": self.marker_id,
            "mapped": {"T_parent_marker": self.T_parent_marker_mapped.tolist(), "side_m": self.side_mapped_m},
            "true": {"T_parent_marker": self.T_parent_marker_true.tolist(), "side_m": self.side_true_m},
            "delta": self.delta,
        }


def draw_map(
    errors: MapErrors, rng: np.random.Generator, markers: Sequence[tuple[str, np.ndarray, float]]
) -> list[MarkerDraw]:
    """True placement of ``markers`` ((id, mapped ``T_parent_marker``, mapped side) each), in
    order; 7 standard normals per marker (module docstring)."""
    e = errors
    out = []
    for marker_id, T_map, side_m in markers:
        z = rng.standard_normal(7)
        d_p = z[:3] * [e.position_sigma_m, e.position_sigma_m, e.height_sigma_m]
        yaw, tilt_x, tilt_y = np.radians(z[3:6] * [e.yaw_sigma_deg, e.tilt_sigma_deg, e.tilt_sigma_deg])
        scale = float(z[6] * e.print_scale_sigma)
        T_map = np.asarray(T_map, dtype=float)
        T_true = T_map.copy()  # untouched where nothing was drawn (keeps −0.0 entries bit-exact)
        if yaw != 0.0 or tilt_x != 0.0 or tilt_y != 0.0:
            T_true[:3, :3] = T_map[:3, :3] @ Rz(yaw) @ Rx(tilt_x) @ Ry(tilt_y)
        if np.any(d_p != 0.0):
            T_true[:3, 3] = T_map[:3, 3] + d_p
        delta = {
            "position_m": d_p.tolist(), "yaw_deg": math.degrees(yaw), "tilt_x_deg": math.degrees(tilt_x),
            "tilt_y_deg": math.degrees(tilt_y), "scale": scale,
        }
        out.append(MarkerDraw(str(marker_id), T_map, T_true, float(side_m), float(side_m) * (1.0 + scale), delta))
    return out


def placed_as_drawn(code: FloorCode, draw: MarkerDraw, T_world_parent: np.ndarray | None = None) -> FloorCode:
    """``code`` (a mapped :class:`FloorCode`, payload unchanged) at its true pose and printed
    size; ``T_world_parent`` places a marker whose parent frame is not the world (None:
    the world). The code itself when nothing moved."""
    T_world_marker = draw.T_parent_marker_true if T_world_parent is None else T_world_parent @ draw.T_parent_marker_true
    scale = draw.side_true_m / draw.side_mapped_m
    if scale == 1.0 and np.array_equal(T_world_marker, code.T_world_marker):
        return code
    return dataclasses.replace(
        code, T_world_marker=T_world_marker, side_m=code.side_m * scale, points_marker_m=code.points_marker_m * scale
    )


# -- timing -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraTiming:
    """Per frame of one camera: delay (ns, image stamp − capture time) and drop flag."""

    delay_ns: np.ndarray  # (N,) int64
    dropped: np.ndarray  # (N,) bool

    def to_json(self) -> dict:
        return {"delay_ns": self.delay_ns.tolist(), "dropped": self.dropped.tolist()}


def draw_timing(
    errors: TimingErrors, rng: np.random.Generator, n_frames: int, cam_names: Sequence[str]
) -> dict[str, CameraTiming]:
    """Delays and drops of ``n_frames`` frames per camera, cameras in order; per camera
    ``n_frames`` standard normals then ``n_frames`` uniforms."""
    e = errors
    out = {}
    for name in cam_names:
        z = rng.standard_normal(n_frames)
        u = rng.random(n_frames)
        delay_ns = np.round((e.latency_s + e.jitter_sigma_s * z) * 1e9).astype(np.int64)
        out[name] = CameraTiming(delay_ns, u < e.drop_probability)
    return out


# -- vehicle: bumps and slip ----------------------------------------------------------------------
@dataclass(frozen=True)
class BumpField:
    """Pitch and roll of the AGV as smooth random fields of its floor position: each
    ``σ·√(2/M)·Σ cos(ω_i·p + φ_i)`` with ω_i ~ N(0, I/ℓ²) (random Fourier features of a
    Gaussian covariance σ²·exp(−|Δp|²/(2ℓ²)))."""

    pitch_sigma_rad: float
    roll_sigma_rad: float
    wavevectors_per_m: np.ndarray  # (2, M, 2): pitch, roll
    phases_rad: np.ndarray  # (2, M)

    @property
    def is_flat(self) -> bool:
        return self.pitch_sigma_rad == 0.0 and self.roll_sigma_rad == 0.0

    def angles_rad(self, xy_m) -> tuple[float, float]:
        """(pitch θ, roll γ) at floor position ``xy_m`` (2,)."""
        p = np.asarray(xy_m, dtype=float)[:2]
        m = self.phases_rad.shape[1]
        waves = np.cos(self.wavevectors_per_m @ p + self.phases_rad).sum(axis=1) * math.sqrt(2.0 / m)
        return float(self.pitch_sigma_rad * waves[0]), float(self.roll_sigma_rad * waves[1])

    def apply(self, T_world_agv_flat: np.ndarray) -> tuple[np.ndarray, float, float]:
        """The bumped pose ``[Rz(ψ)·Rx(θ)·Ry(γ), t]`` of a flat pose ``[Rz(ψ), t]``, θ and γ
        at its position; the flat pose itself (the same array) when the floor is flat."""
        if self.is_flat:
            return T_world_agv_flat, 0.0, 0.0
        pitch, roll = self.angles_rad(T_world_agv_flat[:2, 3])
        R = T_world_agv_flat[:3, :3] @ Rx(pitch) @ Ry(roll)
        return se3.make(R, T_world_agv_flat[:3, 3]), pitch, roll

    def to_json(self) -> dict:
        return {
            "pitch_sigma_rad": self.pitch_sigma_rad, "roll_sigma_rad": self.roll_sigma_rad,
            "wavevectors_per_m": self.wavevectors_per_m.tolist(), "phases_rad": self.phases_rad.tolist(),
        }


def draw_bumps(errors: BumpErrors, rng: np.random.Generator) -> BumpField:
    """The bump field; 2·M·2 standard normals, then 2·M uniforms."""
    m = BUMP_COMPONENTS
    waves = rng.standard_normal((2, m, 2)) / errors.correlation_m
    phases = rng.uniform(0.0, 2.0 * np.pi, (2, m))
    return BumpField(math.radians(errors.pitch_sigma_deg), math.radians(errors.roll_sigma_deg), waves, phases)


def draw_slip(errors: SlipErrors, rng: np.random.Generator, n_steps: int) -> np.ndarray:
    """Slip fraction (n_steps,) of each odometry step: ``fraction + sigma·n``."""
    return errors.fraction + errors.sigma * rng.standard_normal(n_steps)


# -- the record -----------------------------------------------------------------------------------
@dataclass
class Draws:
    """What every source drew in one recording, as plain JSON-ready data.

    ``sources`` maps a source name to its draws (``None`` where the scenario has no use for
    it): ``calibration`` {camera: :meth:`CameraDraw.to_json`}, ``map`` [:meth:`MarkerDraw.to_json`],
    ``timing`` {"stamp_ns": [...], "cameras": {camera: :meth:`CameraTiming.to_json`}},
    ``bumps`` {"field": …, "capture_ns": [...], "pitch_deg": {camera: [...]}, "roll_deg": …}
    or per-frame lists, ``slip`` {"fraction": [...]} per odometry step; ``inject`` (only when the
    scenario option ``inject`` is set) [:meth:`agvviz.sim.inject.InjectSpec.to_json`]: each
    injected fault with the frames it affects.
    """

    profile: str
    seed: int
    parameters: dict
    sources: dict = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(
            {"profile": self.profile, "seed": self.seed, "parameters": self.parameters, "sources": self.sources},
            allow_nan=False, separators=(",", ":"), default=_plain,
        )


def _plain(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def new_draws(realism: Realism, seed: int) -> Draws:
    return Draws(profile=realism.name, seed=int(seed), parameters=realism.parameters(),
                 sources={s: None for s in SOURCES})


def metadata_values(draws: Draws) -> dict[str, str]:
    """The ``agvviz.realism`` MCAP metadata record's values."""
    return {"draws": draws.to_json()}
