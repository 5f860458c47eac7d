"""Suspect stretches (consecutive suspects of one cause), the run-level findings' stretches, and the
run summary's ``suspects`` entry."""

from __future__ import annotations

from typing import Iterable

from agvviz.model.suspects import CAUSES, CHECKS, RunFinding, SuspectStretch


# -- stretches and the summary ------------------------------------------------------------------
def suspect_stretches(frames: Iterable) -> list[SuspectStretch]:
    """Consecutive suspect frames of one camera with one cause (and the same marker / camera named),
    no clean solved frame between them; rejected frames do not break a stretch. ``frames``: anything
    with ``index``, ``cam_name``, ``solved`` and ``suspect`` (a :class:`FrameResult`), in file order.
    Stretches are listed by their first frame."""
    open_: dict[str, list] = {}  # camera -> [stretch fields]
    done: list[SuspectStretch] = []

    def close(cam: str) -> None:
        s = open_.pop(cam, None)
        if s is not None:
            done.append(SuspectStretch(**s))

    for frame in frames:
        suspect = frame.suspect
        cam = frame.cam_name
        if suspect is None:
            if frame.solved:
                close(cam)
            continue
        s = open_.get(cam)
        if s is not None and (s["cause"], s["marker_id"], s["cam_name"]) == (suspect.cause, suspect.marker_id, suspect.cam_name):
            s["last_frame"], s["last_time_ns"] = suspect.frame_index, suspect.log_time_ns
            s["n_frames"] += 1
            s["max_sigma"] = max(s["max_sigma"], suspect.sigma)
            continue
        close(cam)
        open_[cam] = dict(
            first_frame=suspect.frame_index, last_frame=suspect.frame_index, first_time_ns=suspect.log_time_ns,
            last_time_ns=suspect.log_time_ns, n_frames=1, cause=suspect.cause, message=suspect.message,
            next_step=suspect.next_step, cam_name=suspect.cam_name, marker_id=suspect.marker_id,
            max_sigma=float(suspect.sigma),
        )
    for cam in list(open_):
        close(cam)
    return sorted(done, key=lambda s: (s.first_frame, s.first_time_ns, s.cam_name))


def finding_stretch(finding: RunFinding) -> SuspectStretch:
    """A run-level finding as one stretch: from the first to the last frame it covers."""
    return SuspectStretch(
        first_frame=finding.first_frame, last_frame=finding.last_frame, first_time_ns=finding.first_time_ns,
        last_time_ns=finding.last_time_ns, n_frames=finding.n_frames, cause=finding.cause, message=finding.message,
        next_step=finding.next_step, cam_name=finding.cam_name, max_sigma=float(finding.sigma), run_level=True,
    )


def all_stretches(frames: Iterable, findings: Iterable[RunFinding] = ()) -> list[SuspectStretch]:
    """The stretches a user is shown: each run-level finding's stretch, and the frames' own
    stretches (:func:`suspect_stretches`) except those a finding already says — of its camera
    with its cause (a time offset flagged frame by frame where the vehicle turned is the run's
    offset). By first frame."""
    findings = [f for f in findings if f.frame_indices]
    said = {(f.cam_name, f.cause) for f in findings}
    own = [s for s in suspect_stretches(frames) if (s.cam_name, s.cause) not in said]
    return sorted(own + [finding_stretch(f) for f in findings], key=lambda s: (s.first_frame, s.first_time_ns, s.cam_name))


def finding_dict(finding: RunFinding) -> dict:
    """A run-level finding as plain values (the summary stores it; not the frames it covers)."""
    return {
        "cam_name": finding.cam_name, "check": finding.check, "cause": finding.cause,
        "sigma": round(float(finding.sigma), 3), "message": finding.message, "next_step": finding.next_step,
        "offset_ms": None if finding.offset_s is None else round(finding.offset_s * 1000, 3),
        "offset_sigma_ms": None if finding.offset_sigma_s is None else round(finding.offset_sigma_s * 1000, 3),
        "steps": finding.steps, "n_frames": finding.n_frames,
        "first_frame": finding.first_frame if finding.frame_indices else None,
        "last_frame": finding.last_frame if finding.frame_indices else None,
    }


def stretch_dict(stretch: SuspectStretch) -> dict:
    """A stretch as plain values (the summary stores it)."""
    return {
        "first_frame": stretch.first_frame, "last_frame": stretch.last_frame,
        "first_time_ns": stretch.first_time_ns, "last_time_ns": stretch.last_time_ns,
        "n_frames": stretch.n_frames, "cause": stretch.cause, "message": stretch.message,
        "next_step": stretch.next_step, "cam_name": stretch.cam_name, "marker_id": stretch.marker_id,
        "max_sigma": round(float(stretch.max_sigma), 3), "run_level": stretch.run_level,
    }


def suspects_summary(frames: Iterable, checked: bool = True, findings: Iterable[RunFinding] = ()) -> dict:
    """The run summary's ``suspects`` entry: ``checked`` (the check stage ran), ``frames`` (suspect
    frames: solved frames with a suspect of their own or covered by a run-level finding),
    ``solved`` (solved frames checked), ``by_cause`` and ``by_check`` (counts of those frames,
    each under its own suspect's cause and check, else its finding's; every name of
    :data:`CAUSES` / :data:`CHECKS` present, zeros included), ``findings`` (the run-level
    findings, :func:`finding_dict` each; ``covered`` the frames they add) and ``stretches``
    (:func:`all_stretches`, :func:`stretch_dict` each)."""
    frames = list(frames)
    findings = list(findings)
    covering = {}  # (camera, frame index) -> the first finding that covers it
    for finding in findings:
        for index in finding.frame_indices:
            covering.setdefault((finding.cam_name, index), finding)
    by_cause = {c: 0 for c in CAUSES}
    by_check = {c: 0 for c in CHECKS}
    n = covered = 0
    for f in frames:
        finding = covering.get((f.cam_name, f.index)) if f.solved else None
        what = f.suspect or finding
        if what is None:
            continue
        n += 1
        covered += f.suspect is None
        by_cause[what.cause] = by_cause.get(what.cause, 0) + 1
        by_check[what.check] = by_check.get(what.check, 0) + 1
    return {
        "checked": bool(checked),
        "frames": n,
        "solved": sum(1 for f in frames if f.solved),
        "by_cause": by_cause,
        "by_check": by_check,
        "findings": [finding_dict(f) for f in findings],
        "covered": covered,
        "stretches": [stretch_dict(s) for s in all_stretches(frames, findings)],
    }
