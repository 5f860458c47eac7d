"""qr_floor — paper 000: an AGV with a forward, downward-tilted camera drives over a floor grid
of QR codes whose payloads carry their own world coordinates.

World: codes on a square grid (``grid_spacing_m``) covering the track with a margin, each
rotated in the floor plane by a seeded multiple of 90°, printed black on white with a 4-module
quiet zone, on a grey floor. Path: a rounded rectangle (straights and quarter turns) driven
at ``speed_mps``. Camera ``front`` sits ``cam_height_m`` above the AGV origin and looks
forward so its optical axis meets the floor ``cam_lookahead_m`` ahead (paper 000 §7: 1500 mm
height, 1000 mm horizontal distance).

Option ``marker_family``: ``qr`` (default) lays the QR codes above; an OpenCV ArUco dictionary
(``DICT_4X4_50``, …) or AprilTag family (``DICT_APRILTAG_36h11``, …) lays that family's markers
instead — ids 0, 1, … row-major on the same grid, ``code_size_m`` the side of the black border,
:data:`ARUCO_QUIET_ZONE_MODULES` of white around, drawn as printed
(:func:`agvviz.markers.aruco.aruco_modules`) — and the recorded marker map is of that dictionary
with every marker's world corners, so ``agvviz run`` detects and solves them with no side file.

Recorded: calibration, ``/tf_static`` (agv → cam_front) and the marker map once at the first
time stamp (``write_map=false``: no map, the QR payloads are then the only source of the codes'
coordinates); then per frame ``/agv/ground_truth`` (world), ``/agv/odometry`` (odom) and the
JPEG frame, all at the frame's log time, in that order.

Error sources (``realism``, :mod:`agvviz.sim.realism`; default ``typical``; ``ideal``: none): the
calibration and ``/tf_static`` written are the recorded (perturbed) ones, the map and the
payloads the mapped (nominal) code placement, while rendering and truth use the true camera,
mount and code placement; a frame stamped t shows the world at its capture time t − delay
(then ``/agv/ground_truth`` gets a sample at the capture time too, before or after the one at
t); a dropped frame has no image (it is still rendered, so the other frames do not change);
floor bumps pitch and roll the true AGV; wheel slip scales the odometry steps. Image formation
and print (``imaging``, :mod:`agvviz.sim.imaging`) follow the same profile: the codes are printed
once (ink spread, paper warp and texture, glare, dirt, occlusion), each frame is exposed while
the AGV moves (motion blur over ``exposure_s``, rolling shutter; ``time_samples`` and
``rows_per_band`` trade speed for accuracy) and goes through illumination, vignetting, defocus,
blur, shot and read noise and JPEG. A frame's capture instant is the middle of its middle row's
exposure (:func:`agvviz.sim.realism.exposure_start_s`). ``blur_sigma_px``, ``noise_sigma_dn``
and ``jpeg_quality`` set to other than their defaults override the profile's lens blur, read
noise and JPEG quality (:func:`agvviz.sim.realism.scenario_imaging`). The draws are in the
``agvviz.realism`` metadata record, written before the first message (not under ``ideal``).

Faults injected on purpose (``inject``, :mod:`agvviz.sim.inject`): a moved, turned or rescaled
code (``marker``), a code whose QR text carries wrong coordinates (``payload``), a wrong
recorded extrinsic or, with ``from_s``, a camera knocked mid-run (``camera``), and a camera
time offset (``timing``), each recorded with the frames it affects in the draws' ``inject``
source. Geometry prone to the planar (IPPE mirror) ambiguity comes from the options alone:
small markers seen small and off their normal (docs/realism.md, "Mirror flips on purpose").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agvviz.model import topics
from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.geometry.camera import PinholeCamera
from agvviz.settings import MAX_FRAMES, MAX_IMAGE_SAMPLES, check_total, setting
from agvviz.settings import validate as check_fields
from agvviz.sim.qr_texture import PAYLOAD_RESOLUTION_M, QUIET_ZONE_MODULES, make_floor_code
from agvviz.sim.render import FloorScene, encode_jpeg
from agvviz.sim import imaging as im
from agvviz.recording.schemas import REALISM_METADATA
from agvviz.sim import realism as rl
from agvviz.sim import inject as inj
from agvviz.geometry import euler, se3
from agvviz.markers.aruco import aruco_modules
from agvviz.markers.dictionary import aruco_dictionary
from agvviz.markers.types import ArucoError
from agvviz.sim.room import placed, roof_code
from agvviz.sim.trajectory import RoundedRectangleTrack, dead_reckoning, forward_camera_mount, sample_track, track_pose

NAME = "qr_floor"
DESCRIPTION = "Paper 000: AGV with a tilted camera over a floor grid of QR codes carrying their world coordinates"

CAM_NAME = "front"
#: Codes cover the track's outer extent plus this margin on every side (the camera sees up to
#: ~2.7 m ahead and ~1.7 m sideways with the default mount).
GRID_MARGIN_M = 3.0
#: Smallest QR symbol (version 1) is 21 modules: the label (symbol + quiet zone) is at most
#: this many times the symbol side.
MAX_LABEL_TO_SYMBOL = (21 + 2 * QUIET_ZONE_MODULES) / 21
#: At most this many codes on the floor (each is a QR symbol drawn into the scene).
MAX_CODES = 20_000
#: ``marker_family`` of the QR codes; any other value names an ArUco/AprilTag dictionary.
QR_FAMILY = "qr"
#: White margin around an ArUco/AprilTag marker's black border, in modules.
ARUCO_QUIET_ZONE_MODULES = 2



@dataclass(frozen=True)
class Options:
    duration_s: float = setting(20.0, "recording length in seconds", min=0.01, max=3600.0)
    rate_hz: float = setting(10.0, "camera frame rate (also ground-truth and odometry rate)", min=0.1, max=200.0)
    speed_mps: float = setting(1.0, "AGV speed along the track in m/s", min=0.0, max=10.0)
    track_length_m: float = setting(6.0, "length of the track's straights along world x", min=0.0, max=100.0)
    track_width_m: float = setting(3.0, "length of the track's straights along world y", min=0.0, max=100.0)
    turn_radius_m: float = setting(1.0, "radius of the track's quarter turns", min=0.01, max=50.0)
    cam_height_m: float = setting(1.5, "camera height above the floor", min=0.05, max=20.0)
    cam_lookahead_m: float = setting(1.0, "horizontal distance from the camera to where its optical axis meets the floor", min=0.0, max=50.0)
    code_size_m: float = setting(0.5, "QR symbol side between its outer vertices (quiet zone excluded)", min=0.01, max=5.0)
    grid_spacing_m: float = setting(1.5, "distance between neighbouring code centres", min=0.01, max=20.0)
    with_midpoints: bool = setting(False, "payload carries the 4 edge midpoints too (8 points)")
    width_px: int = setting(1280, "image width", min=16, max=8192)
    height_px: int = setting(1024, "image height", min=16, max=8192)
    focal_px: float = setting(1000.0, "focal length fx = fy in pixels (principal point at the image centre)", min=1.0, max=100000.0)
    k1: float = setting(-0.05, "radial distortion k1 (OpenCV plumb_bob)", min=-1.0, max=1.0)
    k2: float = setting(0.01, "radial distortion k2 (OpenCV plumb_bob)", min=-1.0, max=1.0)
    blur_sigma_px: float = setting(0.8, "Gaussian optical blur sigma in pixels", min=0.0, max=20.0)
    noise_sigma_dn: float = setting(2.0, "Gaussian sensor noise sigma in digital numbers", min=0.0, max=100.0)
    jpeg_quality: int = setting(95, "JPEG quality 1..100", min=1, max=100)
    supersample: int = setting(4, "s x s samples per pixel for area integration", min=1, max=16)
    time_samples: int = setting(2, "imaging: renders averaged over each row's exposure (motion blur accuracy)", min=1, max=64)
    rows_per_band: int = setting(32, "imaging: rows rendered at one time under a rolling shutter (smaller: more exact, slower)", min=1, max=8192)
    odom_scale_error: float = setting(0.01, "odometry distance scale error (0.01 = +1 %)", min=-0.5, max=0.5)
    odom_heading_bias_deg_per_s: float = setting(0.1, "odometry heading drift in deg/s", min=-10.0, max=10.0)
    odom_step_noise_m: float = setting(0.002, "odometry position noise per step and axis (sigma, m)", min=0.0, max=1.0)
    odom_heading_noise_deg: float = setting(0.05, "odometry heading noise per step (sigma, deg)", min=0.0, max=10.0)
    realism: str = setting("typical", rl.HELP_PROFILE, rl.PROFILE_NAMES)
    realism_off: str = setting("", rl.HELP_OFF)
    realism_set: str = setting("", rl.HELP_SET)
    inject: str = setting("", inj.HELP)
    write_map: bool = setting(
        True,
        "write /markers/map; false: the QR payloads are the recording's only source of code "
        "coordinates (marker_family=qr only)",
    )
    marker_family: str = setting(
        QR_FAMILY,
        "floor markers: qr (codes carrying their world coordinates), or an OpenCV ArUco dictionary "
        "(DICT_4X4_50, ...) or AprilTag family (DICT_APRILTAG_36h11, ...): ids 0..N-1 on the grid, "
        "code_size_m their black border's side, the map of their corners recorded",
    )


def realism_sources(options: dict) -> tuple[str, ...]:
    """The error sources (:data:`agvviz.sim.realism.SOURCES`) this scenario applies under the
    recorded options ``options`` (a dict, as in a recording's metadata): every source: the AGV drives on a bumpy floor with wheel odometry and a camera."""
    return rl.SOURCES


def validate(options: Options) -> None:
    """Raise ``ValueError`` naming the first impossible option and what to do about it."""
    check_fields(options)
    o = options
    positive = ("duration_s", "rate_hz", "turn_radius_m", "code_size_m", "grid_spacing_m", "focal_px")
    for name in positive:
        if getattr(o, name) <= 0:
            raise ValueError(f"{name} must be > 0, got {getattr(o, name)}")
    non_negative = (
        "speed_mps", "track_length_m", "track_width_m", "cam_lookahead_m", "blur_sigma_px",
        "noise_sigma_dn", "odom_step_noise_m", "odom_heading_noise_deg",
    )
    for name in non_negative:
        if getattr(o, name) < 0:
            raise ValueError(f"{name} must be ≥ 0, got {getattr(o, name)}")
    if round(o.duration_s * o.rate_hz) < 1:
        raise ValueError(f"duration_s · rate_hz = {o.duration_s * o.rate_hz:g} < 1: no frame to record")
    check_total("frames = duration_s × rate_hz", round(o.duration_s * o.rate_hz), MAX_FRAMES,
                "shorten duration_s or lower rate_hz")
    check_total("samples per image = width_px × height_px × supersample²",
                o.width_px * o.height_px * o.supersample**2, MAX_IMAGE_SAMPLES,
                "use a smaller image or a lower supersample")
    half_x = o.track_length_m / 2.0 + o.turn_radius_m + GRID_MARGIN_M
    half_y = o.track_width_m / 2.0 + o.turn_radius_m + GRID_MARGIN_M
    check_total("floor codes ≈ (track extent / grid_spacing_m)²",
                int(2 * (half_x // o.grid_spacing_m) + 1) * int(2 * (half_y // o.grid_spacing_m) + 1), MAX_CODES,
                "increase grid_spacing_m or shrink the track")
    if o.cam_height_m <= 0:
        raise ValueError(f"cam_height_m must be > 0 (camera above the floor), got {o.cam_height_m}")
    if o.width_px < 16 or o.height_px < 16:
        raise ValueError(f"image must be at least 16×16 px, got {o.width_px}×{o.height_px}")
    if not 1 <= o.jpeg_quality <= 100:
        raise ValueError(f"jpeg_quality must lie in 1..100, got {o.jpeg_quality}")
    if not 1 <= o.supersample <= 16:
        raise ValueError(f"supersample must lie in 1..16, got {o.supersample}")
    if o.time_samples < 1 or o.rows_per_band < 1:
        raise ValueError(f"time_samples and rows_per_band must be ≥ 1, got {o.time_samples}, {o.rows_per_band}")
    if abs(o.odom_scale_error) >= 0.5:
        raise ValueError(f"odom_scale_error must lie in (-0.5, 0.5), got {o.odom_scale_error}")
    n_codes = (2 * int(half_x // o.grid_spacing_m) + 1) * (2 * int(half_y // o.grid_spacing_m) + 1)
    label_to_symbol = _check_family(o, n_codes)
    for name, value, step in (("code_size_m", o.code_size_m / 2.0, "0.2 mm"), ("grid_spacing_m", o.grid_spacing_m, "0.1 mm")):
        if o.marker_family != QR_FAMILY:
            break  # only QR payloads carry coordinates on the 0.1 mm grid
        if abs(value / PAYLOAD_RESOLUTION_M - round(value / PAYLOAD_RESOLUTION_M)) > 1e-6:
            raise ValueError(
                f"{name} must be a multiple of {step} so code vertices sit on the payload's 0.1 mm grid"
            )
    if o.code_size_m * label_to_symbol >= o.grid_spacing_m:
        raise ValueError(
            f"codes would overlap: a {o.code_size_m} m code with its quiet zone is up to "
            f"{o.code_size_m * label_to_symbol:.3f} m wide, grid_spacing_m is {o.grid_spacing_m}; "
            "increase grid_spacing_m or decrease code_size_m"
        )
    rl.check_timing(rl.make_realism(o.realism, o.realism_off, o.realism_set).timing, 1.0 / o.rate_hz)
    injected = inj.parse_inject(o.inject)
    if injected.payloads() and o.marker_family != QR_FAMILY:
        raise ValueError(f"inject: payload needs QR codes (marker_family=qr): {o.marker_family} markers carry no coordinates")
    ids = marker_ids(o.marker_family, n_codes)  # build_scene's ids, row-major
    inj.check_targets(injected, ids, [CAM_NAME], ids if o.marker_family == QR_FAMILY else ())
    timing = rl.make_realism(o.realism, o.realism_off, o.realism_set).timing
    inj.check_frame_times(injected, abs(timing.latency_s) + 5.0 * timing.jitter_sigma_s, 1.0 / o.rate_hz,
                          (round(o.duration_s * o.rate_hz) - 1) / o.rate_hz)
    if not o.write_map and o.marker_family != QR_FAMILY:
        raise ValueError(f"write_map=false needs marker_family=qr: {o.marker_family} markers carry no coordinates, the map is all there is")
    # The lens model must be one-to-one over the image: d(r·(1 + k1 r² + k2 r⁴))/dr > 0 up to
    # beyond the image corner's normalised radius.
    corner_r = math.hypot(o.width_px / 2.0, o.height_px / 2.0) / o.focal_px
    r = np.linspace(0.0, 1.5 * corner_r, 200)
    if np.any(1.0 + 3.0 * o.k1 * r**2 + 5.0 * o.k2 * r**4 <= 0.0):
        raise ValueError(
            f"k1 = {o.k1}, k2 = {o.k2} fold the lens model over inside the image "
            f"(normalised corner radius {corner_r:.2f}); use smaller distortion"
        )


def _check_family(o: Options, n_codes: int) -> float:
    """Check ``marker_family`` (a known family with at least ``n_codes`` ids, no midpoints for
    ArUco) and return its label side ÷ symbol side (the overlap check's factor)."""
    if o.marker_family == QR_FAMILY:
        return MAX_LABEL_TO_SYMBOL
    try:
        dictionary = aruco_dictionary(o.marker_family)
    except ArucoError as exc:
        raise ValueError(f"marker_family: {exc} (or 'qr')") from None
    count = dictionary.bytesList.shape[0]
    if n_codes > count:
        raise ValueError(
            f"marker_family: the floor grid holds {n_codes} markers but {o.marker_family} has {count} ids; "
            "increase grid_spacing_m, shrink the track or use a larger dictionary"
        )
    if o.with_midpoints:
        raise ValueError("with_midpoints applies to QR payloads only (marker_family=qr)")
    modules = dictionary.markerSize + 2
    return (modules + 2 * ARUCO_QUIET_ZONE_MODULES) / modules


def marker_ids(marker_family: str, n_codes: int) -> list[str]:
    """The ids :func:`build_scene` gives its ``n_codes`` codes: ``Q000``, ``Q001``… (QR) or
    ``0``, ``1``… (ArUco/AprilTag)."""
    return [f"Q{k:03d}" if marker_family == QR_FAMILY else str(k) for k in range(n_codes)]


def make_camera(options: Options) -> PinholeCamera:
    """The ``front`` camera: fx = fy = focal_px, principal point at the image centre."""
    K = np.array(
        [
            [options.focal_px, 0.0, (options.width_px - 1) / 2.0],
            [0.0, options.focal_px, (options.height_px - 1) / 2.0],
            [0.0, 0.0, 1.0],
        ]
    )
    return PinholeCamera(K, np.array([options.k1, options.k2, 0.0, 0.0, 0.0]), options.width_px, options.height_px)


def make_track(options: Options) -> RoundedRectangleTrack:
    return RoundedRectangleTrack(options.track_length_m, options.track_width_m, options.turn_radius_m)


def build_scene(options: Options, rng: np.random.Generator) -> FloorScene:
    """The floor: codes ``Q000``, ``Q001``… (ArUco/AprilTag: ids ``0``, ``1``…) on the grid
    (row-major from the lower-left), each rotated by a random multiple of 90°, and seeded
    floor/ink/paper grey levels.

    Draws one integer per code, then three uniforms, from ``rng``.
    """
    track = make_track(options)
    half_x = options.track_length_m / 2.0 + options.turn_radius_m + GRID_MARGIN_M
    half_y = options.track_width_m / 2.0 + options.turn_radius_m + GRID_MARGIN_M
    spacing_mm = round(options.grid_spacing_m * 1e4) / 10.0  # exact on the 0.1 mm grid
    nx = int(half_x // options.grid_spacing_m)
    ny = int(half_y // options.grid_spacing_m)
    centers = [
        (track.center_xy_m[0] + i * spacing_mm / 1000.0, track.center_xy_m[1] + j * spacing_mm / 1000.0)
        for j in range(-ny, ny + 1)
        for i in range(-nx, nx + 1)
    ]
    quarter_turns = rng.integers(0, 4, size=len(centers))
    if options.marker_family == QR_FAMILY:
        codes = tuple(
            make_floor_code(f"Q{k:03d}", center, int(turns), options.code_size_m, options.with_midpoints)
            for k, (center, turns) in enumerate(zip(centers, quarter_turns))
        )
    else:
        codes = tuple(
            placed(
                roof_code(aruco_modules(options.marker_family, k), str(k), options.code_size_m, ARUCO_QUIET_ZONE_MODULES),
                se3.make(euler.Rz(int(turns) * np.pi / 2.0), [center[0], center[1], 0.0]),
            )
            for k, (center, turns) in enumerate(zip(centers, quarter_turns))
        )
    floor_dn, black_dn, white_dn = rng.uniform([110.0, 20.0, 210.0], [140.0, 30.0, 230.0])
    return FloorScene(codes=codes, floor_dn=float(floor_dn), black_dn=float(black_dn), white_dn=float(white_dn))


def marker_map(scene: FloorScene, marker_family: str = QR_FAMILY) -> dict:
    """The ``agvviz.MarkerMap`` message of the scene's codes (QR codes with their payloads, or
    the ArUco/AprilTag markers of dictionary ``marker_family`` with their world corners)."""
    if marker_family != QR_FAMILY:
        return {
            "dictionary": marker_family,
            "markers": [
                {"id": code.marker_id, "side_m": code.side_m, "corners_world_m": code.points_world_m[:4].tolist()}
                for code in scene.codes
            ],
        }
    return {
        "dictionary": "qr",
        "markers": [
            {
                "id": code.marker_id,
                "side_m": code.side_m,
                "corners_world_m": code.points_world_m[:4].tolist(),
                "payload": code.payload,
            }
            for code in scene.codes
        ],
    }


def _inject_details(injected, true_scene, camera, T_world_cam, stamps_ns, capture_ns, written, T_agv_cam_knocked) -> dict:
    """What each injected item affects, for the draws (:meth:`agvviz.sim.inject.InjectSpec.to_json`),
    by the stamps (ns) of the frames written (``written``: not dropped): a marker or payload item
    the frames that show the code whole (``frames_in_view_ns``; a payload item also the
    ``payload`` text printed), a camera item the frames it affects (``frames_ns``: every frame, or
    those captured from ``from_s`` on, then with ``from_ns`` = first stamp + from_s and the
    knocked true mount ``T_parent_cam_true_after``), a timing item its ``offset_ns`` and frames."""
    codes = {c.marker_id: c for c in true_scene.codes}
    t0_ns = int(stamps_ns[0])
    shown = [k for k in range(len(stamps_ns)) if written[k]]
    details = {}
    for kind, items in (("marker", injected.markers()), ("payload", injected.payloads())):
        for target in items:
            code = codes[target]
            in_view = inj.frames_in_view(camera, [T_world_cam[k] for k in shown], code.points_world_m[:4], stamps_ns[shown])
            details[(kind, target)] = {"frames_in_view_ns": in_view}
            if kind == "payload":
                details[(kind, target)]["payload"] = code.payload
    for name, item in injected.cameras().items():
        if item.from_s is None:
            details[("camera", name)] = {"frames_ns": [int(stamps_ns[k]) for k in shown]}
        else:
            details[("camera", name)] = {
                "from_ns": t0_ns + int(round(item.from_s * 1e9)),
                "frames_ns": [int(stamps_ns[k]) for k in shown if inj.knocked(item, (int(capture_ns[k]) - t0_ns) * 1e-9)],
                "T_parent_cam_true_after": T_agv_cam_knocked.tolist(),
            }
    for name, item in injected.timings().items():
        details[("timing", name)] = {"offset_ns": int(round(item.get("offset_ms") * 1e6)),
                                     "frames_ns": [int(stamps_ns[k]) for k in shown]}
    return details


def record(
    writer,
    options: Options,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Write the whole recording to ``writer`` (an open :class:`RecordingWriter`).

    Random draws from ``np.random.default_rng(seed)`` in this order: scene, odometry, then the
    sensor (read) noise of each frame — the same seed and options give identical messages. The
    error sources draw from their own generators (:func:`agvviz.sim.realism.source_rng`; the
    imaging effects from :func:`agvviz.sim.imaging.source_rngs` (seed, 0, code index) for the
    print and (seed, 1, frame index) per frame).
    """
    validate(options)
    o = options
    realism = rl.make_realism(o.realism, o.realism_off, o.realism_set)
    rng = np.random.default_rng(seed)
    scene = build_scene(options, rng)  # as mapped: the map and the payloads
    camera = make_camera(options)  # true
    T_agv_cam = forward_camera_mount(options.cam_height_m, options.cam_lookahead_m)  # true
    track = make_track(options)
    trajectory = sample_track(track, options.speed_mps, options.rate_hz, options.duration_s)
    stamps_ns = trajectory.log_time_ns
    total = len(stamps_ns)
    slip = rl.draw_slip(realism.slip, rl.source_rng(seed, "slip"), total - 1)
    T_odom_agv = dead_reckoning(
        trajectory,
        rng,
        scale_error=options.odom_scale_error,
        heading_bias_rad_per_s=math.radians(options.odom_heading_bias_deg_per_s),
        step_noise_m=options.odom_step_noise_m,
        heading_noise_rad=math.radians(options.odom_heading_noise_deg),
        slip_fraction=slip,
    )
    calib = rl.draw_calibration(realism.calibration, rl.source_rng(seed, "calibration"), {CAM_NAME: (camera, T_agv_cam)})
    marker_draws = rl.draw_map(
        realism.map, rl.source_rng(seed, "map"), [(c.marker_id, c.T_world_marker, c.side_m) for c in scene.codes]
    )
    # Errors injected on purpose (option inject, agvviz.sim.inject), on top of the draws.
    injected = inj.parse_inject(o.inject)
    marker_draws = [inj.apply_to_marker(d, injected.markers().get(d.marker_id)) for d in marker_draws]
    calib = {name: inj.apply_to_camera(d, injected.cameras().get(name)) for name, d in calib.items()}
    knock = injected.cameras().get(CAM_NAME)  # a from_s item: the true mount moves mid-run
    T_agv_cam_knocked = inj.knocked_mount(T_agv_cam, knock)
    true_scene = dataclasses.replace(scene, codes=tuple(
        rl.placed_as_drawn(inj.apply_to_payload(c, injected.payloads().get(c.marker_id)), d)
        for c, d in zip(scene.codes, marker_draws)
    ))
    timing = rl.draw_timing(realism.timing, rl.source_rng(seed, "timing"), total, [CAM_NAME])[CAM_NAME]
    timing = inj.apply_to_timing(timing, injected.timings().get(CAM_NAME))
    bumps = rl.draw_bumps(realism.bumps, rl.source_rng(seed, "bumps"))
    imaging, jpeg_quality = rl.scenario_imaging(realism, o)
    image_seed = int(seed) % 2**64
    printed_scene = im.print_scene(true_scene, imaging, image_seed, key=rl.PRINT_KEY)

    def true_pose(t_ns: int, k: int) -> tuple[np.ndarray, float, float]:
        """True ``T_world_agv`` (bumps included) at ``t_ns``, near frame k's stamp."""
        flat = trajectory.T_world_agv[k] if t_ns == stamps_ns[k] else track_pose(track, o.speed_mps, (t_ns - stamps_ns[0]) * 1e-9)
        return bumps.apply(flat)

    capture_ns = stamps_ns - timing.delay_ns
    truth = [true_pose(int(stamps_ns[k]), k) for k in range(total)]
    captured = [truth[k] if capture_ns[k] == stamps_ns[k] else true_pose(int(capture_ns[k]), k) for k in range(total)]
    draws = rl.new_draws(realism, seed)
    draws.sources.update(
        calibration={CAM_NAME: calib[CAM_NAME].to_json()},
        map=[d.to_json() for d in marker_draws],
        timing={"stamp_ns": stamps_ns, "cameras": {CAM_NAME: timing.to_json()}},
        bumps={
            "field": bumps.to_json(),
            "stamp_pitch_deg": np.degrees([p for _, p, _ in truth]), "stamp_roll_deg": np.degrees([r for _, _, r in truth]),
            "capture_pitch_deg": {CAM_NAME: np.degrees([p for _, p, _ in captured])},
            "capture_roll_deg": {CAM_NAME: np.degrees([r for _, _, r in captured])},
        },
        slip={"fraction": slip},
        imaging=rl.imaging_record(imaging, jpeg_quality, o.time_samples, o.rows_per_band),
    )
    if injected:
        T_world_cam = [captured[k][0] @ (T_agv_cam_knocked if inj.knocked(knock, (int(capture_ns[k]) - int(stamps_ns[0])) * 1e-9)
                                         else T_agv_cam) for k in range(total)]
        draws.sources["inject"] = injected.to_json(_inject_details(
            injected, true_scene, camera, T_world_cam, stamps_ns, capture_ns, ~timing.dropped, T_agv_cam_knocked,
        ))
    if not realism.is_ideal or injected:  # an ideal recording stays message for message what it was
        writer.write_metadata(REALISM_METADATA, rl.metadata_values(draws))

    t0_ns = int(stamps_ns[0])
    writer.write_calibration(CAM_NAME, calib[CAM_NAME].recorded_camera, t0_ns)
    writer.write_tf_static([(AGV_FRAME, camera_frame(CAM_NAME), calib[CAM_NAME].T_parent_cam_recorded)], t0_ns)
    if o.write_map:
        writer.write_marker_map(marker_map(scene, o.marker_family), t0_ns)
    for k in range(total):
        t_ns, t_capture_ns = int(stamps_ns[k]), int(capture_ns[k])
        T_world_agv_capture = captured[k][0]
        if t_capture_ns < t_ns:
            writer.write_pose(topics.GROUND_TRUTH_TOPIC, T_world_agv_capture, WORLD_FRAME, t_capture_ns)
        writer.write_pose(topics.GROUND_TRUTH_TOPIC, truth[k][0], WORLD_FRAME, t_ns)
        if t_capture_ns > t_ns:
            writer.write_pose(topics.GROUND_TRUTH_TOPIC, T_world_agv_capture, WORLD_FRAME, t_capture_ns)
        writer.write_pose(topics.ODOMETRY_TOPIC, T_odom_agv[k], "odom", t_ns)
        t_capture_s = (t_capture_ns - t0_ns) * 1e-9
        mount = T_agv_cam_knocked if inj.knocked(knock, t_capture_s) else T_agv_cam  # whole frame: its capture's
        T_world_cam_capture = T_world_agv_capture @ mount

        def pose_at_time(t_s: float, t_capture_s=t_capture_s, T_capture=T_world_cam_capture, mount=mount) -> np.ndarray:
            """True T_world_cam at t_s (s from the first stamp) during the exposure."""
            if t_s == t_capture_s:
                return T_capture
            return bumps.apply(track_pose(track, o.speed_mps, t_s))[0] @ mount

        rngs = im.source_rngs(image_seed, rl.FRAME_KEY, k)
        rngs["read_noise"] = rng  # the scenario's own stream: ideal frames are what they were
        image = im.render_camera_frame(
            printed_scene, camera, pose_at_time, rl.exposure_start_s(imaging, camera.height_px, t_capture_s),
            imaging, rngs, time_samples=o.time_samples, rows_per_band=o.rows_per_band, supersample=o.supersample,
        )
        if not timing.dropped[k]:  # a dropped frame is rendered all the same: later frames' noise stays
            writer.write_image(CAM_NAME, encode_jpeg(image, jpeg_quality), "jpeg", t_ns)
        if progress is not None:
            progress(k + 1, total)
