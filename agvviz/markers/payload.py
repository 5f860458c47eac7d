"""QR payload codec: a code's id and the world coordinates of its feature points.

Paper 000 stores, in each floor QR code, the plane coordinates of the code's feature points, so
that one decoded code is enough to localise the camera. A code on a floor is untrusted input:
:func:`parse_payload` is strict and rejects everything that is not exactly the format below,
with a :class:`PayloadError` whose message names the reason.

Format (version ``AGV1``), printable ASCII, no spaces, at most :data:`MAX_PAYLOAD_CHARS`::

    AGV1;id=<ID>;mm=<P>;<P>;<P>;<P>[;<P>;<P>;<P>;<P>]

    ID  = [A-Za-z0-9_-]{1,32}
    P   = NUM,NUM            (x, y on the floor plane; z = 0)
        | NUM,NUM,NUM        (x, y, z)
    NUM = -?(0|[1-9][0-9]{0,7})(\\.[0-9])?     millimetres, |NUM| <= 10 000 000 (10 km)

The points are world coordinates (metres in the API, millimetres with at most one decimal in the
text, so the resolution is 0.1 mm) of the code's four vertices TL, TR, BR, BL in OpenCV ArUco
order as printed, optionally followed by the four edge midpoints top, right, bottom, left
(:mod:`agvviz.conventions`). All points have the same dimensionality. The vertices must form a
convex quadrilateral with edges of at least :data:`MIN_EDGE_M`, all points must be coplanar
(:func:`agvviz.geometry.plane.marker_frame_from_corners`) and each midpoint must lie within
:data:`MIDPOINT_TOL_FRACTION` of its edge's length from that edge's midpoint.

Example: ``AGV1;id=A17;mm=1000,2000;1500,2000;1500,1500;1000,1500``.

The parser accepts ``-0`` and a trailing ``.0``; :func:`encode_payload` always writes the
shortest form (``0``, ``1500``, ``1500.5``) and writes 2-D points when every z is 0 at the
format's resolution.
"""

from __future__ import annotations

from agvviz.errors import InputError

import re
from dataclasses import dataclass

import numpy as np

from agvviz.geometry.plane import DegenerateGeometryError, marker_frame_from_corners

#: Version prefix of the payload format this module reads and writes.
PAYLOAD_PREFIX = "AGV1"
#: Longest accepted payload, checked before any parsing.
MAX_PAYLOAD_CHARS = 256
#: Largest accepted |coordinate| in millimetres (10 km).
MAX_ABS_COORD_MM = 10_000_000
#: Shortest accepted edge between consecutive vertices (metres).
MIN_EDGE_M = 1e-3
#: A midpoint may sit this fraction of its edge's length away from the edge's true midpoint.
MIDPOINT_TOL_FRACTION = 0.05
#: Coplanarity tolerance handed to ``marker_frame_from_corners`` (metres).
PLANARITY_TOL_M = 1e-3

_ID_RE = re.compile(r"[A-Za-z0-9_-]{1,32}")
_NUM = r"(-?)(0|[1-9][0-9]{0,7})(?:\.([0-9]))?"
_POINT_RE = re.compile(rf"{_NUM},{_NUM}(?:,{_NUM})?")
_VERSION_RE = re.compile(r"AGV[0-9]{1,4}")
_FIELD_NAME_RE = re.compile(r"([A-Za-z0-9_]{1,16})=")
_ALLOWED_POINT_COUNTS = (4, 8)


class PayloadError(InputError):
    """A QR payload that is not a valid ``AGV1`` payload, or a value that cannot be encoded."""


@dataclass(frozen=True, eq=False)
class QrPayload:
    """Contents of one agvviz QR code.

    Attributes
    ----------
    marker_id : str
        Code id, ``[A-Za-z0-9_-]{1,32}``.
    points_world_m : np.ndarray, shape (4, 3) or (8, 3)
        World coordinates (metres) of TL, TR, BR, BL, then optionally the edge midpoints
        top, right, bottom, left.
    """

    marker_id: str
    points_world_m: np.ndarray


def encode_payload(payload: QrPayload) -> str:
    """Write ``payload`` as ``AGV1`` text.

    Coordinates are rounded to the format's resolution (0.1 mm); points whose z are all 0 after
    rounding are written as 2-D. The result is checked by :func:`parse_payload`, so whatever
    this returns is accepted by the parser.

    Raises
    ------
    PayloadError
        Bad id, wrong point count or shape, non-finite or out-of-range coordinates, degenerate
        geometry (also when rounding makes it so), or text longer than ``MAX_PAYLOAD_CHARS``.
    """
    if not isinstance(payload.marker_id, str) or not _ID_RE.fullmatch(payload.marker_id):
        raise PayloadError(
            f"invalid marker id {payload.marker_id!r}: use 1-32 characters from [A-Za-z0-9_-]"
        )
    points = np.asarray(payload.points_world_m, dtype=float)
    if points.ndim != 2 or points.shape[0] not in _ALLOWED_POINT_COUNTS or points.shape[1] != 3:
        raise PayloadError(f"points_world_m must have shape (4, 3) or (8, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise PayloadError("points_world_m contains NaN or inf")
    tenths_mm = np.round(points * 1e4)
    if np.any(np.abs(tenths_mm) > MAX_ABS_COORD_MM * 10):
        raise PayloadError(
            f"coordinate out of range: {np.max(np.abs(points)):.1f} m > {MAX_ABS_COORD_MM / 1000:.0f} m"
        )
    tenths_mm = tenths_mm.astype(np.int64)
    if not np.any(tenths_mm[:, 2]):
        tenths_mm = tenths_mm[:, :2]
    point_texts = [",".join(_format_tenths_mm(int(v)) for v in row) for row in tenths_mm]
    text = f"{PAYLOAD_PREFIX};id={payload.marker_id};mm=" + ";".join(point_texts)
    parse_payload(text)
    return text


def parse_payload(text: str | bytes) -> QrPayload:
    """Parse ``AGV1`` payload text (see the module docstring for the grammar).

    Parameters
    ----------
    text : str or bytes
        The decoded QR text; bytes must be ASCII.

    Returns
    -------
    QrPayload
        With ``points_world_m`` of shape (4, 3) or (8, 3) in metres (z = 0 for 2-D points).

    Raises
    ------
    PayloadError
        With a message naming the first problem found.
    """
    if isinstance(text, (bytes, bytearray)):
        if len(text) > MAX_PAYLOAD_CHARS:
            raise PayloadError(f"payload too long: {len(text)} bytes > {MAX_PAYLOAD_CHARS}")
        try:
            text = bytes(text).decode("ascii")
        except UnicodeDecodeError as exc:
            raise PayloadError(
                f"payload is not ASCII: byte 0x{text[exc.start]:02x} at position {exc.start}"
            ) from None
    if not isinstance(text, str):
        raise PayloadError(f"payload must be str or bytes, got {type(text).__name__}")
    if len(text) > MAX_PAYLOAD_CHARS:
        raise PayloadError(f"payload too long: {len(text)} chars > {MAX_PAYLOAD_CHARS}")
    for position, char in enumerate(text):
        if not "!" <= char <= "~":
            raise PayloadError(
                f"forbidden character U+{ord(char):04X} at position {position}: "
                "only printable ASCII without spaces or line breaks is allowed"
            )

    fields = text.split(";")
    _check_version(fields[0])
    if len(fields) < 3:
        raise PayloadError("missing fields: expected 'AGV1;id=...;mm=...'")
    marker_id = _named_field(fields[1], "id", position=1)
    if not _ID_RE.fullmatch(marker_id):
        raise PayloadError(f"invalid marker id {marker_id!r}: use 1-32 characters from [A-Za-z0-9_-]")
    first_point = _named_field(fields[2], "mm", position=2)
    point_texts = [first_point, *fields[3:]]
    for index, point_text in enumerate(point_texts):
        name = _FIELD_NAME_RE.match(point_text)
        if name:
            what = "duplicate" if name.group(1) in ("id", "mm") else "unexpected"
            raise PayloadError(f"{what} field '{name.group(1)}' after point {index - 1}")
    if len(point_texts) not in _ALLOWED_POINT_COUNTS:
        raise PayloadError(f"expected 4 or 8 points, got {len(point_texts)}")
    points_mm = [_parse_point(point_text, index) for index, point_text in enumerate(point_texts)]
    if len({len(p) for p in points_mm}) != 1:
        raise PayloadError("mixed 2-D and 3-D points: write all points as x,y or all as x,y,z")
    points_world_m = np.array([p if len(p) == 3 else (*p, 0.0) for p in points_mm]) / 1000.0
    _check_geometry(points_world_m)
    points_world_m.setflags(write=False)
    return QrPayload(marker_id=marker_id, points_world_m=points_world_m)


def _check_version(field: str) -> None:
    if field == PAYLOAD_PREFIX:
        return
    if _VERSION_RE.fullmatch(field):
        raise PayloadError(
            f"unsupported payload version {field!r}: this agvviz reads {PAYLOAD_PREFIX!r}"
        )
    raise PayloadError(f"not an agvviz payload: expected it to start with '{PAYLOAD_PREFIX};'")


def _named_field(field: str, name: str, position: int) -> str:
    found = _FIELD_NAME_RE.match(field)
    if found is None:
        raise PayloadError(f"field {position} must be '{name}=...', got {field[:40]!r}")
    if found.group(1) == "id" and name == "mm":
        raise PayloadError("duplicate field 'id'")
    if found.group(1) != name:
        raise PayloadError(
            f"field {position} must be '{name}', got '{found.group(1)}' (fields are id then mm)"
        )
    return field[found.end():]


def _parse_point(point_text: str, index: int) -> tuple[float, ...]:
    match = _POINT_RE.fullmatch(point_text)
    if match is None:
        raise PayloadError(
            f"point {index} is malformed: {point_text[:40]!r} (expected x,y or x,y,z in "
            "millimetres with at most 8 integer digits and 1 decimal, e.g. 1500,-20.5)"
        )
    groups = match.groups()
    values = []
    for sign, integer, decimal in zip(groups[0::3], groups[1::3], groups[2::3]):
        if integer is None:
            continue
        # Regex-checked digits only: at most 8 integer digits and 1 decimal digit.
        tenths = int(integer) * 10 + (int(decimal) if decimal else 0)
        if tenths > MAX_ABS_COORD_MM * 10:
            raise PayloadError(
                f"point {index} coordinate {integer} mm out of range (|v| <= {MAX_ABS_COORD_MM} mm)"
            )
        values.append((-tenths if sign else tenths) / 10.0 + 0.0)
    return tuple(values)


def _check_geometry(points_world_m: np.ndarray) -> None:
    for i in range(len(points_world_m)):
        for j in range(i + 1, len(points_world_m)):
            if np.array_equal(points_world_m[i], points_world_m[j]):
                raise PayloadError(f"duplicate points: point {i} equals point {j}")
    vertices = points_world_m[:4]
    edges = np.roll(vertices, -1, axis=0) - vertices
    edge_lengths = np.linalg.norm(edges, axis=1)
    if np.min(edge_lengths) < MIN_EDGE_M:
        raise PayloadError(
            f"degenerate geometry: a vertex edge is {np.min(edge_lengths) * 1000:.1f} mm long "
            f"(< {MIN_EDGE_M * 1000:.0f} mm)"
        )
    try:
        _, points_marker_m = marker_frame_from_corners(points_world_m, PLANARITY_TOL_M)
    except DegenerateGeometryError as exc:
        raise PayloadError(f"degenerate geometry: {exc}") from None
    quad = points_marker_m[:4, :2]
    quad_edges = np.roll(quad, -1, axis=0) - quad
    next_edges = np.roll(quad_edges, -1, axis=0)
    turns = quad_edges[:, 0] * next_edges[:, 1] - quad_edges[:, 1] * next_edges[:, 0]
    # TL, TR, BR, BL in the marker frame (x right, y up) turn clockwise: every cross < 0.
    if not np.all(turns < 0):
        raise PayloadError(
            "degenerate geometry: vertices do not form a convex quadrilateral in TL, TR, BR, BL order"
        )
    for k in range(4, len(points_world_m)):
        edge = k - 4
        expected = (vertices[edge] + vertices[(edge + 1) % 4]) / 2.0
        miss_m = float(np.linalg.norm(points_world_m[k] - expected))
        if miss_m > MIDPOINT_TOL_FRACTION * edge_lengths[edge]:
            name = ("top", "right", "bottom", "left")[edge]
            raise PayloadError(
                f"degenerate geometry: {name} midpoint (point {k}) is {miss_m * 1000:.1f} mm from "
                f"the midpoint of its edge (tolerance {MIDPOINT_TOL_FRACTION:.0%} of the edge)"
            )


def _format_tenths_mm(tenths: int) -> str:
    sign = "-" if tenths < 0 else ""
    whole, decimal = divmod(abs(tenths), 10)
    return f"{sign}{whole}" + (f".{decimal}" if decimal else "")
