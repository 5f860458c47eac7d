"""uwb_room — paper 003: four wall cameras watch an ArUco code on the AGV's roof; four UWB
anchors take over when the cameras are blocked.

World (§3.1): an 8 × 7 m room; on the middle of each wall a camera (``cam_south`` …, height
``cam_height_m``, looking at the room's centre on the floor, 1280×1024 by default; Table 5's
640×480 and 320×240 through ``width_px``/``height_px`` at the same field of view) and a UWB
anchor (``A_south`` …, height ``anchor_height_m``). On the AGV: a 183 mm ArUco code
(``DICT_5X5_50``: 7 × 26.14 mm cells with the border, as in §2.2.2) face up on the roof, and
the UWB tag above the AGV's centre.

Variants:

* ``path`` — the AGV drives a rounded rectangle in the middle of the room at 0.2 m/s (§2.3);
  from ``block_start_s`` to ``block_end_s`` an obstacle hides the code from every camera
  (§3.3's blocked road).
* ``static_grid`` — §3.2: the AGV stands at each of the 30 points of a grid every
  ``grid_spacing_m`` (120 … 720 × 120 … 600 cm) for ``fixes_per_point`` camera frames and as
  many UWB rounds, one point after the other (1 s gaps between points).

UWB (§2.1.1): the tag ranges to the anchors in turn, ``uwb_rate_hz`` rounds per second, by
single-sided two-way ranging on free-running device clocks (:mod:`agvviz.sim.uwb`): clock
offsets, drifts of ``clock_drift_ppm`` (σ, per device), timestamp noise, 15.65 ps ticks, and
on each range with probability ``nlos_probability`` an NLOS excess path uniform in
[``nlos_excess_min_m``, ``nlos_excess_max_m``].

Recorded at the first time stamp: calibrations, ``/tf_static`` (world → cam_<wall>, agv →
marker_<id>, agv → uwb_tag), ``/markers/map`` (frame ``agv``) and ``/uwb/anchors``. Then, in
time order: per camera frame ``/agv/ground_truth`` and the four JPEG frames; per range
``/agv/ground_truth`` and ``/uwb/range``.

Error sources (``realism``, :mod:`agvviz.sim.realism`; default ``typical``; ``ideal``: none): each wall
camera's calibration and ``/tf_static`` extrinsic are the recorded (perturbed) ones and the
map's roof code is where it was meant to be, while rendering and truth use the true cameras and
the code's true place and print size on the roof; each camera's frame stamped t shows the AGV at
its own capture time t − delay (``/agv/ground_truth`` then also gets a sample at every capture
time); a dropped frame of a camera has no image (still rendered, so nothing else changes);
floor bumps pitch and roll the true AGV (truth, roof code and tag). No odometry, so no slip.
Image formation and print (``imaging``, :mod:`agvviz.sim.imaging`) follow the same profile: the
roof code is printed once, each camera's frame is exposed while the AGV moves (motion blur,
rolling shutter; ``time_samples``, ``rows_per_band``), then illumination, vignetting, defocus,
blur, shot and read noise and JPEG; the capture instant is the middle of the middle row's
exposure. ``blur_sigma_px``, ``noise_sigma_dn`` and ``jpeg_quality`` set to other than their
defaults override the profile's (:func:`agvviz.sim.realism.scenario_imaging`). The draws are in the ``agvviz.realism`` metadata record, written before the first message
(not under ``ideal``). Faults injected on purpose (``inject``, :mod:`agvviz.sim.inject`): the roof
code moved (``marker:<marker_id>``, AGV frame), a wall camera's extrinsic wrong or knocked from
``from_s`` on (``camera:<wall>``, world frame) and its images stamped late (``timing:<wall>``);
each is in the draws' ``inject`` source with the frames it affects (then written under ``ideal`` too).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agvviz.model import topics
from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.geometry import se3
from agvviz.geometry.camera import PinholeCamera
from agvviz.settings import MAX_FRAMES, MAX_IMAGE_SAMPLES, MAX_UWB_ROUNDS, check_total, setting
from agvviz.settings import validate as check_fields
from agvviz.markers.aruco import aruco_modules
from agvviz.markers.dictionary import aruco_dictionary, is_aruco_dictionary
from agvviz.sim import imaging as im
from agvviz.recording.schemas import REALISM_METADATA
from agvviz.sim import inject as inj
from agvviz.sim import realism as rl
from agvviz.sim.render import FloorScene, encode_jpeg
from agvviz.sim.room import WALLS, agv_pose, grid_points, horizontal_fov_focal_px, look_at, placed, roof_code, wall_points
from agvviz.sim.trajectory import SIM_START_TIME_NS, RoundedRectangleTrack
from agvviz.sim.uwb import DeviceClock, simulate_twr

NAME = "uwb_room"
DESCRIPTION = "Paper 003: four wall cameras + ArUco on the AGV, four UWB anchors, blocked stretch; static grid variant"

TAG_ID = "T0"
TAG_FRAME = "uwb_tag"
VARIANTS = ("path", "static_grid")
#: Time between two static-grid points, while the AGV moves (nothing is recorded).
GRID_GAP_S = 1.0



@dataclass(frozen=True)
class Options:
    variant: str = setting("path", "path (driving, blocked stretch) or static_grid (§3.2's 30 points)", VARIANTS)
    duration_s: float = setting(40.0, "recording length in seconds (path variant)", min=0.01, max=3600.0)
    rate_hz: float = setting(10.0, "camera frame rate (all four cameras at once)", min=0.1, max=200.0)
    speed_mps: float = setting(0.2, "AGV speed along the path (paper 003: 0.2 m/s)", min=0.0, max=10.0)
    block_start_s: float = setting(14.0, "the obstacle hides the code from all cameras from here (path variant)", min=0.0, max=3600.0)
    block_end_s: float = setting(24.0, "… until here (block_end_s <= block_start_s: never blocked)", min=0.0, max=3600.0)
    track_length_m: float = setting(3.0, "path: length of the straights along x", min=0.0, max=100.0)
    track_width_m: float = setting(2.0, "path: length of the straights along y", min=0.0, max=100.0)
    turn_radius_m: float = setting(0.6, "path: radius of the quarter turns", min=0.01, max=50.0)
    grid_spacing_m: float = setting(1.2, "static grid: distance between test points (paper: 120 cm)", min=0.01, max=100.0)
    fixes_per_point: int = setting(100, "static grid: camera frames and UWB rounds at each point (paper: 100)", min=1, max=10000)
    static_point_m: str = setting("", "static grid: one point 'x,y' (m) instead of the 30, e.g. 2.4,2.4 (Table 5)")
    room_length_m: float = setting(8.0, "room size along x", min=0.5, max=1000.0)
    room_width_m: float = setting(7.0, "room size along y", min=0.5, max=1000.0)
    width_px: int = setting(1280, "image width (paper 003 Table 5: 1280, 640, 320)", min=16, max=8192)
    height_px: int = setting(1024, "image height (Table 5: 1024, 480, 240)", min=16, max=8192)
    hfov_deg: float = setting(70.0, "horizontal field of view of every camera (sets the focal length)", min=1.0, max=150.0)
    k1: float = setting(-0.02, "radial distortion k1 (OpenCV plumb_bob)", min=-1.0, max=1.0)
    cam_height_m: float = setting(2.8, "camera height on the walls", min=0.1, max=100.0)
    dictionary: str = setting("DICT_5X5_50", "OpenCV ArUco dictionary of the roof code")
    marker_id: int = setting(7, "id of the roof code", min=0, max=999)
    marker_side_m: float = setting(0.183, "roof code side incl. its black border (paper: 183 mm)", min=0.001, max=10.0)
    roof_height_m: float = setting(0.35, "height of the AGV roof (the code) above the floor", min=0.0, max=10.0)
    tag_height_m: float = setting(0.45, "height of the UWB tag above the floor", min=0.0, max=10.0)
    anchor_height_m: float = setting(2.2, "height of the UWB anchors", min=0.01, max=100.0)
    uwb_rate_hz: float = setting(10.0, "UWB rounds per second (one range per anchor each)", min=0.1, max=1000.0)
    reply_delay_us: float = setting(150.0, "anchor reply delay of single-sided TWR (µs)", min=1.0, max=100000.0)
    timestamp_noise_ns: float = setting(0.1, "UWB timestamp noise sigma (ns)", min=0.0, max=1000.0)
    clock_drift_ppm: float = setting(2.0, "sigma of each UWB device's clock drift (ppm)", min=0.0, max=1000.0)
    nlos_probability: float = setting(0.05, "probability that a range is NLOS", min=0.0, max=1.0)
    nlos_excess_min_m: float = setting(0.2, "NLOS excess path, lower bound (m)", min=0.0, max=100.0)
    nlos_excess_max_m: float = setting(0.8, "NLOS excess path, upper bound (m)", min=0.0, max=100.0)
    blur_sigma_px: float = setting(0.8, "Gaussian optical blur sigma in pixels", min=0.0, max=20.0)
    noise_sigma_dn: float = setting(2.0, "Gaussian sensor noise sigma in digital numbers", min=0.0, max=100.0)
    jpeg_quality: int = setting(95, "JPEG quality 1..100", min=1, max=100)
    supersample: int = setting(4, "s x s samples per pixel for area integration", min=1, max=16)
    time_samples: int = setting(2, "imaging: renders averaged over each row's exposure (motion blur accuracy)", min=1, max=64)
    rows_per_band: int = setting(32, "imaging: rows rendered at one time under a rolling shutter (smaller: more exact, slower)", min=1, max=8192)
    realism: str = setting("typical", rl.HELP_PROFILE, rl.PROFILE_NAMES)
    realism_off: str = setting("", rl.HELP_OFF)
    realism_set: str = setting("", rl.HELP_SET)
    inject: str = setting(
        "",
        "errors injected on purpose, ';'-separated: marker:<marker_id>:dx_m=…(agv frame),yaw_deg=…,scale=…; "
        "camera:<wall>:pitch_deg=…,dz_m=…[,from_s=…] (world frame; from_s: knocked then); "
        "timing:<wall>:offset_ms=… (walls south, east, north, west; keys in agvviz/sim/inject.py)",
    )


def realism_sources(options: dict) -> tuple[str, ...]:
    """The error sources (:data:`agvviz.sim.realism.SOURCES`) this scenario applies under the
    recorded options ``options`` (a dict, as in a recording's metadata): no odometry, so no wheel slip."""
    return tuple(s for s in rl.SOURCES if s != "slip")


def validate(options: Options) -> None:
    """Raise ``ValueError`` naming the first impossible option and what to do about it."""
    check_fields(options)
    o = options
    for name in (
        "duration_s", "rate_hz", "turn_radius_m", "grid_spacing_m", "room_length_m", "room_width_m",
        "marker_side_m", "uwb_rate_hz", "reply_delay_us", "cam_height_m", "anchor_height_m",
    ):
        if getattr(o, name) <= 0:
            raise ValueError(f"{name} must be > 0, got {getattr(o, name)}")
    for name in (
        "speed_mps", "track_length_m", "track_width_m", "timestamp_noise_ns", "clock_drift_ppm",
        "nlos_excess_min_m", "blur_sigma_px", "noise_sigma_dn", "roof_height_m", "tag_height_m",
    ):
        if getattr(o, name) < 0:
            raise ValueError(f"{name} must be ≥ 0, got {getattr(o, name)}")
    if o.fixes_per_point < 1:
        raise ValueError(f"fixes_per_point must be ≥ 1, got {o.fixes_per_point}")
    if not 0.0 <= o.nlos_probability <= 1.0:
        raise ValueError(f"nlos_probability must lie in [0, 1], got {o.nlos_probability}")
    if o.nlos_excess_max_m < o.nlos_excess_min_m:
        raise ValueError("nlos_excess_max_m must be ≥ nlos_excess_min_m")
    if o.width_px < 16 or o.height_px < 16:
        raise ValueError(f"image must be at least 16×16 px, got {o.width_px}×{o.height_px}")
    if not 1.0 <= o.hfov_deg <= 150.0:
        raise ValueError(f"hfov_deg must lie in [1, 150], got {o.hfov_deg}")
    if not 1 <= o.jpeg_quality <= 100 or not 1 <= o.supersample <= 16:
        raise ValueError("jpeg_quality must lie in 1..100 and supersample in 1..16")
    if o.time_samples < 1 or o.rows_per_band < 1:
        raise ValueError(f"time_samples and rows_per_band must be ≥ 1, got {o.time_samples}, {o.rows_per_band}")
    check_total("samples per image = width_px × height_px × supersample²",
                o.width_px * o.height_px * o.supersample**2, MAX_IMAGE_SAMPLES,
                "use a smaller image or a lower supersample")
    if o.variant == "path":
        frames, rounds, how = round(o.duration_s * o.rate_hz), o.duration_s * o.uwb_rate_hz, "shorten duration_s"
    else:
        points = 1 if o.static_point_m else 30
        frames, rounds, how = points * o.fixes_per_point, points * o.fixes_per_point, "lower fixes_per_point"
    check_total("frames per camera", frames, MAX_FRAMES, f"{how} or lower rate_hz")
    check_total("UWB rounds", rounds, MAX_UWB_ROUNDS, f"{how} or lower uwb_rate_hz")
    if not is_aruco_dictionary(o.dictionary):
        raise ValueError(f"dictionary {o.dictionary!r} is not an OpenCV ArUco dictionary (e.g. DICT_5X5_50)")
    count = aruco_dictionary(o.dictionary).bytesList.shape[0]
    if not 0 <= o.marker_id < count:
        raise ValueError(f"marker_id must lie in 0..{count - 1} for {o.dictionary}, got {o.marker_id}")
    timing = rl.make_realism(o.realism, o.realism_off, o.realism_set).timing
    rl.check_timing(timing, 1.0 / o.rate_hz)
    injected = inj.parse_inject(o.inject)
    inj.check_targets(injected, [str(o.marker_id)], WALLS, ())
    inj.check_frame_times(injected, abs(timing.latency_s) + 5.0 * timing.jitter_sigma_s, 1.0 / o.rate_hz, _last_frame_s(o))
    if o.variant == "path":
        half_x = o.track_length_m / 2.0 + o.turn_radius_m
        half_y = o.track_width_m / 2.0 + o.turn_radius_m
        if 2 * half_x >= o.room_length_m or 2 * half_y >= o.room_width_m:
            raise ValueError("the path does not fit in the room; shrink the track or enlarge the room")
        if round(o.duration_s * o.rate_hz) < 1:
            raise ValueError("duration_s · rate_hz < 1: no frame to record")
    elif o.static_point_m:
        try:
            x, y = (float(v) for v in o.static_point_m.split(","))
        except ValueError:
            raise ValueError(f"static_point_m must be 'x,y' in metres, got {o.static_point_m!r}") from None
        if not (0 < x < o.room_length_m and 0 < y < o.room_width_m):
            raise ValueError(f"static_point_m {o.static_point_m} is outside the room")
    elif (o.room_length_m <= 6 * o.grid_spacing_m) or (o.room_width_m <= 5 * o.grid_spacing_m):
        raise ValueError(f"a 6 × 5 grid every {o.grid_spacing_m} m does not fit in the room")


def _last_frame_s(o: Options) -> float:
    """The last camera frame's time after the first (as :func:`_schedule` places them)."""
    if o.variant == "path":
        return (round(o.duration_s * o.rate_hz) - 1) / o.rate_hz
    points = 1 if o.static_point_m else 30
    period_s = max(o.fixes_per_point / o.rate_hz, o.fixes_per_point / o.uwb_rate_hz) + GRID_GAP_S
    return (points - 1) * period_s + (o.fixes_per_point - 1) / o.rate_hz


def make_camera(o: Options) -> PinholeCamera:
    """Every wall camera: fx = fy from ``hfov_deg``, principal point at the image centre."""
    f = horizontal_fov_focal_px(o.width_px, o.hfov_deg)
    K = np.array([[f, 0.0, (o.width_px - 1) / 2.0], [0.0, f, (o.height_px - 1) / 2.0], [0.0, 0.0, 1.0]])
    return PinholeCamera(K, np.array([o.k1, 0.0, 0.0, 0.0, 0.0]), o.width_px, o.height_px)


def camera_poses(o: Options) -> dict[str, np.ndarray]:
    """``T_world_cam`` of each wall camera, looking at the room's centre on the floor."""
    centre = np.array([o.room_length_m / 2.0, o.room_width_m / 2.0, 0.0])
    return {wall: look_at(p, centre) for wall, p in wall_points(o.room_length_m, o.room_width_m, 0.05, o.cam_height_m).items()}


def anchor_positions(o: Options) -> dict[str, np.ndarray]:
    """World position of each anchor ``A_<wall>``."""
    return {f"A_{wall}": p for wall, p in wall_points(o.room_length_m, o.room_width_m, 0.02, o.anchor_height_m).items()}


def marker_corners_agv(o: Options) -> np.ndarray:
    """The roof code's corners TL, TR, BR, BL in the agv frame (face up, top edge forward)."""
    h = o.marker_side_m / 2.0
    return np.array([[-h, h, o.roof_height_m], [h, h, o.roof_height_m], [h, -h, o.roof_height_m], [-h, -h, o.roof_height_m]])


@dataclass(frozen=True)
class _Schedule:
    """When things happen (s from the start) and where the AGV is then."""

    frame_times_s: np.ndarray
    range_times_s: np.ndarray
    blocked: Callable[[float], bool]
    pose: Callable[[float], np.ndarray]


def _schedule(o: Options, n_anchors: int, rng: np.random.Generator) -> _Schedule:
    slot_s = 1.0 / (o.uwb_rate_hz * n_anchors)
    if o.variant == "path":
        track = RoundedRectangleTrack(
            o.track_length_m, o.track_width_m, o.turn_radius_m, (o.room_length_m / 2.0, o.room_width_m / 2.0)
        )

        def pose(t_s: float) -> np.ndarray:
            xy, direction, _ = track.at(np.array([o.speed_mps * t_s]))
            return agv_pose(xy[0], float(direction[0]) - np.pi / 2.0)

        frames = np.arange(round(o.duration_s * o.rate_hz)) / o.rate_hz
        ranges = np.arange(0.5 * slot_s, o.duration_s, slot_s)
        return _Schedule(frames, ranges, lambda t: o.block_start_s <= t < o.block_end_s, pose)

    points = (
        np.array([[float(v) for v in o.static_point_m.split(",")]]) if o.static_point_m else grid_points(o.grid_spacing_m)
    )
    headings = rng.uniform(-np.pi, np.pi, len(points))
    dwell_s = max(o.fixes_per_point / o.rate_hz, o.fixes_per_point / o.uwb_rate_hz)
    period_s = dwell_s + GRID_GAP_S
    frames = np.concatenate([p * period_s + np.arange(o.fixes_per_point) / o.rate_hz for p in range(len(points))])
    rounds = np.concatenate([p * period_s + np.arange(o.fixes_per_point) / o.uwb_rate_hz for p in range(len(points))])
    ranges = (rounds[:, None] + (np.arange(n_anchors) + 0.5) * slot_s).ravel()

    def grid_pose(t_s: float) -> np.ndarray:
        # The AGV moves on in the middle of the gap, so a capture a little before a point's
        # first fix (timing errors) sees it at that point already.
        index = min(max(int((t_s + GRID_GAP_S / 2.0) // period_s), 0), len(points) - 1)
        return agv_pose(points[index], float(headings[index]))

    return _Schedule(frames, ranges, lambda t: False, grid_pose)


def _standing(true_pose, *times_s: float) -> bool:
    """The true AGV pose is the same at every time of ``times_s`` (piecewise-constant poses of
    the static grid: the same at the start, the capture and the end of an exposure)."""
    first = true_pose(times_s[0])[0]
    return all(np.array_equal(true_pose(t)[0], first) for t in times_s[1:])


def _inject_details(injected, true_code, calib, captures, timing, stamps_ns, schedule, true_pose, T_agv_marker_true, mount) -> dict:
    """What each injected item affects, for the draws (:meth:`agvviz.sim.inject.InjectSpec.to_json`),
    by frame stamp (ns) of the frames written (not dropped): a marker item per camera the frames
    that show the roof code whole (``frames_in_view_ns``), a camera item the frames it affects
    (``frames_ns``: all, or those captured from ``from_s`` on, then with ``from_ns`` and the
    knocked true ``T_parent_cam_true_after``), a timing item its ``offset_ns`` and frames."""
    t0_ns = int(stamps_ns[0])
    details = {}
    written = {wall: [k for k in range(len(stamps_ns)) if not timing[wall].dropped[k]] for wall in WALLS}
    for target in injected.markers():
        corners = true_code.points_marker_m[:4]
        in_view = {}
        for wall in WALLS:
            ks = [k for k in written[wall] if not schedule.blocked(captures[wall][k])]
            points = [se3.transform_points(true_pose(captures[wall][k])[0] @ T_agv_marker_true, corners) for k in ks]
            in_view[wall] = inj.frames_in_view(
                calib[wall].true_camera, [mount(wall, k) for k in ks], np.array(points).reshape(len(ks), 4, 3), stamps_ns[ks]
            )
        details[("marker", target)] = {"frames_in_view_ns": in_view}
    for wall, item in injected.cameras().items():
        if item.from_s is None:
            details[("camera", wall)] = {"frames_ns": [int(stamps_ns[k]) for k in written[wall]]}
        else:
            details[("camera", wall)] = {
                "from_ns": t0_ns + int(round(item.from_s * 1e9)),
                "frames_ns": [int(stamps_ns[k]) for k in written[wall] if inj.knocked(item, captures[wall][k])],
                "T_parent_cam_true_after": inj.knocked_mount(calib[wall].T_parent_cam_true, item).tolist(),
            }
    for wall, item in injected.timings().items():
        details[("timing", wall)] = {"offset_ns": int(round(item.get("offset_ms") * 1e6)),
                                     "frames_ns": [int(stamps_ns[k]) for k in written[wall]]}
    return details


def record(writer, options: Options, seed: int, progress: Callable[[int, int], None] | None = None) -> None:
    """Write the whole recording to ``writer`` (an open :class:`RecordingWriter`).

    Random draws from ``np.random.default_rng(seed)`` in this order: static-grid headings,
    device clocks, scene grey levels, then per event in time order the NLOS draw and TWR noise
    of each range and the sensor (read) noise of each frame. The error sources draw from their
    own generators (:func:`agvviz.sim.realism.source_rng`; imaging: :func:`agvviz.sim.imaging.source_rngs`
    (seed, 0, 0) for the roof code's print, (seed, 1, frame index, camera index) per frame).
    """
    validate(options)
    o = options
    realism = rl.make_realism(o.realism, o.realism_off, o.realism_set)
    rng = np.random.default_rng(seed)
    camera = make_camera(o)
    cams = camera_poses(o)
    anchors = anchor_positions(o)
    anchor_ids = list(anchors)
    schedule = _schedule(o, len(anchor_ids), rng)
    tag_clock = DeviceClock(rng.uniform(0.0, 10.0), rng.normal(0.0, o.clock_drift_ppm))
    anchor_clocks = {a: DeviceClock(rng.uniform(0.0, 10.0), rng.normal(0.0, o.clock_drift_ppm)) for a in anchor_ids}
    roof_dn, black_dn, white_dn = rng.uniform([80.0, 20.0, 210.0], [120.0, 30.0, 230.0])
    code = roof_code(aruco_modules(o.dictionary, o.marker_id), str(o.marker_id), o.marker_side_m, 2)
    T_agv_marker = se3.make(np.eye(3), [0.0, 0.0, o.roof_height_m])  # as mapped
    T_agv_tag = se3.make(np.eye(3), [0.0, 0.0, o.tag_height_m])

    calib = rl.draw_calibration(
        realism.calibration, rl.source_rng(seed, "calibration"), {wall: (camera, cams[wall]) for wall in WALLS}
    )
    (marker_draw,) = rl.draw_map(realism.map, rl.source_rng(seed, "map"), [(str(o.marker_id), T_agv_marker, o.marker_side_m)])
    # Errors injected on purpose (option inject, agvviz.sim.inject), on top of the draws.
    injected = inj.parse_inject(o.inject)
    marker_draw = inj.apply_to_marker(marker_draw, injected.markers().get(str(o.marker_id)))
    calib = {wall: inj.apply_to_camera(d, injected.cameras().get(wall)) for wall, d in calib.items()}
    knocked_cams = {wall: inj.knocked_mount(cams[wall], injected.cameras().get(wall)) for wall in WALLS}
    true_code = rl.placed_as_drawn(code, marker_draw, np.eye(4))  # in the agv frame: placed per frame below
    T_agv_marker_true = marker_draw.T_parent_marker_true
    t0_ns = SIM_START_TIME_NS
    stamps_ns = np.array([t0_ns + int(round(float(t) * 1e9)) for t in schedule.frame_times_s], dtype=np.int64)
    timing = rl.draw_timing(realism.timing, rl.source_rng(seed, "timing"), len(stamps_ns), WALLS)
    timing = {wall: inj.apply_to_timing(t, injected.timings().get(wall)) for wall, t in timing.items()}
    bumps = rl.draw_bumps(realism.bumps, rl.source_rng(seed, "bumps"))
    imaging, jpeg_quality = rl.scenario_imaging(realism, o)
    image_seed = int(seed) % 2**64
    (printed_code,) = im.print_scene(
        FloorScene(codes=(true_code,), floor_dn=float(roof_dn), black_dn=float(black_dn), white_dn=float(white_dn)),
        imaging, image_seed, key=rl.PRINT_KEY,
    ).codes

    def true_pose(t_s: float) -> tuple[np.ndarray, float, float]:
        return bumps.apply(schedule.pose(t_s))

    def capture_s(k: int, wall: str) -> float:
        """Capture time of camera ``wall``'s frame k (s from the start; exactly the frame time
        without a delay)."""
        delay_ns = int(timing[wall].delay_ns[k])
        t_s = float(schedule.frame_times_s[k])
        return t_s if delay_ns == 0 else (int(stamps_ns[k]) - delay_ns - t0_ns) * 1e-9

    captures = {wall: [capture_s(k, wall) for k in range(len(stamps_ns))] for wall in WALLS}
    angles = {wall: [true_pose(t)[1:] for t in captures[wall]] for wall in WALLS}
    draws = rl.new_draws(realism, seed)
    draws.sources.update(
        calibration={wall: d.to_json() for wall, d in calib.items()},
        map=[marker_draw.to_json()],
        timing={"stamp_ns": stamps_ns, "cameras": {wall: t.to_json() for wall, t in timing.items()}},
        bumps={
            "field": bumps.to_json(),
            "capture_pitch_deg": {wall: np.degrees([a[0] for a in angles[wall]]) for wall in WALLS},
            "capture_roll_deg": {wall: np.degrees([a[1] for a in angles[wall]]) for wall in WALLS},
        },
        imaging=rl.imaging_record(imaging, jpeg_quality, o.time_samples, o.rows_per_band),
    )

    def mount(wall: str, k: int) -> np.ndarray:
        """Camera ``wall``'s true T_world_cam for its frame k (knocked from ``from_s`` on)."""
        return knocked_cams[wall] if inj.knocked(injected.cameras().get(wall), captures[wall][k]) else cams[wall]

    if injected:
        draws.sources["inject"] = injected.to_json(_inject_details(
            injected, true_code, calib, captures, timing, stamps_ns, schedule, true_pose, T_agv_marker_true, mount,
        ))
    if not realism.is_ideal or injected:  # an ideal recording stays message for message what it was
        writer.write_metadata(REALISM_METADATA, rl.metadata_values(draws))

    for wall in WALLS:
        writer.write_calibration(wall, calib[wall].recorded_camera, t0_ns)
    writer.write_tf_static(
        [(WORLD_FRAME, camera_frame(wall), calib[wall].T_parent_cam_recorded) for wall in WALLS]
        + [(AGV_FRAME, f"marker_{o.marker_id}", T_agv_marker), (AGV_FRAME, TAG_FRAME, T_agv_tag)],
        t0_ns,
    )
    writer.write_marker_map(
        {
            "dictionary": o.dictionary,
            "markers": [
                {"id": str(o.marker_id), "side_m": o.marker_side_m, "corners_world_m": marker_corners_agv(o), "frame": AGV_FRAME}
            ],
        },
        t0_ns,
    )
    writer.write_json(
        topics.UWB_ANCHORS_TOPIC, "agvviz.UwbAnchors", {"anchors": [{"id": a, "position_m": p} for a, p in anchors.items()]}, t0_ns
    )

    # Events: (time s, kind, detail): 0 camera frame (detail: frame index), 1 UWB range
    # (anchor), 2 truth at a capture time that is not a frame time (exact ns).
    events = sorted(
        [(float(t), 0, k) for k, t in enumerate(schedule.frame_times_s)]
        + [(float(t), 1, anchor_ids[i % len(anchor_ids)]) for i, t in enumerate(schedule.range_times_s)]
        + sorted({
            (captures[wall][k], 2, int(stamps_ns[k] - timing[wall].delay_ns[k]))
            for wall in WALLS for k in range(len(stamps_ns)) if timing[wall].delay_ns[k] != 0
        })
    )
    total = len(schedule.frame_times_s)
    done = 0
    for t_s, kind, detail in events:
        t_ns = detail if kind == 2 else t0_ns + int(round(t_s * 1e9))
        T_world_agv = true_pose(t_s)[0]
        writer.write_pose(topics.GROUND_TRUTH_TOPIC, T_world_agv, WORLD_FRAME, t_ns)
        if kind == 2:
            continue
        if kind == 1:
            anchor = detail
            tag_m = se3.transform_points(T_world_agv @ T_agv_tag, np.zeros((1, 3)))[0]
            nlos = rng.random() < o.nlos_probability
            excess = rng.uniform(o.nlos_excess_min_m, o.nlos_excess_max_m) if nlos else 0.0
            exchange = simulate_twr(
                float(np.linalg.norm(tag_m - anchors[anchor])), t_s, tag_clock, anchor_clocks[anchor], rng,
                reply_delay_s=o.reply_delay_us * 1e-6, timestamp_noise_s=o.timestamp_noise_ns * 1e-9,
                nlos_excess_m=excess,
            )
            writer.write_json(
                topics.UWB_RANGE_TOPIC, "agvviz.UwbRange",
                {"tag": TAG_ID, "anchor": anchor, "t1_ns": exchange.t1_ns, "t2_ns": exchange.t2_ns,
                 "t3_ns": exchange.t3_ns, "t4_ns": exchange.t4_ns, "range_m": exchange.range_m},
                t_ns,
            )
            continue
        k = detail
        for c, wall in enumerate(WALLS):
            t_capture_s = captures[wall][k]
            T_world_agv_capture = T_world_agv if t_capture_s == t_s else true_pose(t_capture_s)[0]
            T_world_marker_capture = T_world_agv_capture @ T_agv_marker_true
            codes = () if schedule.blocked(t_capture_s) else (placed(printed_code, T_world_marker_capture),)
            scene = FloorScene(codes=codes, floor_dn=float(roof_dn), black_dn=float(black_dn), white_dn=float(white_dn))

            def pose_at_time(t_exposure_s: float, t_capture_s=t_capture_s, M0=T_world_marker_capture, C=mount(wall, k)):
                """The wall camera as seen from the code held at its capture pose M0: the code
                at M(t) seen from C is the code at M0 seen from M0·M(t)⁻¹·C (the roof around
                it is uniform)."""
                if t_exposure_s == t_capture_s:
                    return C
                M = true_pose(t_exposure_s)[0] @ T_agv_marker_true
                return M0 @ se3.inverse(M) @ C

            rngs = im.source_rngs(image_seed, rl.FRAME_KEY, k, c)
            rngs["read_noise"] = rng  # the scenario's own stream: ideal frames are what they were
            t_start_s = rl.exposure_start_s(imaging, o.height_px, t_capture_s)
            t_end_s = t_start_s + (o.height_px - 1) * imaging.line_delay_s + imaging.exposure_s
            errors = imaging
            if t_start_s != t_capture_s and _standing(true_pose, t_start_s, t_capture_s, t_end_s):
                # The AGV stands still over the exposure (static grid): every exposure sample is
                # the capture pose, so a single render is the same image (to the float rounding of
                # the average over time samples: exact for 1, 2, 4 …), faster.
                errors, t_start_s = dataclasses.replace(imaging, exposure_s=0.0, line_delay_s=0.0), t_capture_s
            image = im.render_camera_frame(
                scene, calib[wall].true_camera, pose_at_time, t_start_s,
                errors, rngs, time_samples=o.time_samples, rows_per_band=o.rows_per_band, supersample=o.supersample,
            )
            if not timing[wall].dropped[k]:  # a dropped frame is rendered all the same: nothing else changes
                writer.write_image(wall, encode_jpeg(image, jpeg_quality), "jpeg", t_ns)
        done += 1
        if progress is not None:
            progress(done, total)
