"""The default layout of a run with UWB (paper 003), shipped inside its ``.rrd``.

::

    ┌───────────────────────────────┬──────────────────────────────┐
    │ 3D world: room, wall cameras, │ the four camera images (2×2) │
    │ anchors, truth / camera / UWB │ detected (cyan) and          │
    │ / fused trajectories          │ reprojected (magenta) corners│
    ├───────────────────────────────┼───────────────┬──────────────┤
    │ ranges per anchor (2×2):      │ 2-D errors:   │ switches /   │
    │ measured, from truth, from    │ camera, UWB,  │ gates / cam  │
    │ estimate; gated ranges (×)    │ fused         │ used / GDOP /│
    │                               │               │ summary      │
    └───────────────────────────────┴───────────────┴──────────────┘
"""

from __future__ import annotations

import rerun.blueprint as rrb

from agvviz.viz import paths
from agvviz.viz.blueprint import world_3d_view


def uwb_blueprint(cam_names: list[str], fixed_cams: set[str], anchor_ids: list[str]) -> rrb.Blueprint:
    """Layout for a run with cameras ``cam_names`` (``fixed_cams`` fixed in the world) and
    UWB anchors ``anchor_ids``; the time panel follows recording time (UWB and cameras run at
    different rates)."""
    images = [
        rrb.Spatial2DView(origin=paths.image(c, c in fixed_cams), name=f"camera {c}") for c in cam_names
    ]
    image_panel = rrb.Grid(*images) if len(images) > 1 else (images[0] if images else rrb.Spacer())
    world = world_3d_view("world: truth (green), camera (orange), UWB (blue), fused (yellow)", cam_names, fixed_cams)
    ranges = rrb.Grid(
        *[
            rrb.TimeSeriesView(
                origin="/",
                contents=[f"/uwb/range/{a}/**"],
                name=f"range {a} [m]",
                plot_legend=rrb.PlotLegend(visible=False),
            )
            for a in anchor_ids
        ]
    )
    errors = rrb.TimeSeriesView(
        origin="/",
        contents=[
            f"/{paths.ERROR_POSITION_MM}",
            f"/{paths.ERROR_UWB_POSITION_M}",
            f"/{paths.ERROR_FUSED_POSITION_M}",
            f"/{paths.ERROR_REJECTED}",
        ],
        name="position errors [m]: camera, UWB, fused",
        plot_legend=rrb.PlotLegend(visible=True),
    )
    documents = rrb.Tabs(
        rrb.TextLogView(origin=paths.EVENTS_FUSION, name="switches"),
        rrb.TextLogView(origin=paths.EVENTS_UWB_GATE, name="gates"),
        rrb.TimeSeriesView(origin=paths.FUSION_CAMERA_USED, name="camera used"),
        rrb.TimeSeriesView(origin=paths.UWB_GDOP, name="GDOP"),
        rrb.TextDocumentView(origin=paths.RUN_SUMMARY, name="summary"),
        rrb.TextDocumentView(origin=paths.RUN_MANIFEST, name="manifest"),
        active_tab=0,
    )
    top = rrb.Horizontal(world, image_panel, column_shares=[0.5, 0.5])
    bottom = rrb.Horizontal(ranges, errors, documents, column_shares=[0.42, 0.33, 0.25])
    return rrb.Blueprint(
        rrb.Vertical(top, bottom, row_shares=[0.55, 0.45]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=paths.TIMELINE_TIME),
        auto_views=False,
    )
