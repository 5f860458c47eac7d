"""Picking a tab of a layout by name (:func:`agvviz.viz.blueprints.with_active_tab`, used by
docs/make_pictures.py --tab): on a layout in the form Rerun 0.41's viewer reads it out
(``ViewerClient.get_blueprint().blueprint``; the ids and names below are as a study run's layout
came back from a headless viewer, trimmed to its tabs)."""

from __future__ import annotations

import copy

import pytest

from agvviz.errors import InputError
from agvviz.viz.blueprints import tab_names, with_active_tab

TOP = "/container/top"
REPORT = "/container/report"


def _layout() -> dict:
    """Top-level tabs (figures, RMSE, report); the report is itself tabs (report, summary, JSON);
    a horizontal container with a view that is not a tab; a view named by its origin only."""
    return {
        "/viewport": {"ViewportBlueprint": {"root_container": "top"}},
        TOP: {"ContainerBlueprint": {
            "container_kind": "Tabs", "active_tab": "container/figures",
            "contents": ["container/figures", "container/rmse", "container/report"],
        }},
        "/container/figures": {"ContainerBlueprint": {
            "container_kind": "Horizontal", "contents": ["view/fig9"],
            "display_name": "paper figures 9–11 (h 0.2667 m, z 2 m, N 4)",
        }},
        "/view/fig9": {"ViewBlueprint": {"class_identifier": "TimeSeries", "display_name": "fig 9: mean t1 (m)"}},
        "/container/rmse": {"ContainerBlueprint": {"container_kind": "Grid", "contents": [], "display_name": "RMSE per solver vs σ"}},
        REPORT: {"ContainerBlueprint": {
            "container_kind": "Tabs", "active_tab": "view/paper", "display_name": "report",
            "contents": ["view/paper", "view/summary", "view/json", "view/unnamed"],
        }},
        "/view/paper": {"ViewBlueprint": {"class_identifier": "TextDocument", "display_name": "report (paper vs ours, every cell)"}},
        "/view/summary": {"ViewBlueprint": {"class_identifier": "TextDocument", "display_name": "summary"}},
        "/view/json": {"ViewBlueprint": {"class_identifier": "TextDocument", "display_name": "summary (JSON)"}},
        "/view/unnamed": {"ViewBlueprint": {"class_identifier": "TextDocument", "space_origin": "run/manifest"}},
        "/time_panel": {"TimePanelBlueprint": {"timeline": "sigma_mpx"}},
    }


def _active(layout: dict) -> tuple[str, str]:
    return layout[TOP]["ContainerBlueprint"]["active_tab"], layout[REPORT]["ContainerBlueprint"]["active_tab"]


def test_tab_names_lists_every_tab_child_and_names_an_unnamed_view_by_its_origin():
    assert tab_names(_layout()) == [
        "paper figures 9–11 (h 0.2667 m, z 2 m, N 4)", "RMSE per solver vs σ", "report",
        "report (paper vs ours, every cell)", "summary", "summary (JSON)", "run/manifest",
    ]


def test_a_nested_tab_is_shown_with_the_tab_around_it():
    layout = _layout()
    before = copy.deepcopy(layout)
    shown = with_active_tab(layout, "summary (JSON)")
    assert _active(shown) == ("container/report", "view/json")
    assert layout == before  # a copy: the layout read back stays as it was


def test_a_whole_name_wins_over_a_longer_name_it_starts():
    # "summary" is whole for one tab and the start of "summary (JSON)"; "report" likewise.
    assert _active(with_active_tab(_layout(), "Summary")) == ("container/report", "view/summary")
    assert _active(with_active_tab(_layout(), "report")) == ("container/report", "view/paper")


def test_the_start_of_one_name_picks_it_and_leaves_other_tabs_alone():
    shown = with_active_tab(_layout(), "paper figures")
    assert _active(shown) == ("container/figures", "view/paper")
    assert _active(with_active_tab(_layout(), "rmse per")) == ("container/rmse", "view/paper")


@pytest.mark.parametrize("name, message", [
    ("CRLB cells", "no tab is named 'CRLB cells'"),
    ("fig 9", "no tab is named 'fig 9'"),  # a view inside a tab is no tab
])
def test_a_name_no_tab_has_is_one_line_naming_the_tabs(name, message):
    with pytest.raises(InputError, match="no tab is named") as error:
        with_active_tab(_layout(), name)
    assert message in str(error.value) and "RMSE per solver vs σ" in str(error.value) and "\n" not in str(error.value)


def test_a_name_several_tabs_start_with_is_refused():
    with pytest.raises(InputError, match="2 tabs start with 'summ'"):
        with_active_tab({**_layout(), "/view/summary": {"ViewBlueprint": {"display_name": "summary table"}}}, "summ")


def test_a_layout_whose_containers_list_children_with_a_leading_slash():
    """A sweep .rrd's layout came back from the viewer with ``/view/<id>`` in ``contents``."""
    layout = _layout()
    for archetypes in layout.values():
        container = archetypes.get("ContainerBlueprint")
        if container:
            container["contents"] = ["/" + ref for ref in container["contents"]]
            if "active_tab" in container:
                container["active_tab"] = "/" + container["active_tab"]
    assert _active(with_active_tab(layout, "summary (JSON)")) == ("/container/report", "/view/json")
