"""The palette: every colour of every view, defined once. A colour means the same thing in 3D,
on images and in plots, and the legend names it (``LEGEND``).

Colours are RGB on the viewer's dark background. Pick from here; do not define colours in a
logger: ``tests/test_palette.py`` scans agvviz/ and fails on an RGB or hex literal anywhere else.
The table in docs/architecture.md ("The palette") lists them; keep it in step.
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

#: Background lines of a chart: the zero of a difference, an image's frame.
COLOR_ZERO = (130, 130, 130)
COLOR_IMAGE_FRAME = (110, 110, 110)
#: A difference B − A (``agvviz diff``).
COLOR_DELTA = (235, 235, 235)

#: Audit (``agvviz audit``): a marker or camera found misplaced, one that agrees with the map
#: (its estimated outline), one seen too little to judge; the recorded map is COLOR_MARKER.
COLOR_FLAGGED = COLOR_REJECTED
COLOR_OK = COLOR_CORRECTED
COLOR_SEEN_TOO_LITTLE = COLOR_STALE

#: Each pose solver of a study (p4p Monte-Carlo), and the CRLB they are held against. Told apart
#: by hue: lm and its variants are warm, closed forms cool, the bound a light grey.
SOLVER_COLORS = {
    "p4p": (60, 120, 255),
    "lm": (230, 40, 40),
    "lm_pixel": (255, 160, 0),
    "lm_amb": (255, 110, 200),
    "ippe": (40, 200, 90),
    "sqpnp": (0, 210, 230),
    "crlb": (230, 230, 230),
}
#: Their names, for the study plots' titles (the plots have no legend).
SOLVER_COLOR_NAMES = {
    "p4p": "blue",
    "lm": "red",
    "lm_pixel": "orange",
    "lm_amb": "pink",
    "ippe": "green",
    "sqpnp": "cyan",
    "crlb": "white",
}
#: Each method of a CNOEM study (multi-frame correction), and its CRLB.
CNOEM_COLORS = {
    "cnoem": (230, 40, 40),
    "cnoem_multistart": (255, 120, 120),
    "bundle": (255, 160, 0),
    "ippe_first": (40, 200, 90),
    "ippe_first_nav": (60, 120, 255),
    "ippe_mean_nav": (200, 120, 255),
    "crlb": (230, 230, 230),
}
#: A solver or method not in the tables above.
COLOR_OTHER = (200, 200, 200)

#: Error-budget sources (``agvviz budget``): a source that adds to the error, one whose share is
#: negative (switching it off made the error larger: interaction), and interaction/other.
COLOR_BUDGET_SOURCE = (255, 140, 0)
COLOR_BUDGET_NEGATIVE = (90, 200, 230)
COLOR_BUDGET_INTERACTION = (150, 150, 150)
#: Each error source's line in the budget's per-frame plots (``agvviz.sim.realism.SOURCES``;
#: ``imaging.<effect>`` takes imaging's), the recording's own error (all on) and the floor.
BUDGET_SOURCE_COLORS = {
    "calibration": (230, 40, 40),
    "map": (80, 160, 255),
    "timing": (240, 220, 60),
    "bumps": (170, 110, 255),
    "slip": (0, 200, 180),
    "imaging": (255, 0, 200),
}
#: Their names, for the plots' titles (the plots have no legend).
BUDGET_SOURCE_COLOR_NAMES = {
    "calibration": "red",
    "map": "blue",
    "timing": "yellow",
    "bumps": "violet",
    "slip": "teal",
    "imaging": "magenta",
}
COLOR_BUDGET_ALL_ON = (255, 255, 255)
COLOR_BUDGET_FLOOR = COLOR_ZERO


def budget_source_color(source: str) -> tuple[int, int, int]:
    """The colour of error source ``source`` in the budget's per-frame plots."""
    return BUDGET_SOURCE_COLORS.get(source.split(".")[0], COLOR_OTHER)


def solver_color_name(name: str) -> str:
    """The name of a study solver's colour (:data:`SOLVER_COLORS`) for view titles."""
    return SOLVER_COLOR_NAMES.get(name, "light grey")


def budget_source_color_name(source: str) -> str:
    """The name of :func:`budget_source_color` ``(source)`` for view titles."""
    return BUDGET_SOURCE_COLOR_NAMES.get(source.split(".")[0], "light grey")


def solver_color(name: str) -> tuple[int, int, int]:
    """The colour of study solver or CNOEM method ``name``."""
    return SOLVER_COLORS.get(name) or CNOEM_COLORS.get(name) or COLOR_OTHER


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
#: titles. Every one stands apart from the colours the overlay also draws: truth green, the
#: markers' blue, the UWB blue, the detected cyan and the white codes of the images
#: (``tests/test_palette.py`` holds the distance). No blue and no green among them.
PALETTE = (
    (255, 140, 0), (255, 0, 200), (240, 220, 60), (170, 110, 255),
    (230, 60, 60), (255, 170, 200), (150, 75, 30), (170, 170, 30),
)
PALETTE_NAMES = ("orange", "magenta", "yellow", "violet", "red", "pink", "brown", "olive")
#: A diff's runs: A and B.
COLOR_RUN_A = PALETTE[0]
COLOR_RUN_B = PALETTE[1]


def color_of(index: int) -> tuple[int, int, int]:
    """The colour of an overlay's run ``index``."""
    return PALETTE[index % len(PALETTE)]


def color_name(index: int) -> str:
    """The name of :func:`color_of` ``(index)`` for view titles."""
    return PALETTE_NAMES[index % len(PALETTE_NAMES)]
