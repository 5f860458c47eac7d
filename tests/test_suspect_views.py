"""Where a user sees suspect frames (issue 25) and the CI gates on them.

A :class:`RunLogger` is fed synthetic FrameResults, some carrying a
:class:`~agvviz.model.suspects.Suspect`, and the ``.rrd`` is read back with Rerun's own chunk API
(:mod:`agvviz.viz.readback`): the ``events/suspects`` rows, the solver panel text and the
``errors/suspect/*`` markers must sit at exactly the suspect frames, with the frame's values.
The gates (``run --fail-if``, ``diff --fail-if`` on suspect counts) are checked on synthetic
summaries and runs, their JUnit XML parsed back with the standard library and, when installed,
with junitparser (a third-party reader of the format CI tools read).
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from agvviz.evaluation import gates, suspect_report
from agvviz.evaluation.expression import ExpressionError
from agvviz.evaluation.junit import junit_xml
from agvviz.evaluation.summary_table import summary_rows
from agvviz.model.frames import REJECT_SOLVER, FrameResult, MarkerObservation
from agvviz.model.suspects import (
    CAUSE_MAP_ENTRY,
    CAUSE_MIRROR_FLIP,
    CAUSES,
    CHECK_AMBIGUITY,
    CHECK_MARKERS,
    CHECK_MOTION,
    CheckResult,
    Suspect,
)
from agvviz.viz import paths
from agvviz.viz.readback import read_rrd, scalar_series, text_documents, text_logs
from agvviz.viz.run_logger import RunLogger

CAM = "front"
T0_NS = 1_700_000_000_000_000_000
DT_NS = 100_000_000
N = 16
REJECTED = {9}
MAP_MESSAGE = ("code Q015 disagrees with Q024 by 2.2 m and with the odometry by 2.2 m: "
               "Q015's map entry is likely wrong")
MAP_NEXT = "`agvviz audit` can estimate where it is"
FLIP_MESSAGE = "mirror-pose flip: ambiguity ratio 1.3, the other pose agrees with the odometry"


def _suspect(index: int, cause: str) -> Suspect:
    if cause == CAUSE_MAP_ENTRY:
        checks = (CheckResult(CHECK_MOTION, 38.0, 5.0, "pose step 2.21 m, odometry step 0.05 m"),
                  CheckResult(CHECK_MARKERS, 41.5, 5.0, "Q015 vs Q024: 2.2 m"))
        return Suspect(index, T0_NS + index * DT_NS, CAM, CHECK_MARKERS, 41.5, cause, MAP_MESSAGE, MAP_NEXT,
                       marker_id="Q015", checks=checks)
    checks = (CheckResult(CHECK_AMBIGUITY, 7.2, 4.0, "ratio 1.3"),)
    return Suspect(index, T0_NS + index * DT_NS, CAM, CHECK_AMBIGUITY, 7.2, cause, FLIP_MESSAGE,
                   "look at the ghost pose in 3D", checks=checks)


#: Suspect frames and their causes: a stretch of a wrong map entry, then one flipped frame.
SUSPECTS = {5: CAUSE_MAP_ENTRY, 6: CAUSE_MAP_ENTRY, 7: CAUSE_MAP_ENTRY, 12: CAUSE_MIRROR_FLIP}


def _frames(truth: bool = True, suspects: dict = SUSPECTS) -> list[FrameResult]:
    rng = np.random.default_rng(25)
    frames = []
    for i in range(N):
        rejected = REJECT_SOLVER if i in REJECTED else None
        corners = rng.uniform(0, 30, (4, 2))
        obs = MarkerObservation("Q015", "payload", corners, np.zeros((4, 3)),
                                reprojected_px=None if rejected else corners + 0.1)
        T = np.eye(4)
        T[0, 3] = 0.1 * i
        frames.append(FrameResult(
            index=i, log_time_ns=T0_NS + i * DT_NS, cam_name=CAM, image_format="png", image_bytes=b"",
            observations=(obs,), rejected=rejected, T_world_agv=None if rejected else T,
            reproj_rms_px=None if rejected else 0.05 + 0.01 * i,
            T_world_agv_truth=T if truth else None,
            position_error_m=None if rejected or not truth else 0.001 * (1 + i),
            heading_error_deg=None if rejected or not truth else 0.01 * i,
            suspect=_suspect(i, suspects[i]) if i in suspects and not rejected else None,
        ))
    return frames


def _summary(frames: list[FrameResult], suspects: dict = SUSPECTS, with_section: bool = True) -> dict:
    """A run summary in the shape the check stage writes (``summary["suspects"]``)."""
    solved = sum(f.solved for f in frames)
    summary = {
        "frames": len(frames), "solved": solved, "rejected": {REJECT_SOLVER: len(frames) - solved},
        "position_error_mm": {"rmse": 9.5, "median": 8.0, "p95": 15.0, "max": 16.0, "n": solved},
        "heading_error_deg": {"rmse": 0.1, "median": 0.07, "p95": 0.14, "max": 0.15, "n": solved},
        "pitch_error_deg": {"rmse": None, "median": None, "p95": None, "max": None, "n": 0},
        "roll_error_deg": {"rmse": None, "median": None, "p95": None, "max": None, "n": 0},
        "reproj_rms_px": {"rmse": 0.12, "median": 0.11, "p95": 0.2, "max": 0.2, "n": solved},
        "recording_damage": [], "warnings": [],
    }
    if with_section:
        by_cause: dict[str, int] = {}
        for cause in suspects.values():
            by_cause[cause] = by_cause.get(cause, 0) + 1
        stretches = []
        for first, last, cause, message, next_step, marker, sigma in (
            (5, 7, CAUSE_MAP_ENTRY, MAP_MESSAGE, MAP_NEXT, "Q015", 41.5),
            (12, 12, CAUSE_MIRROR_FLIP, FLIP_MESSAGE, "look at the ghost pose in 3D", None, 7.2),
        ):
            if first in suspects:
                stretches.append({
                    "first_frame": first, "last_frame": last, "first_time_ns": T0_NS + first * DT_NS,
                    "last_time_ns": T0_NS + last * DT_NS, "n_frames": last - first + 1, "cause": cause,
                    "message": message, "next_step": next_step, "cam_name": CAM, "marker_id": marker,
                    "max_sigma": sigma,
                })
        summary["suspects"] = {"frames": len(suspects), "by_cause": by_cause, "stretches": stretches}
    return summary


def _write(path: Path, frames: list[FrameResult], summary: dict, name: str = "synthetic-lm") -> Path:
    with RunLogger(path, recording_name=name, recording_id="test-suspects", recording_start_ns=T0_NS) as logger:
        logger.log_camera_static(CAM, _camera(), np.eye(4))
        for frame in frames:
            logger.log_frame(frame)
        logger.log_manifest({"recording_name": name, "recording_sha256": "ab", "settings": {"solver": "lm"}})
        logger.log_summary(summary)
    return path


def _camera():
    from agvviz.geometry.camera import PinholeCamera

    return PinholeCamera(K=np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]), width_px=32, height_px=24)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    frames = _frames()
    path = _write(tmp_path_factory.mktemp("suspects") / "run.rrd", frames, _summary(frames))
    return path, frames, read_rrd(path)


# -- the .rrd ----------------------------------------------------------------------------------
def test_suspects_log_has_one_warning_per_suspect_frame(run):
    _, frames, contents = run
    rows = text_logs(contents, paths.EVENTS_SUSPECTS)
    assert [frame for frame, _, _ in rows] == sorted(SUSPECTS)
    assert {level for _, level, _ in rows} == {"WARN"}
    text = dict((frame, text) for frame, _, text in rows)
    # check, σ, limit, cause in words, marker and camera, message, next step
    # the row's first line is what the panel shows: cause, where, σ, short enough to be read
    # whole (≤ 55 characters beside the frame column); the terminal's sentence follows
    head, full = text[5].split("\n", 1)
    assert head == f"marker map entry (Q015, {CAM}) · 42σ"
    assert all(len(t.split("\n", 1)[0]) <= 55 for t in text.values())
    assert full == (f"frame 5 (marker Q015, camera {CAM}): markers check 41.5σ (limit 5σ), likely cause: "
                    f"marker map entry — {MAP_MESSAGE}; next: {MAP_NEXT}")
    assert "ambiguity check 7.2σ (limit 4σ)" in text[12] and "mirror-pose flip" in text[12]
    assert FLIP_MESSAGE in text[12]


def test_solver_panel_says_suspect_instead_of_solved(run):
    _, frames, contents = run
    panel = text_documents(contents, paths.LM_THIS_FRAME)
    assert sorted(panel) == list(range(N))
    for frame in frames:
        text = panel[frame.index]
        if frame.index in SUSPECTS:
            assert f"suspect: {frame.suspect.message}" in text and "solved" not in text.split("\n")[0]
            assert f"next: {frame.suspect.next_step}" in text
        elif frame.solved:
            assert "solved" in text and "suspect" not in text
        else:
            assert "rejected" in text


def test_suspect_markers_sit_on_the_error_lines_at_the_suspect_frames(run):
    _, frames, contents = run
    for entity, value in (
        (paths.ERROR_POSITION_MM, lambda f: 1000.0 * f.position_error_m),
        (paths.ERROR_HEADING_DEG, lambda f: f.heading_error_deg),
        (paths.ERROR_REPROJ_RMS_PX, lambda f: f.reproj_rms_px),
    ):
        idx, values = scalar_series(contents, paths.error_suspect(entity))
        np.testing.assert_array_equal(idx, sorted(SUSPECTS))
        np.testing.assert_array_equal(values, [value(frames[i]) for i in sorted(SUSPECTS)])
        # the same frames' values on the plotted line itself
        line_idx, line = scalar_series(contents, entity)
        np.testing.assert_array_equal(line[np.isin(line_idx, idx)], values)


def test_without_truth_the_reprojection_plot_still_marks_them(tmp_path):
    frames = _frames(truth=False)
    contents = read_rrd(_write(tmp_path / "notruth.rrd", frames, _summary(frames)))
    idx, _ = scalar_series(contents, paths.error_suspect(paths.ERROR_REPROJ_RMS_PX))
    np.testing.assert_array_equal(idx, sorted(SUSPECTS))
    from agvviz.viz.readback import has_rows

    assert not has_rows(contents, paths.error_suspect(paths.ERROR_POSITION_MM), "Scalars:scalars")


def test_a_clean_run_has_no_suspect_rows_and_its_layout_no_suspects_log(tmp_path):
    frames = _frames(suspects={})
    contents = read_rrd(_write(tmp_path / "clean.rrd", frames, _summary(frames, suspects={})))
    assert paths.EVENTS_SUSPECTS not in contents.entity_paths
    from agvviz.viz.readback import has_rows

    assert not has_rows(contents, paths.error_suspect(paths.ERROR_REPROJ_RMS_PX), "Scalars:scalars")


def test_layout_shows_the_suspects_log_and_markers():
    from agvviz.viz.blueprints import default_blueprint

    def views(blueprint):
        found = []

        def walk(item):
            if hasattr(item, "contents") and isinstance(getattr(item, "contents"), (list, tuple)):
                for child in item.contents:
                    walk(child)
            found.append(item)

        walk(blueprint.root_container)
        return found

    with_suspects = views(default_blueprint([CAM], has_suspects=True))
    names = [getattr(v, "name", None) for v in with_suspects]
    assert "suspects (checks without truth)" in names
    assert "suspects (checks without truth)" not in [getattr(v, "name", None) for v in views(default_blueprint([CAM]))]


def test_equal_settings_give_equal_rrd(tmp_path):
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip("rerun CLI not found next to the interpreter")
    frames = _frames()
    for name in ("a.rrd", "b.rrd"):
        _write(tmp_path / name, _frames(), _summary(frames))
    other = _frames(suspects={**SUSPECTS, 3: CAUSE_MIRROR_FLIP})
    _write(tmp_path / "c.rrd", other, _summary(frames))

    def compare(x, y):
        return subprocess.run([cli, "rrd", "compare", "--unordered", tmp_path / x, tmp_path / y],
                              capture_output=True, timeout=60, check=False).returncode

    assert compare("a.rrd", "b.rrd") == 0
    assert compare("a.rrd", "c.rrd") != 0


# -- the terminal ------------------------------------------------------------------------------
def test_summary_rows_count_suspects_per_cause():
    rows = dict(summary_rows(_summary(_frames()), {}))
    assert rows["suspect frames (checks without truth)"] == "4 of 15 solved"
    assert rows["suspect stretches"] == "2"
    assert rows["  marker map entry"] == "3" and rows["  mirror-pose flip"] == "1"
    assert "suspect stretches" not in dict(summary_rows(_summary(_frames(), with_section=False), {}))


def test_stretch_rows_are_capped_with_a_count_of_the_rest():
    summary = _summary(_frames())
    rows, more = suspect_report.stretch_rows(summary, T0_NS)
    assert more == 0
    assert rows[0][:5] == ["5–7 (3)", "0.50–0.70", "marker map entry", f"marker Q015, camera {CAM}", "41.5"]
    assert rows[0][5:] == [MAP_MESSAGE, MAP_NEXT]
    assert rows[1][0] == "12 (1)" and rows[1][1] == "1.20"
    many = {**summary, "suspects": {**summary["suspects"], "stretches": summary["suspects"]["stretches"] * 15}}
    rows, more = suspect_report.stretch_rows(many, T0_NS)
    assert len(rows) == suspect_report.MAX_STRETCH_ROWS and more == 30 - suspect_report.MAX_STRETCH_ROWS
    assert suspect_report.stretch_lines(many, T0_NS)[-1] == f"… and {more} more"
    assert suspect_report.stretch_rows(_summary(_frames(), suspects={}), T0_NS) == ([], 0)


# -- gates -------------------------------------------------------------------------------------
def test_run_gates_on_suspect_counts():
    summary = _summary(_frames())
    verdicts = gates.run_gates(
        ["suspects > 0", "suspects.map_entry >= 3 and suspects.mirror_flip == 1", "suspects.payload > 0",
         "position_rmse_mm > 10", "suspects_pct > 25", "suspect_stretches == 2 and solved == 15"],
        summary,
    )
    assert [g.holds for g in verdicts] == [True, True, False, False, True, True]
    assert verdicts[0].message == "'suspects > 0' holds (suspects = 4)"
    assert verdicts[4].values == {"suspects_pct": pytest.approx(100 * 4 / 15)}
    # a summary without suspect counts: an error saying so, never a silent 0
    (missing,) = gates.run_gates(["suspects > 0"], _summary(_frames(), with_section=False))
    assert missing.holds is None and "holds no suspect counts" in missing.error
    (no_truth,) = gates.run_gates(["pitch_rmse_deg < 1"], summary)
    assert no_truth.holds is None and "no truth" in no_truth.error
    with pytest.raises(ExpressionError, match="unknown metric 'suspect'.*suspects.map_entry"):
        gates.run_gates(["suspect > 0"], summary)
    with pytest.raises(ExpressionError, match="unknown metric 'B.suspects'"):
        gates.run_gates(["B.suspects > 0"], summary)
    assert set(gates.run_metric_names()) >= {f"suspects.{c}" for c in CAUSES}


def _parse_junit(text: str):
    root = ET.fromstring(text)
    assert root.tag == "testsuites"
    (suite,) = root.findall("testsuite")
    return root, suite


def test_junit_xml_reads_back_with_a_junit_reader(tmp_path):
    verdicts = gates.run_gates(["suspects > 0", "frames < 1", "roll_max_deg > 1"], _summary(_frames()))
    text = junit_xml("run", "agvviz run synthetic-lm", verdicts, properties={"rrd": "runs/x.rrd"},
                     details="suspect stretches:\nframes 5–7")
    root, suite = _parse_junit(text)
    assert {k: suite.get(k) for k in ("tests", "failures", "errors", "skipped")} == \
        {"tests": "3", "failures": "1", "errors": "1", "skipped": "0"}
    cases = suite.findall("testcase")
    assert [c.get("name") for c in cases] == ["suspects > 0", "frames < 1", "roll_max_deg > 1"]
    assert {c.get("classname") for c in cases} == {"agvviz.run"}
    assert cases[0].find("failure").get("message") == "'suspects > 0' holds (suspects = 4)"
    assert cases[1].find("failure") is None and cases[1].find("error") is None
    assert "no truth" in cases[2].find("error").get("message")
    assert suite.find("properties/property").attrib == {"name": "rrd", "value": "runs/x.rrd"}
    assert suite.find("system-out").text.startswith("suspect stretches")
    junitparser = pytest.importorskip("junitparser")
    path = tmp_path / "verdict.xml"
    path.write_text(text, encoding="utf-8")
    xml = junitparser.JUnitXml.fromfile(str(path))
    (parsed,) = list(xml)
    assert (parsed.tests, parsed.failures, parsed.errors) == (3, 1, 1)
    results = {case.name: [type(r).__name__ for r in case.result] for case in parsed}
    assert results == {"suspects > 0": ["Failure"], "frames < 1": [], "roll_max_deg > 1": ["Error"]}


def test_run_command_gate_exit_codes_and_junit(tmp_path, monkeypatch):
    """`agvviz run --fail-if` through the CLI over a run whose summary is synthetic (the replay
    itself is replaced): exit 1 when a condition holds, 0 when none does, 2 when one cannot be
    evaluated or does not parse (before any work); the JUnit file in each case it is asked for."""
    from agvviz.app import run as app_run
    from agvviz.cli.main import app

    recording = tmp_path / "rec.mcap"
    recording.write_bytes(b"not read: the replay is replaced")
    frames = _frames()
    summary = _summary(frames)
    rrd = _write(tmp_path / "run.rrd", frames, summary)
    calls = []

    def fake_run_recording(path, settings, out_path=None, progress=None, **kwargs):
        calls.append(path)
        return app_run.RunOutcome(out_path=rrd, summary=summary, manifest={"recording_name": "synthetic-lm"},
                                  read_report=None, timing={}, recording_start_ns=T0_NS)

    monkeypatch.setattr(app_run, "run_recording", fake_run_recording)
    runner = CliRunner()
    junit = tmp_path / "ci" / "verdict.xml"
    result = runner.invoke(app, ["run", str(recording), "--fail-if", "suspects > 0", "--junit-xml", str(junit)])
    assert result.exit_code == 1, result.output
    assert "suspect stretches" in result.output and "5–7 (3)" in result.output and "marker map entry" in result.output
    assert "--fail-if holds: suspects > 0 (suspects = 4)" in result.output
    _, suite = _parse_junit(junit.read_text())
    assert suite.get("failures") == "1" and "frames 5–7 (3)" in suite.find("system-out").text
    result = runner.invoke(app, ["run", str(recording), "--fail-if", "suspects.payload > 0",
                                 "--fail-if", "suspects > 10", "--junit-xml", str(junit)])
    assert result.exit_code == 0, result.output
    assert _parse_junit(junit.read_text())[1].get("failures") == "0"
    summary.pop("suspects")
    result = runner.invoke(app, ["run", str(recording), "--fail-if", "suspects > 0", "--junit-xml", str(junit)])
    assert result.exit_code == 2 and "holds no suspect counts" in result.output
    assert _parse_junit(junit.read_text())[1].get("errors") == "1"
    n_calls = len(calls)
    result = runner.invoke(app, ["run", str(recording), "--fail-if", "suspcts > 0"])
    assert result.exit_code == 2 and "unknown metric 'suspcts'" in result.output
    result = runner.invoke(app, ["run", str(recording), "--junit-xml", str(junit)])
    assert result.exit_code == 2 and "give at least one --fail-if" in result.output
    assert len(calls) == n_calls  # refused before any work


def test_diff_gate_on_suspect_counts(tmp_path):
    from agvviz.app.diff import diff

    clean_frames, suspect_frames = _frames(suspects={}), _frames()
    a = _write(tmp_path / "a.rrd", clean_frames, _summary(clean_frames, suspects={}), name="clean")
    b = _write(tmp_path / "b.rrd", suspect_frames, _summary(suspect_frames), name="faulty")
    old = _write(tmp_path / "old.rrd", clean_frames, _summary(clean_frames, with_section=False), name="old")
    junit = tmp_path / "diff.xml"
    outcome = diff(a, b, fail_if=["B.suspects > A.suspects", "B.suspects.map_entry > 5"], junit_path=junit,
                   images=False, n_resamples=50)
    assert outcome.failed and [g.holds for g in outcome.gates] == [True, False]
    assert outcome.gates[0].values == {"B.suspects": 4, "A.suspects": 0}
    c = outcome.comparison
    assert (c.row("suspects").a, c.row("suspects").b) == (0, 4)
    assert (c.row("suspects.map_entry").a, c.row("suspects.map_entry").b) == (0, 3)
    _, suite = _parse_junit(junit.read_text())
    assert (suite.get("tests"), suite.get("failures")) == ("2", "1")
    assert not diff(a, a, fail_if="B.suspects > A.suspects", images=False, n_resamples=50).failed
    # A run written without suspect counts: the condition cannot be evaluated, and says why.
    with pytest.raises(ExpressionError, match="A.suspects has no value: .*no suspect counts"):
        diff(old, b, fail_if="B.suspects > A.suspects", junit_path=junit, images=False, n_resamples=50)
    assert _parse_junit(junit.read_text())[1].get("errors") == "1"
    with pytest.raises(ExpressionError, match="unknown metric 'suspects.nope'"):
        diff(a, b, fail_if="B.suspects.nope > 0")


def test_diff_command_prints_suspect_counts_and_exits_1(tmp_path):
    from agvviz.cli.main import app

    clean_frames, suspect_frames = _frames(suspects={}), _frames()
    a = _write(tmp_path / "a.rrd", clean_frames, _summary(clean_frames, suspects={}), name="clean")
    b = _write(tmp_path / "b.rrd", suspect_frames, _summary(suspect_frames), name="faulty")
    result = CliRunner().invoke(app, ["diff", str(a), str(b), "--no-images", "--fail-if", "B.suspects > 0",
                                      "--junit-xml", str(tmp_path / "v.xml")])
    assert result.exit_code == 1, result.output
    output = " ".join(result.output.split())
    assert "suspect frames (checks without truth): A 0, B 4 (map_entry 0 → 3, mirror_flip 0 → 1)" in output
    assert "--fail-if holds: B.suspects > 0 (B.suspects = 4)" in output
    assert (tmp_path / "v.xml").is_file()


def test_run_gate_on_a_real_replay(qr_small, tmp_path):
    """`agvviz run --fail-if` end to end on a short recording: the counts gate on the replay's
    own summary (exit 1 / 0), the .rrd is written either way, the JUnit names the .rrd."""
    from agvviz.cli.main import app

    runner = CliRunner()
    out, junit = tmp_path / "run.rrd", tmp_path / "verdict.xml"
    args = ["run", str(qr_small), "--out", str(out), "--jobs", "1", "--no-cache", "--junit-xml", str(junit)]
    result = runner.invoke(app, [*args, "--fail-if", "solved >= 1 and frames >= solved"])
    assert result.exit_code == 1, result.output
    assert out.is_file()
    _, suite = _parse_junit(junit.read_text())
    assert suite.get("failures") == "1"
    assert {p.get("name"): p.get("value") for p in suite.iter("property")}["rrd"] == str(out)
    result = runner.invoke(app, [*args, "--fail-if", "solved_pct < 50", "--fail-if", "position_rmse_mm > 1000"])
    assert result.exit_code == 0, result.output
    assert _parse_junit(junit.read_text())[1].get("failures") == "0"
