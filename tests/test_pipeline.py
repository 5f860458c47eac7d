"""The replay pipeline on hand-built messages: solved frames against truth, and every
rejection path recorded with its reason (never a crash, never a silent wrong pose)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agvviz.geometry import PinholeCamera, se3
from agvviz.markers.payload import QrPayload, encode_payload
from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, PoseMsg, RecordedMessage
from agvviz.model.frames import (
    REJECT_IMAGE,
    REJECT_NO_CALIBRATION,
    REJECT_NO_MARKER,
    REJECT_PAYLOAD,
    REJECT_REPROJECTION,
)
from agvviz.replay.graph import replay
from agvviz.settings import RunSettings
from agvviz.sim.qr_texture import make_floor_code, qr_symbol_modules
from agvviz.sim.render import FloorScene, encode_jpeg, render_frame
from agvviz.sim.trajectory import forward_camera_mount

CAM = "front"
T_AGV_CAM = forward_camera_mount(1.5, 1.0)
CAMERA = PinholeCamera(
    np.array([[1000.0, 0, 639.5], [0, 1000.0, 511.5], [0, 0, 1]]),
    np.array([-0.05, 0.01, 0, 0, 0]),
    1280,
    1024,
)
# The AGV at the origin heading +y: the code centred 1 m ahead fills the image centre.
T_WORLD_AGV = se3.make(np.eye(3), [0.0, 0.0, 0.0])


def _msg(topic: str, t_ns: int, value, schema: str = "") -> RecordedMessage:
    return RecordedMessage(topic=topic, log_time_ns=t_ns, schema_name=schema, value=value)


def _static_messages() -> list[RecordedMessage]:
    return [
        _msg(f"/cam/{CAM}/calibration", 0, CalibrationMsg(CAM, f"cam_{CAM}", CAMERA, "plumb_bob")),
        _msg("/tf_static", 0, [FrameTransformMsg("agv", f"cam_{CAM}", T_AGV_CAM)]),
    ]


def _frame(t_ns: int, jpeg: bytes) -> list[RecordedMessage]:
    return [
        _msg("/agv/ground_truth", t_ns, PoseMsg("world", T_WORLD_AGV)),
        _msg(f"/cam/{CAM}/image", t_ns, CompressedFrame(CAM, f"cam_{CAM}", "jpeg", jpeg)),
    ]


def _render(code, seed: int = 0) -> bytes:
    gray = render_frame(
        FloorScene(codes=(code,)), CAMERA, T_WORLD_AGV @ T_AGV_CAM, np.random.default_rng(seed)
    )
    return encode_jpeg(gray, quality=95)


GOOD_CODE = make_floor_code("G1", (0.0, 1.0), quarter_turns=1, side_m=0.5)


def test_solved_frame_matches_truth():
    results = list(replay(_static_messages() + _frame(1_000, _render(GOOD_CODE)), RunSettings()))
    assert len(results) == 1
    r = results[0]
    assert r.rejected is None, r.reject_detail
    assert r.used_marker_id == "G1"
    # ECC corners on a noise-free-ish synthetic frame are ~0.01 px: the pose is within a
    # millimetre; anything wrong in the transform chain (eqs 31–33) is off by decimetres.
    assert r.position_error_m < 2e-3
    assert abs(r.heading_error_deg) < 0.05
    obs = r.observations[0]
    assert np.max(np.linalg.norm(obs.reprojected_px - obs.corners_px, axis=1)) < 0.5


def test_lm_iterations_carry_their_reprojected_corners():
    """One (N, 2) array per LM record: the first is the start pose's reprojection, the last the
    solved pose's, which is what the frame reports as the used code's reprojected corners."""
    (r,) = replay(_static_messages() + _frame(1_000, _render(GOOD_CODE)), RunSettings(solver="lm"))
    assert r.rejected is None and len(r.lm_iterations) >= 2
    assert len(r.lm_iteration_px) == len(r.lm_iterations)
    used = next(o for o in r.observations if o.marker_id == r.used_marker_id)
    np.testing.assert_allclose(r.lm_iteration_px[-1][: len(used.reprojected_px)], used.reprojected_px, atol=1e-9)
    (closed,) = replay(_static_messages() + _frame(1_000, _render(GOOD_CODE)), RunSettings(solver="p4p"))
    assert closed.lm_iteration_px == ()


def test_frame_before_calibration_is_rejected():
    results = list(replay(_frame(1_000, _render(GOOD_CODE)), RunSettings()))
    assert results[0].rejected == REJECT_NO_CALIBRATION
    assert results[0].T_world_agv is None


def test_blank_and_corrupt_frames_are_rejected():
    blank = encode_jpeg(np.full((1024, 1280), 128, np.uint8))
    results = list(replay(_static_messages() + _frame(1, blank) + _frame(2, b"\xff\xd8garbage"), RunSettings()))
    # A frame whose JPEG header cannot be read is no image: rejected before decoding, as
    # inspect reports it (contract.frame_problem).
    assert [r.rejected for r in results] == [REJECT_NO_MARKER, REJECT_IMAGE]
    assert all(r.T_world_agv is None and r.position_error_m is None for r in results)


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os').system('echo pwned')",
        "AGV1;id=X;mm=0,0;0,0;0,0;0,0",  # degenerate: coincident points
        "AGV9;id=X;mm=0,0;500,0;500,-500;0,-500",  # unknown version
    ],
)
def test_hostile_payload_is_a_recorded_rejection(text):
    hostile = dataclasses.replace(GOOD_CODE, payload=text, modules=qr_symbol_modules(text))
    results = list(replay(_static_messages() + _frame(1, _render(hostile)), RunSettings()))
    assert results[0].rejected == REJECT_PAYLOAD, results[0].reject_detail
    assert "payload refused" in results[0].reject_detail
    assert results[0].T_world_agv is None


def test_payload_that_lies_about_its_position_fails_the_reprojection_check():
    """Four image points fix a homography, not a pose: a payload whose points are not the
    printed square (BR claimed 8 cm off) leaves pixels of residual, and the frame is rejected."""
    pts = GOOD_CODE.points_world_m.copy()
    pts[2, :2] += [0.08, 0.0]  # BR corner claimed 8 cm off: a non-square, non-projective lie
    text = encode_payload(QrPayload("L1", pts))
    lying = dataclasses.replace(GOOD_CODE, payload=text, modules=qr_symbol_modules(text))
    results = list(replay(_static_messages() + _frame(1, _render(lying)), RunSettings(max_reproj_px=1.0)))
    assert results[0].rejected == REJECT_REPROJECTION, (results[0].rejected, results[0].reject_detail)
    assert results[0].T_world_agv is None
