"""Run-level findings of the check stage (issue 25): a camera's stamp offset against the odometry,
fitted at the end of the run from all its clean steps, covers every solved frame of the camera.

A synthetic weaving track checks the fit (30 ms late → 30 ms found, on time → nothing); a small
qr_floor recording (seeded, 5 s with one turn, 640×512) with a 30 ms stamp offset injected is
replayed with ``truth=ignore`` (the finding's offset within its tolerance of 30 ms; none on the same
recording without the offset), then run end to end through ``agvviz run --fail-if "suspects > 0"``:
the terminal lists the finding's stretch, the summary counts the frames it covers, the ``.rrd``'s
suspects log has its row at its first frame and the reprojection plot marks every covered frame.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.evaluation import gates, suspect_report
from agvviz.geometry import so3
from agvviz.model.frames import FrameResult
from agvviz.model.suspects import CAUSE_MAP_ENTRY, CAUSE_TIME_OFFSET, CHECK_MOTION, CHECK_TIME, RunFinding, Suspect
from agvviz.replay.checks import CheckSettings, CheckStage, suspects_summary
from agvviz.replay.run import replay_checked
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.readback import document_json, read_rrd, scalar_series, text_logs

SMALL = ["duration_s=5", "width_px=640", "height_px=512", "focal_px=500.0", "supersample=2"]
PERIOD_NS = 100_000_000
T0 = 1_000_000_000


def _pose(x: float, y: float, yaw_rad: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = so3.exp(np.array([0.0, 0.0, yaw_rad]))
    T[:3, 3] = [x, y, 0.0]
    return T


def _track(t_s: float) -> np.ndarray:
    """A vehicle weaving smoothly along x (1 m/s forward, y = 0.5·sin 1.5t, heading along the path)."""
    return _pose(t_s, 0.5 * math.sin(1.5 * t_s), math.atan2(0.75 * math.cos(1.5 * t_s), 1.0))


def _frame(i: int, T: np.ndarray, cam: str = "front") -> FrameResult:
    cov = np.diag([1e-6] * 6)
    return FrameResult(index=i, log_time_ns=T0 + i * PERIOD_NS, cam_name=cam, image_format="jpeg", image_bytes=b"",
                       T_world_agv=T, cov_world_agv=cov, position_cov_world_m2=cov[:3, :3],
                       used_marker_id="Q001", used_marker_ids=("Q001",))


def _stage(late_s: float, n: int = 60) -> tuple[CheckStage, list[FrameResult]]:
    """A check stage fed ``n`` frames of the weaving track stamped ``late_s`` late (perfect odometry)."""
    stage = CheckStage(CheckSettings(), lambda t_ns: _track((t_ns - T0) / 1e9))
    return stage, [stage.check(_frame(i, _track(0.1 * i - late_s))) for i in range(n)]


def test_a_camera_30_ms_late_is_a_run_level_finding_on_every_frame():
    stage, frames = _stage(0.030)
    (finding,) = stage.run_findings()
    assert finding.cam_name == "front" and finding.cause == CAUSE_TIME_OFFSET and finding.check == CHECK_TIME
    # a perfect odometry and exact poses: only the fit's second-order terms remain
    assert finding.offset_s == pytest.approx(0.030, abs=0.001)
    assert finding.sigma > finding.limit_sigma and finding.steps >= 50
    assert finding.frame_indices == tuple(f.index for f in frames) and finding.n_frames == 60
    assert "lag the odometry by 30 ±" in finding.message
    assert not any(f.suspect is not None and f.suspect.cause != CAUSE_TIME_OFFSET for f in frames)
    early, _ = _stage(-0.030)
    assert early.run_findings()[0].offset_s == pytest.approx(-0.030, abs=0.001)
    on_time, frames = _stage(0.0)
    assert on_time.run_findings() == () and all(f.suspect is None for f in frames)
    small, _ = _stage(0.005)  # a few ms: what rolling shutters and odometry filters do, no finding
    assert small.run_findings() == ()


def _finding(frames: range, cam: str = "front") -> RunFinding:
    return RunFinding(cam, CHECK_TIME, CAUSE_TIME_OFFSET, 14.0, 5.0, "camera front's poses lag the odometry by 29 ± 2 ms",
                      "check the stamps", 0.029, 0.002, 50, tuple(frames), tuple(T0 + i * PERIOD_NS for i in frames))


def test_the_summary_counts_the_frames_a_finding_covers_once_each():
    suspect = Suspect(3, T0 + 3 * PERIOD_NS, "front", CHECK_MOTION, 9.0, CAUSE_MAP_ENTRY, "Q1 moved", marker_id="Q1")
    offset = Suspect(7, T0 + 7 * PERIOD_NS, "front", CHECK_TIME, 6.0, CAUSE_TIME_OFFSET, "late")
    frames = [_frame(i, np.eye(4)) for i in range(10)] + [_frame(i, np.eye(4), "rear") for i in range(10)]
    frames[3] = FrameResult(**{**frames[3].__dict__, "suspect": suspect})
    frames[7] = FrameResult(**{**frames[7].__dict__, "suspect": offset})
    frames[5] = FrameResult(5, T0 + 5 * PERIOD_NS, "front", "jpeg", b"", rejected="no_marker")
    covered = [i for i in range(10) if i != 5]  # every solved frame of camera front
    section = suspects_summary(frames, findings=[_finding(covered)])
    # 9 solved front frames flagged (rear untouched), each once: map_entry keeps its own cause
    assert section["frames"] == 9 and section["solved"] == 19 and section["covered"] == 7
    assert section["by_cause"][CAUSE_MAP_ENTRY] == 1 and section["by_cause"][CAUSE_TIME_OFFSET] == 8
    assert section["by_check"][CHECK_TIME] == 8
    stretches = section["stretches"]
    # the frame's own time-offset stretch is the finding's; the map entry's stays
    assert [(s["first_frame"], s["last_frame"], s["cause"], s["run_level"]) for s in stretches] == [
        (0, 9, CAUSE_TIME_OFFSET, True), (3, 3, CAUSE_MAP_ENTRY, False)]
    assert stretches[0]["n_frames"] == 9
    (said,) = section["findings"]
    assert said["offset_ms"] == 29.0 and said["n_frames"] == 9 and said["cam_name"] == "front"
    summary = {"frames": 20, "solved": 19, "suspects": section}
    assert gates.suspect_counts(summary)["suspects"] == 9
    assert gates.suspect_counts(summary)["suspects.time_offset"] == 8
    rows = dict(suspect_report.summary_rows(summary))
    assert rows["suspect frames (checks without truth)"] == "9 of 19 solved"
    assert rows["  run-level findings (whole log)"] == "1: camera time offset, camera front (9 frames)"
    table, _ = suspect_report.stretch_rows(summary, start_ns=T0)
    assert table[0][0] == "0–9 (9, the whole run)" and table[0][2] == "camera time offset"
    line = suspect_report.finding_line(_finding(covered))
    assert line.startswith("frames 0–9 (9, the whole run; camera front): time check 14.0σ (limit 5σ), "
                           "likely cause: camera time offset — camera front's poses lag")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("run_findings")
    found = {"clean": folder / "clean.mcap", "offset": folder / "offset.mcap"}
    # seed 2's 5 s drive: a straight, one left turn (from ≈ 2.9 s), a straight
    scenario_registry.record("qr_floor", found["clean"], seed=2, overrides=SMALL)
    scenario_registry.record("qr_floor", found["offset"], seed=2, overrides=SMALL + ["inject=timing:front:offset_ms=30"])
    return found


def test_a_recording_with_a_30_ms_stamp_offset_gives_the_finding_and_a_clean_one_none(recordings):
    frames, findings = replay_checked(recordings["offset"], RunSettings(truth="ignore"))
    (finding,) = findings
    solved = [f.index for f in frames if f.solved]
    assert finding.cam_name == "front" and finding.cause == CAUSE_TIME_OFFSET
    assert finding.frame_indices == tuple(solved) and len(solved) >= 40
    # bench_checks over 20 seeds: 26–30 ms found for 30 ms, σ ≈ 2 ms from the fit's scatter;
    # the tolerance is 3σ of the fit (the odometry's 10 Hz samples bound the model's accuracy)
    assert finding.offset_s == pytest.approx(0.030, abs=3 * finding.offset_sigma_s + 0.001), finding.message
    assert finding.sigma > 5.0
    # frames flagged on their own where the turn showed it keep their suspect
    assert any(f.suspect is not None and f.suspect.cause == CAUSE_TIME_OFFSET for f in frames)
    clean_frames, clean_findings = replay_checked(recordings["clean"], RunSettings(truth="ignore"))
    assert clean_findings == () and len([f for f in clean_frames if f.solved]) >= 40


def test_run_shows_the_finding_in_the_terminal_summary_rrd_and_gate(recordings, tmp_path):
    from agvviz.cli.main import app

    out = tmp_path / "offset.rrd"
    args = ["run", str(recordings["offset"]), "--out", str(out), "--jobs", "1", "--no-cache"]
    result = CliRunner().invoke(app, [*args, "--fail-if", "suspects > 0"])
    assert result.exit_code == 1, result.output  # the gate counts the covered frames
    output = " ".join(result.output.split())
    assert "the whole run" in output and "camera time offset (camera front)" in output
    assert "poses lag the odometry by" in output
    contents = read_rrd(out)
    summary = document_json(contents, paths.RUN_SUMMARY)
    section = summary["suspects"]
    assert section["frames"] == summary["solved"] and len(section["findings"]) == 1
    assert any(s["run_level"] for s in section["stretches"])
    rows = text_logs(contents, paths.EVENTS_SUSPECTS)
    finding_rows = [(frame, text) for frame, _, text in rows if "the whole run" in text]
    assert len(finding_rows) == 1 and finding_rows[0][0] == section["findings"][0]["first_frame"]
    # every solved frame is marked on the reprojection plot (the finding's or its own suspect)
    reproj = dict(zip(*scalar_series(contents, paths.ERROR_REPROJ_RMS_PX)))
    marked = dict(zip(*scalar_series(contents, paths.error_suspect(paths.ERROR_REPROJ_RMS_PX))))
    assert set(marked) == set(reproj) and len(marked) == summary["solved"]
    assert all(marked[i] == pytest.approx(reproj[i]) for i in marked)
