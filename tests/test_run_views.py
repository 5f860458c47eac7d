"""The views of a camera-pipeline run (issue 13), read back from the ``.rrd``: the ghost only when
the mirror pose is a contender, LM iteration points on ``lm_iter`` only, buffered scalar columns
equal to the per-frame values, line gaps at rejected frames, the max_reproj_px line, relative
time, the summary as the terminal's table, the zoom on a small code.

Exactness: scalars are stored as float64 and compared exactly; Points2D as float32, compared
with the input rounded to float32.
"""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from agvviz.evaluation.summary import FrameScore, summarize
from agvviz.geometry.camera import PinholeCamera
from agvviz.model.frames import REJECT_NO_MARKER, REJECT_REPROJECTION, FrameResult, LmIteration, MarkerObservation
from agvviz.viz import paths
from agvviz.viz.readback import _rows, read_rrd, scalar_series, text_document, document_json, transforms
from agvviz.viz.zoom_placeholder import ZOOM_MIN_CROP_PX, ZOOM_SIDE_PX
from agvviz.viz.zoom_placeholder import zoom_unseen_png
from agvviz.viz.log_uncertainty import GHOST_MAX_AMBIGUITY_RATIO
from agvviz.viz.run_logger import FLUSH_EVERY_FRAMES, RunLogger

CAM = "front"
T0_NS = 1_700_000_000_000_000_000
START_NS = T0_NS - 2_000_000_000  # the recording starts 2 s before the first frame
MAX_REPROJ_PX = 2.0
#: More frames than one flush, so columns cross a flush boundary.
N_FRAMES = FLUSH_EVERY_FRAMES + 40
REJECTED = {5: REJECT_NO_MARKER, 70: REJECT_REPROJECTION, 71: REJECT_NO_MARKER}
#: Frames whose mirror pose is a contender (ambiguity ratio below the threshold).
CONTENDERS = {10, 11, 40, 90}
#: Frames solved in closed form (no LM iterations).
CLOSED_FORM = {20, 21}
SMALL_CODE_FRAME = 30  # a ≈15 px code: the zoomed view shows it




def _pose(x: float, y: float, heading_rad: float) -> np.ndarray:
    c, s = np.cos(heading_rad), np.sin(heading_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [x, y, 0.0]
    return T


def _image_png(width: int = 160, height: int = 120) -> bytes:
    image = np.zeros((height, width, 3), np.uint8)
    image[10:30, 20:40] = 255
    ok, buf = cv2.imencode(".png", image)
    assert ok
    return buf.tobytes()


def _frames(rng: np.random.Generator) -> list[FrameResult]:
    frames = []
    png = _image_png()
    for i in range(N_FRAMES):
        rejected = REJECTED.get(i)
        side_px = 6.0 if i == SMALL_CODE_FRAME else 80.0  # zoomed below 8 px (0.05 × 160 px)
        corners = np.array([[20, 10], [20 + side_px, 10], [20 + side_px, 10 + side_px], [20, 10 + side_px]], float)
        corners += rng.normal(0, 0.2, (4, 2))
        observations = () if rejected == REJECT_NO_MARKER else (
            MarkerObservation(
                marker_id="Q1", payload="Q1", corners_px=corners,
                points_world_m=np.array([[1, 2, 0], [1.5, 2, 0], [1.5, 1.5, 0], [1, 1.5, 0]], float),
                reprojected_px=None if rejected else corners + rng.normal(0, 0.1, (4, 2)),
            ),
        )
        n_records = 0 if rejected == REJECT_NO_MARKER or i in CLOSED_FORM else 3 + i % 3
        lm = tuple(
            LmIteration(cost=10.0 ** -k, reproj_rms_px=1.0 / (k + 1), damping=1e-3 * 10.0 ** -k,
                        step_norm=0.0 if k == 0 else 0.1 / k, accepted=True)
            for k in range(n_records)
        )
        lm_px = tuple(corners + 0.5 * (n_records - k) for k in range(n_records))
        truth = _pose(0.05 * i, 0.02 * i, 0.01 * i)
        solved = rejected is None
        frames.append(FrameResult(
            index=i,
            log_time_ns=T0_NS + i * 100_000_000,
            cam_name=CAM,
            image_format="png",
            image_bytes=png,
            observations=observations,
            rejected=rejected,
            reject_detail="test" if rejected else "",
            used_marker_id=None if rejected == REJECT_NO_MARKER else "Q1",
            T_world_agv=truth if solved else None,
            reproj_rms_px=None if rejected == REJECT_NO_MARKER else (3.0 if rejected else 0.01 * (i % 7)),
            lm_iterations=lm,
            lm_iteration_px=lm_px,
            T_world_agv_truth=truth,
            position_error_m=1e-4 * (i % 11) if solved else None,
            heading_error_deg=0.001 * (i % 5) if solved else None,
            pitch_error_deg=0.002 * (i % 3) if solved else None,
            roll_error_deg=-0.001 * (i % 4) if solved else None,
            position_cov_world_m2=np.diag([1e-8, 2e-8, 4e-8]) if solved else None,
            position_sigma_m=float(np.sqrt(7e-8)) if solved else None,
            ambiguity_ratio=None if rejected == REJECT_NO_MARKER else (2.0 if i in CONTENDERS else 50.0 + i),
            T_world_agv_ghost=truth @ _pose(0.5, 0.0, 0.3) if solved else None,
        ))
    return frames


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    frames = _frames(np.random.default_rng(20241113))
    path = tmp_path_factory.mktemp("views") / "run.rrd"
    logger = RunLogger(path, recording_name="views", recording_id="views", recording_start_ns=START_NS,
                       max_reproj_px=MAX_REPROJ_PX)
    logger.log_camera_static(CAM, PinholeCamera(K=np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]),
                                                width_px=160, height_px=120), np.eye(4))
    for frame in frames:
        logger.log_frame(frame)
    summary = summarize([FrameScore.of(f) for f in frames])
    logger.log_summary(summary)
    assert logger.recording_start_ns == START_NS
    logger.close()
    return frames, summary, read_rrd(path)


def _frames_with(contents, entity: str, component: str) -> list[int]:
    return [int(row[paths.TIMELINE_FRAME]) for row in _rows(contents, entity, component)
            if row.get(paths.TIMELINE_FRAME) is not None]


def test_ghost_only_when_the_mirror_pose_is_a_contender(run):
    frames, _, contents = run
    ghost_frames, _, _ = transforms(contents, paths.AGV_GHOST)
    assert sorted(ghost_frames) == sorted(CONTENDERS)
    assert all(frames[i].ambiguity_ratio < GHOST_MAX_AMBIGUITY_RATIO for i in ghost_frames)
    labels = {int(r[paths.TIMELINE_FRAME]): r["Boxes3D:labels"][0] for r in _rows(contents, paths.AGV_GHOST_BODY, "Boxes3D:labels")}
    assert sorted(labels) == sorted(CONTENDERS)
    assert f"< {GHOST_MAX_AMBIGUITY_RATIO:g}" in labels[10]
    # Cleared at the first frame after each run of contenders: 12 (after 10, 11), 41, 91.
    assert _frames_with(contents, paths.AGV_GHOST_BODY, "Clear:is_recursive") == [12, 41, 91]


def test_lm_iteration_points_on_lm_iter_only(run):
    frames, _, contents = run
    entity = paths.lm_iteration(CAM)
    rows = [r for r in _rows(contents, entity, "Points2D:positions")]
    iterated = [f for f in frames if f.lm_iterations]
    assert [(int(r[paths.TIMELINE_FRAME]), int(r[paths.TIMELINE_LM_ITER])) for r in rows] == [
        (f.index, k) for f in iterated for k in range(len(f.lm_iterations))
    ]
    for row, want in zip(rows, [p for f in iterated for p in f.lm_iteration_px]):
        np.testing.assert_array_equal(np.array(row["Points2D:positions"]), want.astype(np.float32))
    # The lm_iter timeline is on the iteration columns and nowhere else.
    with_lm_iter = {c.entity_path.lstrip("/") for c in contents.store.stream().filter(has_timeline=paths.TIMELINE_LM_ITER)}
    assert with_lm_iter == {paths.LM_COST, paths.LM_LOG10_COST, paths.LM_REPROJ_RMS_PX, paths.LM_DAMPING,
                            paths.LM_STEP_NORM, entity}
    # Closed-form frames say so; their points are cleared on the frame timeline.
    texts = {int(r[paths.TIMELINE_FRAME]): r["TextDocument:text"][0] for r in _rows(contents, paths.LM_THIS_FRAME, "TextDocument:text")}
    assert all("closed-form solver: no iterations" in texts[i] for i in CLOSED_FORM)
    assert "LM, frame 0" in texts[0]
    assert 20 in _frames_with(contents, entity, "Clear:is_recursive")


def test_scalar_columns_equal_per_frame_values(run):
    frames, _, contents = run
    for entity, value in (
        (paths.ERROR_POSITION_MM, lambda f: None if f.position_error_m is None else 1000.0 * f.position_error_m),
        (paths.ERROR_HEADING_DEG, lambda f: f.heading_error_deg),
        (paths.ERROR_PITCH_DEG, lambda f: f.pitch_error_deg),
        (paths.ERROR_ROLL_DEG, lambda f: f.roll_error_deg),
        (paths.ERROR_REPROJ_RMS_PX, lambda f: f.reproj_rms_px),
        (paths.ERROR_POSITION_SIGMA_M, lambda f: f.position_sigma_m),
        (paths.SOLVER_AMBIGUITY_RATIO, lambda f: None if f.ambiguity_ratio is None else min(f.ambiguity_ratio, 100.0)),
        (paths.LM_ITERATIONS, lambda f: len(f.lm_iterations) - 1 if f.lm_iterations else None),
    ):
        # A rejected frame has no value in any series (issue 26), even one it carries.
        want = [(f.index, value(f)) for f in frames if value(f) is not None and f.solved]
        idx, values = scalar_series(contents, entity)
        np.testing.assert_array_equal(idx, [i for i, _ in want], err_msg=entity)
        np.testing.assert_array_equal(values, [v for _, v in want], err_msg=entity)
    # elapsed counts from the recording's start, not from the first frame.
    elapsed_ns, _ = scalar_series(contents, paths.ERROR_POSITION_MM, timeline=paths.TIMELINE_ELAPSED)
    want_ns = [f.log_time_ns - START_NS for f in frames if f.position_error_m is not None]
    np.testing.assert_allclose(elapsed_ns, want_ns, atol=1)  # float seconds → ns: ≤ 1 ns rounding


def test_gaps_at_rejected_frames_and_threshold_line(run):
    frames, _, contents = run
    # No position error on rejected frames, and a Clear there breaks the line.
    assert _frames_with(contents, paths.ERROR_POSITION_MM, "Clear:is_recursive") == sorted(REJECTED)
    # Not even the reprojection RMS of a frame rejected for it is plotted (issue 26): a gap, and a
    # cross on the limit it broke.
    assert _frames_with(contents, paths.ERROR_REPROJ_RMS_PX, "Clear:is_recursive") == sorted(REJECTED)
    assert not set(scalar_series(contents, paths.ERROR_REPROJ_RMS_PX)[0].tolist()) & set(REJECTED)
    idx, values = scalar_series(contents, paths.ERROR_REPROJ_THRESHOLD_PX)
    np.testing.assert_array_equal(idx, np.arange(N_FRAMES))
    assert set(values) == {MAX_REPROJ_PX}
    idx, values = scalar_series(contents, paths.error_rejected(paths.ERROR_REPROJ_RMS_PX, REJECT_REPROJECTION))
    np.testing.assert_array_equal(idx, [70])
    np.testing.assert_array_equal(values, [MAX_REPROJ_PX])
    idx, _ = scalar_series(contents, paths.error_rejected(paths.ERROR_POSITION_MM, REJECT_NO_MARKER))
    np.testing.assert_array_equal(idx, [5, 71])


def test_summary_is_the_terminal_table_in_its_units(run):
    """The summary panel is the terminal's table in mm, degrees and px, its figures computed here
    from the frames (independently of RunStatistics/summarize); the JSON is a tab of its own."""
    frames, summary, contents = run
    text = text_document(contents, paths.RUN_SUMMARY)
    solved = [f for f in frames if f.rejected is None]
    position_mm = np.array([f.position_error_m for f in solved]) * 1000.0
    heading_deg = np.abs([f.heading_error_deg for f in solved])
    reproj_px = np.array([f.reproj_rms_px for f in solved])

    def stats(x):
        return np.sqrt(np.mean(x**2)), np.median(x), np.percentile(x, 95)

    rmse, median, p95 = stats(position_mm)
    assert f"| position RMSE / median / p95 (mm) | {rmse:.2f} / {median:.2f} / {p95:.2f} |" in text
    rmse, median, p95 = stats(heading_deg)
    assert f"| heading RMSE / median / p95 (deg) | {rmse:.3f} / {median:.3f} / {p95:.3f} |" in text
    assert f"| reprojection RMS median (px) | {np.median(reproj_px):.3f} |" in text
    assert f"| frames | {N_FRAMES} |" in text and f"| solved | {len(solved)} |" in text
    assert f"| rejected: {REJECT_NO_MARKER} | 2 |" in text and f"| rejected: {REJECT_REPROJECTION} | 1 |" in text
    assert "```json" not in text and "position_error_mm" not in text  # no raw JSON beside the table
    assert "time per frame" not in text  # wall-clock figures are not stored
    # the whole summary, SI units and all, in its own document (its own tab)
    assert "```json" in text_document(contents, paths.RUN_SUMMARY_JSON)
    assert document_json(contents, paths.RUN_SUMMARY) == summary
    assert document_json(contents, paths.RUN_SUMMARY_JSON) == summary


def test_small_code_is_zoomed(run):
    frames, _, contents = run
    root = paths.zoom(CAM)
    # the crop, then on the next frame (its code no longer small) the placeholder (issue 26)
    assert _frames_with(contents, f"{root}/image", "EncodedImage:blob") == [SMALL_CODE_FRAME, SMALL_CODE_FRAME + 1]
    row = _rows(contents, f"{root}/image/detected", "Points2D:positions")[0]
    crop = cv2.imdecode(np.frombuffer(bytes(_rows(contents, f"{root}/image", "EncodedImage:blob")[0]["EncodedImage:blob"][0]), np.uint8), cv2.IMREAD_UNCHANGED)
    corners = frames[SMALL_CODE_FRAME].observations[0].corners_px
    points = np.array(row["Points2D:positions"])
    # The crop is resized to one square size and holds the code's corners, magnified alike.
    assert crop.shape[:2] == (ZOOM_SIDE_PX, ZOOM_SIDE_PX)
    assert np.all(points >= 0) and np.all(points < ZOOM_SIDE_PX)
    side = max(ZOOM_MIN_CROP_PX, int(np.ceil(3 * np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)))))
    np.testing.assert_allclose(np.ptp(points, axis=0), np.ptp(corners, axis=0) * ZOOM_SIDE_PX / side, rtol=1e-5)
    # On the next frame (its code no longer small) the placeholder says since when and why, and
    # the corners are gone: the last crop is not shown as if it were current (issue 26).
    placeholder = bytes(_rows(contents, f"{root}/image", "EncodedImage:blob")[1]["EncodedImage:blob"][0])
    codes_in_view = bool(frames[SMALL_CODE_FRAME + 1].observations)
    assert placeholder == zoom_unseen_png(SMALL_CODE_FRAME, codes_in_view, crop.ndim == 2, ZOOM_SIDE_PX)
    assert len(_rows(contents, f"{root}/image/detected", "Points2D:positions")[1]["Points2D:positions"]) == 0
