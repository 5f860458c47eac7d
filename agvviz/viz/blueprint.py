"""The default viewer layout shipped inside every run ``.rrd``.

::

    ┌──────────────────────────────┬──────────────────────────────────────┐
    │ 3D world, following the      │ camera image: corners, ids, LM path  │
    │ estimated AGV (markers,      │ (one tab per camera; zoom on a small │
    │ truth vs estimate, ghost,    │  code beside it)                     │
    │ ellipsoid, trajectories)     ├──────────────────────────────────────┤
    │                              │ this frame's solve (text) + LM tabs  │
    ├──────────────┬───────────────┼─────────────┬────────────────────────┤
    │ position err │ heading err   │ reproj RMS  │ summary (terminal      │
    │ (+ rejected) │ (tabs: pitch, │ + threshold │ table) / rejections /  │
    │              │  roll)        │ (tabs)      │ manifest / flips       │
    └──────────────┴───────────────┴─────────────┴────────────────────────┘

Every plot has its legend; the time panel is on ``elapsed`` (seconds since the recording's
start).
"""

from __future__ import annotations

import rerun.blueprint as rrb

from agvviz.viz import budget_logger, paths

_LEGEND = rrb.PlotLegend(visible=True, corner=rrb.Corner2D.LeftTop)


def _error_view(entities: list[str], name: str) -> rrb.TimeSeriesView:
    """Time series of ``entities`` with the rejected-frame markers along the zero line."""
    return rrb.TimeSeriesView(
        origin="/",
        contents=[f"/{e}" for e in [*entities, paths.ERROR_REJECTED]],
        name=name,
        plot_legend=_LEGEND,
    )


#: Where the eye of a 3D view that follows the vehicle starts, from the vehicle's first
#: position (world metres: behind-left and above, so the body, the ellipsoid above it and the
#: codes the camera sees are all in view).
EYE_OFFSET_M = (-2.5, -2.5, 2.2)


def world_3d_view(
    name: str,
    cam_names: list[str],
    fixed_cams: set[str] = frozenset(),
    track: str | None = None,
    start_m: tuple[float, float, float] | None = None,
) -> rrb.Spatial3DView:
    """The 3D world view; ``track``: an entity the eye follows (e.g. the estimated AGV), from
    EYE_OFFSET_M off ``start_m`` (its first position). The 2D overlays of the images (corners,
    ids, LM path: UI-point sizes that would swamp the small frustum images) stay in the 2D
    image views."""
    excluded = [f"- /{e}" for c in cam_names for e in paths.image_overlays(c, c in fixed_cams)]
    eye = None
    if track is not None:
        start = None if start_m is None else [float(v) for v in start_m]
        eye = rrb.EyeControls3D(
            tracking_entity=f"/{track}",
            look_target=start,
            position=None if start is None else [a + b for a, b in zip(start, EYE_OFFSET_M)],
        )
    return rrb.Spatial3DView(origin=paths.WORLD, name=name, contents=["+ $origin/**", *excluded], eye_controls=eye)


def image_view(cam_name: str, fixed: bool = False) -> rrb.Spatial2DView:
    """The recorded image of ``cam_name`` with its corners, code ids and LM path."""
    return rrb.Spatial2DView(
        origin=paths.image(cam_name, fixed),
        name=f"camera {cam_name}: detected corners (cyan), reprojected (magenta), LM path (white)",
    )


def zoom_view(cam_name: str) -> rrb.Spatial2DView:
    """The crop around ``cam_name``'s smallest code (logged only while a code is small)."""
    return rrb.Spatial2DView(
        origin=f"{paths.zoom(cam_name)}/image",
        name=f"camera {cam_name} zoomed on its smallest code: detected (cyan), reprojected (magenta)",
    )


def _lm_panel(lm_iterates: bool) -> rrb.Container | rrb.View:
    """The frame's solve in words and, for an iterating solver, its iterations (log10 bars)."""
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
        rrb.TimeSeriesView(
            origin="/", contents=[f"/{paths.LM_ITERATIONS}"], name="LM trial steps per frame", plot_legend=_LEGEND
        ),
        active_tab=0,
    )
    return rrb.Vertical(text, bars, row_shares=[0.3, 0.7])


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
    start_m: tuple[float, float, float] | None = None,
    budget_sources: list[str] | None = None,
) -> rrb.Blueprint:
    """Build the default layout for a run with cameras ``cam_names`` (fits 1600×1000).

    ``zoom_cams`` had a small code (a zoomed view beside their image); ``lm_iterates``: the
    solver iterated on some frame (else the solver panel is its text alone); ``has_rejections``
    puts the rejection log under the summary; ``has_threshold``: the reprojection plot has
    its ``max_reproj_px`` line; ``ghost_max_ratio`` and ``cov_scale`` are named in the 3D
    view's title; the 3D view follows the estimated AGV from its first position ``start_m``.
    ``budget_sources``: the run holds an error budget of these sources (``run --budget``): its
    table is the active document and its chart and series are tabs beside the position error.
    """
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
    title = ["world: truth (green), camera estimate (orange)"]
    if ghost_max_ratio is not None:
        title.append(f"IPPE mirror pose (violet) when ambiguity ratio < {ghost_max_ratio:g}")
    if cov_scale is not None:
        title.append(f"position 3σ ×{cov_scale:g} (above the body)")
    world_view = world_3d_view(", ".join(title), cam_names, fixed_cams, track=paths.AGV_CAMERA, start_m=start_m)
    documents = rrb.Tabs(
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        rrb.TextLogView(origin=paths.EVENTS_FLIPS, name="flips"),
        *([budget_logger.table_view()] if budget_sources is not None else []),
        active_tab=0 if budget_sources is None else 3,
    )
    if has_rejections:
        documents = rrb.Vertical(
            documents, rrb.TextLogView(origin=paths.EVENTS_REJECTIONS, name="rejections"), row_shares=[0.62, 0.38]
        )
    reprojection = [paths.ERROR_REPROJ_RMS_PX] + ([paths.ERROR_REPROJ_THRESHOLD_PX] if has_threshold else [])
    top = rrb.Horizontal(
        world_view,
        rrb.Vertical(image_panel, _lm_panel(lm_iterates), row_shares=[0.6, 0.4]) if lm_iterates
        else rrb.Vertical(image_panel, _lm_panel(lm_iterates), row_shares=[0.85, 0.15]),
        column_shares=[0.52, 0.48],
    )
    position = _error_view([paths.ERROR_POSITION_MM], "position error [mm]")
    if budget_sources is not None:
        position = rrb.Tabs(
            position,
            budget_logger.shares_view(budget_sources),
            budget_logger.deltas_view(budget_sources),
            budget_logger.errors_view(budget_sources),
            active_tab=0,
        )
    bottom = rrb.Horizontal(
        position,
        rrb.Tabs(
            _error_view([paths.ERROR_HEADING_DEG], "heading error [deg]"),
            _error_view([paths.ERROR_PITCH_DEG], "pitch error [deg]"),
            _error_view([paths.ERROR_ROLL_DEG], "roll error [deg]"),
            active_tab=0,
        ),
        rrb.Tabs(
            _error_view(reprojection, "reprojection RMS [px]" + (" vs max_reproj_px" if has_threshold else "")),
            *([_error_view([paths.ERROR_REPROJ_RMS_PX], "reprojection RMS [px], detail")] if has_threshold else []),
            _error_view([paths.ERROR_POSITION_OVER_CRLB], "position error ÷ CRLB"),
            _error_view([paths.ERROR_NEES], "NEES (6 = consistent)"),
            _error_view([paths.SOLVER_AMBIGUITY_RATIO], "IPPE ambiguity ratio"),
            active_tab=0,
        ),
        documents,
        column_shares=[0.25, 0.23, 0.22, 0.30],
    )
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[0.62, 0.38]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_ELAPSED),
        auto_views=False,
    )
