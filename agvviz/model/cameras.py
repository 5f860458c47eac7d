"""What the replay knows about each camera, frozen: its calibration and extrinsic at the frame being
replayed. Built by the solve stage from :class:`agvviz.replay.sync.SyncState`; a change is a new
value, handed by the replay graph to the later stages and the sinks."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from agvviz.geometry import PinholeCamera
from agvviz.model.messages import CalibrationMsg


@dataclass(frozen=True)
class CameraState:
    """What the replay knows about one camera at the frame being replayed: its calibration and
    extrinsic (from :class:`SyncState`). Frozen: a change is a new state
    (:attr:`agvviz.replay.solve.ReplayContext.cameras`), so stages and sinks are handed values."""

    camera: PinholeCamera | None = None
    calibration_problem: str = ""  # why the last calibration of this camera was refused
    T_agv_cam: np.ndarray | None = None  # T_body_cam (the body frame is a setting)
    T_world_cam: np.ndarray | None = None  # a camera fixed in the world (paper 003's wall cameras)
    calibration: CalibrationMsg | None = None  # the message ``camera`` came from
    extrinsic_problem: str = ""  # why neither extrinsic is known
