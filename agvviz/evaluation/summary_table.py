"""The rows of the table a run prints, fitting the run's kind. Pure: no printing, no Rerun.

A run summary (stored in the ``.rrd``) has one section per kind of output the run produced, and
:func:`summary_rows` shows each section that is there:

- camera frames: ``frames``, ``solved``, ``rejected`` and the error statistics
  (:func:`agvviz.evaluation.summary.summarize`) — shown when the run had camera frames, or had
  nothing else (a run whose every frame failed still says "frames N / solved 0"); with a
  ``truth`` row when truth was given but scored no frame (``truth["note"]``, from
  :meth:`agvviz.replay.solve.Replay.truth_status`: the offset between the time spans);
- UWB fusion: ``fusion`` (:class:`agvviz.evaluation.fusion_summary.FusionStats`);
- corrections: ``correction`` (:class:`agvviz.replay.correct.CorrectionStats`), e.g. a corner-only
  ``auv_under_ice`` run, which has no camera frame and so no frame rows;
- Monte-Carlo trials: ``trials`` (:mod:`agvviz.replay.studies.monte_carlo`): cells × trials × solvers and
  each solver's RMSE ÷ CRLB;
- CNOEM grid trials: ``cnoem_study`` (:mod:`agvviz.replay.studies.cnoem`): cells × trials ×
  methods, each method's mean and RMS error and RMS ÷ CRLB, CNOEM ÷ IPPE against the paper;
- suspect frames (issue 25): ``suspects`` (the check stage's counts,
  :func:`agvviz.replay.checks.suspects_summary`), below the frame rows — suspect frames of the
  solved (or "not checked"), stretches, frames per likely cause
  (:func:`agvviz.evaluation.suspect_report.summary_rows`; the CLI lists the stretches below the table);
- an error budget: ``error_budget`` (``run --budget``,
  :meth:`agvviz.evaluation.error_budget.ErrorBudget.summary`): each source's share.

``timing`` holds the wall-clock figures (:func:`agvviz.evaluation.summary.timing`,
:func:`agvviz.replay.studies.monte_carlo.trials_timing`), printed but never stored.
"""

from __future__ import annotations

from agvviz.evaluation import suspect_report

#: Summary sections that are a run's output on their own, without camera frames.
OTHER_KINDS = ("trials", "cnoem_study", "fusion", "correction")
#: Summary sections of studies (they print their own time row).
STUDY_KINDS = ("trials", "cnoem_study")


def _fmt(value, digits: int = 2) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def _mm(value_m):
    return None if value_m is None else 1000.0 * value_m


def has_frame_rows(summary: dict) -> bool:
    """Whether the table shows the camera-frame rows: the run had camera frames, or it has no
    other output to show (then "frames 0" is the honest answer)."""
    if "frames" not in summary:
        return False
    return summary["frames"] > 0 or not any(kind in summary for kind in OTHER_KINDS)


def summary_rows(summary: dict, timing: dict) -> list[tuple[str, str]]:
    """(metric, value) rows of the run's terminal table, section by section (module docstring)."""
    rows: list[tuple[str, str]] = []
    if "trials" in summary:
        rows += _trials_rows(summary["trials"], timing)
    if "cnoem_study" in summary:
        rows += _cnoem_study_rows(summary["cnoem_study"], timing)
    frames = has_frame_rows(summary)
    if frames:
        rows += _frame_rows(summary, timing)
    if "fusion" in summary:
        rows += _fusion_rows(summary["fusion"])
    if "correction" in summary:
        rows += _correction_rows(summary["correction"])
    if summary.get("error_budget"):
        rows += _budget_rows(summary["error_budget"])
    if not frames and not any(kind in summary for kind in STUDY_KINDS) and timing.get("wall_time_s") is not None:
        rows.append(("wall time (s)", _fmt(timing["wall_time_s"], 1)))
    return rows


def _frame_rows(summary: dict, timing: dict) -> list[tuple[str, str]]:
    rows = [("frames", str(summary["frames"])), ("solved", str(summary["solved"]))]
    rows += [(f"rejected: {reason}", str(count)) for reason, count in summary.get("rejected", {}).items()]
    pos = summary["position_error_mm"]
    hdg = summary["heading_error_deg"]
    rows.append(("position RMSE / median / p95 (mm)", f"{_fmt(pos['rmse'])} / {_fmt(pos['median'])} / {_fmt(pos['p95'])}"))
    rows.append(
        ("heading RMSE / median / p95 (deg)", f"{_fmt(hdg['rmse'], 3)} / {_fmt(hdg['median'], 3)} / {_fmt(hdg['p95'], 3)}")
    )
    rows.append(("reprojection RMS median (px)", _fmt(summary["reproj_rms_px"]["median"], 3)))
    if summary.get("truth", {}).get("note"):  # truth given, no frame scored (issue 23)
        rows.append(("truth", summary["truth"]["note"]))
    rows += suspect_report.summary_rows(summary)
    if "time_per_frame_ms" not in timing:  # a stored summary carries no wall-clock figures
        return rows
    rows.append((
        "time per frame (ms): total / detect / solve",
        f"{_fmt(timing.get('time_per_frame_ms'), 1)} / {_fmt(timing.get('detect_ms'), 1)} / {_fmt(timing.get('solve_ms'), 2)}",
    ))
    if "frames_per_s" in timing:
        rows.append(("throughput (frames/s, incl. logging)", _fmt(timing["frames_per_s"], 1)))
    return rows


def _fusion_rows(f: dict) -> list[tuple[str, str]]:
    """Paper 003: 2-D errors, the mean as the paper reports them."""
    rows = [("UWB ranges / fixes scored", f"{f.get('uwb_ranges', 0)} / {f['uwb_xy_error_mm']['n']}")]
    for label, key in (
        ("camera fix 2-D error mean / p95 (mm)", "camera_xy_error_mm"),
        (f"UWB ({f['uwb']}) 2-D error mean / p95 (mm)", "uwb_xy_error_mm"),
        (f"fused ({f['fusion']}) 2-D error mean / p95 (mm)", "fused_xy_error_mm"),
        ("fused while cameras blocked: mean / p95 (mm)", "fused_blocked_xy_error_mm"),
    ):
        rows.append((label, f"{_fmt(f[key]['mean'])} / {_fmt(f[key]['p95'])}"))
    rows.append(("switches / mean jump (mm)", f"{f['switches']} / {_fmt(f['switch_jump_mm']['mean'])}"))
    rows.append(("UWB ranges gated (residual gate / Kalman)", f"{f['uwb_ranges_gated']} / {f['kalman_ranges_gated']}"))
    return rows


def _correction_rows(c: dict) -> list[tuple[str, str]]:
    """Paper 002: navigation corrected over cycles."""
    return [
        ("correction cycles / applied", f"{c['cycles']} / {c['corrections_applied']}"),
        ("navigation RMSE raw → corrected (mm)", f"{_fmt(_mm(c['nav_rmse_m']))} → {_fmt(_mm(c['corrected_rmse_m']))}"),
        (
            "final error raw → corrected (mm)",
            f"{_fmt(_mm(c['nav_final_error_m']))} → {_fmt(_mm(c['corrected_final_error_m']))}",
        ),
        ("mean correction jump (mm)", _fmt(_mm(c["mean_jump_m"]))),
    ]


def _budget_rows(b: dict) -> list[tuple[str, str]]:
    """The error budget (``run --budget``): each source's share of the position error's mean
    square, with the RMSE the run has without it."""
    rows = [(f"error budget ({b['profile']}): share of position MSE", "% (RMSE with it off, mm)")]
    for s in b["sources"]:
        rows.append((f"  {s['source']}", f"{_fmt(_percent(s['share']), 1)} ({_fmt(s['rmse_off_mm'])})"))
    rows.append(("  interaction/other", _fmt(_percent(b["interaction"]), 1)))
    rows.append(("  floor: every source off (mm)", _fmt(b["floor_rmse_mm"])))
    return rows


def _trials_rows(t: dict, timing: dict) -> list[tuple[str, str]]:
    """Monte-Carlo study: its size, then per solver RMSE ÷ CRLB over the cells and the failures;
    the solver the run's settings name is marked."""
    rows = [
        ("study", str(t["study"])),
        ("cells × trials × solvers", f"{t['cells']} × {t['trials_per_cell']} × {len(t['solvers'])}"),
        ("per solver", "RMSE ÷ CRLB median / max, failed"),
    ]
    marked = t.get("run_solver", {}).get("study_solver")
    for name in t["solvers"]:
        s = t["per_solver"][name]
        ratio = s["rmse_over_crlb"]
        label = f"  {name}{' (the run setting)' if name == marked else ''}"
        rows.append((label, f"{_fmt(ratio['median'], 3)} / {_fmt(ratio['max'], 3)}, {s['failed']}"))
    well = t.get("well_conditioned_max_rmse_over_crlb", {})
    if well:
        rows.append(("well-conditioned cells", str(t["well_conditioned_cells"])))
        rows.append((f"  max RMSE ÷ CRLB {' / '.join(well)}", " / ".join(_fmt(v, 3) for v in well.values())))
    if timing.get("wall_time_s") is not None:
        rows.append(("time (s) / trials per s", f"{_fmt(timing['wall_time_s'], 1)} / {_fmt(timing.get('trials_per_s'), 1)}"))
    return rows


def _cnoem_study_rows(c: dict, timing: dict) -> list[tuple[str, str]]:
    """CNOEM grid study (paper 002, Table 3): its size, the cell (when one), then per method the
    mean and RMS position error of F, RMS ÷ CRLB (median over the cells) and the failures; the
    method the run's settings name is marked; CNOEM ÷ IPPE against the paper's figure."""
    rows = [
        ("study", str(c["study"])),
        ("cells × trials × methods", f"{c['cells']} × {c['trials_per_cell']} × {len(c['methods'])}"),
    ]
    bound = c["crlb_position_m"]
    if c["cells"] == 1:
        rows.append(("cell / CRLB of F's position (m)", f"{c['cell_ids'][0]} / {_fmt(bound['min'], 4)}"))
    else:
        rows.append(("CRLB of F's position min / max (m)", f"{_fmt(bound['min'], 4)} / {_fmt(bound['max'], 4)}"))
    rows.append(("per method: error of F", "mean / RMS (m), RMS ÷ CRLB, failed"))
    marked = c.get("run_setting", {}).get("study_method")
    for name in c["methods"]:
        m = c["per_method"][name]
        label = f"  {name}{' (the run setting)' if name == marked else ''}"
        rows.append((
            label,
            f"{_fmt(m['error_m']['mean'], 4)} / {_fmt(m['error_m']['rmse'], 4)}, "
            f"{_fmt(m['rms_over_crlb']['median'], 3)}, {m['failed']}",
        ))
    ratio = c["cnoem_over_ippe"]
    rows.append((
        f"cnoem ÷ {ratio['baseline']} mean error (paper)",
        f"{_fmt(ratio['ratio_of_means'], 3)} ({ratio['paper']:.3f}, {ratio['paper_scope']})",
    ))
    right = c["cnoem_right_minimum"]
    rows.append(("cnoem right min: nav / multistart (%)",
                 f"{_fmt(_percent(right['all']), 1)} / {_fmt(_percent(right['multistart']), 1)}"))
    if timing.get("wall_time_s") is not None:
        rows.append(("time (s) / trials per s", f"{_fmt(timing['wall_time_s'], 1)} / {_fmt(timing.get('trials_per_s'), 1)}"))
    return rows


def _percent(fraction):
    return None if fraction is None else 100.0 * fraction


def markdown_table(rows: list[tuple[str, str]]) -> str:
    """The terminal table's ``rows`` as a markdown table (metric | value, values right-aligned)."""
    lines = ["| metric | value |", "| :--- | ---: |"]
    for metric, value in rows:
        cells = [text.replace("|", "\\|").strip() for text in (metric, value)]
        indent = "· " if metric.startswith("  ") else ""  # a sub-row (per solver, per method)
        lines.append(f"| {indent}{cells[0]} | {cells[1]} |")
    return "\n".join(lines)
