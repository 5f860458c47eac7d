"""The detect stage (agvviz.replay.detect.stage), its worker pool (detect_pool) and its cache
(detect_cache): detections — and so runs — are the same whoever computes them.

Equality here is exact, not within a tolerance: the same frames go through the same code in
the same segments, whether in this process, in worker processes or read back from Parquet
(float64 round-trips exactly), so any difference is a bug in the plumbing.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from agvviz import scenarios as scenario_registry
from agvviz.replay.detect import cache as detect_cache
from agvviz.replay.detect.stage import DetectParams, SegmentDetector, detection_settings
from agvviz.replay.detect.pool import DetectionFeed
from agvviz.replay.solve import Replay
from agvviz.recording.reader import iter_messages
from agvviz.app.run import run_recording
from agvviz.replay.run import detect_recording, prepare
from agvviz.settings import RunSettings

# 4 s at 10 Hz = 40 frames: several segments of the default keyframe interval (10).
SMALL = ["duration_s=4", "rate_hz=10", "realism=ideal"]


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("detect") / "qr_floor.mcap"
    scenario_registry.record("qr_floor", path, seed=5, overrides=SMALL)
    return path


@pytest.fixture(scope="module")
def uncached_run(recording, tmp_path_factory):
    """The recording replayed with the default settings (solver lm), detecting in this process
    without any cache: the reference that cached and re-detected runs must equal."""
    outcome = run_recording(recording, RunSettings(solver="lm"), tmp_path_factory.mktemp("uncached") / "e.rrd",
                            cache_dir=False, jobs=1)
    assert outcome.timing["detection_source"] == "detected"
    return outcome


@pytest.fixture(scope="module")
def detected_cache(recording, tmp_path_factory) -> tuple[Path, Path]:
    """(cache folder, entry path relative to it) after `detect_recording` with the default
    settings filled a fresh cache. Tests that damage the entry work on a copy
    (:func:`_copy_cache`), so each starts from the same freshly detected entry."""
    cache = tmp_path_factory.mktemp("detected") / "cache"
    info = detect_recording(recording, RunSettings(), cache_dir=cache, jobs=1)
    assert info["source"] == "detected" and info["frames"] == 40
    return cache, Path(info["cache"]).relative_to(cache)


def _copy_cache(detected_cache, tmp_path: Path) -> tuple[Path, Path]:
    """A private copy of the freshly detected cache: (cache folder, its entry)."""
    source, entry = detected_cache
    cache = tmp_path / "cache"
    shutil.copytree(source, cache)
    return cache, cache / entry


def _codes(detections):
    return [
        (c.kind, c.text, c.aruco_id, np.asarray(c.corners_px).tolist(), c.refine_method)
        for c in detections.codes
    ]


def _feed_detections(recording: Path, settings: RunSettings, jobs: int) -> list:
    prepared = prepare(recording, settings)
    feed = DetectionFeed(prepared.replay.detect_params, prepared.replay.detect_job, jobs=jobs)
    with feed:
        out = [
            (m.topic, m.time_ns, _codes(d), d.keyframe)
            for m, d in feed.annotate(iter_messages(recording))
            if d is not None
        ]
    return out


def _inline_detections(recording: Path, settings: RunSettings) -> list:
    """The replay detecting in process, frame by frame (no feed), as `pipeline.replay` does."""
    prepared = prepare(recording, settings)
    replay = prepared.replay
    detectors: dict[str, SegmentDetector] = {}
    out = []
    for message in iter_messages(recording):
        job = replay.detect_job(message) if message.topic.endswith("/image") else None
        if job is None:
            continue
        detector = detectors.setdefault(job.cam_name, SegmentDetector(replay.detect_params))
        d = detector.detect(job)
        out.append((message.topic, message.time_ns, _codes(d), d.keyframe))
    return out


@pytest.mark.parametrize("tracking", [False, True])
def test_detections_do_not_depend_on_workers(recording, tracking):
    settings = RunSettings(tracking=tracking)
    serial = _feed_detections(recording, settings, jobs=1)
    parallel = _feed_detections(recording, settings, jobs=2)
    inline = _inline_detections(recording, settings)
    assert len(serial) == 40
    assert serial == parallel == inline
    keyframes = sum(k for *_, k in serial)
    if tracking:
        # One keyframe per segment of 10 frames at least; tracking must carry most frames
        # of a smooth drive (a fallback makes a frame a keyframe, so ≤ 40).
        assert 4 <= keyframes < 40
    else:
        assert keyframes == 40


def test_tracked_frames_undistort_only_their_codes_regions_with_the_same_result(recording, monkeypatch):
    """A tracked frame of a camera with distortion undistorts only the boxes its tracker reads
    (stage._undistorted_boxes); the detections must equal those of the whole frame undistorted,
    exactly (each undistorted pixel is a function of its own map entry)."""
    from agvviz.replay.detect import stage

    settings = RunSettings(tracking=True)
    boxes_seen = []

    def counted(gray, model, boxes):
        boxes_seen.append(list(boxes))
        return real(gray, model, boxes)

    real = stage._undistorted_boxes
    monkeypatch.setattr(stage, "_undistorted_boxes", counted)
    partial = _inline_detections(recording, settings)
    tracked = sum(not k for *_, k in partial)
    assert tracked >= 20 and len(boxes_seen) >= tracked  # the tracked frames took the partial path
    height, width = 1024, 1280
    assert all(0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height for b in boxes_seen for x0, y0, x1, y1 in b)
    assert max(sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in b) for b in boxes_seen) < 0.5 * width * height
    monkeypatch.setattr(stage, "_undistorted_boxes", lambda gray, model, boxes: stage._undistorted(gray, model))
    whole = _inline_detections(recording, settings)
    assert partial == whole


def test_detection_settings_are_what_detection_depends_on():
    assert detection_settings(RunSettings(solver="p4p", fusion="kalman")) == detection_settings(RunSettings())
    assert detection_settings(RunSettings(refine="subpix")) != detection_settings(RunSettings())
    assert DetectParams.of(RunSettings(tracking=True, keyframe_every=7), None).segment_frames == 35
    assert DetectParams.of(RunSettings(tracking=True, keyframe_every=50), None).segment_frames == 50
    assert DetectParams.of(RunSettings(tracking=True), "DICT_4X4_50").segment_frames == 4
    assert DetectParams.of(RunSettings(tracking=False), None).segment_frames == 4


def _summary_without_timing(summary: dict) -> dict:
    return json.loads(json.dumps(summary, default=str))


def test_second_run_reuses_detections_and_equals_the_first(recording, uncached_run, tmp_path):
    cache = tmp_path / "cache"
    first = run_recording(recording, RunSettings(solver="lm"), tmp_path / "a.rrd", cache_dir=cache, jobs=2)
    assert first.timing["detection_source"] == "detected"
    entries = list(cache.rglob("*.parquet"))
    assert len(entries) == 1
    again = run_recording(recording, RunSettings(solver="lm"), tmp_path / "b.rrd", cache_dir=cache)
    assert again.timing["detection_source"] == "cache"
    assert _summary_without_timing(again.summary) == _summary_without_timing(first.summary)
    # Another solver: the same detections, a different pose.
    other = run_recording(recording, RunSettings(solver="p4p"), tmp_path / "c.rrd", cache_dir=cache)
    assert other.timing["detection_source"] == "cache"
    assert other.summary["solved"] > 30
    # Another refinement is another entry.
    run_recording(recording, RunSettings(refine="subpix"), tmp_path / "d.rrd", cache_dir=cache)
    assert len(list(cache.rglob("*.parquet"))) == 2
    # No cache: the same answer again.
    # (uncached_run: the same settings with cache_dir=False, jobs=1, shared with
    # test_cache_mismatch_falls_back_to_detecting.)
    uncached = uncached_run
    assert uncached.timing["detection_source"] == "detected"
    assert _summary_without_timing(uncached.summary) == _summary_without_timing(first.summary)
    rerun = shutil.which("rerun") or str(Path(__file__).resolve().parents[1] / ".venv/bin/rerun")
    if Path(rerun).exists():
        for other_rrd in (tmp_path / "b.rrd", uncached.out_path):
            result = subprocess.run(
                [rerun, "rrd", "compare", "--unordered", str(tmp_path / "a.rrd"), str(other_rrd)],
                capture_output=True, text=True, timeout=120,
            )
            assert result.returncode == 0, result.stdout + result.stderr


def test_damaged_cache_entry_is_a_miss_and_is_rewritten(recording, detected_cache, tmp_path):
    cache, entry = _copy_cache(detected_cache, tmp_path)
    assert detect_recording(recording, RunSettings(), cache_dir=cache)["source"] == "cache"
    entry.write_bytes(b"PAR1 not really parquet")
    assert detect_cache.load(entry) is None
    outcome = run_recording(recording, RunSettings(), tmp_path / "run.rrd", cache_dir=cache, jobs=1)
    assert outcome.timing["detection_source"] == "detected"
    assert detect_cache.load(entry) is not None
    assert detect_recording(recording, RunSettings(), cache_dir=cache)["source"] == "cache"


def test_cache_key_follows_version_and_inputs(monkeypatch):
    params = DetectParams()
    key = detect_cache.cache_key(params, {"images": {"front": "/cam/front/image"}})
    assert key == detect_cache.cache_key(params, {"images": {"front": "/cam/front/image"}})
    assert key != detect_cache.cache_key(params, {"images": {"front": "/other"}})
    assert key != detect_cache.cache_key(DetectParams(refine="none"), {"images": {"front": "/cam/front/image"}})
    monkeypatch.setattr(detect_cache, "__version__", "999.0")
    assert key != detect_cache.cache_key(params, {"images": {"front": "/cam/front/image"}})


def test_cache_mismatch_falls_back_to_detecting(recording, detected_cache, uncached_run, tmp_path):
    """A cache entry whose frames do not match the recording (it cannot happen for a
    content-keyed entry unless it was tampered with) is abandoned with a warning."""
    cache, entry = _copy_cache(detected_cache, tmp_path)
    frames = detect_cache.load(entry)
    shifted = [type(f)(f.seq, f.cam_name, f.log_time_ns + (1 if f.seq == 5 else 0), f.detections) for f in frames]
    detect_cache.save(entry, shifted)
    outcome = run_recording(recording, RunSettings(), tmp_path / "run.rrd", cache_dir=cache, jobs=1)
    assert any("detection cache did not match" in w for w in outcome.summary["warnings"])
    reference = uncached_run  # RunSettings() (solver lm), cache_dir=False, jobs=1
    assert outcome.summary["solved"] == reference.summary["solved"]


def test_replay_without_a_feed_detects_in_process(recording):
    """`Replay.feed` without detections (tests, benches, in-order callers) detects itself."""
    replay = Replay(RunSettings(tracking=False))
    frames = [f for f in (replay.feed(m) for m in iter_messages(recording)) if f is not None]
    assert len(frames) == 40 and sum(f.solved for f in frames) >= 36


@pytest.mark.parametrize("jobs", [1, 2])
def test_feed_hands_every_detection_over_once_the_last_segment_is_back(recording, jobs):
    """``on_complete`` (a sweep's lead stores its cache then, and its other settings start):
    called once, before the replay has taken the last frames, with exactly the frames the feed
    keeps for the cache by the end — the same numbers, cameras, times and detections."""
    prepared = prepare(recording, RunSettings())
    feed = DetectionFeed(prepared.replay.detect_params, prepared.replay.detect_job, jobs=jobs)
    handed, frames_left = [], []
    feed.on_complete = lambda frames: handed.append(list(frames))
    with feed:
        for message, detections in feed.annotate(iter_messages(recording)):
            if detections is not None and handed and not frames_left:
                frames_left.append(len(feed.frames))  # frames handed out when it was called
    assert len(handed) == 1
    assert frames_left and frames_left[0] < len(feed.frames)  # before the replay was through
    assert [(f.seq, f.cam_name, f.log_time_ns) for f in handed[0]] == [
        (f.seq, f.cam_name, f.log_time_ns) for f in feed.frames]
    assert [_codes(f.detections) for f in handed[0]] == [_codes(f.detections) for f in feed.frames]


def test_cache_entry_is_written_and_read_a_row_group_at_a_time(detected_cache, tmp_path, monkeypatch):
    """An entry holds FRAMES_PER_ROW_GROUP frames per Parquet row group, so what Arrow holds
    while it is written or read does not grow with the recording (issue 27); it reads back
    exactly, as does an entry written in one row group (by agvviz before this change)."""
    import pyarrow.parquet as pq

    _, entry = _copy_cache(detected_cache, tmp_path)
    frames = detect_cache.load(entry)
    assert len(frames) == 40
    monkeypatch.setattr(detect_cache, "FRAMES_PER_ROW_GROUP", 16)
    grouped = tmp_path / "grouped.parquet"
    detect_cache.save(grouped, frames)
    assert pq.ParquetFile(grouped).num_row_groups == 3  # 16 + 16 + 8
    monkeypatch.setattr(detect_cache, "FRAMES_PER_ROW_GROUP", 1000)
    whole = tmp_path / "whole.parquet"
    detect_cache.save(whole, frames)
    assert pq.ParquetFile(whole).num_row_groups == 1
    for path in (grouped, whole):
        back = detect_cache.load(path)
        assert [(f.seq, f.cam_name, f.log_time_ns) for f in back] == [(f.seq, f.cam_name, f.log_time_ns) for f in frames]
        assert [_codes(f.detections) for f in back] == [_codes(f.detections) for f in frames]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "grouped.parquet", "whole.parquet"]  # no temporary left


def _distorted_calibration(width_px: int = 320) -> "CalibrationMsg":
    from agvviz.geometry import PinholeCamera
    from agvviz.model.messages import CalibrationMsg

    K = np.array([[300.0, 0.0, width_px / 2], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
    camera = PinholeCamera(K, np.array([-0.2, 0.05, 0.001, -0.001, 0.0]), width_px, 240)
    return CalibrationMsg("front", "cam_front", camera, "plumb_bob")


def test_the_solve_stage_does_not_build_undistortion_maps(monkeypatch):
    """Only detection undistorts: the solve stage's model has the camera without the maps (≈20-30
    ms and 10 MB for 1280×1024, in every process that solves); detection's then builds them,
    equal to OpenCV's own."""
    import cv2

    from agvviz.replay.detect import stage

    monkeypatch.setattr(stage, "_CAMERA_MODELS", {})
    built = []
    real = stage.cv2.initUndistortRectifyMap
    monkeypatch.setattr(stage.cv2, "initUndistortRectifyMap", lambda *a: built.append(a) or real(*a))
    calibration = _distorted_calibration()
    solving = stage.camera_model(calibration, maps=False)
    assert solving.camera is calibration.camera and solving.undistort_maps is None and not solving.maps_built
    assert built == []
    detecting = stage.camera_model(calibration)
    assert detecting.camera is calibration.camera and detecting.maps_built and len(built) == 1
    c = calibration.camera
    expected = real(c.K, c.dist, None, c.K, (c.width_px, c.height_px), cv2.CV_32FC2)
    np.testing.assert_array_equal(detecting.undistort_maps[0], expected[0])
    assert stage.camera_model(calibration, maps=False) is detecting  # built once, kept
    assert stage.camera_model(calibration) is detecting and len(built) == 1


def test_maps_that_cannot_be_built_reject_the_frames_as_uncalibrated(monkeypatch):
    from agvviz.model.frames import REJECT_NO_CALIBRATION
    from agvviz.replay.detect import stage

    def fails(*args):
        raise stage.cv2.error("OpenCV(4) error: (-4:Insufficient memory) Failed to allocate")

    monkeypatch.setattr(stage, "_CAMERA_MODELS", {})
    monkeypatch.setattr(stage.cv2, "initUndistortRectifyMap", fails)
    calibration = _distorted_calibration(width_px=336)
    assert stage.camera_model(calibration, maps=False).camera is not None  # the solve stage cannot know
    job = stage.FrameJob("front", "jpeg", b"\xff\xd8", calibration)
    detections = SegmentDetector(DetectParams()).detect(job)
    assert detections.reject[0] == REJECT_NO_CALIBRATION
    assert "undistortion maps could not be built" in detections.reject[1] and "'front'" in detections.reject[1]
