"""The default layout of a run with UWB (paper 003), shipped inside its ``.rrd``.

::

    ┌───────────────────────────────┬──────────────────────────────────────────┐
    │ 3D world: room, wall cameras, │ per camera (2×2): the code zoomed in     │
    │ anchors, truth / camera / UWB │ (small codes), the full image in a tab;  │
    │ / fused trajectories          │ detected (cyan), reprojected (magenta)   │
    ├──────────────────────┬────────┴───────────┬──────────────────────────────┤
    │ ranges per anchor    │ camera fix error   │ camera used / fused from     │
    │ (2×2, legends):      │ [mm]               │ (state lanes)                │
    │ measured, expected   ├────────────────────┼──────────────────────────────┤
    │ from truth / fused,  │ UWB and fused      │ switches / gates / GDOP /    │
    │ gated (×)            │ error [mm]         │ summary / manifest           │
    └──────────────────────┴────────────────────┴──────────────────────────────┘

Plots run on the ``elapsed`` timeline (seconds since the recording's first stamp).
"""

from __future__ import annotations

import rerun.blueprint as rrb

from agvviz.viz import paths
from agvviz.viz.blueprint import image_view, world_3d_view, zoom_view
from agvviz.viz.style import COLOR_CAMERA, COLOR_FUSED, COLOR_TRUTH, COLOR_UWB, LEGEND


def uwb_blueprint(
    cam_names: list[str],
    fixed_cams: set[str],
    anchor_ids: list[str],
    zoom_cams: list[str] = (),
    error_range_mm: float | None = None,
) -> rrb.Blueprint:
    """Layout for a run with cameras ``cam_names`` (``fixed_cams`` fixed in the world) and
    UWB anchors ``anchor_ids``. ``zoom_cams``: cameras with a zoomed view of their small code
    (:attr:`RunLogger.zoom_cams`), shown first; ``error_range_mm``: top of the UWB/fused error
    plot's y axis (:meth:`FusionLogger.error_range_mm`; None: fit all data)."""
    cameras = [_camera_panel(c, c in fixed_cams, c in zoom_cams) for c in cam_names]
    if not cameras:
        image_panel = rrb.Spacer()
    elif len(cameras) == 1:
        image_panel = cameras[0]
    else:
        image_panel = rrb.Grid(*cameras, grid_columns=2)
    world = world_3d_view(
        f"3D: {LEGEND[COLOR_TRUTH]} (green), {LEGEND[COLOR_CAMERA]} (orange), {LEGEND[COLOR_UWB]} (blue), "
        f"{LEGEND[COLOR_FUSED]} (yellow); UWB anchors",
        cam_names,
        fixed_cams,
    )
    ranges = rrb.Grid(
        *[
            rrb.TimeSeriesView(
                origin="/",
                contents=[f"/uwb/range/{a}/**"],
                name=f"range to anchor {a} [m]",
                plot_legend=rrb.PlotLegend(visible=True),
            )
            for a in anchor_ids
        ],
        grid_columns=2,
    )
    camera_error = rrb.TimeSeriesView(
        origin="/",
        contents=[f"/{paths.ERROR_POSITION_MM}", f"/{paths.ERROR_REJECTED}"],
        name="camera fix error [mm] (gaps: no camera solved)",
        plot_legend=rrb.PlotLegend(visible=True),
    )
    clamp = "" if error_range_mm is None else f" (axis ≤ {error_range_mm:.0f})"
    fused_error = rrb.TimeSeriesView(
        origin="/",
        contents=[f"/{paths.ERROR_UWB_POSITION_MM}", f"/{paths.ERROR_FUSED_POSITION_MM}"],
        name="UWB, fused error [mm]" + clamp,
        plot_legend=rrb.PlotLegend(visible=True),
        axis_y=None if error_range_mm is None else rrb.ScalarAxis(range=(0.0, error_range_mm)),
    )
    states = rrb.StateTimelineView(
        origin="/",
        contents=[f"/{paths.FUSION_CAMERA_USED}", f"/{paths.FUSION_SOURCE}"],
        name="camera used · fused estimate from",
    )
    log_columns = rrb.TextLogColumns(timeline_columns=[paths.TIMELINE_ELAPSED], text_log_columns=["body"])
    documents = rrb.Tabs(
        rrb.TextLogView(origin=paths.EVENTS_FUSION, name="switches", columns=log_columns),
        rrb.TextLogView(origin=paths.EVENTS_UWB_GATE, name="gates", columns=log_columns),
        rrb.TimeSeriesView(origin=paths.UWB_GDOP, name="GDOP", plot_legend=rrb.PlotLegend(visible=False)),
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        active_tab=0,
    )
    top = rrb.Horizontal(world, image_panel, column_shares=[0.45, 0.55])
    bottom = rrb.Horizontal(
        ranges,
        rrb.Vertical(camera_error, fused_error),
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


def _camera_panel(cam_name: str, fixed: bool, zoomed: bool) -> rrb.View | rrb.Container:
    """The zoomed code (when the camera had a small one) with the full image in a second tab."""
    full = image_view(cam_name, fixed)
    if not zoomed:
        return full
    return rrb.Tabs(zoom_view(cam_name), full, active_tab=0)
