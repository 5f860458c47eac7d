"""Shared pytest configuration.

The ``campaign`` marker (issue 10's long robustness campaign) is deselected unless the
``-m`` expression names it: ``pytest -q`` skips it, ``pytest -q -m campaign`` runs it.
"""

from __future__ import annotations


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "campaign: the long robustness campaign (deselected unless -m names 'campaign')"
    )


def pytest_collection_modifyitems(config, items):
    if "campaign" in (config.getoption("markexpr", "") or ""):
        return
    keep, drop = [], []
    for item in items:
        (drop if item.get_closest_marker("campaign") else keep).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


import pytest


@pytest.fixture(autouse=True, scope="session")
def _detection_cache_in_tmp(tmp_path_factory):
    """Runs store detections in a cache folder (agvviz.replay.detect.cache): the suite's go to a
    temporary folder, never the user's ~/.cache (subprocesses inherit the variable)."""
    import os

    folder = tmp_path_factory.mktemp("detection-cache")
    old = os.environ.get("AGVVIZ_CACHE_DIR")
    os.environ["AGVVIZ_CACHE_DIR"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("AGVVIZ_CACHE_DIR", None)
    else:
        os.environ["AGVVIZ_CACHE_DIR"] = old


#: uwb_room, 3 s at 5 Hz (15 time stamps × 4 wall cameras), the cameras blocked from 1.0 s to
#: 2.0 s, ideal world, seed 4. tests/test_uwb_room.py and tests/test_fusion_views.py both check
#: this one recording and its mean-compensation run, so it is recorded and replayed once.
UWB_ROOM_SMALL = ["duration_s=3", "rate_hz=5", "block_start_s=1.0", "block_end_s=2.0", "realism=ideal"]


@pytest.fixture(scope="session")
def uwb_room_small_run(tmp_path_factory):
    """(recording, outcome) of ``UWB_ROOM_SMALL`` (seed 4) replayed with fusion=mean_compensation.
    Read only: tests must not modify the recording or the run's .rrd."""
    from agvviz import scenarios as scenario_registry
    from agvviz.app.run import run_recording
    from agvviz.settings import RunSettings

    tmp = tmp_path_factory.mktemp("uwb_room_small")
    recording = tmp / "uwb_room.mcap"
    scenario_registry.record("uwb_room", recording, seed=4, overrides=UWB_ROOM_SMALL)
    outcome = run_recording(recording, RunSettings(fusion="mean_compensation"), tmp / "run.rrd")
    return recording, outcome


#: qr_floor, 4 frames at 640×512, ideal world, seed 1: the source of truth that
#: tests/test_real_logs.py, test_ros1_bag.py and test_tf_extrinsic.py rewrite with other tools
#: (rosbags, foxglove-sdk) and compare against, so it is recorded once.
QR_SMALL = ["duration_s=0.4", "width_px=640", "height_px=512", "focal_px=500", "realism=ideal"]


@pytest.fixture(scope="session")
def qr_small(tmp_path_factory):
    """Path of the ``QR_SMALL`` recording (seed 1). Read only."""
    from agvviz.scenarios import record

    path = tmp_path_factory.mktemp("qr_small") / "qr.mcap"
    record("qr_floor", path, seed=1, overrides=QR_SMALL)
    return path


@pytest.fixture(scope="session")
def qr_small_content(qr_small) -> dict:
    """What ``qr_small`` holds, decoded by agvviz's reader: ``images`` [(log time, JPEG bytes)],
    ``calibration`` (camera), ``T_agv_cam``, ``truth`` and ``odometry`` [(log time, T)],
    ``marker_map``. Read only."""
    from agvviz.model.messages import CalibrationMsg, CompressedFrame, FrameTransformMsg, PoseMsg
    from agvviz.recording.reader import iter_messages

    out = {"images": [], "truth": [], "odometry": []}
    for m in iter_messages(qr_small):
        v = m.value
        if isinstance(v, CompressedFrame):
            out["images"].append((m.log_time_ns, v.data))
        elif isinstance(v, CalibrationMsg):
            out["calibration"] = v.camera
        elif isinstance(v, list) and v and isinstance(v[0], FrameTransformMsg):
            out["T_agv_cam"] = v[0].T_parent_child
        elif isinstance(v, PoseMsg) and m.topic == "/agv/ground_truth":
            out["truth"].append((m.log_time_ns, v.T))
        elif isinstance(v, PoseMsg) and m.topic == "/agv/odometry":
            out["odometry"].append((m.log_time_ns, v.T))
        elif isinstance(v, dict) and m.topic == "/markers/map":
            out["marker_map"] = v
    return out
