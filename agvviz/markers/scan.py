"""Which marker family a recording's frames show, when no map says it (issue 23). Pure: no
file I/O, no printing.

:func:`scan_frame` runs every common family on one grayscale frame — QR (zxing-cpp,
:func:`agvviz.markers.qr.detect_qr_codes`), ArUco ``DICT_4X4_1000`` … ``DICT_7X7_1000`` and
``DICT_ARUCO_ORIGINAL``, AprilTag ``16h5``, ``25h9``, ``36h11`` (through
:func:`agvviz.markers.aruco.detect_aruco`, the detector a run uses, without refinement: the
scan needs ids and sizes, not sub-pixel corners). :class:`FamilyScan` collects a few frames per
camera (the caller samples them spread over the recording: decoding every frame of a long log
is not needed to name a family) and :meth:`FamilyScan.findings` says per camera which families
were seen, their ids, in how many frames and how large (px).

False hits. Small dictionaries decode spurious ids on other families' markers and on clutter
(measured on ``opencv_contrib``'s ``singlemarkersoriginal.jpg``, six DICT_6X6_250 markers:
``DICT_4X4_1000`` reads one extra "id 17"; on its ChArUco photo ``DICT_APRILTAG_16h5`` reads an
"id 24"). So:

* the ArUco dictionaries are scanned in their 1000-id versions (the 50/100/250 ones are their
  first ids) and the dictionary reported is the smallest predefined one holding every id seen
  (:func:`smallest_dictionary`);
* a quadrilateral decoded by two families goes to the family seen in more frames overall (then
  the one with more bits, whose code is the less likely to be matched by chance);
* a family counts as found only when it repeats: seen in at least :data:`MIN_FRAMES` sampled
  frames of a camera (one when the camera has one frame); one with fewer than
  :data:`MINOR_SHARE` of the sightings ((frame, id) pairs) of the camera's main family is
  listed as a likely false hit (the "fragile" symbol on a box in that photo, read as 4×4 id 17
  — the same in every frame of a still camera, so repetition alone does not rule it out).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np

#: Families tried, in the order they are reported on a tie.
QR_FAMILY = "qr"
ARUCO_FAMILIES = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL")
APRILTAG_FAMILIES = ("DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h11")
SCAN_FAMILIES = (QR_FAMILY,) + ARUCO_FAMILIES + APRILTAG_FAMILIES
#: Code bits of each family (a quadrilateral read by two families goes to the one with more).
FAMILY_BITS = {
    QR_FAMILY: 441, "DICT_4X4_1000": 16, "DICT_5X5_1000": 25, "DICT_6X6_1000": 36, "DICT_7X7_1000": 49,
    "DICT_ARUCO_ORIGINAL": 25, "DICT_APRILTAG_16h5": 16, "DICT_APRILTAG_25h9": 25, "DICT_APRILTAG_36h11": 36,
}
#: The predefined sizes of each ArUco family (OpenCV's DICT_nXn_{50,100,250,1000} are prefixes
#: of the 1000-id one).
_ARUCO_SIZES = (50, 100, 250, 1000)
#: Frames (of a camera's sample) a family must be seen in to count as found.
MIN_FRAMES = 2
#: A found family with fewer than this share of the sightings of the camera's main family is
#: listed as a likely false hit.
MINOR_SHARE = 0.25
#: Two detections of different families are one marker when their centres are closer than this
#: share of the smaller one's side.
SAME_MARKER_SHARE = 0.5
#: Frames per camera a scan samples by default.
DEFAULT_FRAMES_PER_CAMERA = 20


@dataclass(frozen=True)
class SeenMarker:
    """One code found by one family: its id (int for ArUco/AprilTag; the payload's id for an
    ``AGV1`` QR code, else its text, cut to 40 characters) and corners (4, 2) in pixels."""

    family: str
    marker_id: int | str
    corners_px: np.ndarray = field(compare=False, repr=False)

    @property
    def side_px(self) -> float:
        """Mean edge length (px): the marker's apparent size."""
        return float(np.mean(np.linalg.norm(np.roll(self.corners_px, -1, axis=0) - self.corners_px, axis=1)))

    @property
    def centre_px(self) -> np.ndarray:
        return self.corners_px.mean(axis=0)


def scan_frame(gray: np.ndarray, families: tuple[str, ...] = SCAN_FAMILIES) -> list[SeenMarker]:
    """Every code any of ``families`` finds in the uint8 gray image (each family on its own;
    overlaps between families are resolved later, over all frames: :class:`FamilyScan`)."""
    from agvviz.markers.aruco import detect_aruco
    from agvviz.markers.qr import detect_qr_codes

    seen: list[SeenMarker] = []
    for family in families:
        if family == QR_FAMILY:
            for code in detect_qr_codes(gray, refine="none", fallback_detectors=False):
                seen.append(SeenMarker(QR_FAMILY, _qr_id(code), np.asarray(code.raw_corners_px, dtype=float)))
        else:
            for det in detect_aruco(gray, family, refine="none"):
                seen.append(SeenMarker(family, int(det.marker_id), np.asarray(det.raw_corners_px, dtype=float)))
    return seen


def _qr_id(code) -> str:
    from agvviz.markers.payload import PayloadError, parse_payload

    if code.text is None:
        return "(undecoded)" if code.payload_bytes is None else "(binary payload)"
    try:
        return parse_payload(code.text).marker_id
    except PayloadError:
        return code.text[:40]


def smallest_dictionary(family: str, ids) -> str:
    """The smallest predefined OpenCV dictionary of ``family`` holding every id in ``ids``
    (``DICT_6X6_1000`` with ids ≤ 203 → ``DICT_6X6_250``); other families are returned as they
    are (AprilTag families and ``DICT_ARUCO_ORIGINAL`` come in one size)."""
    if family not in ARUCO_FAMILIES or family == "DICT_ARUCO_ORIGINAL":
        return family
    top = max((int(i) for i in ids), default=0)
    stem = family.rsplit("_", 1)[0]
    size = next(s for s in _ARUCO_SIZES if top < s)
    return f"{stem}_{size}"


def sample_indices(count: int, n: int = DEFAULT_FRAMES_PER_CAMERA) -> list[int]:
    """Up to ``n`` indices of ``count`` frames, spread evenly from the first to the last."""
    if count <= 0 or n <= 0:
        return []
    if count <= n:
        return list(range(count))
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, n)})


@dataclass
class FamilyFinding:
    """What one family showed in one camera's sampled frames.

    ``dictionary`` is the name for a map (:func:`smallest_dictionary`); ``ids`` maps each id
    to the number of sampled frames it was seen in; ``side_px`` are (min, median, max) of the
    apparent sides; ``likely_false`` says why the family is not believed (then it is not a
    finding a run should use)."""

    family: str
    dictionary: str
    frames_seen: int
    frames_sampled: int
    ids: dict
    side_px: tuple[float, float, float]
    likely_false: str = ""

    @property
    def detections(self) -> int:
        """Sightings: (frame, id) pairs."""
        return sum(self.ids.values())

    def describe(self) -> str:
        """One line: family, ids with counts, frames, sizes."""
        ids = sorted(self.ids, key=lambda i: (isinstance(i, str), i))
        shown = ", ".join(f"{i}×{self.ids[i]}" if self.ids[i] > 1 else f"{i}" for i in ids[:30])
        more = f", … ({len(ids)} ids)" if len(ids) > 30 else ""
        lo, med, hi = self.side_px
        size = f"{med:.0f} px" if hi - lo < 1 else f"{med:.0f} px (min {lo:.0f}, max {hi:.0f})"
        extra = f" — likely false hits: {self.likely_false}" if self.likely_false else ""
        return (f"{family_label(self.dictionary)}: in {self.frames_seen} of {self.frames_sampled} sampled frame(s); "
                f"ids {shown}{more} (×n: seen in n frames); side {size}{extra}")


class FamilyScan:
    """Collects :func:`scan_frame` results per camera, then names the families found."""

    def __init__(self):
        self._frames: dict[str, list[list[SeenMarker]]] = {}

    def add(self, cam: str, markers: list[SeenMarker]) -> None:
        """One sampled frame of ``cam`` and what :func:`scan_frame` found in it."""
        self._frames.setdefault(cam, []).append(list(markers))

    def frames_sampled(self, cam: str) -> int:
        return len(self._frames.get(cam, []))

    def cameras(self) -> list[str]:
        return sorted(self._frames)

    def findings(self, cam: str) -> list[FamilyFinding]:
        """Families seen in ``cam``'s sampled frames, the most often seen first; the ones
        that do not repeat, or are far rarer than the main one, carry ``likely_false``."""
        frames = self._frames.get(cam, [])
        support = Counter(f for frame in frames for f in {m.family for m in frame})
        kept = [_resolve_overlaps(frame, support) for frame in frames]
        per_family: dict[str, list] = {}
        for index, frame in enumerate(kept):
            for marker in frame:
                per_family.setdefault(marker.family, []).append((index, marker))
        n = len(frames)
        out = []
        for family, items in per_family.items():
            frames_seen = len({index for index, _ in items})
            id_frames = Counter()
            for marker_id in {(index, m.marker_id) for index, m in items}:
                id_frames[marker_id[1]] += 1
            sides = np.array([m.side_px for _, m in items])
            ids = dict(id_frames)
            dictionary = smallest_dictionary(family, ids) if family != QR_FAMILY else "qr"
            out.append(FamilyFinding(
                family, dictionary, frames_seen, n, ids,
                (float(sides.min()), float(np.median(sides)), float(sides.max())),
            ))
        out.sort(key=lambda f: (-f.frames_seen, -f.detections, _order(f.family)))
        need = min(MIN_FRAMES, n)
        main = next((f for f in out if f.frames_seen >= need), None)
        for finding in out:
            if finding.frames_seen < need:
                finding.likely_false = f"seen in {finding.frames_seen} frame only (a family must repeat)"
            elif main is not None and finding is not main and finding.detections < MINOR_SHARE * main.detections:
                finding.likely_false = (f"{finding.detections} sighting(s) against {main.detections} of "
                                        f"{main.dictionary}")
        return out

    def found(self, cam: str | None = None) -> list[FamilyFinding]:
        """The believed findings of ``cam`` (or of every camera, merged by family: frames and
        id counts added, dictionary re-chosen for all ids)."""
        cams = [cam] if cam is not None else self.cameras()
        merged: dict[str, FamilyFinding] = {}
        for name in cams:
            for f in self.findings(name):
                if f.likely_false:
                    continue
                if f.family not in merged:
                    merged[f.family] = FamilyFinding(f.family, f.dictionary, f.frames_seen, f.frames_sampled,
                                                     dict(f.ids), f.side_px)
                    continue
                m = merged[f.family]
                m.frames_seen += f.frames_seen
                m.frames_sampled += f.frames_sampled
                for i, c in f.ids.items():
                    m.ids[i] = m.ids.get(i, 0) + c
                m.side_px = (min(m.side_px[0], f.side_px[0]), float(np.median([m.side_px[1], f.side_px[1]])),
                             max(m.side_px[2], f.side_px[2]))
                m.dictionary = smallest_dictionary(m.family, m.ids) if m.family != QR_FAMILY else "qr"
        return sorted(merged.values(), key=lambda f: (-f.frames_seen, _order(f.family)))


def _resolve_overlaps(frame: list[SeenMarker], support: Counter) -> list[SeenMarker]:
    """One family per marker: of detections of different families at the same place, keep the
    one whose family is seen in more frames, then the one with more bits."""

    def rank(m: SeenMarker):
        return (support[m.family], FAMILY_BITS.get(m.family, 0), -_order(m.family))

    kept: list[SeenMarker] = []
    for marker in sorted(frame, key=rank, reverse=True):
        clash = any(other.family != marker.family and _same_place(other, marker) for other in kept)
        if not clash:
            kept.append(marker)
    return kept


def _order(family: str) -> int:
    return SCAN_FAMILIES.index(family) if family in SCAN_FAMILIES else len(SCAN_FAMILIES)


def _same_place(a: SeenMarker, b: SeenMarker) -> bool:
    """Whether two detections are one marker read twice: close centres, or either centre
    inside the other's quadrilateral (a small code read inside a larger one's pattern)."""
    import cv2

    if np.linalg.norm(a.centre_px - b.centre_px) < SAME_MARKER_SHARE * min(a.side_px, b.side_px):
        return True
    for inner, outer in ((a, b), (b, a)):
        quad = outer.corners_px.astype(np.float32).reshape(-1, 1, 2)
        if cv2.pointPolygonTest(quad, tuple(float(v) for v in inner.centre_px), False) >= 0:
            return True
    return False


def family_label(dictionary: str) -> str:
    """A short human name: ``DICT_APRILTAG_36h11`` → ``AprilTag 36h11``, ``DICT_6X6_250`` →
    ``ArUco DICT_6X6_250``, ``qr`` → ``QR``."""
    if dictionary == QR_FAMILY:
        return "QR"
    if dictionary.startswith("DICT_APRILTAG_"):
        return f"AprilTag {dictionary.removeprefix('DICT_APRILTAG_')} ({dictionary})"
    return f"ArUco {dictionary}"
