"""Geometry: SO(3)/SE(3), Euler Z-X-Y, pinhole camera. Numpy only — no I/O, no rerun.

Conventions: :mod:`agvviz.conventions`.
"""

from agvviz.geometry import euler, se3, so3
from agvviz.geometry.camera import PinholeCamera
from agvviz.geometry.plane import marker_frame_from_corners

__all__ = ["so3", "se3", "euler", "PinholeCamera", "marker_frame_from_corners"]
