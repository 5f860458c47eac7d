"""Suspect frames in words (issue 25): the line of one suspect frame or run-level finding (the
``.rrd``'s ``events/suspects`` log), the suspect rows of the run's summary table, and the table of
suspect stretches the terminal prints after it. Pure: no printing, no Rerun.

The stretches are grouped by the check stage (:mod:`agvviz.replay.checks`) into
``summary["suspects"]["stretches"]`` (the fields of :class:`agvviz.model.suspects.SuspectStretch`);
this module only says them.
"""

from __future__ import annotations

from agvviz.model.suspects import CAUSES, RunFinding, Suspect

#: At most this many stretches are listed; the rest are counted ("… and N more").
MAX_STRETCH_ROWS = 20
#: The likely causes in plain words.
CAUSE_WORDS = {
    "map_entry": "marker map entry",
    "payload": "code payload",
    "mirror_flip": "mirror-pose flip",
    "extrinsic": "camera extrinsic",
    "time_offset": "camera time offset",
    "time_stamps": "time stamps",
    "uwb": "camera vs UWB",
    "unknown": "unknown",
}
#: Columns of :func:`stretch_rows`.
STRETCH_COLUMNS = ("frames", "time (s)", "cause", "where", "max σ", "finding", "next step")


def cause_words(cause: str) -> str:
    return CAUSE_WORDS.get(cause, str(cause).replace("_", " "))


def _where(cam_name: str | None, marker_id: str | None) -> str:
    parts = []
    if marker_id:
        parts.append(f"marker {marker_id}")
    if cam_name:
        parts.append(f"camera {cam_name}")
    return ", ".join(parts)


def suspect_line(suspect: Suspect) -> str:
    """One line on a suspect frame: the check and its σ against its limit, the likely cause and
    what it names, the finding and the next step, e.g. ``frame 12 (camera front, marker Q015):
    markers check 41.2σ (limit 5σ), likely cause: marker map entry — code Q015 disagrees …;
    next: `agvviz audit` …``."""
    limit = next((c.limit_sigma for c in suspect.checks if c.check == suspect.check), None)
    limit_text = f" (limit {limit:g}σ)" if limit is not None else ""
    where = _where(suspect.cam_name, suspect.marker_id)
    text = (
        f"frame {suspect.frame_index} ({where}): {suspect.check} check {suspect.sigma:.1f}σ{limit_text}, "
        f"likely cause: {cause_words(suspect.cause)} — {suspect.message}"
    )
    if suspect.next_step:
        text += f"; next: {suspect.next_step}"
    return text


def finding_line(finding: RunFinding) -> str:
    """One line on a run-level finding: the frames it covers, the check and its σ against its
    limit, the likely cause, the finding and the next step, e.g. ``frames 0–57 (58, the whole run;
    camera front): time check 14.2σ (limit 5σ), likely cause: camera time offset — camera front's
    poses lag …; next: …``."""
    first, last = finding.first_frame, finding.last_frame
    text = (
        f"frames {first}–{last} ({finding.n_frames}, the whole run; camera {finding.cam_name}): {finding.check} check "
        f"{finding.sigma:.1f}σ (limit {finding.limit_sigma:g}σ), likely cause: {cause_words(finding.cause)} — {finding.message}"
    )
    if finding.next_step:
        text += f"; next: {finding.next_step}"
    return text


def summary_rows(summary: dict) -> list[tuple[str, str]]:
    """The suspect rows of the summary table: suspect frames (of the solved), stretches, then
    the frames per cause (causes with none left out); none without a ``suspects`` section."""
    section = summary.get("suspects")
    if not isinstance(section, dict):
        return []
    if not section.get("checked", True):
        return [("suspect frames (checks without truth)", "not checked (checks=off)")]
    n = int(section.get("frames", 0))
    solved = summary.get("solved")
    of = f" of {solved} solved" if isinstance(solved, int) else ""
    rows = [("suspect frames (checks without truth)", f"{n}{of}")]
    if not n:
        return rows
    rows.append(("suspect stretches", str(len(section.get("stretches") or []))))
    findings = section.get("findings") or []
    if findings:
        said = "; ".join(f"{cause_words(f.get('cause', 'unknown'))}, camera {f.get('cam_name')} ({f.get('n_frames')} frames)"
                         for f in findings)
        rows.append(("  run-level findings (whole log)", f"{len(findings)}: {said}"))
    by_cause = section.get("by_cause") or {}
    ordered = [c for c in CAUSES if c in by_cause] + sorted(c for c in by_cause if c not in CAUSES)
    rows += [(f"  {cause_words(cause)}", str(by_cause[cause])) for cause in ordered if by_cause[cause]]
    return rows


def _seconds(t_ns, start_ns: int | None) -> float:
    return (int(t_ns) - (start_ns or 0)) / 1e9


def stretch_rows(summary: dict, start_ns: int | None = None,
                 max_rows: int = MAX_STRETCH_ROWS) -> tuple[list[list[str]], int]:
    """Rows (:data:`STRETCH_COLUMNS`) of the suspect stretches, at most ``max_rows``, and how
    many more there are. Times in seconds since ``start_ns`` (the recording's first stamp;
    None: the recording clock's seconds)."""
    section = summary.get("suspects")
    stretches = list((section or {}).get("stretches") or []) if isinstance(section, dict) else []
    rows = []
    for s in stretches[:max_rows]:
        first, last = int(s["first_frame"]), int(s["last_frame"])
        frames = str(first) if first == last else f"{first}–{last}"
        whole = ", the whole run" if s.get("run_level") else ""
        t0, t1 = _seconds(s["first_time_ns"], start_ns), _seconds(s["last_time_ns"], start_ns)
        n = int(s.get("n_frames", last - first + 1))
        rows.append([
            f"{frames} ({n}{whole})",
            f"{t0:.2f}" if first == last else f"{t0:.2f}–{t1:.2f}",
            cause_words(s.get("cause", "unknown")),
            _where(s.get("cam_name"), s.get("marker_id")),
            f"{float(s.get('max_sigma', 0.0)):.1f}",
            str(s.get("message", "")),
            str(s.get("next_step", "")),
        ])
    return rows, max(0, len(stretches) - max_rows)


def stretch_lines(summary: dict, start_ns: int | None = None, max_rows: int = MAX_STRETCH_ROWS) -> list[str]:
    """:func:`stretch_rows` as plain lines (the JUnit report's ``system-out``)."""
    rows, more = stretch_rows(summary, start_ns, max_rows)
    lines = [
        f"frames {r[0]}, t {r[1]} s: {r[2]}" + (f" ({r[3]})" if r[3] else "") + f", max {r[4]}σ — {r[5]}"
        + (f"; next: {r[6]}" if r[6] else "")
        for r in rows
    ]
    if more:
        lines.append(f"… and {more} more")
    return lines
