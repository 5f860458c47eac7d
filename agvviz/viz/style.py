"""One palette for every view of every run: a colour means the same thing in 3D, on images
and in plots, and the legend names it (``LEGEND``).

Colours are RGB on the viewer's dark background. Pick from here; do not define colours in a
logger.
"""

from __future__ import annotations

#: Ground truth (simulated recordings, or a reference the log carries).
COLOR_TRUTH = (40, 200, 90)
#: The camera pipeline's estimate (one pose per frame).
COLOR_CAMERA = (255, 140, 0)
#: UWB-only position fixes.
COLOR_UWB = (70, 150, 255)
#: The fused estimate (camera + UWB).
COLOR_FUSED = (250, 220, 60)
#: Dead reckoning / navigation before correction.
COLOR_NAV = (230, 90, 60)
#: The multi-frame corrected trajectory (CNOEM); distinct from truth green.
COLOR_CORRECTED = (235, 80, 235)
#: A stale estimate (the last pose held over a rejected frame).
COLOR_STALE = (150, 150, 150)
#: Marker outlines and labels in 3D.
COLOR_MARKER = (80, 160, 255)
COLOR_MARKER_FILL = (25, 45, 75)  # dark: a faint face on the viewer's dark background
#: UWB anchors.
COLOR_ANCHOR = (120, 190, 255)
#: Corners found by the detector, and the solved pose's reprojection of the marker corners.
COLOR_DETECTED = (0, 230, 255)
COLOR_REPROJECTED = (255, 0, 200)
#: Rejections, thresholds and limits.
COLOR_REJECTED = (230, 40, 40)
COLOR_THRESHOLD = (230, 40, 40)
#: Suspect frames (issue 25): a solved pose that disagrees with what else the log knows. Lime, so
#: it stands out from every error line (orange, violet, light blue, yellow, magenta) and from the
#: red of rejections.
COLOR_SUSPECT = (170, 255, 0)
#: Angle error series.
COLOR_HEADING = (200, 120, 255)
COLOR_PITCH = (90, 200, 230)
COLOR_ROLL = (240, 220, 80)
#: The rejected mirror pose of a planar ambiguity (drawn only when it is a real contender).
COLOR_GHOST = (150, 110, 255)
#: Observed vs theoretical (correction residuals).
COLOR_OBSERVED = (255, 255, 255)
COLOR_THEORETICAL = (255, 170, 0)

#: Legend names of the shared colours, for series names and view titles.
LEGEND = {
    COLOR_TRUTH: "truth",
    COLOR_CAMERA: "camera estimate",
    COLOR_UWB: "UWB",
    COLOR_FUSED: "fused",
    COLOR_NAV: "navigation (uncorrected)",
    COLOR_CORRECTED: "corrected",
    COLOR_DETECTED: "detected corners",
    COLOR_REPROJECTED: "reprojected corners",
    COLOR_REJECTED: "rejected",
    COLOR_SUSPECT: "suspect",
}

#: The runs of an overlay (``agvviz diff``, ``sweep``) in order, with their names for view
#: titles. The first two (a diff's A and B) stand out from the truth green, the blue markers and
#: the white codes of the images.
PALETTE = (
    (255, 140, 0), (255, 0, 200), (30, 144, 255), (240, 220, 60),
    (170, 110, 255), (0, 200, 180), (230, 60, 60), (160, 230, 120),
)
PALETTE_NAMES = ("orange", "magenta", "blue", "yellow", "violet", "teal", "red", "light green")


def color_of(index: int) -> tuple[int, int, int]:
    """The colour of an overlay's run ``index``."""
    return PALETTE[index % len(PALETTE)]


def color_name(index: int) -> str:
    """The name of :func:`color_of` ``(index)`` for view titles."""
    return PALETTE_NAMES[index % len(PALETTE_NAMES)]
