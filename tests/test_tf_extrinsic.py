"""A camera extrinsic published on ``/tf`` (time-varying) instead of ``/tf_static``, in files
written by the Foxglove SDK.

* Published once (a common mistake: a one-shot static publisher on the wrong topic): every
  frame uses it — it is treated as static with a warning that says so (run summary, inspect) —
  and the per-frame errors equal the native recording's (same bytes, same extrinsic: 1e-6 m).
* Published at every frame, never changing: the same, the warning counts the messages.
* A link that really changes, with no sample near the frames: the frames are rejected as
  ``no_extrinsic`` (not ``no_calibration``: the calibration is there), the detail names the
  extrinsic link and suggests ``--extrinsic``; with ``--extrinsic`` they solve.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz.cli.main import app
from agvviz.errors import RunError
from agvviz.geometry import se3
from agvviz.model.frames import REJECT_NO_EXTRINSIC
from agvviz.app.run import run_recording
from agvviz.replay.run import SideInputs, prepare, replay_frames
from agvviz.settings import RunSettings

foxglove = pytest.importorskip("foxglove", reason="foxglove-sdk (test extra) not installed")


@pytest.fixture(scope="module")
def native(qr_small) -> Path:
    """The shared small qr_floor recording (tests/conftest.py ``QR_SMALL``)."""
    return qr_small


@pytest.fixture(scope="module")
def content(qr_small_content) -> dict:
    return qr_small_content


def frame_results(path, side: SideInputs | None = None) -> dict[int, tuple]:
    """time → (rejection, detail, position error m) of every frame, through the run's stages."""
    frames = replay_frames(path, dataclasses.replace(RunSettings(), tracking=False), side=side)
    return {r.log_time_ns: (r.rejected, r.reject_detail, r.position_error_m) for r in frames}


@pytest.fixture(scope="module")
def native_errors(native) -> dict:
    errors = frame_results(native)
    assert len(errors) == 4 and all(rej is None for rej, _, _ in errors.values()), errors
    return errors


def _ts(t_ns: int):
    return foxglove.messages.Timestamp(t_ns // 10**9, t_ns % 10**9)


def _transforms(T: np.ndarray, t_ns: int):
    m = foxglove.messages
    q = se3.to_quaternion_xyzw(T)
    return m.FrameTransforms(transforms=[m.FrameTransform(
        timestamp=_ts(t_ns), parent_frame_id="agv", child_frame_id="cam_front",
        translation=m.Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), rotation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]),
    )])


def write_file(path: Path, content: dict, tf: list[tuple[int, np.ndarray]]) -> Path:
    """Images, calibration and truth of ``content``; the extrinsic only on ``/tf`` at the
    given (stamp, T_agv_cam). (The SDK keeps one message type per topic per process: these
    topics carry the same types as in the other test files that log them.)"""
    m = foxglove.messages
    camera = content["calibration"]
    with foxglove.open_mcap(path, allow_overwrite=True):
        for t_ns, T in tf:
            foxglove.log("/tf", _transforms(T, t_ns), log_time=max(t_ns, 0))
        for (t, jpeg), (_, T_truth) in zip(content["images"], content["truth"]):
            foxglove.log("/front/calibration", m.CameraCalibration(
                timestamp=_ts(t), frame_id="cam_front", width=camera.width_px, height=camera.height_px,
                distortion_model="plumb_bob", D=camera.dist.tolist(), K=camera.K.ravel().tolist()), log_time=t)
            foxglove.log("/front/image_raw/compressed", m.CompressedImage(
                timestamp=_ts(t), frame_id="cam_front", format="jpeg", data=jpeg), log_time=t)
            q = se3.to_quaternion_xyzw(T_truth)
            foxglove.log("/ground_truth", m.PoseInFrame(timestamp=_ts(t), frame_id="world", pose=m.Pose(
                position=m.Vector3(x=T_truth[0, 3], y=T_truth[1, 3], z=T_truth[2, 3]),
                orientation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))), log_time=t)
    return path


def test_extrinsic_published_once_on_tf_is_static_with_a_warning(content, native_errors, tmp_path):
    t0 = content["images"][0][0]
    path = write_file(tmp_path / "lone_tf.mcap", content, [(t0, content["T_agv_cam"])])
    results = frame_results(path)
    assert sorted(results) == sorted(native_errors)
    for t, (_, _, error) in native_errors.items():
        assert results[t][0] is None, results[t]
        assert abs(results[t][2] - error) < 1e-6
    inspected = CliRunner().invoke(app, ["inspect", str(path)])
    assert inspected.exit_code == 0, inspected.stdout
    assert "replay: warning: camera front: its extrinsic link agv → cam_front is published on /tf" in inspected.stdout
    assert "only once" in inspected.stdout and "treated as static" in inspected.stdout
    outcome = run_recording(path, RunSettings(), tmp_path / "lone.rrd")
    assert outcome.summary["solved"] == 4
    assert any("only once" in w and "treated as static" in w for w in outcome.summary["warnings"]), outcome.summary


def test_constant_extrinsic_on_tf_at_every_frame(content, native_errors, tmp_path):
    tf = [(t, content["T_agv_cam"]) for t, _ in content["images"]]
    path = write_file(tmp_path / "constant_tf.mcap", content, tf)
    results = frame_results(path)
    for t, (_, _, error) in native_errors.items():
        assert results[t][0] is None and abs(results[t][2] - error) < 1e-6
    prepared = prepare(path, RunSettings())
    (note,) = prepared.replay.sync.notes.values()
    assert "4 times without ever changing" in note


def test_changing_extrinsic_without_a_pose_near_the_frames_is_no_extrinsic(content, tmp_path):
    """A link that changes (two samples 2 s before the first and after the last frame, beyond
    the 1 s interpolation gap): the frames are rejected as no_extrinsic, naming the link and
    --extrinsic; an --extrinsic side file solves them."""
    times = [t for t, _ in content["images"]]
    moved = se3.make(np.eye(3), np.array([0.01, 0.0, 0.0])) @ content["T_agv_cam"]
    path = write_file(tmp_path / "moving_tf.mcap", content,
                      [(times[0] - 2_000_000_000, content["T_agv_cam"]), (times[-1] + 2_000_000_000, moved)])
    results = frame_results(path)
    assert all(rej == REJECT_NO_EXTRINSIC for rej, _, _ in results.values()), results
    detail = next(iter(results.values()))[1]
    assert "no extrinsic" in detail and "agv → cam_front (2 samples" in detail
    assert "--extrinsic front=x,y,z,qx,qy,qz,qw" in detail
    with pytest.raises(RunError, match="4 frame.s. rejected as no_extrinsic .first: .*--extrinsic front="):
        run_recording(path, RunSettings(), tmp_path / "moving.rrd")
    from agvviz.recording.sidefiles import parse_extrinsic

    q = se3.to_quaternion_xyzw(content["T_agv_cam"])
    t = content["T_agv_cam"][:3, 3]
    text = ",".join(repr(float(v)) for v in [*t, *q])
    side = SideInputs(extrinsics={"front": parse_extrinsic("front", text, "agv")})
    assert all(rej is None for rej, _, _ in frame_results(path, side).values())


def test_hold_only_constant_links_and_forget_the_note_when_a_link_changes():
    """Fed message by message (the library's streaming use): a lone /tf link is held with a
    note; once a different sample arrives it is time-varying again and the note goes."""
    from agvviz.geometry.tf_buffer import PoseSeries
    from agvviz.replay.sync import SyncState
    from agvviz.model.messages import FrameTransformMsg, RecordedMessage

    series = PoseSeries()
    series.add(20, np.eye(4))
    series.add(10, np.eye(4))  # out of order, same pose
    assert series.is_constant()
    series.add(5, se3.make(np.eye(3), np.array([0.0, 0.0, 1e-9])))
    assert not series.is_constant()

    sync = SyncState(body_frame="agv")
    T1 = se3.make(np.eye(3), np.array([0.1, 0.0, 0.5]))
    sync.add(RecordedMessage("/tf", 0, "", [FrameTransformMsg("agv", "cam_front", T1, 0)], role="tf", stamp_ns=0))
    T, _, _ = sync.extrinsic("front", "cam_front", 10_000_000_000)  # 10 s later: held
    np.testing.assert_array_equal(T, T1)
    assert "only once" in sync.notes["cam_front"]
    T2 = se3.make(np.eye(3), np.array([0.2, 0.0, 0.5]))
    sync.add(RecordedMessage("/tf", 1, "", [FrameTransformMsg("agv", "cam_front", T2, 1)], role="tf", stamp_ns=1))
    T, _, why = sync.extrinsic("front", "cam_front", 10_000_000_000)
    assert T is None and "--extrinsic front=" in why and "agv → cam_front (2 samples" in why
    assert sync.notes == {}
