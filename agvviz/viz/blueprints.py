"""Every viewer layout (Rerun blueprint) agvviz ships inside an ``.rrd`` — one module for all of them.

Builders, by the file they lay out:

- a run: :func:`default_blueprint` (camera runs), :func:`uwb_blueprint` (UWB and fusion, paper
  003), :func:`correction_blueprint` (the correction cycle, paper 002), :func:`trials_blueprint`
  (a p4p Monte-Carlo study run), :func:`cnoem_trials_blueprint` (a CNOEM grid study run); the
  error budget's views join the default layout of ``agvviz run --budget``;
- ``agvviz budget``: :func:`budget_blueprint`; ``agvviz audit``: :func:`audit_blueprint`;
  ``agvviz diff`` / ``sweep``: :func:`overlay_blueprint`;
- the studies' own report files: :func:`study_blueprint` (Monte-Carlo) and
  :func:`cnoem_report_blueprint` (CNOEM grid).

:func:`with_active_tab` shows a tab, picked by name, of a layout as the viewer reads it back
(docs/make_pictures.py ``--tab``: pictures of tabs a layout does not open on).

Views take their origins from :mod:`agvviz.viz.paths` only.
Longer than 600 lines because it holds the ten layouts side by side (each a single function that reads top to
bottom like its sketch), so a new view is added in one place; splitting it by layout would
bring back a blueprint file per logger.

The default run layout::

    ┌──────────────────────────────┬──────────────────────────────────────┐
    │ 3D world, the whole run in   │ camera image: corners, ids, LM path  │
    │ view (markers, truth vs      │ (one tab per camera; zoom on a small │
    │ estimate, ghost, ellipsoid,  │  code beside it)                     │
    │ trajectories)                ├──────────────────────────────────────┤
    │                              │ this frame's solve (text) + LM tabs  │
    ├──────────────┬───────────────┼─────────────┬────────────────────────┤
    │ position err │ heading err   │ reproj RMS  │ summary (terminal      │
    │ (+ rejected, │ (tabs: pitch, │ + threshold │ table) / manifest /    │
    │  suspect)    │  roll)        │ (tabs)      │ flips; suspects log /  │
    │              │               │             │ rejections log         │
    └──────────────┴───────────────┴─────────────┴────────────────────────┘

A run's time series are on ``elapsed`` (seconds since the recording's start, ``vs t [s]`` in
their titles); their y axes come from the whole run (:func:`run_plot_axes`); they have no legend
(in Rerun 0.41 it sits on the data): the title names the series, and a rejected frame is a gap
with a red × (:mod:`agvviz.viz.log_rejections`).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from agvviz.errors import InputError
from agvviz.evaluation.error_budget import ErrorBudget
from agvviz.model.frames import REJECT_REPROJECTION
from agvviz.model.studies import CellResult
from agvviz.viz import paths
from agvviz.viz.style import (
    COLOR_CAMERA,
    COLOR_CORRECTED,
    COLOR_FUSED,
    COLOR_NAV,
    COLOR_TRUTH,
    COLOR_UWB,
    LEGEND,
    SOLVER_COLORS,
    budget_source_color_name,
    color_of,
    solver_color_name,
)

#: A run's logs: the time in seconds and the line (no entity path column).
#: The suspects' and rejections' logs: the frame (``#13``: narrower than the elapsed time, which
#: took a third of the panel and cut the body short) and the body, whose first line holds the key
#: facts (:mod:`agvviz.viz.log_findings`' rows).
_LOG_COLUMNS = rrb.TextLogColumns(timeline_columns=[paths.TIMELINE_FRAME], text_log_columns=["body"])
#: A run's time series name their series in the title (a legend in Rerun 0.41 sits on the data).
_NO_LEGEND = rrb.PlotLegend(visible=False)

# -- a run's time series: axes from the whole run's data ------------------------------------------
#: Above a plot's highest value, a band this fraction of the data's span high holds the
#: rejected-frame crosses (at the band's middle): they neither hide a value nor leave the axis.
MARKER_BAND = 0.08
#: A plot whose largest value is more than this many times its 99th percentile is clipped at that
#: percentile (its title says so and how many values are above): a few metre-size UWB outliers
#: (NLOS) would flatten every other value.
CLIP_OVER_P99 = 3.0


@dataclass(frozen=True)
class PlotAxis:
    """The y axis of one time-series plot, set from the whole run's values (Rerun's auto range
    follows what is on screen and cut extremes off): ``low``..``high`` holds every value (or
    says in ``note`` where it clips), ``marker_y`` is where rejected-frame crosses sit."""

    low: float
    high: float
    marker_y: float
    note: str = ""

    def scalar_axis(self) -> rrb.ScalarAxis:
        return rrb.ScalarAxis(range=(self.low, self.high))

    def holds(self, value: float) -> bool:
        return self.low <= value <= self.high


def plot_axis(extents: list[tuple[float, float]], *, include_zero: bool = True, note: str = "") -> PlotAxis:
    """The axis of a plot whose series span ``extents`` ((lowest, highest) each): every value
    (and 0 unless ``include_zero`` is False) inside, the marker band above."""
    lows = [low for low, _ in extents] + ([0.0] if include_zero or not extents else [])
    highs = [high for _, high in extents] + ([0.0] if include_zero or not extents else [])
    low, high = min(lows), max(highs)
    span = high - low if high > low else max(abs(high), 1.0)
    return PlotAxis(
        low=low - 0.03 * span, high=high + 2.0 * MARKER_BAND * span, marker_y=high + MARKER_BAND * span, note=note
    )


def clipped_axis(values: list[float], unit: str) -> PlotAxis:
    """:func:`plot_axis` of ``values`` (≥ 0), clipped at their 99th percentile when the largest is
    more than CLIP_OVER_P99 times it; the note then says where and what is above."""
    if not values:
        return plot_axis([])
    data = np.asarray(values, dtype=float)
    p99, largest = float(np.quantile(data, 0.99)), float(data.max())
    if largest <= CLIP_OVER_P99 * p99:
        return plot_axis([(float(data.min()), largest)])
    above = int(np.sum(data > p99))
    return plot_axis(
        [(float(data.min()), p99)],
        note=f"clipped at {p99:.0f} {unit} ({above} of {len(data)} above, max {largest:.0f})",
    )


def run_plot_axes(
    extents: dict[str, tuple[float, float]], *, max_reproj_px: float | None, rejection_reasons: list[str]
) -> dict[str, PlotAxis]:
    """The axis of the plot of each series of :data:`paths.REJECTION_MARKED` from ``extents``
    (entity → (lowest, highest) value of the run). The reprojection plot ranges to its data: it
    reaches up to ``max_reproj_px`` only when frames were rejected for their reprojection (their
    crosses sit on that line), else its title says the limit is above the axis."""
    axes = {}
    for entity in paths.REJECTION_MARKED:
        series = [extents[entity]] if entity in extents else []
        note = ""
        if entity == paths.ERROR_NEES:
            series += [extents[e] for e in (paths.ERROR_NEES_EXPECTED, paths.ERROR_NEES_BOUND_99) if e in extents]
        if entity == paths.ERROR_REPROJ_RMS_PX and max_reproj_px is not None:
            if REJECT_REPROJECTION in rejection_reasons:
                series.append((max_reproj_px, max_reproj_px))
            elif not plot_axis(series).holds(max_reproj_px):
                note = f"max_reproj_px {max_reproj_px:g} above the axis"
        axes[entity] = plot_axis(series, note=note)
    return axes


def series_title(quantity: str, *, rejected: bool = False, suspect: bool = False, note: str = "") -> str:
    """A time series' title: the quantity with its unit against the run's time (``t [s]``:
    seconds since the recording's start, the timeline a run opens on), where its axis clips, and
    what its markers mean (no legend: in Rerun 0.41 it sits on the data). Most important first:
    a narrow view cuts the end off."""
    parts = [f"{quantity} vs t [s]"]
    if note:
        parts.append(note)
    if rejected:
        parts.append("× rejected (hover: why)")
    if suspect:
        parts.append("◆ suspect")
    return " · ".join(parts)


def series_view(
    entity: str,
    quantity: str,
    axis: PlotAxis | None,
    *,
    rejected: bool = False,
    suspect: bool = False,
    extra: tuple[str, ...] = (),
) -> rrb.TimeSeriesView:
    """The plot of ``entity`` (+ ``extra`` lines) against the run's time with the rejected-frame
    crosses (``errors/rejected/<series>/*``) and, on the error plots, the suspect diamonds
    (``errors/suspect/<series>``, at the frame's value on the line); y axis ``axis``."""
    contents = [entity, *extra]
    if suspect and entity in paths.SUSPECT_MARKED:
        contents.append(paths.error_suspect(entity))
    if rejected:
        contents.append(paths.error_rejected_all(entity))
    return rrb.TimeSeriesView(
        origin="/",
        contents=[f"/{e}" for e in contents],
        name=series_title(quantity, rejected=rejected, suspect=suspect and entity in paths.SUSPECT_MARKED,
                          note="" if axis is None else axis.note),
        plot_legend=_NO_LEGEND,
        axis_y=None if axis is None else axis.scalar_axis(),
    )


#: Direction (world, from the scene's centre) the default run view's eye looks from: behind-left
#: and above, so the vehicles, the 3σ ellipsoid above the body and the codes on the floor are
#: seen from outside and at an angle.
RUN_EYE_DIRECTION = (-0.55, -0.75, 0.75)
#: The viewer's vertical field of view (Rerun 0.41: ``Eye.DEFAULT_FOV_Y``, 55°); a view is wider
#: than tall, so the vertical angle is the one a scene must fit in.
VIEWER_FOV_Y_DEG = 55.0


def world_3d_view(
    name: str,
    cam_names: list[str],
    fixed_cams: set[str] = frozenset(),
    eye: rrb.EyeControls3D | None = None,
) -> rrb.Spatial3DView:
    """The 3D world view with the eye ``eye`` (None: Rerun's default). The 2D overlays of the
    images (corners, ids, LM path: UI-point sizes that would swamp the small frustum images) stay
    in the 2D image views.

    No view of a run tracks an entity: Rerun 0.41 places a tracking eye at 1.5 × the radius of
    the tracked entity's *own* bounding box (``re_view_spatial/src/eye.rs``,
    ``handle_tracking_entity``) whatever position the blueprint gives, and the estimated AGV's own
    box is its 0.5 m axes: the eye sat inside the 0.8 m body."""
    excluded = [f"- /{e}" for c in cam_names for e in paths.image_overlays(c, c in fixed_cams)]
    return rrb.Spatial3DView(origin=paths.WORLD, name=name, contents=["+ $origin/**", *excluded], eye_controls=eye)


def fitting_eye(low_m, high_m, direction=RUN_EYE_DIRECTION, fov_y_deg: float = VIEWER_FOV_Y_DEG) -> rrb.EyeControls3D:
    """An eye that keeps the box ``low_m``..``high_m`` (world, m) whole in view: it looks at the
    box's centre from ``direction``, at the distance where the box's bounding sphere fits the
    vertical field of view ``fov_y_deg`` (so every point of the box is in view, from any
    direction, and the eye is outside the box)."""
    low, high = np.asarray(low_m, dtype=float), np.asarray(high_m, dtype=float)
    center = (low + high) / 2.0
    radius = max(float(np.linalg.norm(high - low)) / 2.0, 0.5)
    distance = radius / np.sin(np.radians(fov_y_deg) / 2.0)
    unit = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    return rrb.EyeControls3D(position=center + unit * distance, look_target=center, eye_up=(0.0, 0.0, 1.0))


def framing_eye(low_m, high_m, direction=(-0.45, -0.9, 1.0), min_extent_m: float = 2.0) -> rrb.EyeControls3D:
    """An eye that frames the box ``low_m``..``high_m`` (world, m): looking at its centre from
    ``direction`` × its largest side (default: from the south-west, above), z up."""
    low, high = np.asarray(low_m, dtype=float), np.asarray(high_m, dtype=float)
    center = (low + high) / 2.0
    extent = max(float(np.max(high - low)), min_extent_m)
    return rrb.EyeControls3D(position=center + np.asarray(direction) * extent, look_target=center, eye_up=(0.0, 0.0, 1.0))


def image_view(cam_name: str, fixed: bool = False) -> rrb.Spatial2DView:
    """The recorded image of ``cam_name`` with its corners, code ids and LM path."""
    return rrb.Spatial2DView(
        origin=paths.image(cam_name, fixed),
        name=f"camera {cam_name}: detected corners (cyan), reprojected (magenta), LM path (white)",
    )


def zoom_view(cam_name: str) -> rrb.Spatial2DView:
    """The crop around ``cam_name``'s smallest code (logged only while a code is small)."""
    return rrb.Spatial2DView(
        origin=paths.zoom_image(cam_name),
        name=f"camera {cam_name} zoomed on its smallest code: detected (cyan), reprojected (magenta)",
    )


def _lm_panel(lm_iterates: bool, steps_axis: PlotAxis | None = None, rejected: bool = False) -> rrb.Container | rrb.View:
    """The frame's solve in words and, for an iterating solver, its iterations (log10 bars) and
    its trial steps per frame (y axis ``steps_axis``; crosses on ``rejected`` frames)."""
    text = rrb.TextDocumentView(origin=paths.LM_THIS_FRAME, name="solver, this frame")
    if not lm_iterates:
        return text
    bars = rrb.Tabs(
        rrb.BarChartView(
            origin=paths.LM_LOG10_COST_PER_ITERATION,
            name="log10 LM cost per iteration (this frame)",
            plot_legend=rrb.PlotLegend(visible=False),
        ),
        rrb.BarChartView(
            origin=paths.LM_LOG10_DAMPING_PER_ITERATION,
            name="log10 LM damping λ per iteration",
            plot_legend=rrb.PlotLegend(visible=False),
        ),
        rrb.BarChartView(
            origin=paths.LM_LOG10_STEP_NORM_PER_ITERATION,
            name="log10 LM step norm per trial step",
            plot_legend=rrb.PlotLegend(visible=False),
        ),
        series_view(paths.LM_ITERATIONS, "LM trial steps per frame", steps_axis, rejected=rejected),
        active_tab=0,
    )
    return rrb.Vertical(text, bars, row_shares=[0.3, 0.7])


#: The title of the note a run without ground truth shows where its error plots would be.
NO_TRUTH_TITLE = "no truth in this recording: errors cannot be scored; see σ and reprojection"


def no_truth_view() -> rrb.TextDocumentView:
    """The note of a run without ground truth (``run/no_truth``,
    :meth:`agvviz.viz.run_logger.RunLogger.log_no_truth`), in the place of its error plots."""
    return rrb.TextDocumentView(origin=paths.RUN_NO_TRUTH, name=NO_TRUTH_TITLE)


def summary_json_view() -> rrb.TextDocumentView:
    """The whole run summary as JSON (unrounded): a tab behind the summary table, for tools."""
    return rrb.TextDocumentView(origin=paths.RUN_SUMMARY_JSON, name="summary (JSON)")


def default_blueprint(
    cam_names: list[str],
    *,
    fixed_cams: set[str] = frozenset(),
    zoom_cams: list[str] = (),
    lm_iterates: bool = True,
    has_rejections: bool = False,
    has_threshold: bool = False,
    ghost_max_ratio: float | None = None,
    cov_scale: float | None = None,
    scene_m: tuple | None = None,
    budget_sources: list[str] | None = None,
    has_suspects: bool = False,
    axes: dict[str, PlotAxis] | None = None,
    max_reproj_px: float | None = None,
    has_truth: bool = True,
    sigma_axis: PlotAxis | None = None,
) -> rrb.Blueprint:
    """Build the default layout for a run with cameras ``cam_names`` (fits 1600×1000).

    ``zoom_cams`` had a small code (a zoomed view beside their image); ``lm_iterates``: the
    solver iterated on some frame (else the solver panel is its text alone); ``has_rejections``
    puts the rejection log under the summary; ``has_threshold``: the reprojection plot has
    its ``max_reproj_px`` line; ``ghost_max_ratio`` and ``cov_scale`` are named in the 3D
    view's title; the 3D view's eye frames ``scene_m``, the (low, high) corners of everything the
    run put in the world around the vehicle (:meth:`FrameLogger.scene_extent_m`: both vehicles'
    whole paths with their bodies and cameras, the codes seen), from outside at every frame.
    ``budget_sources``: the run holds an error budget of these sources (``run --budget``): its
    table is the active document, and the budget's whole layout (:func:`budget_layout`) a
    top-level tab (:data:`BUDGET_TAB`) beside the run's (its chart was unreadable in a quarter panel).
    ``has_suspects``: the suspects log (one line per suspect frame) under the summary, before
    the rejections, and the suspect diamonds on the error plots. ``axes``: each time series' y
    axis (:func:`run_plot_axes`; None: Rerun's auto range); ``max_reproj_px``: the limit line's
    value, drawn only when the reprojection axis reaches it. ``has_truth`` False (no frame
    carried ground truth): the plots that need truth (position, heading, pitch and roll error,
    error ÷ CRLB, NEES) give their place to :func:`no_truth_view` over the position σ plot (y
    axis ``sigma_axis``) — what a run knows without truth.
    """
    axes = axes or {}
    image_views = []
    for cam_name in cam_names:
        view = image_view(cam_name, cam_name in fixed_cams)
        if cam_name in zoom_cams:
            view = rrb.Horizontal(view, zoom_view(cam_name), column_shares=[0.6, 0.4])
        image_views.append(view)
    if not image_views:
        image_panel = rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary")
    elif len(image_views) == 1:
        image_panel = image_views[0]
    else:
        image_panel = rrb.Tabs(*image_views)
    title = ["world: truth (green), camera estimate (orange)" if has_truth else "world: camera estimate (orange; no truth)"]
    if ghost_max_ratio is not None:
        title.append(f"IPPE mirror pose (violet) when ambiguity ratio < {ghost_max_ratio:g}")
    if cov_scale is not None:
        title.append(f"position 3σ ×{cov_scale:g} (above the body)")
    world_view = world_3d_view(
        ", ".join(title), cam_names, fixed_cams, eye=None if scene_m is None else fitting_eye(*scene_m)
    )
    documents = rrb.Tabs(
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        rrb.TextLogView(origin=paths.EVENTS_FLIPS, name="flips"),
        *([budget_table_view()] if budget_sources is not None else []),
        summary_json_view(),
        active_tab=0 if budget_sources is None else 3,
    )
    logs = [
        *([rrb.TextLogView(origin=paths.EVENTS_SUSPECTS, name="suspects (checks without truth)", columns=_LOG_COLUMNS)]
          if has_suspects else []),
        *([rrb.TextLogView(origin=paths.EVENTS_REJECTIONS, name="rejections", columns=_LOG_COLUMNS)] if has_rejections else []),
    ]
    if logs:
        documents = rrb.Vertical(
            documents, logs[0] if len(logs) == 1 else rrb.Tabs(*logs, active_tab=0), row_shares=[0.62, 0.38]
        )
    reproj_axis = axes.get(paths.ERROR_REPROJ_RMS_PX)
    limit_in_sight = has_threshold and (reproj_axis is None or max_reproj_px is None or reproj_axis.holds(max_reproj_px))
    top = rrb.Horizontal(
        world_view,
        rrb.Vertical(image_panel, _lm_panel(lm_iterates, axes.get(paths.LM_ITERATIONS), has_rejections), row_shares=[0.6, 0.4])
        if lm_iterates
        else rrb.Vertical(image_panel, _lm_panel(lm_iterates), row_shares=[0.85, 0.15]),
        column_shares=[0.52, 0.48],
    )

    def plot(entity: str, quantity: str, extra: tuple[str, ...] = ()) -> rrb.TimeSeriesView:
        return series_view(entity, quantity, axes.get(entity), rejected=has_rejections, suspect=has_suspects, extra=extra)

    limit = "red: max_reproj_px" + (f" {max_reproj_px:g}" if max_reproj_px is not None else "")
    reprojection = plot(
        paths.ERROR_REPROJ_RMS_PX,
        "reprojection RMS [px]" + (f", {limit}" if limit_in_sight else ""),
        extra=(paths.ERROR_REPROJ_THRESHOLD_PX,) if limit_in_sight else (),
    )
    ambiguity = plot(paths.SOLVER_AMBIGUITY_RATIO, "IPPE ambiguity ratio (capped at 100)")
    if not has_truth:
        # Nothing to score against: no empty error plots; the note says why, the σ and the
        # reprojection (what a run knows without truth) take their room.
        sigma = series_view(paths.ERROR_POSITION_SIGMA_M, "position σ (√trace of the covariance) [m]", sigma_axis)
        bottom = rrb.Horizontal(
            rrb.Vertical(no_truth_view(), sigma, row_shares=[0.4, 0.6]),
            rrb.Tabs(reprojection, ambiguity, active_tab=0),
            documents,
            column_shares=[0.36, 0.34, 0.30],
        )
    else:
        position = plot(paths.ERROR_POSITION_MM, "position error [mm]")
        bottom = rrb.Horizontal(
            position,
            rrb.Tabs(
                plot(paths.ERROR_HEADING_DEG, "heading error [deg]"),
                plot(paths.ERROR_PITCH_DEG, "pitch error [deg]"),
                plot(paths.ERROR_ROLL_DEG, "roll error [deg]"),
                active_tab=0,
            ),
            rrb.Tabs(
                reprojection,
                plot(paths.ERROR_POSITION_OVER_CRLB, "position error ÷ CRLB"),
                plot(
                    paths.ERROR_NEES,
                    "NEES (orange), its mean dof (green) and 99 % bound (red)",
                    extra=(paths.ERROR_NEES_EXPECTED, paths.ERROR_NEES_BOUND_99),
                ),
                ambiguity,
                active_tab=0,
            ),
            documents,
            column_shares=[0.25, 0.23, 0.22, 0.30],
        )
    run = rrb.Vertical(top, bottom, row_shares=[0.62, 0.38], name="run")
    if budget_sources is not None:  # the budget's whole layout in a tab beside the run's
        run = rrb.Tabs(run, budget_layout(budget_sources, name=BUDGET_TAB), active_tab=0)
    return rrb.Blueprint(
        run,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )


# -- UWB and camera–UWB fusion (paper 003) -----------------------------------------------------
#
#     ┌───────────────────────────────┬──────────────────────────────────────────┐
#     │ 3D world: room, wall cameras, │ per camera (2×2): the code zoomed in     │
#     │ anchors, truth / camera / UWB │ (small codes), the full image in a tab;  │
#     │ / fused trajectories          │ detected (cyan), reprojected (magenta)   │
#     ├──────────────────────┬────────┴───────────┬──────────────────────────────┤
#     │ ranges per anchor    │ camera fix error   │ camera used / fused from     │
#     │ (2×2, one key):      │ [mm]               │ (state lanes)                │
#     │ measured, expected   ├────────────────────┼──────────────────────────────┤
#     │ from truth / fused,  │ UWB and fused      │ switches / gates / GDOP /    │
#     │ gated (×)            │ error [mm]         │ summary / manifest           │
#     └──────────────────────┴────────────────────┴──────────────────────────────┘

def uwb_blueprint(
    cam_names: list[str],
    fixed_cams: set[str],
    anchor_ids: list[str],
    zoom_cams: list[str] = (),
    *,
    camera_axis: PlotAxis | None = None,
    camera_rejected: bool = False,
    error_axis: PlotAxis | None = None,
    range_axes: dict[str, PlotAxis] | None = None,
    room_m: tuple | None = None,
    has_truth: bool = True,
) -> rrb.Blueprint:
    """Layout for a run with cameras ``cam_names`` (``fixed_cams`` fixed in the world) and
    UWB anchors ``anchor_ids``. ``zoom_cams``: cameras with a zoomed view of their small code
    (:attr:`RunLogger.zoom_cams`), shown first. The y axes, from the whole run
    (:class:`PlotAxis`; None: Rerun's auto range): ``camera_axis`` of the camera fix error (with
    the crosses of rejected frames when ``camera_rejected``), ``error_axis`` of the UWB/fused error
    (:meth:`FusionLogger.error_axis`: clipped, and saying so, when a few NLOS fixes are far off),
    ``range_axes`` of each anchor's ranges. ``room_m``: the room's (low, high) corners
    (:func:`agvviz.viz.log_uwb.log_room_outline`), which the 3D view frames. ``has_truth`` False
    (no frame carried ground truth): :func:`no_truth_view` and the GDOP plot in the place of the
    camera and UWB/fused error plots."""
    range_axes = range_axes or {}
    cameras = [_camera_panel(c, c in fixed_cams, c in zoom_cams) for c in cam_names]
    if not cameras:
        image_panel = rrb.Spacer()
    elif len(cameras) == 1:
        image_panel = cameras[0]
    else:
        image_panel = rrb.Grid(*cameras, grid_columns=2)
    world = world_3d_view(
        ("3D: " + (f"{LEGEND[COLOR_TRUTH]} (green), " if has_truth else "no truth; "))
        + f"{LEGEND[COLOR_CAMERA]} (orange), {LEGEND[COLOR_UWB]} (blue), "
        f"{LEGEND[COLOR_FUSED]} (yellow); UWB anchors, room outline (grey)",
        cam_names,
        fixed_cams,
        eye=None if room_m is None else framing_eye(*room_m, direction=(-0.25, -0.95, 0.9)),
    )
    range_views = [
        rrb.TimeSeriesView(
            origin="/",
            contents=[f"/{paths.uwb_ranges(a)}/**"],
            name=f"anchor {a}",
            plot_legend=_NO_LEGEND,
            axis_y=range_axes[a].scalar_axis() if a in range_axes else None,
        )
        for a in anchor_ids
    ]
    # One colour key for the four plots (a legend in each would cover half of it).
    ranges = rrb.Vertical(
        rrb.TextDocumentView(origin=paths.UWB_RANGE_KEY, name="UWB range [m] to each anchor vs t [s]"),
        rrb.Grid(*range_views, grid_columns=2),
        row_shares=[0.16, 0.84],
    )
    camera_error = series_view(
        paths.ERROR_POSITION_MM, "camera fix error [mm]", camera_axis, rejected=camera_rejected
    )
    fused_error = rrb.TimeSeriesView(
        origin="/",
        contents=[f"/{paths.ERROR_UWB_POSITION_MM}", f"/{paths.ERROR_FUSED_POSITION_MM}"],
        name=series_title(
            "UWB (blue), fused (yellow) error [mm]", note="" if error_axis is None else error_axis.note
        ),
        plot_legend=_NO_LEGEND,
        axis_y=None if error_axis is None else error_axis.scalar_axis(),
    )
    states = rrb.StateTimelineView(
        origin="/",
        contents=[f"/{paths.FUSION_CAMERA_USED}", f"/{paths.FUSION_SOURCE}"],
        name=STATE_LANES_KEY,
    )
    log_columns = rrb.TextLogColumns(timeline_columns=[paths.TIMELINE_ELAPSED], text_log_columns=["body"])
    gdop = rrb.TimeSeriesView(origin=paths.UWB_GDOP, name="GDOP", plot_legend=rrb.PlotLegend(visible=False))
    documents = rrb.Tabs(
        rrb.TextLogView(origin=paths.EVENTS_FUSION, name="switches", columns=log_columns),
        rrb.TextLogView(origin=paths.EVENTS_UWB_GATE, name="gates", columns=log_columns),
        *([gdop] if has_truth else []),
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        summary_json_view(),
        active_tab=0,
    )
    top = rrb.Horizontal(world, image_panel, column_shares=[0.45, 0.55])
    bottom = rrb.Horizontal(
        ranges,
        rrb.Vertical(camera_error, fused_error) if has_truth else rrb.Vertical(no_truth_view(), gdop),
        rrb.Vertical(states, documents, row_shares=[0.4, 0.6]),
        column_shares=[0.38, 0.27, 0.35],
    )
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[0.52, 0.48]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )


#: The state timeline's title is the key of its lanes: Rerun 0.41 names a lane by its entity path
#: (``StateVisualizer``: the lane label is ``data_result.entity_path``; ``StateConfiguration``'s
#: labels name the states, not the lane; ``StateTimelineView`` has no per-lane name).
STATE_LANES_KEY = "camera_used = fix used · fused_from = fused estimate's source"


def _camera_panel(cam_name: str, fixed: bool, zoomed: bool) -> rrb.View | rrb.Container:
    """The zoomed code (when the camera had a small one) with the full image in a second tab."""
    full = image_view(cam_name, fixed)
    if not zoomed:
        return full
    return rrb.Tabs(zoom_view(cam_name), full, active_tab=0)


# -- the correction cycle (paper 002) ------------------------------------------------------------
#: The 3D view's eye in the corrected vehicle's frame (beside, behind and above it) and the point
#: it looks at (ahead of it), m: the view rides along with the vehicle.
CORRECTION_EYE_POSITION_AGV_M = (3.0, -7.0, 3.0)
CORRECTION_EYE_TARGET_AGV_M = (0.0, 3.0, 0.0)


def correction_blueprint(cam_names: list[str], cycle_highs: dict[str, float] | None = None) -> rrb.Blueprint:
    """Layout of a run with ``correction`` (time panel on ``elapsed``); ``cycle_highs``: the
    closed-cycle plots' largest values by entity (:meth:`~agvviz.viz.log_correction.CorrectionLogger.cycle_axes_high`),
    their y axes from 0 to them. No plot has a legend (in Rerun 0.41 it sits on the data): the
    titles name the series by colour::

        tab "correction run"
        ┌────────────────────────────────────┬─────────────────────────────────┐
        │ 3D: markers, truth / navigation /  │ per camera: the image (when     │
        │ corrected vehicles + trajectories, │ recorded), this frame's corners │
        │ last window's cameras and rays;    │ and the last window's observed  │
        │ the eye follows the corrected AUV  │ / solved corners                │
        ├──────────────┬──────────────┬──────┴───────────┬─────────────────────┤
        │ error vs     │ corrected    │ closed cycles:   │ corrections log /   │
        │ truth [mm]   │ error [mm]   │ RMS, σ vs limits │ summary / manifest  │
        └──────────────┴──────────────┴──────────────────┴─────────────────────┘
        tab "solver iterations (cnoem_iter)": the window's corners per camera and the last
        cycle's cost and RMS per iteration; scrub the ``cnoem_iter`` timeline to watch the
        theoretical corners converge.

    The 3D view's origin is the corrected vehicle, so its eye (behind, beside and above it,
    :data:`CORRECTION_EYE_POSITION_AGV_M`) rides along: the vehicle stays in frame at every time.
    """
    world = rrb.Spatial3DView(
        origin=paths.CORRECTION_AGV_CORRECTED,
        name=f"3D: {LEGEND[COLOR_TRUTH]} (green), {LEGEND[COLOR_NAV]} (red), {LEGEND[COLOR_CORRECTED]} (magenta); "
        "last window's camera positions and closing sight lines (orange)",
        contents=[f"+ /{paths.MARKERS}/**", f"+ /{paths.CORRECTION_WORLD}/**"],
        eye_controls=rrb.EyeControls3D(
            position=CORRECTION_EYE_POSITION_AGV_M, look_target=CORRECTION_EYE_TARGET_AGV_M, eye_up=[0.0, 0.0, 1.0]
        ),
    )
    cameras = [
        rrb.Spatial2DView(
            origin=paths.image(c),
            name=f"camera {c}: window corners observed (white), solved (orange); detected (cyan)",
            contents=["+ $origin/**", f"- {paths.lm_iteration(c)}", f"- {paths.lm_path(c)}"],
        )
        for c in cam_names
    ]
    cycle_highs = cycle_highs or {}

    def from_zero(entity: str) -> rrb.ScalarAxis | None:
        high = cycle_highs.get(entity)
        return rrb.ScalarAxis(range=(0.0, 1.1 * high)) if high else None

    errors = rrb.TimeSeriesView(
        origin="/", contents=[f"/{paths.ERROR_NAV_MM}", f"/{paths.ERROR_CORRECTED_MM}", f"/{paths.ERROR_CORRECTION_JUMP_MM}"],
        name="error [mm]: navigation red, corrected magenta", plot_legend=_NO_LEGEND,
    )
    corrected = rrb.TimeSeriesView(
        origin="/", contents=[f"/{paths.ERROR_CORRECTED_MM}", f"/{paths.ERROR_CORRECTION_JUMP_MM}"],
        name="corrected error [mm], dots: jumps", plot_legend=_NO_LEGEND,
    )
    cycles = rrb.Tabs(
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{paths.CORRECTION_CYCLE_REPROJ_RMS_PX}", f"/{paths.CORRECTION_CYCLE_MAX_REPROJ_PX}"],
            name="cycles: window RMS [px], limit red", plot_legend=_NO_LEGEND,
            axis_y=from_zero(paths.CORRECTION_CYCLE_REPROJ_RMS_PX),
        ),
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{paths.CORRECTION_CYCLE_POSITION_SIGMA_MM}", f"/{paths.CORRECTION_CYCLE_MAX_POSITION_SIGMA_MM}"],
            name="cycles: position σ [mm], limit red", plot_legend=_NO_LEGEND,
            axis_y=from_zero(paths.CORRECTION_CYCLE_POSITION_SIGMA_MM),
        ),
        active_tab=0,
    )
    documents = rrb.Tabs(
        # the frame (narrower than the elapsed time, which was cut) and the line, its key fact first
        rrb.TextLogView(origin=paths.EVENTS_CORRECTIONS, name="corrections (one line per cycle)", columns=_LOG_COLUMNS),
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        summary_json_view(),
        active_tab=0,
    )
    top = rrb.Horizontal(world, rrb.Vertical(*cameras) if cameras else rrb.Spacer(), column_shares=[0.58, 0.42])
    bottom = rrb.Horizontal(errors, corrected, cycles, documents, column_shares=[0.25, 0.22, 0.22, 0.31])
    run_tab = rrb.Vertical(top, bottom, row_shares=[0.6, 0.4], name="correction run")
    iteration_cameras = [
        rrb.Spatial2DView(
            origin=paths.image(c),
            name=f"camera {c}, last window: observed (white), theoretical at the iteration (orange)",
            contents=[f"+ {paths.correction_observed(c)}", f"+ {paths.correction_theoretical(c)}", f"+ {paths.correction_border(c)}"],
        )
        for c in cam_names
    ]
    solver = rrb.Vertical(
        rrb.BarChartView(origin=paths.CORRECTION_COST_PER_ITERATION, name="last cycle: window cost per iteration",
                         plot_legend=rrb.PlotLegend(visible=False)),
        rrb.BarChartView(origin=paths.CORRECTION_REPROJ_RMS_PX_PER_ITERATION, name="last cycle: reprojection RMS [px] per iteration",
                         plot_legend=rrb.PlotLegend(visible=False)),
    )
    iterations_tab = rrb.Horizontal(
        rrb.Vertical(*iteration_cameras) if iteration_cameras else rrb.Spacer(), solver,
        column_shares=[0.6, 0.4], name=f"solver iterations (timeline {paths.TIMELINE_CNOEM_ITER})",
    )
    return rrb.Blueprint(
        rrb.Tabs(run_tab, iterations_tab, active_tab=0),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )


# -- error budget (agvviz budget, agvviz run --budget) --------------------------------------------
def budget_table_view() -> rrb.TextDocumentView:
    """The budget's markdown table."""
    return rrb.TextDocumentView(origin=paths.BUDGET_TABLE, name="error budget")


#: The share chart's geometry (:func:`agvviz.viz.log_budget.log_share_chart`), in the chart's own
#: units: the grid spans BUDGET_CHART_WIDTH across, whatever range of % it shows; each row (a
#: source, then interaction/other) is BUDGET_CHART_ROW high, its label centred above its bar (a
#: label beside the bars was cut at the view's edge).
BUDGET_CHART_WIDTH = 160.0
BUDGET_CHART_ROW = 16.0
BUDGET_CHART_BAR_HALF_HEIGHT = 2.0
BUDGET_CHART_LABEL_ABOVE = 9.0


def budget_share_bounds(n_rows: int) -> rrb.VisualBounds2D:
    """The share chart's view: every row's label, bar and the grid's labels under it (a 2D view
    fitted to its data cut the grid's labels, which hang below their points)."""
    bottom = (n_rows - 1) * BUDGET_CHART_ROW + BUDGET_CHART_LABEL_ABOVE + BUDGET_CHART_ROW / 2
    return rrb.VisualBounds2D(x_range=[-10.0, BUDGET_CHART_WIDTH + 10.0],
                              y_range=[-BUDGET_CHART_LABEL_ABOVE, bottom + 14.0])


def budget_shares_view(sources: list[str]) -> rrb.Spatial2DView:
    """The shares as labelled bars with their bootstrap intervals (:func:`agvviz.viz.log_budget.log_share_chart`:
    one row per source and one for interaction/other); the title says what a negative share is."""
    return rrb.Spatial2DView(
        origin=paths.BUDGET_SHARES, visual_bounds=budget_share_bounds(len(sources) + 1),
        name="share of position error [%], 95 % CI over frames; < 0: error grew with it off (interaction)",
    )


def _budget_key(sources: list[str]) -> str:
    """``calibration red, map blue, …``: each source's line colour, named (the plots have no legend)."""
    return ", ".join(f"{s} {budget_source_color_name(s)}" for s in sources)


def budget_errors_view(sources: list[str]) -> rrb.TimeSeriesView:
    """Per-frame position error with every source on, every source off, and each source off."""
    names = [paths.BUDGET_ALL_ON, paths.BUDGET_ALL_OFF] + list(sources)
    return rrb.TimeSeriesView(origin=paths.BUDGET, contents=[f"$origin/{paths.budget_series_relative(n)}" for n in names],
                              name=f"error [mm], one source off: {_budget_key(sources)}; all on white, all off grey",
                              plot_legend=_NO_LEGEND)


def budget_deltas_view(sources: list[str]) -> rrb.TimeSeriesView:
    """Per-frame error all on − error with each source off: when a source costs what it costs."""
    return rrb.TimeSeriesView(origin=paths.BUDGET, contents=[f"$origin/{paths.budget_series_relative(s, 'delta_mm')}" for s in sources],
                              name=f"error all on − one source off [mm]: {_budget_key(sources)}",
                              plot_legend=_NO_LEGEND)


#: The name of ``run --budget``'s tab holding the budget's layout.
BUDGET_TAB = "error budget: share chart and series"


def budget_layout(sources: list[str], name: str | None = None) -> rrb.Container:
    """The budget's views: table and share chart (the chart as wide as the table, half the
    height) beside the per-frame errors and deltas (wider: their titles name every colour)."""
    return rrb.Horizontal(
        rrb.Vertical(budget_table_view(), budget_shares_view(sources), row_shares=[0.5, 0.5]),
        rrb.Vertical(budget_errors_view(sources), budget_deltas_view(sources)),
        column_shares=[0.42, 0.58], name=name,
    )


def budget_blueprint(budget: ErrorBudget) -> rrb.Blueprint:
    """Table and bar chart beside the per-frame errors (all on, each source off) and deltas,
    against ``elapsed`` (the time panel opens on it)."""
    return rrb.Blueprint(
        budget_layout([s.source for s in budget.sources]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )


# -- agvviz audit ------------------------------------------------------------------------------------
def audit_eye(result) -> rrb.EyeControls3D | None:
    """From above and a little south, framing every mapped marker and the solved path."""
    points = [f.corners_world_mapped for f in result.estimate.markers] + [result.estimate.T_world_agv[:, :3, 3]]
    points = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 3) for p in points])
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        return None
    return framing_eye(points.min(axis=0), points.max(axis=0), direction=(0.0, -0.45, 1.05))


def audit_blueprint(result, axes: dict[str, PlotAxis] | None = None) -> rrb.Blueprint:
    """The 3D map (recorded vs estimated, framed whole, ids shown) with the residual plots under
    it (each marker's corner residual, flagged markers red; odometry in mm and in degrees apart),
    the report beside them at full height (its marker table fits without scrolling). Plots
    against ``elapsed`` (seconds since the recording's start; the time panel opens on it);
    ``axes``: each plot's y axis (by origin) from the whole audit (None: Rerun's auto range).
    """
    axes = axes or {}

    def odometry(entity: str, name: str) -> rrb.TimeSeriesView:
        axis = axes.get(entity)
        return rrb.TimeSeriesView(origin=entity, name=name, plot_legend=_NO_LEGEND,
                                  axis_y=axis.scalar_axis() if axis is not None else None)

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin=paths.WORLD, eye_controls=audit_eye(result),
                                  name="map: mapped (blue, ids) vs estimated (red: flagged, magenta: agrees, grey: seen too little); "
                                  "path: solved (magenta), start (orange), truth (green)"),
                rrb.Horizontal(
                    odometry(paths.AUDIT_RESIDUALS, "corner RMS [px]: flagged red"),
                    odometry(paths.AUDIT_ODOMETRY_XY_MM, "odometry step [mm]"),
                    odometry(paths.AUDIT_ODOMETRY_HEADING_DEG, "odometry turn [°]"),
                    column_shares=[0.4, 0.3, 0.3],
                ),
                row_shares=[0.66, 0.34],
            ),
            rrb.TextDocumentView(origin=paths.AUDIT_REPORT, name="audit"),
            column_shares=[0.54, 0.46],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )


# -- overlay of several runs (agvviz diff, agvviz sweep) ----------------------------------------------
#: Per-frame quantities an overlay draws, with their axis label (the unit is part of the key).
ERROR_LABELS = {
    "position_mm": "position error [mm]",
    "heading_deg": "heading error [deg]",
    "pitch_deg": "pitch error [deg]",
    "roll_deg": "roll error [deg]",
    "reproj_px": "reprojection RMS [px]",
}


def format_magnification(factor: float) -> str:
    """``200.0`` → ``"×200"``."""
    return f"×{factor:g}"


def delta_view_name(key: str) -> str:
    """Title of a Δ plot, with its sign convention: ``Δ |position error| = B − A [mm];
    positive = B worse``."""
    quantity, unit = ERROR_LABELS[key].split(" [")
    return f"Δ |{quantity}| = B − A [{unit}: positive = B worse"


#: Height of the overlay's colour key row: its title bar, and each line of text at 1600×1000 (a
#: line holds about KEY_LINE_CHARS characters; a sweep of many settings wraps).
KEY_TITLE_SHARE = 0.04
KEY_LINE_SHARE = 0.025
KEY_LINE_CHARS = 200


def key_row_share(runs: list) -> float:
    """The share of the window's height the colour key of ``runs`` needs (its text:
    :func:`agvviz.viz.overlay.key_markdown`, each run's label and colour, then about 120
    characters on truth, corners and the magnification)."""
    chars = sum(len(r.label) + 10 for r in runs) + 120
    return KEY_TITLE_SHARE + KEY_LINE_SHARE * math.ceil(chars / KEY_LINE_CHARS)

#: Eye of the close-up, in the truth AGV's body frame (the view's origin, so it moves and turns
#: with the AGV): about 2 m away, behind-left and above.
OVERLAY_FOLLOW_EYE_POSITION_M = (-0.9, -1.3, 1.1)


def _overlay_eye(truth) -> rrb.EyeControls3D | None:
    """A view from the south-west, above, that frames the whole truth trajectory."""
    if truth is None or len(truth.T_world_agv) == 0:
        return None
    positions = truth.T_world_agv[:, :3, 3]
    low, high = positions.min(axis=0), positions.max(axis=0)
    center = (low + high) / 2.0
    extent = max(float(np.max(high - low)), 2.0)
    return rrb.EyeControls3D(
        position=center + np.array([-0.35, -0.9, 0.9]) * extent,
        look_target=center,
        eye_up=(0.0, 0.0, 1.0),
    )


def overlay_blueprint(
    runs: list,
    cam_names: list[str],
    deltas: list[str],
    truth=None,
    magnification: float | None = None,
    fixed_cams: set[str] | frozenset[str] = frozenset(),
    layer_entities: dict[str, set[str]] | None = None,
) -> rrb.Blueprint:
    """Default layout: 3D trajectories (with each run's magnified error arrows when
    ``magnification`` is given, and a close-up that follows the truth AGV) and the image with
    every run's corners on top; the colour key (:data:`paths.COMPARE_KEY`) across the width;
    error plots of all runs (and the per-frame differences, with a zero line) with the comparison
    report below. Opens paused, on the ``frame`` timeline. ``fixed_cams``: cameras fixed in the
    world (wall cameras), named so in their views.

    One key names every run's colour for all views: the 3D views label no run (labels at the
    AGV collide where the runs agree) and say the magnification once in their title; the plots
    have no legend (Rerun 0.41 draws it on the data, :data:`_NO_LEGEND`)."""
    views = [rrb.Spatial3DView(origin=paths.WORLD, name="world: runs in the key's colours", eye_controls=_overlay_eye(truth))]
    if magnification is not None:
        factor = format_magnification(magnification)
        views = [
            rrb.Spatial3DView(
                origin=paths.WORLD, name=f"whole run: paths with errors {factor}", eye_controls=_overlay_eye(truth),
                # The runs' own paths lie on the truth; their paths with errors magnified show the difference.
                contents=[
                    "+ $origin/**", *[f"- /{paths.overlay_trajectory(r.key)}" for r in runs], f"- /{paths.OVERLAY_ERROR_VECTORS}/**"
                ],
            ),
            # Origin on the truth AGV: the view follows it (the world moves around it).
            rrb.Spatial3DView(
                origin=paths.AGV_TRUTH, name=f"at the AGV: errors {factor} (estimate − truth)",
                eye_controls=rrb.EyeControls3D(
                    position=OVERLAY_FOLLOW_EYE_POSITION_M, look_target=(0.0, 0.0, 0.0), eye_up=(0.0, 0.0, 1.0)
                ),
                contents=[f"+ /{paths.WORLD}/**", *[f"- /{paths.overlay_agv_marker(r.key)}" for r in runs]],
            ),
        ]
    if cam_names:
        images = [
            rrb.Spatial2DView(
                origin=paths.overlay_image(cam),
                name=f"{'wall camera' if cam in fixed_cams else 'camera'} {cam}: detected cyan, reprojected in each run's colour",
            )
            for cam in cam_names
        ]
        views.append(images[0] if len(images) == 1 else rrb.Tabs(*images))
    shares = {1: [1.0], 2: [0.5, 0.5], 3: [0.4, 0.3, 0.3]}[len(views)]
    top = views[0] if len(views) == 1 else rrb.Horizontal(*views, column_shares=shares)
    key = rrb.TextDocumentView(origin=paths.COMPARE_KEY, name="colour key")
    error_views = [
        rrb.TimeSeriesView(origin=paths.overlay_errors(key), name=label, plot_legend=_NO_LEGEND)
        for key, label in ERROR_LABELS.items()
    ]
    if deltas:  # a diff: each run's errors, and their difference B − A
        plots = [
            rrb.Tabs(*error_views),
            rrb.Tabs(*[
                rrb.TimeSeriesView(origin=paths.overlay_delta(key), name=delta_view_name(key), plot_legend=_NO_LEGEND)
                for key in deltas
            ]),
        ]
        shares = [0.3, 0.3, 0.4]
    else:
        plots = [error_views[0], rrb.Tabs(*error_views[1:])]
        shares = [0.22, 0.22, 0.56]
    report = rrb.TextDocumentView(origin=paths.COMPARE_REPORT, name="comparison")
    layer_views = _layer_views(runs, layer_entities or {})
    bottom = rrb.Horizontal(*plots, rrb.Tabs(report, *layer_views) if layer_views else report, column_shares=shares)
    return rrb.Blueprint(
        rrb.Vertical(top, key, bottom, row_shares=[0.55, key_row_share(runs), 0.45 - key_row_share(runs)]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_FRAME, play_state="paused"),
        auto_views=False,
    )


def _layer_views(runs: list, layer_entities: dict[str, set[str]]) -> list:
    """Tabs beside the report of a sweep ``.rrd`` (each run's layers under ``settings/<key>/``):
    the LM trial steps per frame, a series per run in its colour, and each run's suspects log."""
    keyed = [(i, r) for i, r in enumerate(runs) if r.key in layer_entities]
    views = []
    with_lm = [(i, r) for i, r in keyed if paths.LM_ITERATIONS in layer_entities[r.key]]
    if with_lm:
        # lines and a point at each value: a frame without steps is a gap (the run logs a Clear
        # there), so a setting that iterates on few frames (ippe) shows as points, not as a
        # line drawn across frames it did not iterate on
        views.append(rrb.TimeSeriesView(
            origin="/", plot_legend=_NO_LEGEND,
            name="LM trial steps per frame, each setting in its colour of the key above (a gap: no LM steps on that frame)",
            contents=[f"/{paths.sweep_layer(r.key, paths.LM_ITERATIONS)}" for _, r in with_lm],
            overrides={
                paths.sweep_layer(r.key, paths.LM_ITERATIONS): [
                    rr.SeriesLines.from_fields(colors=[color_of(i)], names=r.label),
                    rr.SeriesPoints.from_fields(colors=[color_of(i)], names=r.label, marker_sizes=[2.5]),
                ]
                for i, r in with_lm
            },
        ))
    for _, r in keyed:
        if paths.EVENTS_SUSPECTS in layer_entities[r.key]:
            views.append(rrb.TextLogView(origin=paths.sweep_layer(r.key, paths.EVENTS_SUSPECTS), name=f"suspects {r.label}"))
    return views


# -- studies: p4p Monte-Carlo and CNOEM grid ---------------------------------------------------------
#: The tabs of a Monte-Carlo layout. Rerun plots a time series against the time panel's one
#: timeline, so every tab plots against σ (``sigma_mpx``, the timeline the layout opens on): no
#: tab opens empty. Paper cells are also on ``snr_db``, the paper's own axis for figures 9–11.
MC_TABS = ("figures", "rmse", "crlb", "report")
#: The multi-frame methods, plotted against the bound apart from the (much worse) IPPE baselines.
CNOEM_WINDOW_METHODS = ("cnoem", "cnoem_multistart", "bundle")
#: Cells whose error-against-trial plots get a tab of their own (the others: change a view's origin).
CNOEM_MAX_FEATURED_CELLS = 8


def mc_default_tab(results: dict[str, CellResult]) -> str:
    """The tab a study opens on: the paper's figures 9–11 when it has their cells, else the
    RMSE per solver."""
    if any(paths.mc_paper_group(cid) == paths.MC_FIG9_11 for cid in results):
        return "figures"
    return "rmse"


def _mc_groups(results: dict[str, CellResult]) -> list[str]:
    """Every cell group (paper groups, then CRLB groups), in recording order."""
    paper = [g for cid in results if (g := paths.mc_paper_group(cid))]
    crlb = [g for cid in results if (g := paths.mc_crlb_group(cid))]
    return list(dict.fromkeys(paper + crlb))


def _mc_group_title(group: str) -> str:
    """``mc/crlb/tilt30_h0.2667_z2_n4`` → ``tilt 30°, h 0.2667 m, z 2 m, N 4``."""
    words = []
    for part in group.rsplit("/", 1)[-1].split("_"):
        for key, unit in (("tilt", "°"), ("h", " m"), ("z", " m"), ("n", "")):
            if part.startswith(key) and part[len(key):].replace(".", "").isdigit():
                words.append(f"{'N' if key == 'n' else key} {part[len(key):]}{unit}")
                break
    return ", ".join(words)


def _mc_axis(results: dict[str, CellResult], group: str) -> rrb.TimeAxis:
    """The x axis of a study plot: the σ (mpx) of the group's cells and 5 % beyond, wherever the
    time cursor is (by default the axis follows the cursor)."""
    sigmas = [round(r.sigma_px * 1000) for cid, r in results.items()
              if group in (paths.mc_paper_group(cid), paths.mc_crlb_group(cid))]
    margin = max(1, round(0.05 * (max(sigmas) - min(sigmas))))
    return rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.absolute(seq=min(sigmas) - margin),
                                                 end=rrb.TimeRangeBoundary.absolute(seq=max(sigmas) + margin)))


def _mc_plot(origin: str, name: str, axis: rrb.TimeAxis) -> rrb.TimeSeriesView:
    """A study plot: no legend (in Rerun 0.41 it sits on the data); the tab's or the view's title
    names the colours (:func:`_mc_key`)."""
    return rrb.TimeSeriesView(origin=origin, name=name, axis_x=axis, plot_legend=_NO_LEGEND)


def _mc_key(with_crlb: bool = False) -> str:
    """``p4p blue, lm red, …``: each solver's colour, named, in the palette's order."""
    names = [s for s in SOLVER_COLORS if s != "crlb"]
    return ", ".join(f"{s} {solver_color_name(s)}" for s in names) + (
        f"; CRLB {solver_color_name('crlb')}" if with_crlb else "")


def study_blueprint(
    results: dict[str, CellResult], *, active: str | None = None, documents: tuple[tuple[str, str], ...] = ()
) -> rrb.Blueprint:
    """The study's layout, every plot against σ in milli-pixels (timeline ``sigma_mpx``) with
    one legend per tab; ``active`` the tab it opens on (figures, rmse, crlb or report; default
    :func:`mc_default_tab`), ``documents`` extra (origin, name) text documents beside the
    report (a run's summary and manifest)."""
    active = mc_default_tab(results) if active is None else active
    if active not in MC_TABS:
        raise ValueError(f"unknown tab {active!r}; valid: {', '.join(MC_TABS)}")
    # Rerun 0.41 plots a series against a timeline only (no x-y plot): σ is the sequence
    # timeline sigma_mpx, whose ticks read "#13 376" — the title says what they are
    x = "vs σ [mpx] (x: #σ in milli-pixels)"
    groups = _mc_groups(results)

    def axis(group: str) -> rrb.TimeAxis:
        return _mc_axis(results, group)

    tabs = {}
    if paths.MC_FIG9_11 in groups:
        g = paths.MC_FIG9_11
        tabs["figures"] = rrb.Vertical(
            rrb.Horizontal(*[_mc_plot(f"{g}/t{i}_mean", f"fig {8 + i}: mean t{i} [m] {x}", axis(g)) for i in (1, 2, 3)]),
            rrb.Horizontal(
                _mc_plot(f"{g}/rmse_mm", f"RMSE of t [mm], thin lines its 95 % CI; CRLB {solver_color_name('crlb')}; {x}", axis(g)),
                _mc_plot(f"{g}/rmse_over_crlb", f"RMSE ÷ CRLB {x}", axis(g)),
            ),
            name=f"paper figures 9–11 ({_mc_group_title(g)}): {_mc_key()}",
        )
    if groups:
        tabs["rmse"] = rrb.Grid(
            *[_mc_plot(f"{g}/rmse_mm", f"{_mc_group_title(g)}: RMSE of t [mm], 95 % CI {x}", axis(g)) for g in groups],
            name=f"RMSE per solver vs σ: {_mc_key(with_crlb=True)}",
        )
        tabs["crlb"] = rrb.Grid(
            *[_mc_plot(f"{g}/rmse_over_crlb", f"{_mc_group_title(g)}: RMSE ÷ CRLB {x}", axis(g)) for g in groups],
            name=f"RMSE ÷ CRLB vs σ: {_mc_key()}",
        )
    texts = [rrb.TextDocumentView(origin=paths.MC_REPORT, name="report (paper vs ours, every cell)")]
    texts += [rrb.TextDocumentView(origin=origin, name=name) for origin, name in documents]
    tabs["report"] = rrb.Tabs(*texts, active_tab=0, name="report")
    if active not in tabs:
        active = "report"
    names = list(tabs)
    return rrb.Blueprint(
        rrb.Tabs(*tabs.values(), active_tab=names.index(active)),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_SIGMA_MPX),
        auto_views=False,
    )


def trials_blueprint(outcome) -> rrb.Blueprint:
    """The layout of a Monte-Carlo study run (``outcome``: its
    :class:`~agvviz.model.studies.TrialsOutcome`): :func:`study_blueprint` with the run's summary
    and manifest beside the report. The per-trial errors (``mc/trials/...``, timeline ``trial``)
    stay in the ``.rrd`` for a view added by hand; no tab shows them (a cloud of dots per trial
    index told the solvers apart worse than a line per solver with its interval)."""
    return study_blueprint(
        outcome.results,
        documents=((paths.RUN_SUMMARY, "summary"), (paths.RUN_MANIFEST, "manifest"), (paths.RUN_SUMMARY_JSON, "summary (JSON)")),
    )


def cnoem_trials_blueprint(outcome) -> rrb.Blueprint:
    """The layout of a CNOEM grid study run (``outcome``: its
    :class:`~agvviz.model.studies.CnoemTrialsOutcome`): per featured cell (the first
    :data:`CNOEM_MAX_FEATURED_CELLS`), the
    multi-frame methods' error against trial with the CRLB above all methods' (the IPPE
    baselines' errors are metres, the window methods' decimetres); the report, summary and
    manifest beside them; timeline ``trial``."""
    cell_views = []
    for cell_id in list(outcome.results)[:CNOEM_MAX_FEATURED_CELLS]:
        origin = paths.cnoem_trial_errors(cell_id)
        cell_views.append(
            rrb.Vertical(
                rrb.TimeSeriesView(
                    origin=origin, contents=[f"$origin/{m}" for m in (*CNOEM_WINDOW_METHODS, "crlb")],
                    name=f"{cell_id}: multi-frame methods, position error of F (m) per trial, CRLB (grey)",
                    plot_legend=rrb.PlotLegend(visible=True),
                ),
                rrb.TimeSeriesView(
                    origin=origin, name=f"{cell_id}: every method, position error of F (m) per trial",
                    plot_legend=rrb.PlotLegend(visible=True),
                ),
                name=cell_id,
            )
        )
    texts = [rrb.TextDocumentView(origin=paths.CNOEM_REPORT, name="report")]
    texts += [
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        summary_json_view(),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(*cell_views) if cell_views else rrb.Spacer(),
            rrb.Tabs(*texts),
            column_shares=[0.6, 0.4],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_TRIAL),
        auto_views=False,
    )


def cnoem_report_blueprint() -> rrb.Blueprint:
    """The CNOEM grid study's own ``.rrd`` (:func:`agvviz.viz.log_studies.write_cnoem_report_rrd`):
    the per-cell series beside the report, on timeline ``cell``."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"/{paths.CNOEM_MEAN_ERROR_M}", name="mean position error of F [m] per cell"),
                rrb.TimeSeriesView(origin=f"/{paths.CNOEM_RATIO_TO_IPPE_FIRST}", name="CNOEM ÷ IPPE per cell (paper: 0.217 overall)"),
                rrb.TimeSeriesView(origin=f"/{paths.CNOEM_RMS_OVER_CRLB}", name="RMS ÷ multi-frame CRLB per cell"),
            ),
            rrb.TextDocumentView(origin=f"/{paths.CNOEM_REPORT}", name="report"),
            column_shares=[0.55, 0.45],
        ),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_CELL),
        auto_views=False,
    )


# -- a tab of a layout, picked by name (docs/make_pictures.py --tab) ----------------------------------
def views_in(node) -> list[rrb.View]:
    """Every view of a layout: below a :class:`rrb.Blueprint`, a container, or the view itself."""
    if isinstance(node, rrb.Blueprint):
        node = node.root_container
    if isinstance(node, rrb.View):
        return [node]
    return [view for child in getattr(node, "contents", ()) for view in views_in(child)]


def tab_names(blueprint: dict) -> list[str]:
    """The name of every tab in ``blueprint`` (a layout as the viewer reads it out:
    ``rerun.experimental.ViewerClient.get_blueprint().blueprint``, blueprint entity path →
    archetype → field), in file order: each child of a Tabs container, named by its
    ``display_name`` (a view without one by its origin, as the viewer shows it)."""
    return [name for _, name in _tabs(blueprint)]


def with_active_tab(blueprint: dict, tab: str) -> dict:
    """A copy of ``blueprint`` (as in :func:`tab_names`) that shows the tab ``tab``: the Tabs
    container holding it has it active, and so does every Tabs container around that one (the
    branch that holds it), so a tab nested in a tab shows too. ``tab`` is matched against the
    tabs' names case-insensitively, whole first, else as the start of exactly one name
    ("paper figures" picks "paper figures 9–11 (…)"). No match, or several: InputError naming
    the tabs."""
    tabs = _tabs(blueprint)
    wanted = tab.strip().casefold()
    matches = [ref for ref, name in tabs if name.casefold() == wanted]
    if not matches:
        matches = [ref for ref, name in tabs if name.casefold().startswith(wanted)]
    if len(matches) != 1:
        listed = "; ".join(dict.fromkeys(name for _, name in tabs)) or "none"
        how = "no tab is named" if not matches else f"{len(matches)} tabs start with"
        raise InputError(f"{how} {tab!r} in this layout; its tabs: {listed}")
    # each container or view's key → (its container's key, how that container lists it)
    parent = {
        _key(child): (key, child)
        for key, archetypes in blueprint.items()
        for child in archetypes.get("ContainerBlueprint", {}).get("contents", [])
    }
    result = copy.deepcopy(blueprint)
    key = _key(matches[0])
    while key in parent:
        key, listed = parent[key]
        container = result[key]["ContainerBlueprint"]
        if container.get("container_kind") == "Tabs":
            container["active_tab"] = listed
    return result


def _key(ref: str) -> str:
    """A container's reference to a child (``view/<id>``, or ``/view/<id>`` in some layouts) → the child's key."""
    return "/" + ref.lstrip("/")


def _tabs(blueprint: dict) -> list[tuple[str, str]]:
    """(reference as a container lists it, e.g. ``view/<id>``, name) of every child of a Tabs container."""
    tabs = []
    for archetypes in blueprint.values():
        container = archetypes.get("ContainerBlueprint", {})
        if container.get("container_kind") != "Tabs":
            continue
        for ref in container.get("contents", []):
            child = blueprint.get(_key(ref), {})
            fields = child.get("ContainerBlueprint") or child.get("ViewBlueprint") or {}
            name = fields.get("display_name") or fields.get("space_origin") or fields.get("container_kind") or ref
            tabs.append((ref, name))
    return tabs
