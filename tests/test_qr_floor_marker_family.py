"""qr_floor's ``marker_family`` option: ArUco / AprilTag markers on the floor instead of QR codes,
replayed by ``agvviz run`` from the recorded map alone (issue 23 item 2)."""

from __future__ import annotations

import pytest

from agvviz import scenarios as scenario_registry
from agvviz.app.run import run_recording
from agvviz.scenarios import ScenarioError
from agvviz.settings import RunSettings

# 4 frames of a half-size camera (640×512, f = 500 px, 2×2 supersampling) over the default grid
# of 0.5 m markers: ≈2 s to record and replay each.
SMALL = ["duration_s=0.8", "rate_hz=5", "realism=ideal", "width_px=640", "height_px=512", "focal_px=500", "supersample=2"]
#: Largest accepted position error. Under ``ideal`` only the render's blur (0.8 px), noise (2 DN)
#: and JPEG remain; ECC corners are ≈0.05 px off on such renders, ≈2 mm of position here (a
#: 0.5 m marker ≈150 px wide from ≈1.8 m). 20 mm is the Cramér–Rao bound at σ ≈ 0.5 px for this
#: camera (DESIGN §8: 6 mm at 0.3 px with twice the focal length): margin for a hard frame, and
#: far below what a turned corner order does (the camera mirrored about the marker: metres).
MAX_POSITION_ERROR_MM = 20.0


@pytest.mark.parametrize("family", ["DICT_APRILTAG_36h11", "DICT_5X5_100"])
def test_floor_markers_replay_without_side_file(family, tmp_path):
    recording = tmp_path / f"{family}.mcap"
    scenario_registry.record("qr_floor", recording, seed=5, overrides=SMALL + [f"marker_family={family}"])
    outcome = run_recording(recording, RunSettings(), tmp_path / "run.rrd", jobs=1, cache_dir=False)
    s = outcome.summary
    assert s["frames"] == 4 and s["solved"] == 4, s.get("rejected")
    assert s["position_error_mm"]["n"] == 4
    assert s["position_error_mm"]["max"] < MAX_POSITION_ERROR_MM
    assert s["heading_error_deg"]["max"] < 0.5


@pytest.mark.parametrize(
    "overrides,match",
    [
        (["marker_family=DICT_9X9_1"], "unknown ArUco dictionary"),
        (["marker_family=DICT_APRILTAG_36h10"], "36h10 is not supported"),
        (["marker_family=DICT_4X4_50"], "holds 63 markers but DICT_4X4_50 has 50 ids"),
        (["marker_family=DICT_5X5_100", "with_midpoints=true"], "QR payloads only"),
    ],
)
def test_marker_family_refused_with_one_line(overrides, match):
    with pytest.raises(ScenarioError, match=match):
        scenario_registry.build_options("qr_floor", overrides)
