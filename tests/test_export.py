"""agvviz export --format tum: a synthetic run with known poses is written, exported, and the
TUM lines parsed back and compared with the poses that went in."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from agvviz.app.export import ExportError, export_run, tum_time
from agvviz.geometry import se3
from agvviz.model.frames import REJECT_NO_MARKER, FrameResult
from agvviz.viz.run_logger import RunLogger

T0_NS = 1_700_000_000_123_456_789
N = 12
REJECTED = {4}


def _poses(rng: np.random.Generator) -> list[np.ndarray]:
    return [
        se3.make(Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix(), rng.uniform(-20, 20, 3))
        for _ in range(N)
    ]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    rng = np.random.default_rng(42)
    truth, estimate = _poses(rng), _poses(rng)
    path = tmp_path_factory.mktemp("export") / "synthetic.rrd"
    with RunLogger(path, recording_name="synthetic-lm", recording_id="export-test") as logger:
        for i in range(N):
            rejected = REJECT_NO_MARKER if i in REJECTED else None
            logger.log_frame(FrameResult(
                index=i, log_time_ns=T0_NS + i * 33_333_333, cam_name="front", image_format="jpeg",
                image_bytes=b"", rejected=rejected, T_world_agv=None if rejected else estimate[i],
                T_world_agv_truth=truth[i],
            ))
        logger.log_manifest({"recording_name": "synthetic-lm"})
    return path, truth, estimate


def _read_tum(path) -> tuple[list[str], np.ndarray]:
    stamps, values = [], []
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            continue
        fields = line.split()
        assert len(fields) == 8, line
        stamps.append(fields[0])
        values.append([float(x) for x in fields[1:]])
    return stamps, np.array(values)


def test_tum_files_hold_the_logged_poses(run, tmp_path):
    path, truth, estimate = run
    written = {item.which: item for item in export_run(path, "tum", tmp_path)}
    assert written["truth"].poses == N and written["estimate"].poses == N - len(REJECTED)
    for which, poses, frames in (
        ("truth", truth, range(N)),
        ("estimate", estimate, [i for i in range(N) if i not in REJECTED]),
    ):
        stamps, values = _read_tum(written[which].path)
        assert written[which].path.name == f"synthetic.{which}.tum"
        assert stamps == [tum_time(T0_NS + i * 33_333_333) for i in frames]
        want = np.array([poses[i] for i in frames])
        # Rerun stores translation and rotation as float32: ≈2e-6 m at 20 m, ≈1e-7 in R.
        np.testing.assert_allclose(values[:, :3], want[:, :3, 3], atol=1e-5)
        # Quaternions (x, y, z, w) checked with scipy's independent conversion.
        R = Rotation.from_quat(values[:, 3:7]).as_matrix()
        np.testing.assert_allclose(R, want[:, :3, :3], atol=1e-6)
        assert np.all(values[:, 6] >= 0)
        np.testing.assert_allclose(np.linalg.norm(values[:, 3:7], axis=1), 1.0, atol=1e-8)


def test_tum_time_is_exact():
    assert tum_time(1_700_000_000_123_456_789) == "1700000000.123456789"
    assert tum_time(5) == "0.000000005"
    assert tum_time(-1_500_000_000) == "-1.500000000"


def test_export_refuses_bad_requests(run, tmp_path):
    path, _, _ = run
    with pytest.raises(ExportError, match="unknown format 'kitti'"):
        export_run(path, "kitti", tmp_path)
    # A missing output folder is created (issue 10), not an error.
    written = export_run(path, "tum", tmp_path / "missing")
    assert [w.path.parent for w in written] == [tmp_path / "missing"] * 2
    with pytest.raises(ExportError, match="unknown trajectory"):
        export_run(path, "tum", tmp_path, which=("odometry",))


# -- MCAP (Foxglove) -----------------------------------------------------------------------------
def _read_mcap(path) -> tuple[dict, dict, list]:
    """(topic → [(log_time, decoded protobuf)], topic → (schema name, encodings), metadata)
    read with the mcap reader and decoded with the Foxglove protobuf schemas stored in the file."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    messages, schemas = {}, {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            messages.setdefault(channel.topic, []).append((message.log_time, decoded))
            schemas[channel.topic] = (schema.name, schema.encoding, channel.message_encoding)
        metadata = list(reader.iter_metadata())
    return messages, schemas, metadata


def _xyz(v) -> list[float]:
    return [v.x, v.y, v.z]


def _rotation(q) -> np.ndarray:
    return Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()


def test_mcap_holds_the_logged_poses_as_foxglove_messages(run, tmp_path):
    pytest.importorskip("foxglove", reason="foxglove-sdk (the export extra) is not installed")
    path, truth, estimate = run
    written = export_run(path, "mcap", tmp_path)
    assert [(w.which, w.path.name, w.poses) for w in written] == [
        ("estimate", "synthetic.poses.mcap", N - len(REJECTED)), ("truth", "synthetic.poses.mcap", N)]
    messages, schemas, metadata = _read_mcap(written[0].path)
    assert schemas == {
        "/agvviz/estimate/pose": ("foxglove.PoseInFrame", "protobuf", "protobuf"),
        "/agvviz/truth/pose": ("foxglove.PoseInFrame", "protobuf", "protobuf"),
        "/agvviz/tf": ("foxglove.FrameTransforms", "protobuf", "protobuf"),
    }
    assert metadata[0].name == "agvviz" and metadata[0].metadata["run"] == "synthetic-lm"
    transforms_by_child = {}
    for log_time, message in messages["/agvviz/tf"]:
        (tf,) = message.transforms
        assert tf.parent_frame_id == "world"
        assert tf.timestamp.seconds * 1_000_000_000 + tf.timestamp.nanos == log_time
        transforms_by_child.setdefault(tf.child_frame_id, []).append(tf)
    assert sorted(transforms_by_child) == ["agv_estimate", "agv_truth"]  # body frame "agv" (no manifest entry)
    for which, poses, frames in (
        ("truth", truth, range(N)),
        ("estimate", estimate, [i for i in range(N) if i not in REJECTED]),
    ):
        got = messages[f"/agvviz/{which}/pose"]
        want_ns = [T0_NS + i * 33_333_333 for i in frames]
        assert [t for t, _ in got] == want_ns  # log time = the frame's recording time, exact
        assert [m.timestamp.seconds * 1_000_000_000 + m.timestamp.nanos for _, m in got] == want_ns
        assert {m.frame_id for _, m in got} == {"world"}
        want = np.array([poses[i] for i in frames])
        # Rerun stores poses as float32 (≈2e-6 m at 20 m, ≈1e-7 in R); protobuf keeps float64.
        np.testing.assert_allclose([_xyz(m.pose.position) for _, m in got], want[:, :3, 3], atol=1e-5)
        np.testing.assert_allclose([_rotation(m.pose.orientation) for _, m in got], want[:, :3, :3], atol=1e-6)
        tfs = transforms_by_child[f"agv_{which}"]
        np.testing.assert_allclose([_xyz(tf.translation) for tf in tfs], want[:, :3, 3], atol=1e-5)
        np.testing.assert_allclose([_rotation(tf.rotation) for tf in tfs], want[:, :3, :3], atol=1e-6)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_mcap_without_the_sdk_names_the_extra(run, tmp_path, monkeypatch):
    path, _, _ = run
    monkeypatch.setitem(__import__("sys").modules, "foxglove", None)  # `import foxglove` fails
    with pytest.raises(ExportError, match=r"pip install 'agvviz\[export\]'"):
        export_run(path, "mcap", tmp_path)
    assert not list(tmp_path.iterdir())


# -- TUM checked against evo ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def qr_floor_run(tmp_path_factory):
    from agvviz import scenarios as scenario_registry
    from agvviz.app.run import run_recording
    from agvviz.settings import RunSettings

    tmp = tmp_path_factory.mktemp("evo")
    recording = tmp / "qr.mcap"
    scenario_registry.record("qr_floor", recording, seed=3, overrides=["duration_s=3", "rate_hz=5", "track_length_m=1", "realism=ideal"])
    return run_recording(recording, RunSettings(solver="ippe"), tmp / "qr-ippe.rrd").out_path


@pytest.mark.parametrize("align", ["none", "se3"])
def test_tum_export_gives_evo_ape_equal_to_agvviz(qr_floor_run, tmp_path, align):
    """``evo_ape tum truth.tum estimate.tum [--align]`` through evo's library equals agvviz's own
    APE (diff/compare's ape_trans_rmse_mm) of the same run."""
    pytest.importorskip("evo", reason="evo (the test extra) is not installed")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    from agvviz.app.run_series import load_run
    from agvviz.evaluation.comparison import run_metrics

    written = {w.which: w.path for w in export_run(qr_floor_run, "tum", tmp_path)}
    traj_ref = file_interface.read_tum_trajectory_file(str(written["truth"]))
    traj_est = file_interface.read_tum_trajectory_file(str(written["estimate"]))
    # Stamps are the same frames' times: associate exactly (max_diff far below the 0.1 s frame gap).
    traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=1e-4)
    if align == "se3":
        traj_est.align(traj_ref, correct_scale=False)  # Umeyama, as evo_ape --align
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    evo_rmse_mm = ape.get_statistic(metrics.StatisticsType.rmse) * 1000.0

    run = load_run(qr_floor_run)
    ours = run_metrics(run, align=align)
    assert traj_est.num_poses == ours["solved"] > 5
    # The TUM text writes positions with 9 significant digits: each coordinate of either pose is
    # off by at most 5e-9 of its magnitude, so each frame's error (and hence the RMSE, by the
    # triangle inequality of the RMS norm) by at most 2·√3·5e-9·max|coordinate|; the alignment of
    # se3 moves it by the same order. Twice that bound is allowed.
    max_coord_m = max(np.abs(traj_ref.positions_xyz).max(), np.abs(traj_est.positions_xyz).max())
    tolerance_mm = 2 * (2 * np.sqrt(3) * 5e-9 * max_coord_m) * 1000.0
    assert abs(evo_rmse_mm - ours["ape_trans_rmse_mm"]) <= tolerance_mm, (evo_rmse_mm, ours["ape_trans_rmse_mm"])


# -- a run without truth (issue 23: most real logs) ----------------------------------------------
@pytest.fixture(scope="module")
def runs_with_and_without_truth(tmp_path_factory):
    """The same 3-frame qr_floor recording replayed as recorded and with its truth topic
    dropped (rewritten with mcap's own writer)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from agvviz import scenarios as scenario_registry
    from agvviz.app.run import run_recording
    from agvviz.settings import RunSettings

    tmp = tmp_path_factory.mktemp("no_truth")
    recording = tmp / "qr.mcap"
    scenario_registry.record("qr_floor", recording, seed=2, overrides=["duration_s=0.6", "rate_hz=5", "realism=ideal"])
    no_truth = tmp / "qr_no_truth.mcap"
    with open(recording, "rb") as f_in, open(no_truth, "wb") as f_out:
        reader = make_reader(f_in)
        writer = Writer(f_out)
        writer.start(profile=reader.get_header().profile, library="test")
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if channel.topic == "/agv/ground_truth":
                continue
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id], dict(channel.metadata))
            writer.add_message(channels[channel.id], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time)
        writer.finish()
    with_truth = run_recording(recording, RunSettings(solver="ippe"), tmp / "with.rrd").out_path
    without = run_recording(no_truth, RunSettings(solver="ippe"), tmp / "without.rrd")
    assert without.summary["position_error_mm"]["n"] == 0 and without.summary["solved"] == 3
    return with_truth, without.out_path


def test_export_without_truth_writes_the_estimate_and_says_so(runs_with_and_without_truth, tmp_path):
    with_truth, without = runs_with_and_without_truth
    written = export_run(without, "tum", tmp_path)
    assert [(w.which, w.path.name, w.poses) for w in written] == [("estimate", "without.estimate.tum", 3)]
    assert "no ground truth" in written.missing["truth"]
    assert not (tmp_path / "without.truth.tum").exists()
    # the estimate does not depend on the truth: equal to the run that had it
    reference_written = export_run(with_truth, "tum", tmp_path / "ref")
    reference = {w.which: w for w in reference_written}
    assert reference["truth"].poses == 3 and not reference_written.missing
    got_stamps, got = _read_tum(written[0].path)
    want_stamps, want = _read_tum(reference["estimate"].path)
    assert got_stamps == want_stamps
    np.testing.assert_array_equal(got, want)
    # asking for the truth alone is still an error: there is nothing to write
    with pytest.raises(ExportError, match="no truth trajectory .*no ground truth"):
        export_run(without, "tum", tmp_path, which=("truth",))


def test_export_mcap_without_truth(runs_with_and_without_truth, tmp_path):
    pytest.importorskip("foxglove", reason="foxglove-sdk (the export extra) is not installed")
    _, without = runs_with_and_without_truth
    written = export_run(without, "mcap", tmp_path)
    assert [(w.which, w.path.name, w.poses) for w in written] == [("estimate", "without.poses.mcap", 3)]
    assert "truth" in written.missing
    messages, schemas, metadata = _read_mcap(written[0].path)
    assert sorted(schemas) == ["/agvviz/estimate/pose", "/agvviz/tf"]
    assert len(messages["/agvviz/estimate/pose"]) == 3
    assert metadata[0].metadata["trajectories"] == "estimate"


def test_cli_export_without_truth_exits_0_and_names_the_missing_truth(runs_with_and_without_truth, tmp_path):
    import subprocess
    import sys

    _, without = runs_with_and_without_truth
    (tmp_path / "without.truth.tum").write_text("# stale\n")  # an earlier export's file: named, kept
    proc = subprocess.run([sys.executable, "-m", "agvviz", "export", str(without), "--out-dir", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = " ".join(proc.stdout.split())
    assert "estimate: 3 poses" in out
    assert "truth: not written — the run has no ground truth" in out
    assert "was left as it was" in out and (tmp_path / "without.truth.tum").read_text() == "# stale\n"
    assert (tmp_path / "without.estimate.tum").is_file()
