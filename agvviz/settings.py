"""Run settings and ``--set key=value`` parsing, shared by scenarios and runs.

Every settings object is a frozen dataclass whose fields carry a type, a default and a
``metadata={"help": ...}`` line (and optionally ``"choices"``, and for numbers the inclusive
bounds ``"min"`` / ``"max"``). :func:`apply_overrides` turns ``["key=value", ...]`` into a new
instance with clear errors for unknown keys and bad values; :func:`validate` checks types,
finiteness, choices and bounds before any work is done (an absurd ``duration_s=1e9`` must
fail at once, not after allocating), and :func:`check_total` caps the work an option
combination asks for (frames = duration × rate, pixels per frame, …).
"""

from __future__ import annotations

from agvviz.errors import InputError

import dataclasses
import math
import re
import typing
from dataclasses import dataclass, field

from agvviz.conventions import DEFAULT_GIMBAL_THRESHOLD
from agvviz.fusion.common import FUSION_NAMES
from agvviz.solvers.multi_camera import CAMERA_SELECT
from agvviz.solvers.ambiguity import POLICIES as AMBIGUITY_POLICIES
from agvviz.solvers.registry import SOLVER_NAMES
from agvviz.solvers.uncertainty import SystematicSigmas
from agvviz.uwb.localize import METHODS as UWB_METHODS


class SettingsError(InputError):
    """A ``--set key=value`` that names no setting or carries a value of the wrong kind."""


#: Caps on the total work of one recording (checked by the scenarios with :func:`check_total`
#: once every option lies within its own bounds): frames per camera (an hour at 10 Hz), area
#: samples of one rendered image (width × height × supersample², float32: 256 MB per array),
#: and UWB ranging rounds.
MAX_FRAMES = 36_000
MAX_IMAGE_SAMPLES = 2**26
MAX_UWB_ROUNDS = 1_000_000

#: Bounds of a numeric ``sigma_px`` (the field is a string because it may be ``auto``).
SIGMA_PX_MIN = 1e-4
SIGMA_PX_MAX = 100.0


def setting(
    default,
    help: str,
    choices: tuple[str, ...] | None = None,
    *,
    min: float | None = None,  # noqa: A002 - the metadata keys are "min" and "max"
    max: float | None = None,  # noqa: A002
):
    """A settings or scenario-options field: default, one-line help, optional choices, and for
    numbers optional inclusive bounds ``min ≤ value ≤ max`` (checked by :func:`validate`,
    shown by :func:`describe`)."""
    meta = {"help": help}
    if choices is not None:
        meta["choices"] = choices
    if min is not None:
        meta["min"] = min
    if max is not None:
        meta["max"] = max
    if min is not None and max is not None and not min <= max:
        raise ValueError(f"setting bounds {min}..{max} are empty")
    return field(default=default, metadata=meta)


def _fmt(value) -> str:
    """A number as short as it reads back exactly: 3600, 0.1, 1e+09, 0.30000000000000004."""
    if isinstance(value, float):
        short = f"{value:g}"
        return short if float(short) == value else repr(value)
    return str(value)


def bounds_text(f: dataclasses.Field) -> str:
    """``"0.1..3600"``, ``"≥ 0"``, ``"≤ 5"`` or ``""`` for a field's bounds metadata."""
    lo, hi = f.metadata.get("min"), f.metadata.get("max")
    if lo is not None and hi is not None:
        return f"{_fmt(lo)}..{_fmt(hi)}"
    if lo is not None:
        return f"≥ {_fmt(lo)}"
    if hi is not None:
        return f"≤ {_fmt(hi)}"
    return ""


def check_total(what: str, value: float, limit: float, hint: str) -> None:
    """Refuse an option combination whose total work ``value`` (e.g. frames = duration_s ×
    rate_hz) exceeds ``limit``: ``SettingsError("frames = duration_s × rate_hz = 1e+10
    exceeds the limit 20000; …")``. Call it from a scenario's ``validate`` after
    :func:`validate` has bounded every factor."""
    if not value <= limit:  # also refuses NaN
        raise SettingsError(f"{what} = {_fmt(value)} exceeds the limit {_fmt(limit)}; {hint}")




@dataclass(frozen=True)
class RunSettings:
    """Settings of one replay (``agvviz run --set key=value``)."""

    solver: str = setting("lm", "pose solver", SOLVER_NAMES)
    objective: str = setting(
        "pixel",
        "LM objective: pixel = paper 000 eq 22 (maximum likelihood for pixel noise), "
        "depth = eq 23 (the paper's depth-weighted residual)",
        ("pixel", "depth"),
    )
    lm_max_iterations: int = setting(50, "maximum LM iterations per frame", min=1, max=1000)
    refine: str = setting(
        "ecc",
        "corner refinement: ecc (template alignment; best on real photos, docs/refinement.md), subpix "
        "(cornerSubPix), contour (OpenCV's CORNER_REFINE_CONTOUR: ArUco only), apriltag (the AprilTag "
        "edge refinement: the library's own on AprilTags, OpenCV's on ArUco; not QR), none",
        ("ecc", "subpix", "contour", "apriltag", "none"),
    )
    markers: str = setting(
        "all",
        "markers per camera frame: all (one LM over the corners of every marker in view, markers "
        "that fail a chi-square test against the others left out) or largest (paper 000: the "
        "largest code only)",
        ("all", "largest"),
    )
    marker_outlier_p: float = setting(
        1e-3,
        "markers=all: probability that a consistent marker fails the chi-square test and is left out",
        min=1e-12, max=0.5,
    )
    corner_bias_px: float = setting(
        0.3,
        "each marker's systematic corner error σ (px): added to the pixel noise in the joint "
        "solve's chi-square test across markers, and a source of the pose covariance "
        "(covariance=full: the marker's outline seen grown or shrunk by this much, an apparent "
        "scale its pose's fit cannot see; docs/uncertainty.md) (0.3 px measured on real photos: "
        "docs/joint-solve.md)",
        min=0.0, max=100.0,
    )
    covariance: str = setting(
        "full",
        "pose covariance: full (pixel noise + corner bias + calibration + extrinsic + map, the cov_* "
        "settings; docs/uncertainty.md) or pixel (pixel noise only, as before issue 25)",
        ("full", "pixel"),
    )
    cov_qr_outline_px: float = setting(
        0.07,
        "covariance=full: a QR symbol's outline shift σ (px), in place of corner_bias_px for QR codes "
        "(no solid border: its ECC-refined outline moves less; measured on the typical world's "
        "renders: docs/uncertainty.md)",
        min=0.0, max=100.0,
    )
    # The cov_* defaults are the `typical` realism profile's σ's (agvviz.sim.realism.PROFILES
    # ["typical"]: a carefully calibrated and surveyed AGV); tests/test_uncertainty.py holds
    # them equal. A real log uses them unless told its calibration and survey are better/worse.
    cov_focal_px: float = setting(0.1, "covariance=full: σ of the focal lengths fx, fy each (px)", min=0.0, max=1e4)
    cov_principal_point_px: float = setting(
        0.1, "covariance=full: σ of the principal point cx, cy each (px)", min=0.0, max=1e4
    )
    cov_k1: float = setting(0.00025, "covariance=full: σ of the radial distortion k1", min=0.0, max=1.0)
    cov_k2: float = setting(0.0001, "covariance=full: σ of the radial distortion k2", min=0.0, max=1.0)
    cov_tangential: float = setting(
        0.00003, "covariance=full: σ of the tangential distortion p1, p2 each", min=0.0, max=1.0
    )
    cov_extrinsic_rotation_deg: float = setting(
        0.02, "covariance=full: σ of each camera extrinsic's rotation, per axis (deg)", min=0.0, max=90.0
    )
    cov_extrinsic_translation_m: float = setting(
        0.0001, "covariance=full: σ of each camera extrinsic's translation, per axis (m)", min=0.0, max=10.0
    )
    cov_map_position_m: float = setting(
        0.0001, "covariance=full: σ of each marker's mapped position along x and y each (m)", min=0.0, max=10.0
    )
    cov_map_height_m: float = setting(
        0.0001, "covariance=full: σ of each marker's mapped height z (m)", min=0.0, max=10.0
    )
    cov_map_yaw_deg: float = setting(
        0.007, "covariance=full: σ of each marker's mapped yaw about its normal (deg)", min=0.0, max=180.0
    )
    cov_map_tilt_deg: float = setting(
        0.015, "covariance=full: σ of each marker's tilt about its x and y axes each (deg)", min=0.0, max=90.0
    )
    cov_map_scale: float = setting(
        0.00015, "covariance=full: σ of each marker's printed scale (fraction of its side)", min=0.0, max=1.0
    )
    max_reproj_px: float = setting(
        2.0, "reject a frame whose RMS reprojection error exceeds this (px)", min=1e-3, max=1e4
    )
    gimbal_threshold: float = setting(
        DEFAULT_GIMBAL_THRESHOLD,
        "paper 000 eq 57 threshold T on |r32| for pitch = ±90°",
        min=0.5,
        max=1.0 - 1e-12,
    )
    truth_max_dt_s: float = setting(
        0.005, "largest time gap between a frame and the ground truth it is scored against (s)", min=0.0, max=10.0
    )
    truth_max_gap_s: float = setting(
        0.05,
        "ground truth and odometry are interpolated on SE(3) at each frame's stamp between two "
        "samples at most this far apart (s); beyond it (and beyond truth_max_dt_s of the nearest "
        "sample) a frame is not scored, and the run says how many",
        min=0.0, max=10.0,
    )
    body_frame: str = setting(
        "auto",
        "the robot's body frame: camera extrinsics are chained from it through /tf_static and /tf, "
        "truth and estimates are its pose; auto = agv for agvviz recordings, base_link for other "
        "files (agv when their transforms have no base_link)",
    )
    time_source: str = setting(
        "auto",
        "message time stamps: header (the message's own stamp), log (the file's log time) or auto "
        "(log for agvviz recordings, header for other files)",
        ("auto", "header", "log"),
    )
    camera_select: str = setting(
        "best",
        "several cameras at one time: best (largest marker, paper 003) or combine (joint LM)",
        CAMERA_SELECT,
    )
    floor_constraint: bool = setting(
        True,
        "world-fixed cameras watching a marker on the AGV: refine the AGV on the floor (x, y, heading)",
    )
    uwb: str = setting(
        "least_squares", "UWB fix: centroid (paper 003 eqs 3-6) or least_squares (Gauss-Newton)", UWB_METHODS
    )
    uwb_gate: str = setting(
        "residual", "UWB NLOS/outlier gate: residual (chi-square on range residuals) or none", ("residual", "none")
    )
    uwb_sigma_m: float = setting(
        0.05, "UWB range standard deviation for the gates and covariances (m)", min=1e-4, max=10.0
    )
    fusion: str = setting(
        "mean_compensation",
        "camera-UWB fusion: camera_only, mean_compensation (paper 003 eqs 13-16) or kalman",
        FUSION_NAMES,
    )
    kalman_gate_chi2: float = setting(
        9.0, "Kalman filter gate on a range's squared Mahalanobis distance", min=0.01, max=1e6
    )
    camera_sigma_m: float = setting(
        0.005, "Kalman filter: camera fix standard deviation per axis (m)", min=1e-6, max=10.0
    )
    ambiguity: str = setting(
        "lowest_error",
        "planar pose ambiguity (two IPPE branches): lowest_error (reprojection), continuity "
        "(closest rotation to the previous frame) or odometry (previous pose moved by /agv/odometry)",
        AMBIGUITY_POLICIES,
    )
    feature_points: str = setting(
        "vertices",
        "points the solver uses per QR code: vertices (4) or finder (vertices + the finder "
        "patterns' corners, each refined on its own with cornerSubPix)",
        ("vertices", "finder"),
    )
    tracking: bool = setting(
        True,
        "between keyframes, follow each decoded code from its predicted corners by ECC template "
        "alignment instead of searching the whole frame (falls back to full detection when a "
        "check fails)",
    )
    keyframe_every: int = setting(
        10, "tracking: full detection on every K-th frame of each camera (K)", min=1, max=100
    )
    sigma_px: str = setting(
        "auto",
        "pixel noise σ for covariances and the Cramér–Rao bound: auto (pooled residuals of the "
        "frames so far) or a number in px",
    )
    correction: str = setting(
        "none",
        "paper 002 navigation correction over cycles of marker sightings (/agv/odometry): none, "
        "cnoem (point-to-ray cost, eqs 12-13) or bundle (pixel reprojection over the window)",
        ("none", "cnoem", "bundle"),
    )
    cycle_distance_m: float = setting(
        3.0, "correction: travel that closes a correction cycle (m)", min=0.01, max=10000.0
    )
    cnoem_update: str = setting(
        "lm", "correction=cnoem: lm (Gauss-Newton/Levenberg-Marquardt) or paper (first-order, eqs 14-20)", ("lm", "paper")
    )
    truth: str = setting(
        "use",
        "ground truth: use (score every pose against it), or ignore (replay as if the recording had none: "
        "no errors, no NEES; the checks never read truth in either mode)",
        ("use", "ignore"),
    )
    checks: str = setting(
        "on", "check every solved pose against what else the log knows (docs/suspects.md): on or off", ("on", "off")
    )
    checks_limit_sigma: float = setting(
        5.0, "checks: a frame is a suspect when a check's disagreement exceeds this many σ", min=1.0, max=100.0
    )
    checks_pose_floor_m: float = setting(
        0.0005, "checks: position σ added per axis to every pose's covariance, a margin on top of its own (m)",
        min=0.0, max=10.0,
    )
    checks_pose_floor_deg: float = setting(
        0.02, "checks: rotation σ added per axis to every pose's covariance, a margin on top of its own (deg)",
        min=0.0, max=90.0,
    )
    checks_odom_m_per_m: float = setting(
        0.02, "checks: odometry position σ per metre travelled (m/m)", min=0.0, max=10.0
    )
    checks_odom_deg_per_m: float = setting(
        0.5, "checks: odometry heading σ per metre travelled (deg/m)", min=0.0, max=90.0
    )
    checks_odom_deg_per_deg: float = setting(
        0.02, "checks: odometry heading σ per degree turned (deg/deg)", min=0.0, max=10.0
    )
    checks_floor_tilt_deg: float = setting(
        0.35, "checks: with planar (wheel) odometry, σ of the floor's tilt between two poses (deg): the odometry "
        "carries no roll, pitch or height", min=0.0, max=90.0,
    )
    checks_floor_height_m: float = setting(
        0.005, "checks: with planar (wheel) odometry, σ of the floor's height between two poses (m; plus distance × tilt)",
        min=0.0, max=10.0,
    )
    checks_ambiguity_ratio: float = setting(
        4.0, "checks: IPPE ambiguity ratio below which the motion's likelihood ratio may name a mirror flip",
        min=1.0, max=1e6,
    )
    checks_map_sigma_m: float = setting(
        0.005, "checks: σ of a marker's map entry, against which its payload's coordinates are checked (m)",
        min=1e-6, max=10.0,
    )

    def __post_init__(self):
        validate(self)
        if not 0.0 < self.gimbal_threshold < 1.0:
            raise SettingsError(f"gimbal_threshold must lie in (0, 1), got {self.gimbal_threshold}")
        if self.max_reproj_px <= 0 or not math.isfinite(self.max_reproj_px):
            raise SettingsError(f"max_reproj_px must be a positive number, got {self.max_reproj_px}")
        if self.lm_max_iterations < 1:
            raise SettingsError(f"lm_max_iterations must be ≥ 1, got {self.lm_max_iterations}")
        for name in ("uwb_sigma_m", "kalman_gate_chi2", "camera_sigma_m"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise SettingsError(f"{name} must be a positive number, got {value}")
        if not (self.cycle_distance_m > 0 and math.isfinite(self.cycle_distance_m)):
            raise SettingsError(f"cycle_distance_m must be a positive number, got {self.cycle_distance_m}")
        if not (self.truth_max_gap_s >= 0 and math.isfinite(self.truth_max_gap_s)):
            raise SettingsError(f"truth_max_gap_s must be ≥ 0, got {self.truth_max_gap_s}")
        if not re.fullmatch(r"[A-Za-z0-9_./-]{1,256}", self.body_frame):
            raise SettingsError(
                f"body_frame must be auto or a frame name (letters, digits, _ . / -), got {self.body_frame!r}"
            )
        if self.truth_max_dt_s < 0:
            raise SettingsError(f"truth_max_dt_s must be ≥ 0, got {self.truth_max_dt_s}")
        if self.sigma_px != "auto":
            try:
                value = parse_number("sigma_px", self.sigma_px)
            except SettingsError:
                value = float("nan")
            if not (value > 0 and math.isfinite(value)):
                raise SettingsError(f"sigma_px must be auto or a positive number of pixels, got {self.sigma_px!r}")
            if not SIGMA_PX_MIN <= value <= SIGMA_PX_MAX:
                raise SettingsError(
                    f"sigma_px must be auto or lie in {_fmt(SIGMA_PX_MIN)}..{_fmt(SIGMA_PX_MAX)} px, got {self.sigma_px!r}"
                )

    @property
    def systematic_sigmas(self) -> SystematicSigmas | None:
        """The systematic sources of the pose covariance (``covariance=full``), or ``None`` for
        the pixel-noise-only covariance (``covariance=pixel``)."""
        if self.covariance == "pixel":
            return None
        return SystematicSigmas(
            corner_bias_px=self.corner_bias_px,
            qr_outline_px=self.cov_qr_outline_px,
            focal_px=self.cov_focal_px,
            principal_point_px=self.cov_principal_point_px,
            k1=self.cov_k1, k2=self.cov_k2, p1=self.cov_tangential, p2=self.cov_tangential,
            extrinsic_rotation_rad=math.radians(self.cov_extrinsic_rotation_deg),
            extrinsic_translation_m=self.cov_extrinsic_translation_m,
            map_position_m=self.cov_map_position_m,
            map_height_m=self.cov_map_height_m,
            map_yaw_rad=math.radians(self.cov_map_yaw_deg),
            map_tilt_rad=math.radians(self.cov_map_tilt_deg),
            map_scale=self.cov_map_scale,
        )

    @property
    def sigma_px_value(self) -> float | None:
        """The fixed pixel σ, or ``None`` for ``sigma_px=auto``."""
        return None if self.sigma_px == "auto" else float(self.sigma_px)

    def label(self) -> str:
        """Short label of the settings that differ from the defaults, for names and titles."""
        defaults = type(self)()
        parts = [self.solver]
        for f in dataclasses.fields(self):
            if f.name != "solver" and getattr(self, f.name) != getattr(defaults, f.name):
                parts.append(f"{f.name}={getattr(self, f.name)}")
        return "-".join(parts)


#: Settings that act only on UWB ranges (the ``uwb.range`` role).
UWB_SETTINGS = ("uwb", "uwb_gate", "uwb_sigma_m", "fusion", "kalman_gate_chi2", "camera_sigma_m")
#: Settings of the Kalman filter alone (``fusion=kalman``).
KALMAN_SETTINGS = ("kalman_gate_chi2", "camera_sigma_m")


def inapplicable(settings: RunSettings, *, has_uwb: bool, has_odometry: bool, n_cameras: int) -> dict[str, str]:
    """Setting name → why it does not apply, for each setting changed from its default that
    cannot act on a recording with this data (``fusion=kalman`` without UWB ranges, a
    ``correction`` without odometry to correct, ``camera_select`` with fewer than two cameras) or
    under the other settings (``kalman_gate_chi2`` when ``fusion`` is not kalman,
    ``cycle_distance_m`` without a correction). The reasons complete the sentence "NAME=VALUE
    does not apply: …". A run replays with these reset (:func:`without`) and keeps them out of
    its name."""
    defaults = RunSettings()
    changed = {f.name for f in dataclasses.fields(settings) if getattr(settings, f.name) != getattr(defaults, f.name)}
    reasons = {}
    if not has_uwb:
        for name in UWB_SETTINGS:
            reasons[name] = "the recording has no UWB ranges (no uwb.range topic)"
    if not has_odometry:
        for name in ("correction", "cycle_distance_m", "cnoem_update"):
            reasons[name] = "the recording has no odometry (no odometry topic), the navigation a correction corrects"
    if n_cameras < 2:
        reasons["camera_select"] = (
            f"the recording has {n_cameras} camera image topic{'s' if n_cameras != 1 else ''}; it chooses among "
            "several cameras at one time"
        )
    effective = without(settings, {name: "" for name in changed & reasons.keys()})
    if effective.fusion != "kalman":
        for name in KALMAN_SETTINGS:
            reasons.setdefault(name, f"fusion is {effective.fusion}, not kalman")
    if effective.correction == "none":
        for name in ("cycle_distance_m", "cnoem_update"):
            reasons.setdefault(name, "correction is none")
    elif effective.correction != "cnoem":
        reasons.setdefault("cnoem_update", f"correction is {effective.correction}, not cnoem")
    return {name: reasons[name] for name in (f.name for f in dataclasses.fields(settings)) if name in changed & reasons.keys()}


def without(settings: RunSettings, names) -> RunSettings:
    """A copy of ``settings`` with the fields ``names`` back at their defaults."""
    defaults = RunSettings()
    return dataclasses.replace(settings, **{name: getattr(defaults, name) for name in names})


def validate(obj) -> None:
    """Check every field of a settings or scenario-options dataclass: its type (an int is a
    valid float; a bool is only a bool), finiteness of numbers, ``choices`` metadata and the
    inclusive ``min`` / ``max`` bounds ("duration_s (recording length in seconds) must lie in
    0.01..3600, got 1e+09")."""
    for name, kind in field_types(type(obj)).items():
        value = getattr(obj, name)
        accepted = (float, int) if kind is float else (kind,)
        if isinstance(value, bool) != (kind is bool) or not isinstance(value, accepted):
            raise SettingsError(f"{name} must be of type {kind.__name__}, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise SettingsError(f"{name} must be a finite number, got {value}")
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        lo, hi = f.metadata.get("min"), f.metadata.get("max")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            what = f"{f.name} ({f.metadata['help']})" if f.metadata.get("help") else f.name
            if lo is not None and hi is not None:
                allowed = f"lie in {bounds_text(f)}"
            else:
                allowed = f"be {bounds_text(f)}"
            raise SettingsError(f"{what} must {allowed}, got {_fmt(value)}")
    for f in dataclasses.fields(obj):
        choices = f.metadata.get("choices")
        if choices is not None and getattr(obj, f.name) not in choices:
            raise SettingsError(
                f"{f.name}={getattr(obj, f.name)!r} is not one of: {', '.join(choices)}"
            )


_INT_RE = re.compile(r"[+-]?[0-9]+")
_FLOAT_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE = ("nan", "+nan", "-nan", "inf", "+inf", "-inf", "infinity", "+infinity", "-infinity")


def parse_number(name: str, text: str) -> float:
    """A finite float from ASCII decimal text (``1``, ``-0.5``, ``2e-3``); SettingsError for
    anything else, naming NaN and infinities as not finite."""
    if text.strip().lower() in _NON_FINITE:
        raise SettingsError(f"{name}={text!r}: expected a finite number")
    if not _FLOAT_RE.fullmatch(text) or len(text) > 100:
        raise SettingsError(f"{name}={text!r}: expected a number")
    value = float(text)
    if not math.isfinite(value):
        raise SettingsError(f"{name}={text!r}: expected a finite number")
    return value


def _coerce(name: str, kind, text: str):
    if kind is bool:
        lowered = text.strip().lower()
        if lowered in ("1", "true", "yes", "on"):
            return True
        if lowered in ("0", "false", "no", "off"):
            return False
        raise SettingsError(f"{name}={text!r}: expected true or false")
    if kind is int:
        # ASCII digits only: Python's int() also reads "１" (full-width), "٣" and "1_000".
        if not _INT_RE.fullmatch(text) or len(text) > 100:
            raise SettingsError(f"{name}={text!r}: expected an integer")
        return int(text, 10)
    if kind is float:
        return parse_number(name, text)
    if kind is str:
        return text
    raise SettingsError(f"{name}: settings of type {kind} cannot be set from the command line")


def field_types(cls) -> dict[str, type]:
    """Field name → Python type of a settings dataclass (resolving string annotations)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def apply_overrides(base, pairs: list[str] | tuple[str, ...]):
    """A copy of the dataclass instance ``base`` with ``key=value`` overrides applied."""
    types = field_types(type(base))
    changes = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        key = key.strip()
        if not sep or not key:
            raise SettingsError(f"--set {pair!r}: expected key=value")
        if key not in types:
            raise SettingsError(
                f"unknown setting {key!r}; valid settings: {', '.join(sorted(types))}"
            )
        changes[key] = _coerce(key, types[key], value.strip())
    try:
        return dataclasses.replace(base, **changes)
    except SettingsError:
        raise
    except (TypeError, ValueError) as exc:
        raise SettingsError(str(exc)) from None


def describe(cls) -> list[tuple[str, str, str, str]]:
    """(name, type, default, help) rows of a settings dataclass, for ``--help`` and listings."""
    rows = []
    types = field_types(cls)
    for f in dataclasses.fields(cls):
        help_text = f.metadata.get("help", "")
        if "choices" in f.metadata:
            help_text += f" ({'|'.join(f.metadata['choices'])})"
        if bounds_text(f):
            help_text += f" [{bounds_text(f)}]"
        rows.append((f.name, types[f.name].__name__, repr(f.default), help_text))
    return rows


def as_dict(obj) -> dict:
    return dataclasses.asdict(obj)
