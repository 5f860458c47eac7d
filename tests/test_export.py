"""agvviz export --format tum: a synthetic run with known poses is written, exported, and the
TUM lines parsed back and compared with the poses that went in."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from agvviz.export import ExportError, export_run, tum_time
from agvviz.geometry import se3
from agvviz.results import REJECT_NO_MARKER, FrameResult
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
