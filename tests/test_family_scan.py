"""Issue 23, starting without a map: which marker family a recording's frames show.

Frames are rendered with OpenCV's own marker generator (ArUco, AprilTag) and the ``qrcode``
encoding agvviz uses (a QR code with an ``AGV1`` payload), written into Foxglove MCAP files with
the Foxglove SDK (a third-party writer, as a robot's log would be), and scanned by
``agvviz.replay.detect.family_scan`` / ``agvviz inspect`` / ``agvviz run``. The real photo
``../shared/data/opencv_contrib_aruco/singlemarkersoriginal.jpg`` (six DICT_6X6_250 markers,
ids 23, 40, 62, 98, 124, 203 — opencv_contrib's own test expectation) checks the scan on a
photograph with clutter.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from agvviz.geometry import se3
from agvviz.replay.detect.family_scan import FamilyMismatchError, family_check, map_skeleton_yaml, scan_recording
from agvviz.markers.scan import FamilyScan, sample_indices, scan_frame, smallest_dictionary
from agvviz.errors import InputError
from agvviz.recording.sidefiles import SideFileError, load_marker_map
from agvviz.replay.run import SideInputs, prepare
from agvviz.settings import RunSettings

foxglove = pytest.importorskip("foxglove", reason="foxglove-sdk is not installed")

W, H = 640, 480
FX = 500.0
T0_NS = 1_700_000_000_000_000_000
DT_NS = 100_000_000
N_FRAMES = 6
SIDE_PX = 84  # rendered side of a marker (its black square / the tag's black border)
APRIL_IDS = (1, 4, 9)
ARUCO_IDS = (3, 17, 60)  # DICT_5X5_1000 ids: 60 ≥ 50, so the smallest dictionary is DICT_5X5_100


def _data_dir() -> Path:
    """../shared/data from the repository (the main checkout) or from a worktree under /work/wt."""
    here = Path(__file__).resolve()
    for base in (here.parents[2], here.parents[3]):
        candidate = base / "shared" / "data"
        if candidate.is_dir():
            return candidate
    return here.parents[2] / "shared" / "data"


SINGLE_MARKERS = _data_dir() / "opencv_contrib_aruco" / "singlemarkersoriginal.jpg"


def _marker(dictionary: str, marker_id: int) -> np.ndarray:
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.generateImageMarker(d, marker_id, SIDE_PX, borderBits=1)


def _qr(text: str) -> np.ndarray:
    from agvviz.markers.qr import qr_modules

    modules = qr_modules(text)  # True = dark, (n, n), no quiet zone
    return cv2.resize(np.where(modules, 0, 255).astype(np.uint8), (SIDE_PX * 2, SIDE_PX * 2),
                      interpolation=cv2.INTER_NEAREST)


def render(k: int, kind: str) -> np.ndarray:
    """Frame ``k``: three markers on a light grey wall, moving 6 px per frame, blurred a little."""
    img = np.full((H, W), 190, np.uint8)
    if kind == "qr":
        patches = [_qr(f"AGV1;id=Q{i};mm=0,0;100,0;100,-100;0,-100") for i in (1, 2)]
    elif kind == "apriltag":
        patches = [_marker("DICT_APRILTAG_36h11", i) for i in APRIL_IDS]
    else:
        patches = [_marker("DICT_5X5_1000", i) for i in ARUCO_IDS]
    x = 40 + 6 * k
    for j, patch in enumerate(patches):
        patch = cv2.copyMakeBorder(patch, 16, 16, 16, 16, cv2.BORDER_CONSTANT, value=255)
        y = 60 + (j % 2) * 180
        img[y:y + patch.shape[0], x:x + patch.shape[1]] = patch
        x += patch.shape[1] + 40
    return cv2.GaussianBlur(img, (3, 3), 0.8)


def write_recording(path: Path, kind: str, marker_map: dict | None = None) -> Path:
    """A Foxglove MCAP (the SDK's writer): JPEG frames, a calibration, the camera on the body."""
    from foxglove.channels import (CameraCalibrationChannel, CompressedImageChannel,
                                   FrameTransformsChannel)

    m = foxglove.messages
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, allow_overwrite=True, context=context)
    try:
        images = CompressedImageChannel("/front/image", context=context)
        calibration = CameraCalibrationChannel("/front/calibration", context=context)
        tf_static = FrameTransformsChannel("/tf_static", context=context)
        q = se3.to_quaternion_xyzw(np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]]))
        tf_static.log(m.FrameTransforms(transforms=[m.FrameTransform(
            timestamp=m.Timestamp(T0_NS // 10**9, 0), parent_frame_id="base_link", child_frame_id="cam_front",
            translation=m.Vector3(x=0.2, y=0.0, z=0.5), rotation=m.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))]),
            log_time=T0_NS)
        if marker_map is not None:
            channel = foxglove.Channel("/markers/map", schema=foxglove.Schema(
                name="agvviz.MarkerMap", encoding="jsonschema", data=b"{}"), message_encoding="json", context=context)
            channel.log(json.dumps(marker_map).encode(), log_time=T0_NS)
        for k in range(N_FRAMES):
            t = T0_NS + k * DT_NS
            stamp = m.Timestamp(t // 10**9, t % 10**9)
            calibration.log(m.CameraCalibration(
                timestamp=stamp, frame_id="cam_front", width=W, height=H, distortion_model="plumb_bob",
                D=[0.0] * 5, K=[FX, 0, W / 2 - 0.5, 0, FX, H / 2 - 0.5, 0, 0, 1]), log_time=t)
            ok, jpeg = cv2.imencode(".jpg", render(k, kind), [cv2.IMWRITE_JPEG_QUALITY, 95])
            images.log(m.CompressedImage(timestamp=stamp, frame_id="cam_front", format="jpeg", data=jpeg.tobytes()),
                       log_time=t)
    finally:
        writer.close()
    return path


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("families")
    return {kind: write_recording(tmp / f"{kind}.mcap", kind) for kind in ("apriltag", "aruco", "qr")}


def _agvviz(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "agvviz", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


# -- the pure parts ------------------------------------------------------------------------------
def test_sample_indices_spread_over_the_recording():
    assert sample_indices(5, 20) == [0, 1, 2, 3, 4]
    picked = sample_indices(10_000, 20)
    assert len(picked) == 20 and picked[0] == 0 and picked[-1] == 9_999
    assert max(np.diff(picked)) - min(np.diff(picked)) <= 1
    assert sample_indices(0) == []


def test_smallest_dictionary_holds_every_id():
    assert smallest_dictionary("DICT_6X6_1000", [23, 40, 203]) == "DICT_6X6_250"
    assert smallest_dictionary("DICT_5X5_1000", [3, 17, 60]) == "DICT_5X5_100"
    assert smallest_dictionary("DICT_4X4_1000", [49]) == "DICT_4X4_50"
    assert smallest_dictionary("DICT_4X4_1000", [999]) == "DICT_4X4_1000"
    assert smallest_dictionary("DICT_APRILTAG_36h11", [500]) == "DICT_APRILTAG_36h11"
    # OpenCV's smaller dictionaries are the first ids of the 1000-id one (what makes this valid)
    small, large = (cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, n)) for n in ("DICT_6X6_250", "DICT_6X6_1000"))
    np.testing.assert_array_equal(small.bytesList, large.bytesList[:250])


@pytest.mark.parametrize("kind, family, ids", [
    ("apriltag", "DICT_APRILTAG_36h11", set(APRIL_IDS)),
    ("aruco", "DICT_5X5_100", set(ARUCO_IDS)),
    ("qr", "qr", {"Q1", "Q2"}),
])
def test_rendered_frames_name_their_family(kind, family, ids):
    scan = FamilyScan()
    for k in range(3):
        scan.add("front", scan_frame(render(k, kind)))
    found = scan.found()
    assert [f.dictionary for f in found] == [family], [f.describe() for f in scan.findings("front")]
    assert set(found[0].ids) == ids and found[0].frames_seen == 3
    want_side = SIDE_PX * (2 if kind == "qr" else 1)
    # contour corners of a blurred, JPEG-free render: within 2 px of the drawn side
    assert abs(found[0].side_px[1] - want_side) <= 2.0, found[0].side_px


@pytest.mark.skipif(not SINGLE_MARKERS.is_file(), reason=f"real photo {SINGLE_MARKERS} not present (see shared/data/MANIFEST.md)")
def test_real_photo_names_dict_6x6_and_its_ids():
    """opencv_contrib's singlemarkersoriginal.jpg: DICT_6X6_250, ids 23, 40, 62, 98, 124, 203
    (its test's expectation); a box's "fragile" symbol reads as DICT_4X4 id 17 and must be
    reported as a likely false hit, not as a family found."""
    scan = FamilyScan()
    scan.add("cam", scan_frame(cv2.imread(str(SINGLE_MARKERS), cv2.IMREAD_GRAYSCALE)))
    found = scan.found()
    assert [f.dictionary for f in found] == ["DICT_6X6_250"]
    assert set(found[0].ids) == {23, 40, 62, 98, 124, 203}
    assert all(f.likely_false for f in scan.findings("cam") if f.family != "DICT_6X6_1000")


# -- recordings --------------------------------------------------------------------------------
def test_scan_recording_samples_and_names(recordings):
    prepared = prepare(recordings["apriltag"], RunSettings())
    scan = scan_recording(prepared, frames_per_camera=4)
    assert scan.cameras() == ["front"] and scan.frames_sampled("front") == 4
    (finding,) = scan.found()
    assert finding.dictionary == "DICT_APRILTAG_36h11" and set(finding.ids) == set(APRIL_IDS)
    assert all(count == 4 for count in finding.ids.values())
    # after the probe frames only the families seen are looked for: the same findings
    narrowed = scan_recording(prepared, frames_per_camera=4, probe_frames=1)
    assert [(f.dictionary, f.ids) for f in narrowed.found()] == [(finding.dictionary, finding.ids)]


def test_inspect_lists_the_families_and_writes_a_map_skeleton(recordings, tmp_path):
    rec = recordings["apriltag"]
    out = tmp_path / "map.yaml"
    proc = _agvviz("inspect", rec, "--write-markers", out)
    # exit 1: as it is (no map) a run could use no frame; inspect says why and what to do
    assert proc.returncode == 1, proc.stderr
    text = " ".join(proc.stdout.split())
    assert "replay: the frames show DICT_APRILTAG_36h11 markers and no marker map places them" in text
    assert "can be used" not in text
    assert "markers seen in sampled frames" in text
    assert "AprilTag 36h11 (DICT_APRILTAG_36h11): in 6 of 6 sampled frame(s); ids 1×6, 4×6, 9×6" in text
    assert f"side {SIDE_PX - 1}" in text or f"side {SIDE_PX}" in text or f"side {SIDE_PX + 1}" in text
    assert "--write-markers map.yaml" in text and "marker map skeleton written" in text
    skeleton = yaml.safe_load(out.read_text())
    assert skeleton["dictionary"] == "DICT_APRILTAG_36h11"
    assert [m["id"] for m in skeleton["markers"]] == list(APRIL_IDS)
    assert all(m["side_m"] is None and m["pose"] is None for m in skeleton["markers"])
    assert "FILL IN" in out.read_text()
    # as written, the side-file reader refuses it by name
    with pytest.raises(SideFileError, match=r"markers\[0\] \(id 1\): side_m and pose empty — fill in"):
        load_marker_map(out)
    # filled in, it is a valid --markers map
    for k, marker in enumerate(skeleton["markers"]):
        marker["side_m"] = 0.16
        marker["pose"] = [1.0 + k, 3.0, 1.2, 0.7071068, 0, 0, 0.7071068]
    out.write_text(yaml.safe_dump(skeleton))
    loaded = load_marker_map(out)
    assert loaded["dictionary"] == "DICT_APRILTAG_36h11" and [m["id"] for m in loaded["markers"]] == ["1", "4", "9"]
    # the filled map passes run's family check, and inspect's
    family_check(prepare(rec, RunSettings(), side=SideInputs(marker_map=loaded)), str(rec))
    proc = _agvviz("inspect", rec, "--markers", out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "the map's family (DICT_APRILTAG_36h11) is seen in the sampled frames" in proc.stdout


def test_inspect_refuses_to_write_the_map_over_an_input(recordings, tmp_path):
    rec = recordings["aruco"]
    proc = _agvviz("inspect", rec, "--write-markers", rec)
    assert proc.returncode == 3 and proc.stderr.startswith("error: --write-markers") and "input" in proc.stderr
    assert proc.stderr.count("\n") == 1


def test_run_without_a_map_names_the_family_and_the_next_command(recordings, tmp_path):
    rec = recordings["aruco"]
    proc = _agvviz("run", rec, "--out", tmp_path / "x.rrd", "--jobs", "1")
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: no marker map, and the frames show ArUco DICT_5X5_100")
    assert "ids 3, 17, 60" in lines[0]
    assert f"agvviz inspect {rec} --write-markers map.yaml" in lines[0]
    assert not (tmp_path / "x.rrd").exists()


def test_qr_frames_need_no_map(recordings):
    rec = recordings["qr"]
    family_check(prepare(rec, RunSettings()), str(rec))  # QR codes carry their own positions
    with pytest.raises(Exception, match="only QR codes"):
        map_skeleton_yaml(scan_recording(prepare(rec, RunSettings()), 3), "qr")


def test_a_map_of_another_family_is_one_line(recordings, tmp_path):
    rec = recordings["apriltag"]
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text(yaml.safe_dump({"dictionary": "DICT_6X6_250", "markers": [
        {"id": 1, "side_m": 0.16, "pose": [1.0, 3.0, 1.2, 0.7071068, 0, 0, 0.7071068]}]}))
    with pytest.raises(FamilyMismatchError, match="the marker map says ArUco DICT_6X6_250, but the frames show AprilTag 36h11"):
        family_check(prepare(rec, RunSettings(), side=SideInputs(marker_map=load_marker_map(wrong))), str(rec))
    proc = _agvviz("inspect", rec, "--markers", wrong)
    assert proc.returncode == 1
    assert "map says DICT_6X6_250, frames show DICT_APRILTAG_36h11" in " ".join(proc.stdout.split())
    proc = _agvviz("run", rec, "--markers", wrong, "--out", tmp_path / "w.rrd", "--jobs", "1")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "the marker map says" in proc.stderr


def test_a_recorded_map_of_another_family(tmp_path):
    """The map inside the recording (/markers/map), as a robot's log could carry it."""
    marker_map = {"dictionary": "DICT_4X4_50", "markers": [{"id": "1", "side_m": 0.2, "corners_world_m": [
        [0, 0.1, 1.1], [0.2, 0.1, 1.1], [0.2, 0.1, 0.9], [0, 0.1, 0.9]]}]}
    rec = write_recording(tmp_path / "mapped.mcap", "apriltag", marker_map)
    prepared = prepare(rec, RunSettings())
    assert prepared.replay.ctx.marker_map["dictionary"] == "DICT_4X4_50"
    with pytest.raises(FamilyMismatchError, match="says ArUco DICT_4X4_50, but the frames show AprilTag 36h11"):
        family_check(prepared, str(rec))


@pytest.mark.parametrize("suffix", ["yaml", "json"])
def test_a_map_id_listed_twice_is_one_line(tmp_path, suffix):
    document = {"dictionary": "DICT_APRILTAG_36h11", "markers": [
        {"id": 4, "side_m": 0.16, "pose": [1.0, 3.0, 1.2, 0, 0, 0, 1]},
        {"id": 4, "side_m": 0.16, "pose": [2.0, 3.0, 1.2, 0, 0, 0, 1]}]}
    path = tmp_path / f"dup.{suffix}"
    path.write_text(yaml.safe_dump(document) if suffix == "yaml" else json.dumps(document))
    with pytest.raises(SideFileError, match=r"marker id '4' appears twice \(entries 0 and 1"):
        load_marker_map(path)
    proc = _agvviz("inspect", tmp_path / "missing.mcap", "--markers", path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "appears twice" in proc.stderr


def test_a_recorded_map_with_an_id_twice_is_one_line(tmp_path):
    """An agvviz.MarkerMap in the recording listing id 1 twice: the replay refused it and then
    rejected every frame as no_marker with exit 0; now inspect and run say why in one line."""
    corners = [[0, 0.1, 1.1], [0.2, 0.1, 1.1], [0.2, 0.1, 0.9], [0, 0.1, 0.9]]
    marker_map = {"dictionary": "DICT_APRILTAG_36h11", "markers": [
        {"id": "1", "side_m": 0.2, "corners_world_m": corners}, {"id": "1", "side_m": 0.2, "corners_world_m": corners}]}
    rec = write_recording(tmp_path / "dup.mcap", "apriltag", marker_map)
    proc = _agvviz("run", rec, "--out", tmp_path / "d.rrd", "--jobs", "1")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith("error: the marker map cannot be used: id 1 appears more than once")
    proc = _agvviz("inspect", rec)
    assert proc.returncode == 1 and "the marker map cannot be used: id 1 appears more than once" in proc.stdout


def test_a_qr_map_with_an_id_twice_is_named():
    """The replay would keep the last of two entries of a QR id silently; the check names it
    (counted, not compared pairwise: a 200 000-code map stays linear)."""
    from types import SimpleNamespace

    from agvviz.replay.detect.family_scan import map_problem

    corners = [[0, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0]]
    markers = [{"id": f"Q{i}", "corners_world_m": corners} for i in range(200_000)] + [{"id": "Q7", "corners_world_m": corners}]
    ctx = SimpleNamespace(marker_map={"dictionary": "qr", "markers": markers}, marker_map_problem="")
    prepared = SimpleNamespace(replay=SimpleNamespace(ctx=ctx))
    assert map_problem(prepared) == "marker map: id Q7 appears more than once"
    ctx.marker_map = {"dictionary": "qr", "markers": markers[:-1]}
    assert map_problem(prepared) == ""


def test_frames_in_the_detection_cache_are_not_scanned_again_the_map_is(recordings, tmp_path, monkeypatch):
    """A run whose detections are in the cache passed the family check when they were detected
    (the cache key holds the recording's content and the marker family): its frame scan is not
    made again. The marker map is still checked, and `detect_recording`, which also fills the
    cache, refuses frames of the wrong family as `run` does."""
    from agvviz.app.run import run_recording
    from agvviz.replay.detect import family_scan
    from agvviz.replay.run import detect_recording

    with pytest.raises(FamilyMismatchError, match="no marker map, and the frames show ArUco DICT_5X5_100"):
        detect_recording(recordings["aruco"], RunSettings(), cache_dir=tmp_path / "cache", jobs=1)
    assert not list((tmp_path / "cache").rglob("*.parquet"))

    scans = []
    real_scan = family_scan.scan_recording
    monkeypatch.setattr(family_scan, "scan_recording", lambda *a, **k: scans.append(1) or real_scan(*a, **k))
    rec, cache = recordings["qr"], tmp_path / "cache"
    first = run_recording(rec, RunSettings(), tmp_path / "a.rrd", cache_dir=cache, jobs=1)
    assert first.timing["detection_source"] == "detected" and len(scans) == 1
    second = run_recording(rec, RunSettings(solver="ippe"), tmp_path / "b.rrd", cache_dir=cache, jobs=1)
    assert second.timing["detection_source"] == "cache" and len(scans) == 1  # no second scan
    run_recording(rec, RunSettings(), tmp_path / "c.rrd", cache_dir=False, jobs=1)
    assert len(scans) == 2  # without a cache: scanned
    # the map is checked still (here one carried by the recording, with an id listed twice)
    corners = [[0, 0.1, 1.1], [0.2, 0.1, 1.1], [0.2, 0.1, 0.9], [0, 0.1, 0.9]]
    dup = write_recording(tmp_path / "dup.mcap", "apriltag", {"dictionary": "DICT_APRILTAG_36h11", "markers": [
        {"id": "1", "side_m": 0.2, "corners_world_m": corners}, {"id": "1", "side_m": 0.2, "corners_world_m": corners}]})
    with pytest.raises(InputError, match="the marker map cannot be used: id 1 appears more than once"):
        family_check(prepare(dup, RunSettings()), str(dup), frames_checked=True)
