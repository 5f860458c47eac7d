"""Nothing stale (issue 26): a panel whose source stopped says so instead of showing old data
as current.

- ``uwb_room``'s zoom panels: while a camera does not see its small code (the blocked stretch),
  the zoom shows a placeholder "small code not seen since frame N" (N the last frame it was
  seen), not the last crisp crop, and its corners are gone.
- ``auv_under_ice`` (corner observations only): each camera panel says why it has no image and,
  once a cycle closed, which window it shows.
- ``diff``: B's error arrow is absent (an empty batch) on every frame B rejected.
- a camera frame dropped altogether (uwb_room, a quarter of the frames dropped): the zoom shows
  "no image at this frame" at that frame instead of the previous crop.

Recordings are small: uwb_room 3 s at 640×512 with the code hidden from 1.0 to 1.8 s; a
corner-only auv_under_ice drive of 6 s; qr_floor 1.5 s at 640×512 replayed twice, B with
``max_reproj_px = 0.1`` so about half its frames are rejected (tests/test_rejected_views.py).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agvviz.app.diff import diff
from agvviz.app.run import run_recording
from agvviz.scenarios import record
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz import readback
from agvviz.viz.log_frames import ZOOM_SIDE_PX
from agvviz.viz.zoom_placeholder import zoom_unseen_png
from agvviz.viz.readback import encoded_images, points2d, read_rrd, text_logs

UWB_SMALL = ["duration_s=3", "width_px=640", "height_px=512", "block_start_s=1.0", "block_end_s=1.8"]
QR_SMALL = ["duration_s=1.5", "width_px=640", "height_px=512", "focal_px=500"]


def _latest_at(by_frame: dict[int, object], frame: int):
    """What the viewer shows at ``frame``: the last value logged at or before it (None: none)."""
    before = [f for f in by_frame if f <= frame]
    return by_frame[max(before)] if before else None


@pytest.fixture(scope="module")
def uwb_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("uwb_stale")
    record("uwb_room", tmp / "uwb.mcap", seed=0, overrides=UWB_SMALL)
    run_recording(tmp / "uwb.mcap", RunSettings(), tmp / "run.rrd", jobs=1, cache_dir=False)
    return read_rrd(tmp / "run.rrd")


def test_zoom_says_since_when_its_code_is_unseen_and_shows_it_when_seen(uwb_run):
    contents = uwb_run
    cams = sorted(p.split("/")[1].removeprefix("cam_") for p in contents.entity_paths
                  if p.startswith(paths.ZOOM + "/") and p.endswith("/image"))
    assert len(cams) >= 2, cams  # the cameras that saw the code small
    checked_unseen = checked_seen = 0
    for cam in cams:
        images = encoded_images(contents, paths.zoom_image(cam))
        zoom_corners = points2d(contents, paths.zoom_detected(cam))
        detected = points2d(contents, paths.detected(cam, True))  # the camera's own corners per frame
        seen_frames = sorted(f for f, pts in detected.items() if len(pts))
        unseen_frames = sorted(f for f, pts in detected.items() if not len(pts) and f > seen_frames[0])
        assert unseen_frames, f"camera {cam}: the blocked stretch is in the recording"
        for f in unseen_frames:
            last_seen = max(s for s in seen_frames if s < f)
            png, media = _latest_at(images, f)
            gray = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).ndim == 2
            assert png == zoom_unseen_png(last_seen, False, gray, ZOOM_SIDE_PX), (cam, f, last_seen)
            assert len(_latest_at(zoom_corners, f)) == 0  # no corners drawn over the placeholder
            checked_unseen += 1
        for f in seen_frames:
            png, _ = _latest_at(images, f)
            image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
            # a crop of the recorded image (the floor around the code is mid-grey), not the
            # placeholder (black but for its few words)
            assert np.median(image) > 40 and np.ptp(image) > 50, (cam, f)
            assert len(_latest_at(zoom_corners, f)) >= 4
            checked_seen += 1
    assert checked_unseen >= len(cams) and checked_seen >= 10 * len(cams)


def test_zoom_placeholder_keeps_the_crops_size_and_channels():
    for gray in (True, False):
        image = cv2.imdecode(np.frombuffer(zoom_unseen_png(12, True, gray, ZOOM_SIDE_PX), np.uint8), cv2.IMREAD_UNCHANGED)
        assert image.shape[:2] == (ZOOM_SIDE_PX, ZOOM_SIDE_PX) and (image.ndim == 2) == gray
        assert image.max() > 0  # the words are drawn


def test_corner_only_camera_panels_say_why_they_have_no_image(tmp_path):
    record("auv_under_ice", tmp_path / "auv.mcap", seed=0, overrides=["duration_s=6"])
    run_recording(tmp_path / "auv.mcap", RunSettings(correction="cnoem"), tmp_path / "run.rrd", jobs=1, cache_dir=False)
    contents = read_rrd(tmp_path / "run.rrd")
    cycles = text_logs(contents, paths.EVENTS_CORRECTIONS)
    assert cycles, "a cycle closes within 6 s"
    first_cycle_frame = cycles[0][0]
    for cam in ("left", "right"):
        labels = {
            int(row[paths.TIMELINE_FRAME]): row["Points2D:labels"][0]
            for row in readback._rows(contents, paths.correction_status(cam), "Points2D:labels")
        }
        at_start = _latest_at(labels, 0)
        assert at_start.startswith("no image at this frame: corner observations only"), at_start
        assert _latest_at(labels, 5) == at_start
        after = _latest_at(labels, first_cycle_frame)
        assert after == f"window of cycle 0, closed at frame {first_cycle_frame}\n" \
                        "no image: the recording holds corner observations only", after


def test_diff_draws_no_error_arrow_of_b_on_a_frame_b_rejected(tmp_path):
    record("qr_floor", tmp_path / "qr.mcap", seed=0, overrides=QR_SMALL)
    a_path, b_path = tmp_path / "a.rrd", tmp_path / "b.rrd"
    run_recording(tmp_path / "qr.mcap", RunSettings(), a_path, jobs=1, cache_dir=False)
    run_recording(tmp_path / "qr.mcap", RunSettings(max_reproj_px=0.1), b_path, jobs=1, cache_dir=False)
    rejected_b = {frame for frame, _, _ in text_logs(b_path, paths.EVENTS_REJECTIONS)}
    assert len(rejected_b) >= 3
    out = diff(a_path, b_path, overlay_path=tmp_path / "d.rrd").overlay_path
    contents = read_rrd(out)
    for key, rejected in (("b", rejected_b), ("a", set())):
        arrows = {
            int(row[paths.TIMELINE_FRAME]): len(row["Arrows3D:vectors"])
            for row in readback._rows(contents, paths.overlay_error_vector(key), "Arrows3D:vectors")
            if row.get(paths.TIMELINE_FRAME) is not None
        }
        assert set(arrows) >= rejected, "B's rejected frames carry a row (an empty one)"
        for frame, n in arrows.items():
            assert n == (0 if frame in rejected else 1), (key, frame, n)


def _progress_of(recording, settings):
    """(every on_total call, every progress call, the run summary)."""
    totals, done = [], []
    outcome = run_recording(recording, settings, recording.with_suffix(".rrd"), progress=done.append,
                            on_total=totals.append, jobs=1, cache_dir=False)
    return totals, done, outcome.summary


def test_progress_total_of_a_corner_only_run_is_its_corner_messages(tmp_path):
    """``auv_under_ice``'s default recording (corners, no image) showed "0/0": its unit is the
    corner-observation message, counted in the file independently of the run."""
    from mcap.reader import make_reader

    from agvviz.model.topics import CORNERS_TOPIC

    recording = tmp_path / "auv.mcap"
    record("auv_under_ice", recording, seed=0, overrides=["duration_s=4"])
    with open(recording, "rb") as f:  # the mcap library's own reader, not agvviz's
        in_file = sum(1 for _ in make_reader(f).iter_messages(topics=[CORNERS_TOPIC]))
    totals, done, _ = _progress_of(recording, RunSettings(correction="cnoem"))
    assert in_file > 40
    assert totals == [in_file]
    assert done == list(range(1, in_file + 1))


def test_progress_total_of_a_camera_run_is_its_frames(tmp_path):
    recording = tmp_path / "qr.mcap"
    record("qr_floor", recording, seed=0, overrides=QR_SMALL)
    totals, done, summary = _progress_of(recording, RunSettings())
    assert summary["frames"] == 15  # 1.5 s at 10 Hz, one camera
    assert totals == [15] and done == list(range(1, 16))


def test_a_dropped_camera_frame_replaces_the_zoom_crop_at_that_frame(tmp_path):
    """uwb_room 3 s with a quarter of the camera frames dropped: at a frame where a camera has no
    image at all, its zoom (if it showed a crop) shows the "no image at this frame" placeholder
    at that very frame, with no corners, never the previous crop."""
    record("uwb_room", tmp_path / "drop.mcap", seed=0,
           overrides=["duration_s=3", "width_px=640", "height_px=512", "realism_set=timing.drop_probability=0.25"])
    run_recording(tmp_path / "drop.mcap", RunSettings(), tmp_path / "run.rrd", jobs=1, cache_dir=False)
    contents = read_rrd(tmp_path / "run.rrd")
    cams = sorted(p.split("/")[1].removeprefix("cam_") for p in contents.entity_paths
                  if p.startswith(paths.ZOOM + "/") and p.endswith("/image"))
    all_cams = sorted(p.split("/")[2].removeprefix("cam_") for p in contents.entity_paths
                      if p.startswith(paths.FIXED_CAMERAS + "/") and p.endswith("/image"))
    full = {cam: encoded_images(contents, paths.image(cam, True)) for cam in all_cams}
    frames = set().union(*full.values())
    checked = 0
    for cam in cams:
        zooms = encoded_images(contents, paths.zoom_image(cam))
        corners = points2d(contents, paths.zoom_detected(cam))
        crop_frames = {f for f, (png, _) in zooms.items()
                       if np.median(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)) > 40}
        for f in sorted(frames - set(full[cam])):
            earlier = [k for k in zooms if k < f]
            if not earlier or max(earlier) not in crop_frames:
                continue  # the zoom showed no crop before this dropped frame
            last_crop = max(earlier)
            png, _ = zooms.get(f, (None, None))
            image = cv2.imdecode(np.frombuffer(zooms[last_crop][0], np.uint8), cv2.IMREAD_UNCHANGED)
            assert png == zoom_unseen_png(last_crop, False, image.ndim == 2, ZOOM_SIDE_PX, dropped=True), (cam, f)
            assert len(corners[f]) == 0
            checked += 1
    assert checked >= 3  # dropped frames of cameras whose zoom showed a crop


def test_only_a_camera_whose_frame_was_due_counts_as_dropped(tmp_path):
    """Two cameras in sync at 10 Hz, B's frame 5 dropped: B counts as dropped at stamp 5 only.
    Two cameras at 10 Hz firing in turn (A at 0, 100 ms…, B at 50, 150 ms…): never dropped — each
    fires between the other's stamps, and its zoom must not blink."""
    from types import SimpleNamespace

    from agvviz.viz.run_logger import RunLogger

    def flagged(sets):
        logger = RunLogger(tmp_path / "x.rrd", recording_name="t", recording_id="t")
        calls = []
        logger.frames.log_zoom_dropped = lambda cams: calls.append((index, sorted(cams)))
        for index, frames in enumerate(sets):
            logger.log_cameras_missing(frames[0], frames)
        logger.discard()
        return calls

    def frame(cam, index, t_ms):
        return SimpleNamespace(cam_name=cam, index=index, log_time_ns=int(t_ms * 1e6))

    in_sync = [[frame("a", k, 100 * k)] + ([] if k == 5 else [frame("b", k, 100 * k)]) for k in range(10)]
    assert flagged(in_sync) == [(5, ["b"])]
    in_turn = [[frame("a" if k % 2 == 0 else "b", k, 50 * k)] for k in range(20)]
    assert flagged(in_turn) == []
