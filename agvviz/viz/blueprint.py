"""The default viewer layout shipped inside every run ``.rrd``.

::

    ┌──────────────────────────────┬─────────────────────────┐
    │ 3D world                     │ camera image + corners  │
    │ (markers, truth vs estimate, │ (one tab per camera)    │
    │  trajectories, frustum)      ├─────────────────────────┤
    │                              │ LM cost per iteration   │
    ├──────────────┬───────────────┼─────────────┬───────────┤
    │ position err │ heading err   │ reproj RMS  │ summary / │
    │ (+ rejected) │ (tabs: pitch, │ (+ rejected)│ manifest /│
    │              │  roll)        │             │ rejections│
    └──────────────┴───────────────┴─────────────┴───────────┘
"""

from __future__ import annotations

import rerun.blueprint as rrb

from agvviz.viz import paths


def _error_view(entity: str, name: str) -> rrb.TimeSeriesView:
    """Time series of one error with the rejected-frame markers along its zero line."""
    return rrb.TimeSeriesView(
        origin="/",
        contents=[entity, paths.ERROR_REJECTED],
        name=name,
        plot_legend=rrb.PlotLegend(visible=False),
    )


def world_3d_view(name: str, cam_names: list[str], fixed_cams: set[str] = frozenset()) -> rrb.Spatial3DView:
    """The 3D world view. Corner dots are drawn in UI points and would swamp the small
    frustum images, so they stay in the 2D image views only."""
    return rrb.Spatial3DView(
        origin=paths.WORLD,
        name=name,
        contents=["+ $origin/**"]
        + [f"- /{paths.detected(c, c in fixed_cams)}" for c in cam_names]
        + [f"- /{paths.reprojected(c, c in fixed_cams)}" for c in cam_names],
    )


def default_blueprint(cam_names: list[str]) -> rrb.Blueprint:
    """Build the default layout for a run with cameras ``cam_names`` (fits 1600×1000)."""
    image_views = [
        rrb.Spatial2DView(
            origin=paths.image(cam_name),
            name=f"camera {cam_name}: detected (cyan), reprojected (magenta)",
        )
        for cam_name in cam_names
    ]
    if not image_views:
        image_panel = rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary")
    elif len(image_views) == 1:
        image_panel = image_views[0]
    else:
        image_panel = rrb.Tabs(*image_views)
    world_view = world_3d_view(
        "world: truth (green), camera estimate (orange), rejected IPPE mirror pose (violet)", cam_names
    )
    lm_view = rrb.BarChartView(
        origin=paths.LM_COST_PER_ITERATION,
        name="LM cost per iteration (this frame)",
        plot_legend=rrb.PlotLegend(visible=False),
    )
    documents = rrb.Tabs(
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        rrb.TextLogView(origin=paths.EVENTS_REJECTIONS, name="rejections"),
        rrb.TextLogView(origin=paths.EVENTS_FLIPS, name="flips"),
        active_tab=0,
    )
    top = rrb.Horizontal(
        world_view,
        rrb.Vertical(image_panel, lm_view, row_shares=[0.68, 0.32]),
        column_shares=[0.56, 0.44],
    )
    bottom = rrb.Horizontal(
        _error_view(paths.ERROR_POSITION_MM, "position error [mm]"),
        rrb.Tabs(
            _error_view(paths.ERROR_HEADING_DEG, "heading error [deg]"),
            _error_view(paths.ERROR_PITCH_DEG, "pitch error [deg]"),
            _error_view(paths.ERROR_ROLL_DEG, "roll error [deg]"),
            active_tab=0,
        ),
        rrb.Tabs(
            _error_view(paths.ERROR_REPROJ_RMS_PX, "reprojection RMS [px]"),
            _error_view(paths.ERROR_POSITION_OVER_CRLB, "position error ÷ CRLB"),
            _error_view(paths.ERROR_NEES, "NEES (6 = consistent)"),
            _error_view(paths.SOLVER_AMBIGUITY_RATIO, "IPPE ambiguity ratio"),
            active_tab=0,
        ),
        documents,
        column_shares=[0.25, 0.25, 0.22, 0.28],
    )
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[0.64, 0.36]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_FRAME),
        auto_views=False,
    )
