"""A run's default layout frames the vehicle from outside and says when it has no truth (issue 26).

- The 3D view's eye (read back from the layout shipped in the ``.rrd``) tracks no entity — Rerun
  0.41 puts a tracking eye at 1.5 × the tracked entity's own bounding box, inside the AGV body —
  and from it every corner of both vehicle bodies (truth and estimate) at every frame lies in
  the viewer's vertical field of view, the eye outside each body: on a ``qr_floor`` run whose
  estimate is up to 2.8 m off (code Q015 turned 90° in the map) and on the same run with
  ``truth=ignore`` (the last frame too).
- Without truth the layout has no error plot that needs truth (position, heading, pitch, roll,
  error ÷ CRLB, NEES); a note says so where they were (``run/no_truth``), the position σ takes
  their place, and no truth body is drawn; with truth, the plots are there and the note is not.
- The UWB layout without truth likewise drops its error plots for the note.

Recording: qr_floor 3 s at 640×512 (30 frames), one run with truth, one with ``truth=ignore``.
"""

from __future__ import annotations

import numpy as np
import pytest

from agvviz.app.run import run_recording
from agvviz.scenarios import record
from agvviz.settings import RunSettings
from agvviz.viz import paths
from agvviz.viz.blueprints import NO_TRUTH_TITLE, STATE_LANES_KEY, VIEWER_FOV_Y_DEG, uwb_blueprint
from agvviz.viz.log_frames import AGV_BODY_CENTER_M, AGV_BODY_HALF_SIZES_M
from agvviz.viz.readback import blueprint_views, read_rrd, scalar_series, text_document, transforms

QR_OFF = ["duration_s=3", "width_px=640", "height_px=512", "focal_px=500", "inject=marker:Q015:yaw_deg=90"]
#: Error plots that need ground truth.
TRUTH_PLOTS = (paths.ERROR_POSITION_MM, paths.ERROR_HEADING_DEG, paths.ERROR_PITCH_DEG, paths.ERROR_ROLL_DEG,
               paths.ERROR_POSITION_OVER_CRLB, paths.ERROR_NEES)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eye")
    record("qr_floor", tmp / "qr.mcap", seed=0, overrides=QR_OFF)
    out = {}
    for name, settings in (("truth", RunSettings()), ("no_truth", RunSettings(truth="ignore"))):
        out[name] = tmp / f"{name}.rrd"
        run_recording(tmp / "qr.mcap", settings, out[name], jobs=1, cache_dir=False)
    return out


def _body_corners(T_world_agv: np.ndarray) -> np.ndarray:
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    corners_agv = np.asarray(AGV_BODY_CENTER_M) + signs * np.asarray(AGV_BODY_HALF_SIZES_M)
    return corners_agv @ T_world_agv[:3, :3].T + T_world_agv[:3, 3]


def _inside_body(T_world_agv: np.ndarray, point_world: np.ndarray) -> bool:
    local = T_world_agv[:3, :3].T @ (point_world - T_world_agv[:3, 3]) - np.asarray(AGV_BODY_CENTER_M)
    return bool(np.all(np.abs(local) <= np.asarray(AGV_BODY_HALF_SIZES_M)))


def _world_view(rrd):
    views = [v for v in blueprint_views(rrd) if v.kind == "3D"]
    assert len(views) == 1
    return views[0]


@pytest.mark.parametrize("name", ["truth", "no_truth"])
def test_the_3d_eye_sees_both_vehicles_from_outside_at_every_frame(runs, name):
    view = _world_view(runs[name])
    assert view.eye_tracking_entity is None, "a tracking eye sits at 1.5 × the tracked entity's own box"
    eye, target = np.asarray(view.eye_position), np.asarray(view.eye_look_target)
    forward = (target - eye) / np.linalg.norm(target - eye)
    half_fov_rad = np.radians(VIEWER_FOV_Y_DEG / 2)
    entities = [paths.AGV_CAMERA] + ([paths.AGV_TRUTH] if name == "truth" else [])
    frames_checked = set()
    for entity in entities:
        frames, _, poses = transforms(runs[name], entity)
        for frame, T in zip(frames, poses):
            assert not _inside_body(T, eye), (entity, frame)
            rays = _body_corners(T) - eye
            angles = np.arccos(np.clip(rays @ forward / np.linalg.norm(rays, axis=1), -1, 1))
            assert np.all(angles < half_fov_rad + np.radians(0.1)), (entity, frame, np.degrees(angles.max()))
            frames_checked.add(int(frame))
    assert len(frames_checked) >= 29  # the last frame too
    if name == "truth":  # the run holds the frames whose estimate is metres off
        _, errors_mm = scalar_series(runs[name], paths.ERROR_POSITION_MM)
        assert errors_mm.max() > 2000


def _plotted(view) -> set[str]:
    return {q.lstrip("+ ").lstrip("/") for q in view.contents} | {view.origin.lstrip("/")}


def test_a_run_without_truth_says_so_where_its_error_plots_were(runs):
    views = blueprint_views(runs["no_truth"])
    plotted = set().union(*(_plotted(v) for v in views if v.kind == "TimeSeries"))
    assert not plotted & set(TRUTH_PLOTS), plotted & set(TRUTH_PLOTS)
    assert paths.ERROR_POSITION_SIGMA_M in plotted and paths.ERROR_REPROJ_RMS_PX in plotted
    notes = [v for v in views if v.origin == paths.RUN_NO_TRUTH]
    assert [(v.kind, v.name) for v in notes] == [("TextDocument", NO_TRUTH_TITLE)]
    assert "No ground truth" in text_document(runs["no_truth"], paths.RUN_NO_TRUTH)
    contents = read_rrd(runs["no_truth"])
    assert paths.AGV_TRUTH_BODY not in contents.entity_paths  # no "truth" box at the origin
    assert "no truth" in _world_view(runs["no_truth"]).name


def test_a_run_with_truth_plots_its_errors_and_has_no_note(runs):
    views = blueprint_views(runs["truth"])
    plotted = set().union(*(_plotted(v) for v in views if v.kind == "TimeSeries"))
    assert set(TRUTH_PLOTS) <= plotted
    assert not [v for v in views if v.origin == paths.RUN_NO_TRUTH]
    contents = read_rrd(runs["truth"])
    assert paths.RUN_NO_TRUTH not in contents.entity_paths and paths.AGV_TRUTH_BODY in contents.entity_paths


def _walk(blueprint) -> list:
    found = []

    def walk(item):
        for child in getattr(item, "contents", None) or []:
            if not isinstance(child, str):
                walk(child)
        found.append(item)

    walk(blueprint.root_container)
    return found


def test_the_uwb_layout_without_truth_has_the_note_instead_of_its_error_plots():
    cams, anchors = ["east", "west"], ["A_east", "A_west"]
    origins = {True: [], False: []}
    for has_truth in (True, False):
        for view in _walk(uwb_blueprint(cams, set(cams), anchors, has_truth=has_truth)):
            origins[has_truth] += [str(getattr(view, "origin", ""))] + [str(q) for q in (getattr(view, "contents", None) or [])
                                                                       if isinstance(q, str)]
    joined = {k: " ".join(v) for k, v in origins.items()}
    for entity in (paths.ERROR_POSITION_MM, paths.ERROR_UWB_POSITION_MM, paths.ERROR_FUSED_POSITION_MM):
        assert entity in joined[True] and entity not in joined[False], entity
    assert paths.RUN_NO_TRUTH in joined[False] and paths.RUN_NO_TRUTH not in joined[True]
    assert paths.UWB_GDOP in joined[False]


def test_the_state_lanes_are_keyed_by_the_words_of_their_paths():
    """Rerun 0.41 labels a state lane with its entity path: the path's last part reads as words
    and the view's title says what each means."""
    for entity in (paths.FUSION_CAMERA_USED, paths.FUSION_SOURCE):
        word = entity.rsplit("/", 1)[-1]
        assert f"{word} = " in STATE_LANES_KEY and " " not in entity
