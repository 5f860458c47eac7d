"""Simulator: floor codes, AGV trajectories and honest camera rendering. Numpy/OpenCV only —
no files, no rerun, no mcap; every random draw comes from the caller's ``rng``.

- :mod:`agvviz.sim.render` — :class:`FloorCode`, :class:`FloorScene`, :func:`render_frame`,
  :func:`true_corners_px`, :func:`encode_jpeg`
- :mod:`agvviz.sim.qr_texture` — QR module matrices and :func:`make_floor_code`
- :mod:`agvviz.sim.trajectory` — rounded-rectangle track, dead reckoning, camera mount
"""

from agvviz.sim.qr_texture import make_floor_code, qr_symbol_modules
from agvviz.sim.render import (
    FloorCode,
    FloorScene,
    RenderError,
    encode_jpeg,
    render_frame,
    render_irradiance,
    true_corners_px,
)
from agvviz.sim.trajectory import (
    SIM_START_TIME_NS,
    RoundedRectangleTrack,
    Trajectory,
    dead_reckoning,
    forward_camera_mount,
    sample_track,
)

__all__ = [
    "FloorCode",
    "FloorScene",
    "RenderError",
    "encode_jpeg",
    "render_frame",
    "render_irradiance",
    "true_corners_px",
    "make_floor_code",
    "qr_symbol_modules",
    "SIM_START_TIME_NS",
    "RoundedRectangleTrack",
    "Trajectory",
    "dead_reckoning",
    "forward_camera_mount",
    "sample_track",
]
