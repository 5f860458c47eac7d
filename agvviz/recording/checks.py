"""The checks of the recording contract that ``inspect`` and ``run`` both apply, so they agree
on what is wrong with a recording (:mod:`agvviz.recording.contract` runs them over a whole
file, the replay's stages frame by frame):

* :func:`frame_problem` — an image's format, emptiness, size bound (read cheaply from the
  JPEG/PNG header) and size against its camera's calibration;
* :class:`TimeChecks` — image time stamps that repeat or go backwards per camera, a recording
  whose images all share one time stamp or whose messages all sit at log time 0, and ground
  truth that does not overlap the images in time;
* :func:`payload_map_problem` — a QR payload's world coordinates against the recording's own
  marker map (``/markers/map``).
"""

from __future__ import annotations

import struct

import numpy as np

from agvviz.geometry import PinholeCamera
from agvviz.model.frames import REJECT_CALIBRATION_SIZE, REJECT_IMAGE
from agvviz.model.topics import GROUND_TRUTH_TOPIC
from agvviz.recording.values import image_size_problem

#: Image formats of the recording contract (``foxglove.CompressedImage.format``).
IMAGE_FORMATS = ("jpeg", "png")

#: A QR payload vertex may differ from the marker map's corner of the same id by this much (m).
#: Both come from one survey: the payload rounds to 0.1 mm, so honest pairs agree to 0.05 mm;
#: 10 mm is 200× that, yet below the ≈6–21 mm position accuracy of a single-code pose at the
#: design geometry (DESIGN §8), so a disagreement that passes cannot move a pose by more than
#: the pose's own uncertainty.
PAYLOAD_MAP_TOLERANCE_M = 0.010
#: A code whose id the map does not list is accepted only within this many times the map's
#: largest nearest-neighbour spacing (at least 1 m) of a mapped code: on the surveyed floor or
#: one grid step beside it (a map that misses a code), never kilometres away.
UNMAPPED_CODE_SPACINGS = 2.0


def image_header_size(data: bytes, image_format: str) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG IHDR or a JPEG SOF marker, without decoding; ``None``
    when the header cannot be read (then the data is no image: :func:`frame_problem` rejects it)."""
    try:
        if image_format == "png":
            if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR":
                return struct.unpack(">II", data[16:24])
            return None
        if image_format == "jpeg":
            if data[:2] != b"\xff\xd8":
                return None
            at = 2
            while at + 4 <= len(data):
                if data[at] != 0xFF:
                    return None
                marker = data[at + 1]
                if marker == 0xFF:  # fill byte
                    at += 1
                    continue
                if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
                    at += 2
                    continue
                (length,) = struct.unpack(">H", data[at + 2 : at + 4])
                if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                    height, width = struct.unpack(">HH", data[at + 5 : at + 9])
                    return width, height
                if marker == 0xDA or length < 2:  # start of scan before any frame header
                    return None
                at += 2 + length
    except struct.error:
        return None
    return None


def frame_problem(
    image_format: str, data: bytes, camera: PinholeCamera | None, size: tuple[int, int] | None = None
) -> tuple[str, str] | None:
    """Why a recorded camera frame cannot be used, as ``(reason, detail)``, or ``None``.

    ``size`` is the frame's ``(width, height)`` when already known (a decoded image); otherwise
    it is read from the JPEG/PNG header (no decoding). Checks, in order: empty frame, format
    outside :data:`IMAGE_FORMATS`, a side outside 1..:data:`~agvviz.recording.values.MAX_IMAGE_SIDE_PX` px, and a size
    that differs from ``camera``'s calibration (when given). Shared by ``inspect`` and ``run``.
    """
    if len(data) == 0:
        return REJECT_IMAGE, f"{image_format or 'image'} frame is empty (0 bytes)"
    if image_format not in IMAGE_FORMATS:
        return REJECT_IMAGE, (
            f"image format {image_format!r} is not in the recording contract "
            f"({' or '.join(IMAGE_FORMATS)})"
        )
    if size is None:
        size = image_header_size(data, image_format)
    if size is None:
        return REJECT_IMAGE, (
            f"{image_format} frame has no readable {image_format.upper()} header "
            f"({len(data)} bytes starting {data[:4].hex()}): not an image, or damaged"
        )
    width, height = (int(v) for v in size)
    problem = image_size_problem(width, height)
    if problem:
        return REJECT_IMAGE, f"{image_format} frame: {problem}"
    if camera is not None and (width, height) != (camera.width_px, camera.height_px):
        return REJECT_CALIBRATION_SIZE, (
            f"the image is {width}x{height} px but its calibration is for "
            f"{camera.width_px}x{camera.height_px} px; the intrinsics do not apply to it"
        )
    return None


def span_text(first_ns: int, last_ns: int) -> str:
    """``start 2023-11-14 22:13:20.000 UTC, duration 1 min 12.4 s`` (a stamp before 2001 is
    taken as time since the start of a simulation or bag clock: ``start 0.000 s``)."""
    seconds = (last_ns - first_ns) / 1e9
    minutes, rest_s = divmod(abs(seconds), 60.0)
    hours, minutes = divmod(int(minutes), 60)
    sign = "-" if seconds < 0 else ""
    if hours:
        duration = f"{sign}{hours} h {minutes:02d} min {rest_s:04.1f} s"
    elif minutes:
        duration = f"{sign}{minutes} min {rest_s:.1f} s"
    else:
        duration = f"{seconds:.3f} s"
    return f"start {format_ns(first_ns)}, duration {duration}"


class TimeChecks:
    """Time-stamp checks shared by ``inspect`` and ``run``: feed every message with
    :meth:`message` (images return their per-frame verdict), then read :meth:`problems`."""

    def __init__(self):
        self._last_image: dict[str, int] = {}
        self._images: dict[str, list[int]] = {}  # topic -> [count, not increasing, first, last]
        self._truth: list[int] | None = None  # [first, last]
        self._messages = 0
        self._nonzero = False

    def message(self, topic: str, log_time_ns: int, is_image: bool, is_truth: bool | None = None) -> str | None:
        """Record one message; for an image, why its time stamp cannot be used, or ``None``.

        An image whose log time is not after the previous image of the same topic (repeated
        or reversed time stamps) cannot be matched to ground truth or odometry: a replay
        rejects it (:data:`REJECT_TIME`).
        """
        self._messages += 1
        self._nonzero = self._nonzero or log_time_ns != 0
        if is_truth or (is_truth is None and topic == GROUND_TRUTH_TOPIC):
            if self._truth is None:
                self._truth = [log_time_ns, log_time_ns]
            self._truth = [min(self._truth[0], log_time_ns), max(self._truth[1], log_time_ns)]
        if not is_image:
            return None
        stats = self._images.setdefault(topic, [0, 0, log_time_ns, log_time_ns])
        stats[0] += 1
        stats[2], stats[3] = min(stats[2], log_time_ns), max(stats[3], log_time_ns)
        last = self._last_image.get(topic)
        if last is not None and log_time_ns <= last:
            stats[1] += 1
            self._last_image[topic] = max(last, log_time_ns)
            what = "repeats" if log_time_ns == last else "goes back from"
            return (
                f"log time {log_time_ns} ns {what} the previous image's {last} ns on {topic}: "
                "time stamps must increase per camera"
            )
        self._last_image[topic] = log_time_ns
        return None

    def truth_vs_images(self) -> tuple[tuple[int, int], tuple[int, int]] | None:
        """((first, last) truth log time, (first, last) image log time) in ns, or ``None`` when
        no truth or no image has been seen."""
        if self._truth is None or not self._images:
            return None
        first = min(v[2] for v in self._images.values())
        last = max(v[3] for v in self._images.values())
        return (self._truth[0], self._truth[1]), (first, last)

    def problems(self, truth_max_dt_ns: int = 0) -> list[str]:
        """Recording-level problems found so far (one line each)."""
        lines = []
        if self._messages > 1 and not self._nonzero:
            lines.append(
                f"every message ({self._messages}) has log time 0: the recording has no time "
                "stamps, so frames cannot be told apart in time nor matched to ground truth"
            )
        for topic, (count, bad, first, last) in sorted(self._images.items()):
            if count > 1 and first == last and self._nonzero:
                lines.append(
                    f"{topic}: all {count} images share one log time ({first} ns): "
                    f"{count - 1} of them cannot be placed in time"
                )
            elif bad:
                lines.append(
                    f"{topic}: {bad} of {count} images have a log time not after the previous "
                    "image's (time stamps repeated or reversed); they cannot be placed in time"
                )
        if self._truth is not None and self._images:
            first = min(v[2] for v in self._images.values())
            last = max(v[3] for v in self._images.values())
            t0, t1 = self._truth
            if t1 < first - truth_max_dt_ns or t0 > last + truth_max_dt_ns:
                lines.append(
                    f"ground truth ({GROUND_TRUTH_TOPIC}, {span_text(t0, t1)}) does not overlap the "
                    f"images ({span_text(first, last)}) in time: no frame can be scored against truth"
                )
        return lines


class QrMap(dict):
    """World corners (4, 3) per id of a QR marker map (a dict, built once and not changed), with
    an index of the codes' centres built on first use (:class:`CentreIndex`): the nearest mapped
    code to a point and each code's nearest neighbour, in memory O(n) whatever the map size (a
    200 000-code map: no n × n array)."""

    _index = None

    def centre_index(self) -> "CentreIndex":
        """The :class:`CentreIndex` of the codes' centres (the mean of their 4 corners)."""
        if self._index is None:
            self._index = CentreIndex(self)
        return self._index


#: Up to this many codes the centres are searched by numpy in blocks of rows; above it by
#: ``scipy.spatial.cKDTree``, whose import costs ≈0.2–0.5 s of a run's start (issue 27).
SMALL_MAP_CODES = 4096
_ROWS_PER_BLOCK = 256  # numpy search: a block's distances are _ROWS_PER_BLOCK × n floats


class CentreIndex:
    """Nearest-centre queries over a QR map's code centres: numpy for a map of up to
    :data:`SMALL_MAP_CODES` codes (a block of rows at a time: memory O(n)), a k-d tree above.
    Both give the Euclidean distance √(dx² + dy² + dz²)."""

    def __init__(self, qr_map: dict):
        self.centres = np.array(
            [np.asarray(c, dtype=float).mean(axis=0) for c in qr_map.values()]
        ).reshape(-1, 3)
        self._tree = None
        if len(self.centres) > SMALL_MAP_CODES:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.centres)

    def nearest_neighbour_distances_m(self) -> np.ndarray:
        """Each code's distance to its nearest other code (needs at least two codes)."""
        if self._tree is not None:
            distances, _ = self._tree.query(self.centres, k=2)  # itself, then its nearest
            return distances[:, 1]
        out = np.empty(len(self.centres))
        for start in range(0, len(self.centres), _ROWS_PER_BLOCK):
            block = self.centres[start:start + _ROWS_PER_BLOCK]
            d = np.sqrt(np.sum((block[:, None, :] - self.centres[None, :, :]) ** 2, axis=2))
            d[np.arange(len(block)), np.arange(start, start + len(block))] = np.inf  # not itself
            out[start:start + len(block)] = d.min(axis=1)
        return out

    def nearest_distance_m(self, point: np.ndarray) -> float:
        """Distance from ``point`` (3,) to the nearest code centre (needs at least one code)."""
        if self._tree is not None:
            return float(self._tree.query(point, k=1)[0])
        return float(np.sqrt(np.sum((self.centres - np.asarray(point, dtype=float)) ** 2, axis=1)).min())


def _index_of(qr_map: dict) -> CentreIndex:
    return qr_map.centre_index() if isinstance(qr_map, QrMap) else CentreIndex(qr_map)


def qr_map_of(marker_map: dict) -> QrMap:
    """World corners (4, 3) per id of a QR ``agvviz.MarkerMap`` (dictionary ``"qr"``); empty
    for ArUco maps and for markers mounted on the vehicle."""
    out = QrMap()
    if not isinstance(marker_map, dict) or marker_map.get("dictionary") != "qr":
        return out
    for entry in marker_map.get("markers", []):
        if entry.get("frame", "world") != "world":
            continue
        corners = np.asarray(entry.get("corners_world_m"), dtype=float)
        if corners.shape == (4, 3) and np.all(np.isfinite(corners)):
            out[str(entry.get("id"))] = corners
    return out


def unmapped_tolerance_m(qr_map: dict[str, np.ndarray]) -> float:
    """How far from the nearest mapped code a code the map does not list may be (m):
    :data:`UNMAPPED_CODE_SPACINGS` × the largest nearest-neighbour distance between mapped
    codes' centres, at least 1 m. Nearest neighbours from :class:`CentreIndex` (memory O(n))."""
    spacing = 0.0
    if len(qr_map) > 1:
        spacing = float(_index_of(qr_map).nearest_neighbour_distances_m().max())
    return max(1.0, UNMAPPED_CODE_SPACINGS * spacing)


def payload_map_problem(
    marker_id: str, points_world_m: np.ndarray, qr_map: dict[str, np.ndarray], unmapped_tol_m: float | None = None
) -> str | None:
    """Why a QR payload (its id and world points; the first four are the vertices) disagrees
    with the recording's marker map, or ``None``. No map, no check."""
    if not qr_map:
        return None
    vertices = np.asarray(points_world_m, dtype=float)[:4]
    mapped = qr_map.get(marker_id)
    if mapped is not None:
        error = float(np.max(np.linalg.norm(vertices - mapped, axis=1)))
        if error > PAYLOAD_MAP_TOLERANCE_M:
            return (
                f"code {marker_id}: payload vertices are up to {error * 1000:.1f} mm from the marker "
                f"map's corners of that id (tolerance {PAYLOAD_MAP_TOLERANCE_M * 1000:g} mm)"
            )
        return None
    tol = unmapped_tolerance_m(qr_map) if unmapped_tol_m is None else unmapped_tol_m
    centre = vertices.mean(axis=0)
    nearest = _index_of(qr_map).nearest_distance_m(centre)
    if nearest > tol:
        return (
            f"code {marker_id} is not in the marker map and its payload puts it {nearest:.1f} m "
            f"from the nearest mapped code (at most {tol:.1f} m accepted)"
        )
    return None


def format_ns(t_ns: int | None, start_ns: int | None = None) -> str:
    """A time stamp for people: ``+72.400 s`` after ``start_ns`` when given; else a UTC date and
    time (``2023-11-14 22:13:20.000 UTC``) for stamps from 2001 on, seconds (``3.900 s``) for
    earlier ones (a simulation or bag clock from zero); ``-`` for none."""
    import datetime

    if t_ns is None:
        return "-"
    if start_ns is not None:
        return f"{'+' if t_ns >= start_ns else '-'}{abs(t_ns - start_ns) / 1e9:.3f} s"
    if t_ns < 978_307_200 * 10**9:  # 2001-01-01 UTC
        return f"{t_ns / 1e9:.3f} s"
    seconds, nanos = divmod(t_ns, 10**9)
    when = datetime.datetime.fromtimestamp(seconds, tz=datetime.timezone.utc)
    return f"{when:%Y-%m-%d %H:%M:%S}.{nanos // 10**6:03d} UTC"
