"""Tracking predicted from odometry: the floor homography (agvviz.geometry.homography), the
jobs the replay builds (Replay.detect_job) and the detect stage's motion hint (SegmentDetector).

Frames: a small default ``qr_floor`` recording (3.2 s at 10 Hz = 32 frames: one whole tracking
segment of 30 and the first two of the next), at half resolution (640×512, f = 500 px) with the
scenario's lens distortion and odometry errors, recorded once for the module.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.geometry import euler, se3
from agvviz.geometry.homography import floor_homography, plane_homography
from agvviz.geometry.plane import DegenerateGeometryError
from agvviz.geometry.tf_buffer import PoseSeries
from agvviz.replay.detect.stage import DetectParams, SegmentDetector
from agvviz.replay.detect.pool import DetectionFeed
from agvviz.model.messages import PoseMsg
from agvviz.recording.reader import iter_messages
from agvviz.model.topics import ROLE_ODOMETRY
from agvviz.replay.run import prepare
from agvviz.settings import RunSettings
from agvviz.sim.trajectory import forward_camera_mount

FRAMES = 32
OVERRIDES = ["duration_s=3.2", "width_px=640", "height_px=512", "focal_px=500", "supersample=2", "realism=ideal"]
#: Tracked corners against full detection's on the same frame: both are ECC runs to the same
#: optimum from different starts (zxing's corners, the prediction), stopped when the
#: correlation changes by < 1e-5 in an iteration (tests/test_tracking.py). On these frames
#: (modules of 2.5–5 px) the stopping points differ by ≤ 0.013 px, with or without the hint
#: (measured); a corner on a neighbouring ECC optimum or a slipped template is ≥ 0.5 px off.
SAME_OPTIMUM_PX = 0.02


# -- the homography ------------------------------------------------------------------------------

def _project(K: np.ndarray, points_cam_m: np.ndarray) -> np.ndarray:
    assert np.all(points_cam_m[:, 2] > 0.1)  # in front of the camera
    uvw = points_cam_m @ K.T
    return uvw[:, :2] / uvw[:, 2:]


def _apply(H: np.ndarray, px: np.ndarray) -> np.ndarray:
    uvw = np.c_[px, np.ones(len(px))] @ H.T
    return uvw[:, :2] / uvw[:, 2:]


def _planar_pose(x_m: float, y_m: float, heading_rad: float) -> np.ndarray:
    return se3.make(euler.Rz(heading_rad), [x_m, y_m, 0.0])


#: Round-off of the homography check: pixels ≈ 10³ carried through K⁻¹, a 3×3 product and K
#: (cond(K) ≈ 2·10³ for f = 10³ px, c ≈ 600 px) in float64 (ε = 2.2·10⁻¹⁶) stay within
#: ≈ 10·ε·cond(K)·|x| ≈ 5·10⁻⁹ px of the projection computed the other way (measured ≤ 10⁻¹²).
#: A wrong sign of the plane offset or a transposed rotation is off by pixels.
ROUND_OFF_PX = 1e-8


def test_floor_homography_maps_floor_points_like_projecting_them():
    rng = np.random.default_rng(0)
    K = np.array([[1000.0, 0.0, 639.5], [0.0, 1000.0, 511.5], [0.0, 0.0, 1.0]])
    for case in range(20):
        T_agv_cam_from = forward_camera_mount(1.5, 1.0)
        # a rigid mount, or one that moved a little between the two frames (a /tf link)
        T_agv_cam_to = T_agv_cam_from if case % 2 == 0 else forward_camera_mount(1.45, 1.1)
        T_odom_agv_from = _planar_pose(*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi))
        step = _planar_pose(*rng.uniform(-0.15, 0.15, 2), np.radians(rng.uniform(-10, 10)))
        T_odom_agv_to = T_odom_agv_from @ step
        floor_agv_from = np.c_[rng.uniform(-0.5, 0.5, 50), rng.uniform(0.8, 2.0, 50), np.zeros(50)]
        px_from = _project(K, se3.transform_points(se3.inverse(T_agv_cam_from), floor_agv_from))
        T_cam_to_agv_from = se3.inverse(T_odom_agv_to @ T_agv_cam_to) @ T_odom_agv_from
        px_to = _project(K, se3.transform_points(T_cam_to_agv_from, floor_agv_from))

        H = floor_homography(K, T_odom_agv_from, T_odom_agv_to, T_agv_cam_from, T_agv_cam_to)
        np.testing.assert_allclose(_apply(H, px_from), px_to, rtol=0, atol=ROUND_OFF_PX)
        assert np.max(np.abs(px_to - px_from)) > 5.0  # the points did move: the check means something


def test_plane_homography_any_plane_two_cameras():
    """The general form: a tilted plane, two different camera matrices."""
    rng = np.random.default_rng(1)
    K_from = np.array([[800.0, 0.0, 320.0], [0.0, 820.0, 240.0], [0.0, 0.0, 1.0]])
    K_to = np.array([[600.0, 0.0, 300.0], [0.0, 600.0, 250.0], [0.0, 0.0, 1.0]])
    normal = np.array([0.2, -0.3, -1.0])  # unnormalised: the pair (n, d) scales together
    offset_m = -3.0 * np.linalg.norm(normal)  # the plane 3 m from the "from" camera
    T_to_from = se3.make(euler.Rz(0.1) @ euler.Rx(-0.05), [0.2, -0.1, 0.3])
    xy = rng.uniform(-0.5, 0.5, (30, 2))
    z = (offset_m - xy @ normal[:2]) / normal[2]  # points on the plane, in front of the camera
    points_from = np.c_[xy, z]
    H = plane_homography(K_to, K_from, T_to_from, normal, offset_m)
    np.testing.assert_allclose(
        _apply(H, _project(K_from, points_from)),
        _project(K_to, se3.transform_points(T_to_from, points_from)),
        rtol=0, atol=ROUND_OFF_PX,
    )


def test_camera_on_the_floor_is_degenerate():
    on_floor = forward_camera_mount(1.5, 1.0)
    on_floor[2, 3] = 0.0  # camera centre at floor height
    K = np.diag([500.0, 500.0, 1.0])
    with pytest.raises(DegenerateGeometryError, match="lies on the plane"):
        floor_homography(K, np.eye(4), _planar_pose(0.0, 0.1, 0.0), on_floor)
    with pytest.raises(DegenerateGeometryError, match="NaN"):
        floor_homography(K, np.full((4, 4), np.nan), np.eye(4), forward_camera_mount(1.5, 1.0))


# -- the detect stage ----------------------------------------------------------------------------

@dataclasses.dataclass
class Small:
    path: Path
    replay: object
    messages: list  # image messages
    jobs: list  # FrameJob per image, from Replay.detect_job
    full: list  # per frame: {payload: corners} of full detection (tracking off)


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Small:
    path = tmp_path_factory.mktemp("odometry") / "qr_floor.mcap"
    scenario_registry.record("qr_floor", path, seed=0, overrides=OVERRIDES)
    replay = prepare(path, RunSettings()).replay
    messages = [m for m in iter_messages(path) if m.topic.endswith("/image")]
    jobs = [replay.detect_job(m) for m in messages]
    full_detector = SegmentDetector(DetectParams(tracking=False))
    full = [{c.text: c.corners_px for c in full_detector.detect(job).codes} for job in jobs]
    assert len(jobs) == FRAMES
    return Small(path, replay, messages, jobs, full)


def _detect(jobs, params: DetectParams | None = None):
    detector = SegmentDetector(params or DetectParams())
    return [detector.detect(job) for job in jobs]


def _without_odometry(jobs):
    return [dataclasses.replace(job, T_odom_agv=None, T_agv_cam=None) for job in jobs]


def _with_odometry(jobs, T_odom_agv: list[np.ndarray]):
    return [dataclasses.replace(job, T_odom_agv=T) for job, T in zip(jobs, T_odom_agv, strict=True)]


def test_jobs_carry_the_recorded_odometry_and_the_camera_mount(small):
    odometry = {
        m.time_ns: m.value.T for m in iter_messages(small.path) if m.role == ROLE_ODOMETRY and isinstance(m.value, PoseMsg)
    }
    mount = forward_camera_mount(1.5, 1.0)  # qr_floor's defaults: cam_height_m, cam_lookahead_m
    for message, job in zip(small.messages, small.jobs):
        np.testing.assert_allclose(job.T_odom_agv, odometry[message.time_ns], rtol=0, atol=1e-12)
        np.testing.assert_allclose(job.T_agv_cam, mount, rtol=0, atol=1e-9)  # (a quaternion on file)
    # A recording without odometry: no poses in the job (and so no hint).
    replay = prepare(small.path, RunSettings()).replay
    replay.sync.odometry = PoseSeries()
    job = replay.detect_job(small.messages[0])
    assert job is not None and job.T_odom_agv is None and job.T_agv_cam is None


def test_frame_after_a_segment_start_is_tracked_with_odometry(small):
    params = DetectParams()
    assert params.segment_frames == 30
    with_hint = _detect(small.jobs)
    without = _detect(_without_odometry(small.jobs))
    # Without odometry the frame after a segment's first has no motion known: a keyframe.
    assert without[1].keyframe and "no motion known yet" in without[1].note
    assert without[31].keyframe and "no motion known yet" in without[31].note
    for k in (1, 31):  # the frame after each segment start
        assert with_hint[0 if k == 1 else 30].keyframe
        assert not with_hint[k].keyframe and with_hint[k].tracked >= 1, with_hint[k].note
    assert sum(d.keyframe for d in with_hint) < sum(d.keyframe for d in without)
    assert not any(d.note for d in with_hint)  # no check failed on the scenario's odometry


def test_tracked_corners_with_odometry_are_full_detections_optimum(small):
    compared = 0
    for d, full in zip(_detect(small.jobs), small.full):
        if d.keyframe:
            continue
        for code in d.codes:
            assert code.refine_note == "tracked"
            if code.text in full:  # a code at the image edge may be tracked but not decoded
                assert np.max(np.linalg.norm(code.corners_px - full[code.text], axis=1)) <= SAME_OPTIMUM_PX
                compared += 1
    assert compared >= 20


def _check_never_wrong(detections, full) -> tuple[int, int]:
    """Every tracked code is where full detection puts it; a keyframe is full detection.
    Returns (tracked frames, keyframes that fell back with a reason)."""
    tracked = fell_back = 0
    for d, reference in zip(detections, full):
        if d.keyframe:
            assert {c.text for c in d.codes} == set(reference)
            for c in d.codes:
                np.testing.assert_array_equal(c.corners_px, reference[c.text])
            fell_back += bool(d.note)
            continue
        tracked += 1
        for c in d.codes:
            if c.text in reference:
                assert np.max(np.linalg.norm(c.corners_px - reference[c.text], axis=1)) <= SAME_OPTIMUM_PX
    return tracked, fell_back


def test_grossly_wrong_odometry_falls_back_with_a_reason(small):
    """Frame 1's odometry 0.3 m off sideways (≈15 modules of these codes): the prediction is
    refused and the frame is fully detected, with the failed check named."""
    T_odom_agv = [job.T_odom_agv for job in small.jobs]
    T_odom_agv[1] = T_odom_agv[1] @ _planar_pose(0.3, 0.0, 0.0)
    detections = _detect(_with_odometry(small.jobs, T_odom_agv))
    assert detections[1].keyframe and detections[1].note.startswith("'AGV1;id=")
    _check_never_wrong(detections, small.full)


def test_odometry_20_percent_off_never_gives_wrong_corners(small):
    """Every odometry step 20 % too long (≈1 module per frame here) and turning 2° too far:
    each code is tracked to full detection's corners or the frame falls back to a keyframe."""
    T_odom_agv = [small.jobs[0].T_odom_agv]
    for previous, job in zip(small.jobs, small.jobs[1:]):
        step = se3.inverse(previous.T_odom_agv) @ job.T_odom_agv
        step[:3, 3] *= 1.2
        step[:3, :3] = step[:3, :3] @ euler.Rz(np.radians(2.0))
        T_odom_agv.append(T_odom_agv[-1] @ step)
    tracked, fell_back = _check_never_wrong(_detect(_with_odometry(small.jobs, T_odom_agv)), small.full)
    assert fell_back >= 1  # the wrong predictions were noticed


def _codes(detections):
    return [(c.text, np.asarray(c.corners_px).tolist(), c.refine_note) for c in detections.codes]


def test_detections_with_odometry_do_not_depend_on_workers(small):
    def feed(jobs: int) -> list:
        with DetectionFeed(small.replay.detect_params, small.replay.detect_job, jobs=jobs) as f:
            return [
                (m.time_ns, _codes(d), d.keyframe, d.tracked, d.note)
                for m, d in f.annotate(iter_messages(small.path))
                if d is not None
            ]

    serial, parallel = feed(1), feed(2)
    inline = [(m.time_ns, _codes(d), d.keyframe, d.tracked, d.note) for m, d in zip(small.messages, _detect(small.jobs))]
    assert len(serial) == FRAMES
    assert serial == parallel == inline
    assert not serial[1][2] and not serial[31][2]  # the hint reached the workers
