"""auv_under_ice — paper 002: an AUV under ice corrects its drifting INS/DVL navigation with
ArUco markers hung along its route, seen by a left and a right camera.

World: z up, the ice underside is the plane z = 0 (rendered as the grey "floor" above the
vehicle), the vehicle cruises ``depth_m`` below it. The route is a gentle S (heading
±``route_heading_amp_deg`` over an 80 m period) at ``speed_mps``. Every ``marker_spacing_m`` a
marker of side 0.6 m hangs ``marker_lateral_m`` to alternating sides of the route and
``marker_above_m`` above the vehicle's depth, facing the approaching vehicle, 2° off plumb.

Cameras (agvviz.sim.auv; the paper's Table 1 is an image, so these are our choice): ``left`` and
``right``, 1280×1024 px, f = 1100 px (≈60° horizontal), 0.3 m either side of the centre line,
toed out 10°; extrinsics on /tf_static. Frames at ``frame_rate_hz``.

Navigation (/agv/odometry, frame ``world`` — an INS is initialised in the world, paper eq 3):
dead reckoning of the true motion with a DVL scale error ``dvl_scale_error``, a gyro heading bias
``heading_bias_deg_s`` and heading noise ``heading_noise_deg_sqrt_s`` (random walk), so the error
grows with distance. Truth on /agv/ground_truth; marker map on /markers/map.

Replay: ``agvviz run <rec> --set correction=cnoem`` (or ``bundle``) runs paper 002's correction
cycle; its length is the run setting ``cycle_distance_m`` (default 3 m — the paper gives none).

Images (``images=true``): each frame is rendered exactly (agvviz.sim.render), then its
brightness fluctuates in time and across the image as under ice (paper §1.2): a global gain
1 + ``brightness_time_amp``·sin(2π·0.7 Hz·t + φ) times a moving caustic pattern
1 + ``brightness_space_amp``·sin(k·(u, v) − ω t), then sensor noise and JPEG.
``images=false`` writes the true corners plus N(0, ``sigma_px``²) noise on /markers/corners
(agvviz.CornerObservations) instead — corner-only, fast.

``mode=grid`` is the paper's simulation cell (§3.1, Table 3) in corner-only form: ``trials``
cycles, each a straight approach from a random start frame F towards one marker at distance
``grid_distance_m`` (5/10/15), lateral offset ``grid_lateral_fraction``·L (0/0.2/0.4), vertical
``grid_vertical_fraction``·L (0/0.1/0.2), at ``speed_mps`` (0.5/1/1.5), corner noise ``sigma_px``
(0.5/1/1.5 px), 10 Hz, over a 1.5 m cycle; the navigation starts with the paper's error
(attitude σ 1°, position σ 10 m) and then follows the true motion. Each /markers/corners message
carries its cell and trial. bench/bench_cnoem.py runs the full grid from the same generator.

Error sources (``realism``, :mod:`agvviz.sim.realism`; default ``typical``; route mode only —
grid mode is the paper's cell and takes ``ideal`` only: ``--set realism=ideal``): the recorded calibrations and camera
mounts are perturbed, the map holds the markers where they were meant to hang while images and
corners come from their true placement and print size; each camera's frame stamped t shows the
world at its capture time t − delay (``/agv/ground_truth`` then also gets a sample at each
capture time); dropped frames write neither image nor corners. Bumps and slip do not apply
under water (the route already pitches and rolls). With ``images=true`` the imaging effects of
the profile (:mod:`agvviz.sim.imaging`) apply too: printed markers, exposure while the vehicle
moves (capture instant: the middle of the middle row's exposure; ``time_samples``,
``rows_per_band``), the under-ice brightness on the exposure, then optics, shot and read noise
(``noise_sigma_dn`` set to other than its default overrides the profile's read noise) and JPEG
(the profile's quality unless ``jpeg_quality`` is set); with the ``ideal`` profile's imaging the
frames are exactly those made before the imaging effects existed. Draws in the
``agvviz.realism`` metadata (not under ``ideal``). Route mode takes faults injected on purpose
(``inject``, :mod:`agvviz.sim.inject`): markers moved (by id, every marker of that id), a camera's
extrinsic wrong or knocked from ``from_s`` on, a camera's time offset; recorded in the draws.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agvviz.model import topics
from agvviz.conventions import AGV_FRAME, WORLD_FRAME, camera_frame
from agvviz.geometry import se3
from agvviz.geometry.euler import Rx, Ry, Rz, matrix_from_hpr
from agvviz.markers.aruco import aruco_modules
from agvviz.model.studies import GridCell
from agvviz.settings import MAX_FRAMES, MAX_IMAGE_SAMPLES, check_total, setting
from agvviz.settings import validate as check_fields
from agvviz.sim import auv
from agvviz.sim import imaging as im
from agvviz.recording.schemas import REALISM_METADATA
from agvviz.sim import inject as inj
from agvviz.sim import realism as rl
from agvviz.sim.render import FloorScene, encode_jpeg, render_frame
from agvviz.sim.room import placed, roof_code

NAME = "auv_under_ice"
DESCRIPTION = "Paper 002: under-ice AUV, two cameras, ArUco markers along the route, drifting INS/DVL"

START_TIME_NS = 1_700_000_000_000_000_000
DICTIONARY = "DICT_4X4_50"
ROUTE_PERIOD_M = 80.0



@dataclass(frozen=True)
class Options:
    mode: str = setting("route", "route (a drive along markers) or grid (the paper's Table 3 cell, corner-only)")
    images: bool = setting(False, "route mode: render camera images (true) or write noisy corners only (false)")
    duration_s: float = setting(60.0, "route mode: length of the drive (s)", min=0.01, max=3600.0)
    speed_mps: float = setting(1.0, "vehicle speed (m/s); grid: 0.5, 1 or 1.5 in the paper", min=0.01, max=10.0)
    frame_rate_hz: float = setting(10.0, "camera frame rate (Hz)", min=0.1, max=200.0)
    depth_m: float = setting(10.0, "route mode: depth below the ice (m)", min=0.1, max=1000.0)
    route_heading_amp_deg: float = setting(15.0, "route mode: amplitude of the S-shaped heading (deg)", min=0.0, max=90.0)
    marker_spacing_m: float = setting(12.0, "route mode: distance between markers along the route (m)", min=0.1, max=1000.0)
    marker_lateral_m: float = setting(1.5, "route mode: markers' offset to alternating sides of the route (m)", min=-100.0, max=100.0)
    marker_above_m: float = setting(1.0, "route mode: markers' height above the vehicle's depth (m)", min=-100.0, max=100.0)
    sigma_px: float = setting(1.0, "corner noise σ (px) of corner-only output; grid: 0.5, 1 or 1.5 in the paper", min=0.0, max=100.0)
    dvl_scale_error: float = setting(0.01, "navigation: DVL speed scale error (fraction)", min=0.0, max=0.5)
    heading_bias_deg_s: float = setting(0.02, "navigation: gyro heading bias (deg/s)", min=-10.0, max=10.0)
    heading_noise_deg_sqrt_s: float = setting(0.01, "navigation: heading random walk (deg/√s)", min=0.0, max=10.0)
    brightness_time_amp: float = setting(0.35, "images: amplitude of the global brightness fluctuation in time", min=0.0, max=0.99)
    brightness_space_amp: float = setting(0.3, "images: amplitude of the moving caustic pattern across the image", min=0.0, max=0.99)
    noise_sigma_dn: float = setting(2.0, "images: sensor noise (digital numbers)", min=0.0, max=100.0)
    supersample: int = setting(2, "images: area-integration samples per pixel side", min=1, max=16)
    jpeg_quality: int = setting(92, "images: JPEG quality", min=1, max=100)
    time_samples: int = setting(2, "images: renders averaged over each row's exposure (motion blur accuracy)", min=1, max=64)
    rows_per_band: int = setting(32, "images: rows rendered at one time under a rolling shutter (smaller: more exact, slower)", min=1, max=8192)
    grid_distance_m: float = setting(10.0, "grid mode: marker distance L from F (m)", min=0.1, max=1000.0)
    grid_lateral_fraction: float = setting(0.2, "grid mode: lateral offset as a fraction of L", min=0.0, max=10.0)
    grid_vertical_fraction: float = setting(0.1, "grid mode: vertical offset as a fraction of L", min=0.0, max=10.0)
    trials: int = setting(100, "grid mode: number of cycles (the paper: 1000 per cell)", min=1, max=100000)
    realism: str = setting("typical", rl.HELP_PROFILE + " (route mode; grid mode: ideal)", rl.PROFILE_NAMES)
    inject: str = setting(
        "",
        "errors injected on purpose (route mode), ';'-separated: marker:<id>:dx_m=…,yaw_deg=…; "
        "camera:left|right:pitch_deg=…,dz_m=…[,from_s=…]; timing:left|right:offset_ms=… (keys in agvviz/sim/inject.py)",
    )
    realism_off: str = setting("", rl.HELP_OFF)
    realism_set: str = setting("", rl.HELP_SET)


def realism_sources(options: dict) -> tuple[str, ...]:
    """The error sources (:data:`agvviz.sim.realism.SOURCES`) this scenario applies under the
    recorded options ``options`` (a dict, as in a recording's metadata): no floor (bumps) and no wheels
    (slip) under water; image formation only with ``images=true``."""
    return ("calibration", "map", "timing") + (("imaging",) if options.get("images") else ())


def validate(options: Options) -> None:
    """Raise ``ValueError`` naming the first impossible option."""
    check_fields(options)
    o = options
    if o.mode not in ("route", "grid"):
        raise ValueError(f"mode must be route or grid, got {o.mode!r}")
    for name in ("duration_s", "speed_mps", "frame_rate_hz", "depth_m", "marker_spacing_m", "grid_distance_m"):
        if not getattr(o, name) > 0:
            raise ValueError(f"{name} must be > 0, got {getattr(o, name)}")
    for name in ("sigma_px", "dvl_scale_error", "heading_noise_deg_sqrt_s", "noise_sigma_dn", "grid_lateral_fraction", "grid_vertical_fraction"):
        if getattr(o, name) < 0:
            raise ValueError(f"{name} must be ≥ 0, got {getattr(o, name)}")
    if not (0 <= o.brightness_time_amp < 1 and 0 <= o.brightness_space_amp < 1):
        raise ValueError("brightness amplitudes must lie in [0, 1)")
    if o.supersample < 1 or o.trials < 1 or not 1 <= o.jpeg_quality <= 100:
        raise ValueError("supersample and trials must be ≥ 1 and jpeg_quality in 1..100")
    if o.mode == "grid" and o.images:
        raise ValueError("grid mode is corner-only; set images=false")
    realism = rl.make_realism(o.realism, o.realism_off, o.realism_set)
    rl.check_timing(realism.timing, 1.0 / o.frame_rate_hz)
    if o.mode == "grid" and realism.parameters() != rl.PROFILES["ideal"].parameters():
        raise ValueError("grid mode is the paper's simulation cell without error sources: add --set realism=ideal (the default profile, typical, applies to route mode)")
    injected = inj.parse_inject(o.inject)
    if injected and o.mode == "grid":
        raise ValueError("inject applies to route mode; grid mode is the paper's cell without error sources")
    if o.mode == "route":
        inj.check_targets(injected, [mid for mid, _ in route_markers(o)], list(auv.camera_mounts()), ())
        inj.check_frame_times(injected, abs(realism.timing.latency_s) + 5.0 * realism.timing.jitter_sigma_s,
                              1.0 / o.frame_rate_hz, int(o.duration_s * o.frame_rate_hz) / o.frame_rate_hz)
        check_total("frames = duration_s × frame_rate_hz", round(o.duration_s * o.frame_rate_hz), MAX_FRAMES,
                    "shorten duration_s or lower frame_rate_hz")
        if o.images:
            check_total("samples per image = width × height × supersample²",
                        auv.WIDTH_PX * auv.HEIGHT_PX * o.supersample**2, MAX_IMAGE_SAMPLES,
                        "lower supersample")


# -- route ---------------------------------------------------------------------------------------


def route_pose(o: Options, s_m: float) -> np.ndarray:
    """``T_world_agv`` at arc length ``s_m`` (closed form of the S route; heading ψ(s))."""
    amp = math.radians(o.route_heading_amp_deg)
    k = 2 * math.pi / ROUTE_PERIOD_M
    heading = amp * math.sin(k * s_m)
    # Integrate (−sin ψ, cos ψ) ds numerically on a fine grid (heading 0 → +y).
    n = max(2, int(s_m / 0.05) + 1)
    s = np.linspace(0.0, s_m, n)
    psi = amp * np.sin(k * s)
    x = -np.trapezoid(np.sin(psi), s) if s_m > 0 else 0.0
    y = np.trapezoid(np.cos(psi), s) if s_m > 0 else 0.0
    pitch = math.radians(1.0) * math.sin(2 * math.pi * s_m / 23.0)
    roll = math.radians(1.0) * math.sin(2 * math.pi * s_m / 17.0)
    return se3.make(matrix_from_hpr(heading, pitch, roll), [x, y, -o.depth_m])


def route_markers(o: Options) -> list[tuple[str, np.ndarray]]:
    """(id, T_world_marker) of every marker along the route driven in ``duration_s``."""
    length = o.speed_mps * o.duration_s
    out = []
    tilt = math.radians(auv.MARKER_TILT_DEG)
    for k in range(int(length / o.marker_spacing_m) + 1):
        s = (k + 0.8) * o.marker_spacing_m
        T = route_pose(o, s)
        side = 1.0 if k % 2 == 0 else -1.0
        heading = math.radians(o.route_heading_amp_deg) * math.sin(2 * math.pi * s / ROUTE_PERIOD_M)
        R_face = Rz(heading) @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]) @ Rx(tilt) @ Ry(tilt)
        position = T[:3, 3] + Rz(heading) @ np.array([side * o.marker_lateral_m, 0.0, o.marker_above_m])
        out.append((str(k % 50), se3.make(R_face, position)))
    return out


def navigation(o: Options, truth: list[np.ndarray], dt_s: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Dead reckoning of the true motion: the heading error e grows by bias·dt plus a random walk;
    each step's true displacement is scaled by (1 + DVL scale error) and turned by Rz(e); the
    navigation's attitude is the true one turned by Rz(e)."""
    nav = [truth[0].copy()]
    heading_err = 0.0
    bias = math.radians(o.heading_bias_deg_s)
    noise = math.radians(o.heading_noise_deg_sqrt_s) * math.sqrt(dt_s)
    for a, b in zip(truth, truth[1:]):
        heading_err += bias * dt_s + noise * rng.standard_normal()
        turn = Rz(heading_err)
        position = nav[-1][:3, 3] + turn @ (b[:3, 3] - a[:3, 3]) * (1.0 + o.dvl_scale_error)
        nav.append(se3.make(turn @ b[:3, :3], position))
    return nav


def _brightness(o: Options, t_s: float, shape: tuple[int, int], phase: float) -> np.ndarray:
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    g_time = 1.0 + o.brightness_time_amp * math.sin(2 * math.pi * 0.7 * t_s + phase)
    caustic = 1.0 + o.brightness_space_amp * np.sin(0.011 * u + 0.007 * v - 2.0 * t_s + phase)
    return np.float32(g_time) * caustic.astype(np.float32)


def _record_route(writer, o: Options, rng: np.random.Generator, progress, seed: int) -> None:
    realism = rl.make_realism(o.realism, o.realism_off, o.realism_set)
    cam = auv.camera()  # true
    mounts = auv.camera_mounts()  # true
    calib = rl.draw_calibration(realism.calibration, rl.source_rng(seed, "calibration"), {n: (cam, T) for n, T in mounts.items()})
    t0 = START_TIME_NS
    markers = route_markers(o)
    codes = [placed(roof_code(aruco_modules(DICTIONARY, int(mid)), mid, auv.MARKER_SIDE_M, 1), T) for mid, T in markers]
    marker_draws = rl.draw_map(realism.map, rl.source_rng(seed, "map"), [(c.marker_id, c.T_world_marker, c.side_m) for c in codes])
    # Errors injected on purpose (option inject, agvviz.sim.inject), on top of the draws.
    injected = inj.parse_inject(o.inject)
    marker_draws = [inj.apply_to_marker(d, injected.markers().get(d.marker_id)) for d in marker_draws]
    calib = {name: inj.apply_to_camera(d, injected.cameras().get(name)) for name, d in calib.items()}
    true_codes = [rl.placed_as_drawn(c, d) for c, d in zip(codes, marker_draws)]
    dt = 1.0 / o.frame_rate_hz
    n = int(o.duration_s * o.frame_rate_hz) + 1
    stamps_ns = np.array([t0 + int(round(k * dt * 1e9)) for k in range(n)], dtype=np.int64)
    timing = rl.draw_timing(realism.timing, rl.source_rng(seed, "timing"), n, list(mounts))
    timing = {name: inj.apply_to_timing(t, injected.timings().get(name)) for name, t in timing.items()}

    def mount(name: str, k: int) -> np.ndarray:
        """Camera ``name``'s true T_agv_cam for its frame k (knocked from ``from_s`` on)."""
        item = injected.cameras().get(name)
        capture_s = (int(stamps_ns[k]) - int(timing[name].delay_ns[k]) - t0) * 1e-9
        return inj.knocked_mount(mounts[name], item) if inj.knocked(item, capture_s) else mounts[name]
    imaging, jpeg_quality = rl.scenario_imaging(realism, o)
    # The ideal profile's imaging renders as before the imaging effects existed (render_frame,
    # quantised, then brightness and noise); any other renders through agvviz.sim.imaging.
    ideal_imaging = realism.imaging == rl.PROFILES["ideal"].imaging
    image_seed = int(seed) % 2**64
    draws = rl.new_draws(realism, seed)
    draws.sources.update(
        calibration={name: d.to_json() for name, d in calib.items()},
        map=[d.to_json() for d in marker_draws],
        timing={"stamp_ns": stamps_ns, "cameras": {name: t.to_json() for name, t in timing.items()}},
    )
    if o.images and not ideal_imaging:
        draws.sources["imaging"] = rl.imaging_record(imaging, jpeg_quality, o.time_samples, o.rows_per_band)
    if injected:
        draws.sources["inject"] = injected.to_json(_inject_details(injected, mounts, stamps_ns, timing, mount))
    if not realism.is_ideal or injected:  # an ideal recording stays message for message what it was
        writer.write_metadata(REALISM_METADATA, rl.metadata_values(draws))
    for name in mounts:
        writer.write_calibration(name, calib[name].recorded_camera, t0)
    writer.write_tf_static([(AGV_FRAME, camera_frame(n_), calib[n_].T_parent_cam_recorded) for n_ in mounts], t0)
    writer.write_marker_map(
        {
            "dictionary": DICTIONARY,
            "markers": [{"id": c.marker_id, "side_m": auv.MARKER_SIDE_M, "corners_world_m": c.points_world_m} for c in codes],
        },
        t0,
    )
    truth = [route_pose(o, o.speed_mps * k * dt) for k in range(n)]
    nav = navigation(o, truth, dt, rng)
    scene = FloorScene(codes=tuple(true_codes), floor_dn=150.0, black_dn=20.0, white_dn=215.0)
    if o.images and not ideal_imaging:
        scene = im.print_scene(scene, imaging, image_seed, key=rl.PRINT_KEY)
    phase = rng.uniform(0, 2 * math.pi)
    for k in range(n):
        t_ns = int(stamps_ns[k])
        captured = {}  # camera → true T_world_agv at its capture time
        for name in mounts:
            delay_ns = int(timing[name].delay_ns[k])
            captured[name] = truth[k] if delay_ns == 0 else route_pose(o, o.speed_mps * ((t_ns - delay_ns - t0) * 1e-9))
        extra = sorted({t_ns - int(timing[name].delay_ns[k]): name for name in mounts if timing[name].delay_ns[k] != 0}.items())
        for t_capture_ns, name in [e for e in extra if e[0] < t_ns]:
            writer.write_pose(topics.GROUND_TRUTH_TOPIC, captured[name], WORLD_FRAME, t_capture_ns)
        writer.write_pose(topics.GROUND_TRUTH_TOPIC, truth[k], WORLD_FRAME, t_ns)
        for t_capture_ns, name in [e for e in extra if e[0] > t_ns]:
            writer.write_pose(topics.GROUND_TRUTH_TOPIC, captured[name], WORLD_FRAME, t_capture_ns)
        writer.write_pose(topics.ODOMETRY_TOPIC, nav[k], WORLD_FRAME, t_ns)
        for c, name in enumerate(mounts):
            T_agv_cam = mount(name, k)
            T_world_cam = captured[name] @ T_agv_cam
            dropped = bool(timing[name].dropped[k])  # still rendered / drawn: other frames stay the same
            if o.images and not ideal_imaging:
                t_capture_s = (t_ns - int(timing[name].delay_ns[k]) - t0) * 1e-9

                def pose_at_time(t_s: float, t_capture_s=t_capture_s, T_capture=T_world_cam, T_agv_cam=T_agv_cam):
                    return T_capture if t_s == t_capture_s else route_pose(o, o.speed_mps * t_s) @ T_agv_cam

                rngs = im.source_rngs(image_seed, rl.FRAME_KEY, k, c)
                rngs["read_noise"] = rng
                irradiance = im.render_exposure(
                    scene, cam, pose_at_time, rl.exposure_start_s(imaging, cam.height_px, t_capture_s),
                    exposure_s=imaging.exposure_s, line_delay_s=imaging.line_delay_s, time_samples=o.time_samples,
                    rows_per_band=o.rows_per_band, supersample=o.supersample, pixel_aperture=imaging.pixel_aperture,
                )
                lit = irradiance * _brightness(o, k * dt, irradiance.shape, phase)  # the light under the ice
                frame = im.camera_frame(lit, cam, imaging, rngs)
                if not dropped:
                    writer.write_image(name, encode_jpeg(frame, jpeg_quality), "jpeg", t_ns)
                continue
            if o.images:
                image = render_frame(scene, cam, T_world_cam, rng, supersample=o.supersample, noise_sigma_dn=0.0)
                lit = image.astype(np.float32) * _brightness(o, k * dt, image.shape, phase)
                lit += np.float32(o.noise_sigma_dn) * rng.standard_normal(image.shape, dtype=np.float32)
                if not dropped:
                    writer.write_image(name, encode_jpeg(np.clip(np.rint(lit), 0, 255).astype(np.uint8), o.jpeg_quality), "jpeg", t_ns)
                continue
            seen = []
            T_cam_world = se3.inverse(T_world_cam)
            for c in true_codes:
                px = auv.visible_pixels(cam, T_cam_world @ c.T_world_marker, auv.marker_corners_marker(c.side_m))
                if px is not None:
                    seen.append({"id": c.marker_id, "corners_px": px + rng.normal(0.0, o.sigma_px, px.shape)})
            if seen and not dropped:
                writer.write_json(
                    topics.CORNERS_TOPIC, "agvviz.CornerObservations",
                    {"cam_name": name, "noise_sigma_px": o.sigma_px, "markers": seen}, t_ns,
                )
        if progress is not None:
            progress(k + 1, n)


def _inject_details(injected, mounts, stamps_ns, timing, mount) -> dict:
    """What the camera and timing items affect, for the draws (:meth:`agvviz.sim.inject.InjectSpec.to_json`):
    the stamps (ns) of the frames written (not dropped) that each changes (``frames_ns``; with
    ``from_s`` also ``from_ns`` and the knocked ``T_parent_cam_true_after``), a timing item's
    ``offset_ns``. A marker item carries its values only (its draw in ``map`` holds the moved pose)."""
    t0_ns = int(stamps_ns[0])
    details = {}
    for name, item in injected.cameras().items():
        written = [k for k in range(len(stamps_ns)) if not timing[name].dropped[k]]
        changed = [k for k in written if item.from_s is None or not np.array_equal(mount(name, k), mounts[name])]
        details[("camera", name)] = {"frames_ns": [int(stamps_ns[k]) for k in changed]}
        if item.from_s is not None:
            details[("camera", name)].update(from_ns=t0_ns + int(round(item.from_s * 1e9)),
                                             T_parent_cam_true_after=inj.knocked_mount(mounts[name], item).tolist())
    for name, item in injected.timings().items():
        details[("timing", name)] = {"offset_ns": int(round(item.get("offset_ms") * 1e6)),
                                     "frames_ns": [int(stamps_ns[k]) for k in range(len(stamps_ns)) if not timing[name].dropped[k]]}
    return details


def _record_grid(writer, o: Options, rng: np.random.Generator, progress) -> None:
    cam = auv.camera()
    mounts = auv.camera_mounts()
    t0 = START_TIME_NS
    for name, T in mounts.items():
        writer.write_calibration(name, cam, t0)
    writer.write_tf_static([(AGV_FRAME, camera_frame(n), T) for n, T in mounts.items()], t0)
    cell = GridCell(o.grid_distance_m, o.grid_lateral_fraction, o.grid_vertical_fraction, o.speed_mps, o.sigma_px)
    geometry = auv.cycle_geometry(cell, frame_rate_hz=o.frame_rate_hz)
    if not geometry.clean:
        raise ValueError(f"grid cell {cell.cell_id}: the marker is never fully in view of either camera")
    marker_id = "7"
    dt_ns = int(round(1e9 / o.frame_rate_hz))
    for trial_index in range(o.trials):
        trial = auv.draw_trial(geometry, o.sigma_px, rng, marker_id)
        corners_world = trial.sightings[0].points_world_m
        base = t0 + trial_index * (len(geometry.T_F_agv) + 20) * dt_ns
        writer.write_marker_map(
            {"dictionary": DICTIONARY, "markers": [{"id": marker_id, "side_m": auv.MARKER_SIDE_M, "corners_world_m": corners_world}]},
            base,
        )
        by_frame: dict[int, list] = {}
        for s in trial.sightings:
            by_frame.setdefault(s.frame_index, []).append(s)
        for k, T_F_agv in enumerate(geometry.T_F_agv):
            t_ns = base + (k + 1) * dt_ns
            writer.write_pose(topics.GROUND_TRUTH_TOPIC, trial.T_world_F_truth @ T_F_agv, WORLD_FRAME, t_ns)
            writer.write_pose(topics.ODOMETRY_TOPIC, trial.T_world_F_nav @ T_F_agv, WORLD_FRAME, t_ns)
            for s in by_frame.get(k, []):
                T_cam_marker = se3.inverse(trial.T_world_F_truth @ s.T_F_cam) @ (trial.T_world_F_truth @ geometry.T_F_marker)
                writer.write_json(
                    topics.CORNERS_TOPIC, "agvviz.CornerObservations",
                    {"cam_name": s.cam_name, "cell": cell.cell_id, "trial": trial_index, "noise_sigma_px": o.sigma_px,
                     "markers": [{"id": marker_id, "corners_px": s.pixels_px, "points_marker_m": auv.marker_corners_marker(),
                                  "T_cam_marker_truth": T_cam_marker}]},
                    t_ns,
                )
        if progress is not None:
            progress(trial_index + 1, o.trials)


def record(writer, options: Options, seed: int, progress: Callable[[int, int], None] | None = None) -> None:
    """Write the recording (see the module docstring). All draws from ``np.random.default_rng(seed)``."""
    validate(options)
    rng = np.random.default_rng(seed)
    if options.mode == "grid":
        _record_grid(writer, options, rng, progress)
    else:
        _record_route(writer, options, rng, progress, seed)
