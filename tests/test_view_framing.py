"""3D views frame what matters (issue 26): the uwb_room outline from its anchors, the eye that
frames a box. Fast: no run, an in-memory recording stream."""

from __future__ import annotations

import numpy as np
import rerun as rr

from agvviz.scenarios.uwb_room import Options, anchor_positions
from agvviz.viz.blueprints import framing_eye
from agvviz.viz.log_uwb import log_room_outline


def test_room_outline_is_the_room_inset_by_the_anchors():
    options = Options()
    rec = rr.RecordingStream("agvviz-test-framing")  # memory-less: nothing is sent anywhere
    low, high = log_room_outline(rec, anchor_positions(options))
    # the anchors hang 2 cm inside the walls at anchor_height_m
    np.testing.assert_allclose(low, [0.02, 0.02, 0.0])
    np.testing.assert_allclose(high, [options.room_length_m - 0.02, options.room_width_m - 0.02, options.anchor_height_m])
    assert log_room_outline(rec, {"A": np.zeros(3)}) is None  # one anchor outlines nothing


def test_framing_eye_looks_at_the_box_centre_from_its_size():
    eye = framing_eye([0, 0, 0], [8, 6, 2], direction=(0.0, -1.0, 1.0))
    target = np.asarray(eye.look_target.as_arrow_array().to_pylist()[0])
    position = np.asarray(eye.position.as_arrow_array().to_pylist()[0])
    np.testing.assert_allclose(target, [4, 3, 1])
    np.testing.assert_allclose(position, [4, 3 - 8, 1 + 8])  # 8 m: the box's largest side
