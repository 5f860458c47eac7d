"""Suspect stretches (consecutive suspects of one cause) and the run summary's ``suspects`` entry."""

from __future__ import annotations

from typing import Iterable

from agvviz.model.suspects import CAUSES, CHECKS, SuspectStretch


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


def stretch_dict(stretch: SuspectStretch) -> dict:
    """A stretch as plain values (the summary stores it)."""
    return {
        "first_frame": stretch.first_frame, "last_frame": stretch.last_frame,
        "first_time_ns": stretch.first_time_ns, "last_time_ns": stretch.last_time_ns,
        "n_frames": stretch.n_frames, "cause": stretch.cause, "message": stretch.message,
        "next_step": stretch.next_step, "cam_name": stretch.cam_name, "marker_id": stretch.marker_id,
        "max_sigma": round(float(stretch.max_sigma), 3),
    }


def suspects_summary(frames: Iterable, checked: bool = True) -> dict:
    """The run summary's ``suspects`` entry: ``checked`` (the check stage ran), ``frames`` (suspect
    frames), ``solved`` (solved frames checked), ``by_cause`` and ``by_check`` (counts, every name
    of :data:`CAUSES` / :data:`CHECKS` present, zeros included), ``stretches`` (:func:`stretch_dict` each)."""
    frames = list(frames)
    suspects = [f.suspect for f in frames if f.suspect is not None]
    by_cause = {c: 0 for c in CAUSES}
    by_check = {c: 0 for c in CHECKS}
    for s in suspects:
        by_cause[s.cause] = by_cause.get(s.cause, 0) + 1
        by_check[s.check] = by_check.get(s.check, 0) + 1
    return {
        "checked": bool(checked),
        "frames": len(suspects),
        "solved": sum(1 for f in frames if f.solved),
        "by_cause": by_cause,
        "by_check": by_check,
        "stretches": [stretch_dict(s) for s in suspect_stretches(frames)],
    }
