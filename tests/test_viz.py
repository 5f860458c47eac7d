"""agvviz.viz: log a synthetic run, save it, read it back with Rerun's own chunk API and
compare with what went in.

Exactness: scalars are stored as float64 and compared exactly; Points2D positions are
stored as float32, so they are compared with the input rounded to float32 (exactly); image
bytes are compared byte for byte.
"""

from __future__ import annotations

import dataclasses

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from rerun.chunk import RrdReader

from agvviz.geometry.camera import PinholeCamera
from agvviz.model.frames import (
    REJECT_NO_MARKER,
    REJECT_REPROJECTION,
    REJECT_SOLVER,
    FrameResult,
    LmIteration,
    MarkerObservation,
)
from agvviz.viz import paths
from agvviz.viz.readback import (
    document_json,
    encoded_images,
    line_strips2d,
    points2d,
    read_rrd,
    scalar_series,
    text_document,
    text_logs,
)
from agvviz.viz.log_frames import RunLogError
from agvviz.viz.run_logger import RunLogger

N_FRAMES = 20
CAM = "front"
RECORDING_ID = "test-viz-run"
REJECTED = {3: REJECT_NO_MARKER, 8: REJECT_SOLVER, 13: REJECT_REPROJECTION}
T0_NS = 1_700_000_000_000_000_000
MANIFEST = {"solver": "lm", "recording_sha256": "ab12cd34", "agvviz_version": "0.1.0", "seed": 7}
SUMMARY = {"position_rmse_m": 0.0123, "heading_p95_deg": 0.45, "frames_solved": 17, "frames_rejected": 3}


def _pose(x: float, y: float, heading_rad: float) -> np.ndarray:
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, 0.0]
    return T


def _marker_corners(cx: float, cy: float, side_m: float = 0.5) -> np.ndarray:
    h = side_m / 2
    return np.array(
        [[cx - h, cy + h, 0], [cx + h, cy + h, 0], [cx + h, cy - h, 0], [cx - h, cy - h, 0]], float
    )


def _frames(rng: np.random.Generator) -> list[FrameResult]:
    frames = []
    for i in range(N_FRAMES):
        image = np.full((24, 32, 3), 10 * i, np.uint8)
        fmt = "png" if i % 2 else "jpeg"
        ok, buf = cv2.imencode(".png" if fmt == "png" else ".jpg", image)
        assert ok
        truth = _pose(0.1 * i, 0.05 * i, 0.02 * i)
        rejected = REJECTED.get(i)
        observations = []
        if rejected != REJECT_NO_MARKER:
            for marker_id in ("m1", "m2")[: 1 + i % 2]:
                corners = rng.uniform(0, 30, (4, 2))
                observations.append(
                    MarkerObservation(
                        marker_id=marker_id,
                        payload=f"payload-{marker_id}",
                        corners_px=corners,
                        points_world_m=_marker_corners(1.0, 2.0),
                        reprojected_px=None if rejected else corners + rng.normal(0, 0.3, (4, 2)),
                    )
                )
        estimate = None if rejected else truth @ _pose(*rng.normal(0, 0.01, 2), rng.normal(0, 0.005))
        n_iter = 0 if rejected == REJECT_NO_MARKER else 2 + i % 4
        lm = [
            LmIteration(cost=10.0 / (k + 1) + i, reproj_rms_px=1.0 / (k + 1), damping=1e-3,
                        step_norm=0.1 / (k + 1), accepted=True)
            for k in range(n_iter)
        ]
        frames.append(
            FrameResult(
                index=i,
                log_time_ns=T0_NS + i * 50_000_000,
                cam_name=CAM,
                image_format=fmt,
                image_bytes=buf.tobytes(),
                observations=observations,
                rejected=rejected,
                reject_detail=f"detail of frame {i}" if rejected else "",
                T_world_agv=estimate,
                reproj_rms_px=None if rejected in (REJECT_NO_MARKER, REJECT_SOLVER) else 0.1 * i,
                lm_iterations=lm,
                T_world_agv_truth=truth,
                position_error_m=None if rejected else 0.001 * i,
                heading_error_deg=None if rejected else -0.01 * i,
            )
        )
    return frames


def _camera() -> PinholeCamera:
    return PinholeCamera(K=np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]), width_px=32, height_px=24)


def _write_run(path, frames) -> None:
    logger = RunLogger(path, recording_name="synthetic-lm", recording_id=RECORDING_ID)
    logger.log_world_static([("m1", _marker_corners(1.0, 2.0)), ("m2", _marker_corners(2.0, 2.0))])
    T_agv_cam = np.eye(4)
    T_agv_cam[:3, 3] = [0.0, 0.3, 1.2]
    logger.log_camera_static(CAM, _camera(), T_agv_cam)
    for frame in frames:
        logger.log_frame(frame)
    logger.log_manifest(MANIFEST)
    logger.log_summary(SUMMARY)
    logger.close()


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    frames = _frames(np.random.default_rng(20240501))
    path = tmp_path_factory.mktemp("viz") / "run.rrd"
    _write_run(path, frames)
    return path, frames, read_rrd(path)


def test_entity_tree_and_timelines(run):
    path, _, contents = run
    expected = {
        paths.WORLD, paths.MARKERS, paths.MARKERS_FILL, paths.AGV_TRUTH, paths.AGV_TRUTH_BODY,
        paths.AGV_CAMERA, paths.AGV_CAMERA_BODY, paths.camera(CAM), paths.image(CAM),
        paths.detected(CAM), paths.reprojected(CAM), paths.TRAJECTORY_TRUTH, paths.TRAJECTORY_CAMERA,
        paths.LM_LOG10_COST_PER_ITERATION, paths.LM_THIS_FRAME, paths.LM_COST, paths.LM_REPROJ_RMS_PX, paths.LM_DAMPING,
        paths.LM_STEP_NORM, paths.ERROR_POSITION_MM, paths.ERROR_HEADING_DEG, paths.ERROR_REPROJ_RMS_PX,
        paths.error_rejected(paths.ERROR_POSITION_MM, REJECT_NO_MARKER), paths.EVENTS_REJECTIONS, paths.RUN_MANIFEST,
        paths.RUN_SUMMARY,
    }
    assert expected <= contents.entity_paths, expected - contents.entity_paths
    reader = RrdReader(path)
    # Data timestamps only: no wall-clock log_time / log_tick timelines.
    timelines = {c.name for c in contents.store.schema().index_columns()}
    assert timelines == {paths.TIMELINE_TIME, paths.TIMELINE_FRAME, paths.TIMELINE_ELAPSED, paths.TIMELINE_LM_ITER}
    # The lm_iter timeline must not leak beyond the columns sent for it.
    leaked = {c.entity_path for c in reader.store().stream().filter(has_timeline=paths.TIMELINE_LM_ITER)}
    lm_columns = (paths.LM_COST, paths.LM_LOG10_COST, paths.LM_REPROJ_RMS_PX, paths.LM_DAMPING, paths.LM_STEP_NORM)
    assert leaked == {"/" + p for p in lm_columns}
    assert [r.recording_id for r in reader.recordings()] == [RECORDING_ID]
    assert len(reader.blueprints()) == 1  # the default blueprint travels in the file


def test_scalar_series_equal_input(run):
    _, frames, contents = run
    for entity, attr, scale in (
        (paths.ERROR_POSITION_MM, "position_error_m", 1000.0),
        (paths.ERROR_HEADING_DEG, "heading_error_deg", 1.0),
        (paths.ERROR_REPROJ_RMS_PX, "reproj_rms_px", 1.0),
    ):
        # A rejected frame has no value, even one it carries (the RMS it was rejected for).
        logged = [(f.index, scale * getattr(f, attr)) for f in frames if getattr(f, attr) is not None and f.solved]
        idx, values = scalar_series(contents, entity)
        np.testing.assert_array_equal(idx, [i for i, _ in logged])
        np.testing.assert_array_equal(values, [v for _, v in logged])
    # One marker series per reason on each plot; together they hold every rejected frame.
    for reason in set(REJECTED.values()):
        idx, _ = scalar_series(contents, paths.error_rejected(paths.ERROR_POSITION_MM, reason))
        np.testing.assert_array_equal(idx, sorted(i for i, r in REJECTED.items() if r == reason))
        # The same series on the time timeline carries each frame's log_time_ns.
        t_ns, _ = scalar_series(contents, paths.error_rejected(paths.ERROR_POSITION_MM, reason), timeline=paths.TIMELINE_TIME)
        np.testing.assert_array_equal(t_ns, [frames[i].log_time_ns for i in sorted(REJECTED) if REJECTED[i] == reason])


def test_lm_columns(run):
    _, frames, contents = run
    costs = [it.cost for f in frames for it in f.lm_iterations]
    iters = [k for f in frames for k in range(len(f.lm_iterations))]
    owners = [f.index for f in frames for _ in f.lm_iterations]
    k, values = scalar_series(contents, paths.LM_COST, timeline=paths.TIMELINE_LM_ITER)
    assert len(values) == sum(len(f.lm_iterations) for f in frames)
    np.testing.assert_array_equal(k, iters)
    np.testing.assert_array_equal(values, costs)
    frame_idx, _ = scalar_series(contents, paths.LM_COST, timeline=paths.TIMELINE_FRAME)
    np.testing.assert_array_equal(frame_idx, owners)
    _, step = scalar_series(contents, paths.LM_STEP_NORM, timeline=paths.TIMELINE_LM_ITER)
    np.testing.assert_array_equal(step, [it.step_norm for f in frames for it in f.lm_iterations])


def test_points2d_equal_input(run):
    _, frames, contents = run
    detected = points2d(contents, paths.detected(CAM))
    reprojected = points2d(contents, paths.reprojected(CAM))
    assert sorted(detected) == list(range(N_FRAMES))  # every frame logs (possibly empty) points
    for f in frames:
        want = [o.corners_px for o in f.observations]
        want = np.concatenate(want).astype(np.float32) if want else np.zeros((0, 2))
        np.testing.assert_array_equal(detected[f.index], want)
        want = [o.reprojected_px for o in f.observations if o.reprojected_px is not None]
        want = np.concatenate(want).astype(np.float32) if want else np.zeros((0, 2))
        np.testing.assert_array_equal(reprojected[f.index], want)
    assert detected[3].shape == (0, 2)  # no marker: points cleared


def test_images_stored_unchanged(run):
    _, frames, contents = run
    images = encoded_images(contents, paths.image(CAM))
    assert sorted(images) == list(range(N_FRAMES))
    for f in frames:
        blob, media_type = images[f.index]
        assert blob == f.image_bytes
        assert media_type == {"jpeg": "image/jpeg", "png": "image/png"}[f.image_format]


def test_documents_and_rejections(run):
    _, _, contents = run
    manifest = text_document(contents, paths.RUN_MANIFEST)
    assert "| solver | lm |" in manifest and "ab12cd34" in manifest
    summary = text_document(contents, paths.RUN_SUMMARY)
    assert "| position_rmse_m | 0.0123 |" in summary and "| frames_rejected | 3 |" in summary
    assert document_json(contents, paths.RUN_MANIFEST) == MANIFEST
    assert document_json(contents, paths.RUN_SUMMARY) == SUMMARY
    logs = text_logs(contents, paths.EVENTS_REJECTIONS)
    assert [frame for frame, _, _ in logs] == sorted(REJECTED)
    for frame, level, text in logs:
        assert level == "WARN"
        assert REJECTED[frame] in text and f"detail of frame {frame}" in text


def test_save_is_atomic_and_replaces_target(tmp_path):
    target = tmp_path / "run.rrd"
    target.write_bytes(b"old contents")
    frames = _frames(np.random.default_rng(1))[:3]
    _write_run(target, frames)
    assert os.listdir(tmp_path) == ["run.rrd"]  # no temporary file left behind
    assert sorted(points2d(target, paths.detected(CAM))) == [0, 1, 2]


def test_failed_run_leaves_target_untouched(tmp_path):
    target = tmp_path / "run.rrd"
    target.write_bytes(b"old contents")
    with pytest.raises(RuntimeError, match="pipeline broke"):
        with RunLogger(target, recording_name="x", recording_id="x") as logger:
            logger.log_frame(_frames(np.random.default_rng(1))[0])
            raise RuntimeError("pipeline broke")
    assert os.listdir(tmp_path) == ["run.rrd"]
    assert target.read_bytes() == b"old contents"


def test_bad_input_is_refused(tmp_path):
    from agvviz.errors import OutputError

    # A missing folder is created (issue 10); a folder that cannot be one is an OutputError.
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a folder"):
        RunLogger(tmp_path / "file" / "run.rrd", recording_name="bad", recording_id="bad")
    logger = RunLogger(tmp_path / "ok.rrd", recording_name="bad", recording_id="bad")
    frame = dataclasses.replace(_frames(np.random.default_rng(2))[0], image_format="bmp")
    with pytest.raises(RunLogError, match="image_format 'bmp'"):
        logger.log_frame(frame)
    with pytest.raises(RunLogError, match="shape"):
        logger.log_camera_static(CAM, _camera(), np.eye(3))
    with pytest.raises(RunLogError, match="no image size"):
        logger.log_camera_static(CAM, PinholeCamera(K=np.eye(3)), np.eye(4))
    logger.close()
    with pytest.raises(RunLogError, match="already closed"):
        logger.log_summary({})


def _rerun_cli() -> Path:
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip(f"rerun CLI not found next to {sys.executable}; needed for `rerun rrd compare`")
    return cli


def test_same_run_gives_equal_rrd(tmp_path):
    """Pinned recording id + data-only timelines + size-only chunking: two identical runs are
    equal under `rerun rrd compare --unordered`; a run with one changed error is not."""
    cli = _rerun_cli()
    for name in ("a.rrd", "b.rrd"):
        _write_run(tmp_path / name, _frames(np.random.default_rng(5)))
    changed = _frames(np.random.default_rng(5))
    changed[4] = dataclasses.replace(changed[4], position_error_m=changed[4].position_error_m + 1e-6)
    _write_run(tmp_path / "c.rrd", changed)

    def compare(x: str, y: str) -> int:
        return subprocess.run(
            [cli, "rrd", "compare", "--unordered", tmp_path / x, tmp_path / y],
            capture_output=True, timeout=60, check=False,
        ).returncode

    assert compare("a.rrd", "b.rrd") == 0
    assert compare("a.rrd", "c.rrd") != 0


def test_bad_frame_logs_nothing(tmp_path):
    """A frame refused half-way must not leave half of itself in the file."""
    logger = RunLogger(tmp_path / "partial.rrd", recording_name="partial", recording_id="partial")
    good, bad = _frames(np.random.default_rng(3))[:2]
    logger.log_frame(good)
    nan_obs = dataclasses.replace(bad.observations[0], reprojected_px=np.full((4, 2), np.nan))
    bad = dataclasses.replace(bad, observations=(nan_obs, *bad.observations[1:]))
    with pytest.raises(RunLogError, match="reprojected_px of marker 'm1' contains NaN"):
        logger.log_frame(bad)
    logger.close()
    assert sorted(encoded_images(tmp_path / "partial.rrd", paths.image(CAM))) == [good.index]


def test_lm_paths_equal_input(tmp_path):
    """Each LM record's reprojected points (lm_iteration_px) come back as one strip per point,
    start → final, float32 as rerun stores 2D points; a frame with a different number of
    iterations and points, and NaN (a pose with a point behind the camera), round-trip too."""
    rng = np.random.default_rng(11)
    frames = []
    for i, (n_iter, n_points) in enumerate(((3, 4), (5, 128), (2, 8))):
        frame = _frames(rng)[i]
        per_iteration = [rng.uniform(0, 32, (n_points, 2)) for _ in range(n_iter)]
        if i == 2:
            per_iteration[0] = np.full((n_points, 2), np.nan)
        lm = [LmIteration(cost=1.0, reproj_rms_px=1.0, damping=1e-3, step_norm=0.1, accepted=True)] * n_iter
        frames.append(dataclasses.replace(frame, rejected=None, lm_iterations=lm, lm_iteration_px=tuple(per_iteration),
                                          T_world_agv=frame.T_world_agv_truth))
    _write_run(tmp_path / "lm.rrd", frames)
    strips = line_strips2d(tmp_path / "lm.rrd", paths.lm_path(CAM))
    assert sorted(strips) == [0, 1, 2]
    for frame in frames:
        want = np.stack(frame.lm_iteration_px, axis=1).astype(np.float32)  # (points, iterations, 2)
        got = strips[frame.index]
        assert len(got) == len(want)
        for got_strip, want_strip in zip(got, want):
            np.testing.assert_array_equal(got_strip, want_strip)


def test_timelines_read_as_int64_equal_pyarrows_cast():
    """readback reads timestamp/duration timelines as their int64 values from the same buffers
    (no pyarrow.compute): equal to ``cast(pa.int64())``, with nulls and on a slice."""
    import pyarrow as pa

    from agvviz.viz.readback import as_int64

    values = [0, 1_700_000_000_123_456_789, None, -5, 2**62, None, 7]
    for kind in (pa.timestamp("ns"), pa.duration("ns"), pa.timestamp("us")):
        column = pa.array(values, type=kind)
        for part in (column, column.slice(2, 4), column.slice(1)):
            assert as_int64(part).equals(part.cast(pa.int64()))
            assert as_int64(part).to_pylist() == part.cast(pa.int64()).to_pylist()
