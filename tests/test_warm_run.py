"""Issue 27, a warm run's in-process costs: what was cut must give the same values as before.

* a QR payload parsed once per run (candidates.PayloadMemo) gives what a fresh parse gives, and
  the same problem for a bad payload, every time;
* the detection cache read in one pass (ParquetFile) gives back what was saved, and reading it
  imports neither pyarrow.dataset nor pandas;
* a process that logs to an .rrd does not import pandas (viz.arrow_start), yet pyarrow's
  pandas conversions still work when asked for.
(The small-map centre search is tested in test_marker_map_scale.py; a run's .rrd equality with
`rerun rrd compare` in test_viz.py / test_sweep_file.py.)
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners
from agvviz.markers.payload import PayloadError, QrPayload, encode_payload, parse_payload
from agvviz.model.detections import CodeDetection, FrameDetections
from agvviz.replay.candidates import PayloadMemo
from agvviz.replay.detect import cache
from agvviz.replay.detect.pool import DetectedFrame


def _payload_text(x_m: float) -> str:
    corners = np.array([[x_m, 0.0, 0.0], [x_m + 0.3, 0.0, 0.0], [x_m + 0.3, 0.3, 0.0], [x_m, 0.3, 0.0]])
    return encode_payload(QrPayload(marker_id="Q7", points_world_m=corners))


def _subprocess(code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_memo_gives_what_a_fresh_parse_gives():
    memo = PayloadMemo()
    for text in (_payload_text(1.0), _payload_text(2.5), _payload_text(1.0).encode()):
        payload, T_world_marker, points_marker_m = memo.frame_of(text)
        fresh = parse_payload(text)
        T_fresh, points_fresh = marker_frame_from_corners(fresh.points_world_m)
        assert payload.marker_id == fresh.marker_id
        np.testing.assert_array_equal(payload.points_world_m, fresh.points_world_m)
        np.testing.assert_array_equal(T_world_marker, T_fresh)  # bit for bit: the same arithmetic
        np.testing.assert_array_equal(points_marker_m, points_fresh)
        again = memo.frame_of(text)
        assert again[1] is T_world_marker  # kept, not computed again
        with pytest.raises(ValueError):
            T_world_marker[0, 0] = 5.0  # read-only: no caller can change a later frame's


@pytest.mark.parametrize("text, error", [
    ("AGV1;id=Q1;mm=0,0;1,0;1,1", PayloadError),  # 3 points
    ("not a payload", PayloadError),
])
def test_memo_raises_the_parse_problem_every_time(text, error):
    memo = PayloadMemo()
    with pytest.raises(error) as first:
        parse_payload(text)
    for _ in range(3):
        with pytest.raises(error) as again:
            memo.frame_of(text)
        assert str(again.value) == str(first.value)
        # re-raised with a fresh traceback, not one that grows with every frame
        depth = 0
        tb = again.value.__traceback__
        while tb is not None:
            depth, tb = depth + 1, tb.tb_next
        assert depth <= 2


def test_memo_raises_degenerate_geometry_like_the_fresh_path(monkeypatch):
    from agvviz.replay import candidates

    def degenerate(points):
        raise DegenerateGeometryError("collinear")

    monkeypatch.setattr(candidates, "marker_frame_from_corners", degenerate)
    memo = PayloadMemo()
    for _ in range(2):
        with pytest.raises(DegenerateGeometryError, match="collinear"):
            memo.frame_of(_payload_text(1.0))


def _frames() -> list[DetectedFrame]:
    code = CodeDetection(
        kind="qr", corners_px=np.array([[1.0, 2.0], [3.5, 2.0], [3.5, 4.25], [1.0, 4.25]]),
        raw_corners_px=None, text=_payload_text(1.0), payload_bytes=None, aruco_id=None, n_modules=25,
        finder_px=None, finder_modules=None, refine_method="subpix", refine_note="",
    )
    return [
        DetectedFrame(0, "cam0", 1_000, FrameDetections(codes=(code,), reject=None, detect_s=0.0, keyframe=True)),
        DetectedFrame(1, "cam0", 2_000, FrameDetections(codes=(), reject=("no_marker", "none"), detect_s=0.0)),
    ]


def test_cache_round_trip(tmp_path):
    path = tmp_path / "entry.parquet"
    cache.save(path, _frames())
    loaded = cache.load(path)
    assert [(f.seq, f.cam_name, f.log_time_ns) for f in loaded] == [(0, "cam0", 1_000), (1, "cam0", 2_000)]
    code = loaded[0].detections.codes[0]
    np.testing.assert_array_equal(code.corners_px, _frames()[0].detections.codes[0].corners_px)
    assert code.text == _payload_text(1.0) and code.n_modules == 25 and code.refine_method == "subpix"
    assert loaded[1].detections.reject == ("no_marker", "none") and loaded[0].detections.keyframe


def test_cache_read_imports_neither_dataset_nor_pandas(tmp_path):
    path = tmp_path / "entry.parquet"
    cache.save(path, _frames())
    out = _subprocess(
        "import sys\n"
        "from pathlib import Path\n"
        "from agvviz.replay.detect import cache\n"
        f"frames = cache.load(Path({str(path)!r}))\n"
        "print(len(frames), 'pyarrow.dataset' in sys.modules, 'pandas' in sys.modules)\n"
    )
    assert out == "2 False False"


def test_logging_does_not_import_pandas_yet_to_pandas_works():
    out = _subprocess(
        "import sys, numpy as np\n"
        "import agvviz.viz\n"
        "import rerun as rr\n"
        "rec = rr.RecordingStream('t', recording_id='r')\n"
        "rec.log('p', rr.Points3D(np.zeros((3, 3))), rr.TextDocument('x'))\n"
        "rec.log('s', rr.Scalars([1.0]))\n"
        "before = 'pandas' in sys.modules\n"
        "import pyarrow as pa\n"
        "shape = pa.table({'a': [1, 2]}).to_pandas().shape\n"
        "print(before, shape)\n"
    )
    assert out == "False (2, 1)"
