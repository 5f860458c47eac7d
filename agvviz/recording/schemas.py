"""JSON Schemas (draft 2020-12) of agvviz's custom recording messages, and their checker.

Every custom channel in a recording is JSON-encoded and carries one of these schemas under its
``agvviz.*`` name (DESIGN §4). :func:`validate` checks a payload against a schema by hand for the
small subset of JSON Schema used here (``type``, ``required``, ``properties``, ``items``,
``minItems``/``maxItems``, ``minimum``/``exclusiveMinimum``, ``minLength``) — no ``jsonschema``
dependency. Numbers must be finite; booleans are not numbers.

Units follow :mod:`agvviz.conventions`: metres (``_m``), pixels (``_px``), nanoseconds (``_ns``).
"""

from __future__ import annotations

import math
import sys

#: Name of the MCAP metadata record describing the scenario that produced a recording.
SCENARIO_METADATA = "agvviz.scenario"
#: Name of the MCAP metadata record holding a simulated recording's error-source draws
#: (one value, ``draws``: JSON, see :mod:`agvviz.sim.realism`).
REALISM_METADATA = "agvviz.realism"

_DRAFT = "https://json-schema.org/draft/2020-12/schema"

_POINT3_M = {
    "type": "array",
    "items": {"type": "number"},
    "minItems": 3,
    "maxItems": 3,
}

MARKER_MAP = {
    "$schema": _DRAFT,
    "title": "agvviz.MarkerMap",
    "description": (
        "Fiducial markers fixed in the world. Corners in world metres in OpenCV ArUco order "
        "TL, TR, BR, BL as printed (agvviz.conventions). dictionary is 'qr' for QR codes or an "
        "OpenCV ArUco dictionary name such as 'DICT_6X6_250'; payload is a QR code's text. "
        "frame (optional, default 'world') names the frame the corners are given in: 'agv' for "
        "a marker mounted on the vehicle (paper 003), whose corners_world_m are then in the "
        "agv frame. boards (optional) lists ChArUco boards whose markers are among markers: "
        "their layout (squares, square and marker length, dictionary, legacy_pattern, ids), "
        "pose [x, y, z, qx, qy, qz, qw] of the board frame in frame, and chessboard_corners_m, "
        "the chessboard (saddle) corners in frame by OpenCV's ChArUco corner id (docs/joint-solve.md)."
    ),
    "type": "object",
    "required": ["dictionary", "markers"],
    "properties": {
        "dictionary": {"type": "string", "minLength": 1},
        "markers": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["id", "side_m", "corners_world_m"],
                "properties": {
                    "id": {"type": "string", "minLength": 1},
                    "side_m": {"type": "number", "exclusiveMinimum": 0},
                    "corners_world_m": {
                        "type": "array",
                        "items": _POINT3_M,
                        "minItems": 4,
                        "maxItems": 4,
                    },
                    "payload": {"type": "string"},
                    "frame": {"type": "string", "minLength": 1},
                },
            },
        },
        "boards": {
            "type": "array",
            "items": {
                "type": "object",
                "required": [
                    "type", "squares_x", "squares_y", "square_length_m", "marker_length_m", "dictionary",
                    "legacy_pattern", "ids", "pose", "chessboard_corners_m",
                ],
                "properties": {
                    "type": {"type": "string", "minLength": 1},
                    "squares_x": {"type": "integer", "minimum": 2},
                    "squares_y": {"type": "integer", "minimum": 2},
                    "square_length_m": {"type": "number", "exclusiveMinimum": 0},
                    "marker_length_m": {"type": "number", "exclusiveMinimum": 0},
                    "dictionary": {"type": "string", "minLength": 1},
                    "legacy_pattern": {"type": "boolean"},
                    "ids": {"type": "array", "items": {"type": "integer", "minimum": 0}, "minItems": 1},
                    "pose": {"type": "array", "items": {"type": "number"}, "minItems": 7, "maxItems": 7},
                    "frame": {"type": "string", "minLength": 1},
                    "chessboard_corners_m": {"type": "array", "items": _POINT3_M, "minItems": 1},
                },
            },
        },
    },
}

UWB_RANGE = {
    "$schema": _DRAFT,
    "title": "agvviz.UwbRange",
    "description": (
        "One two-way ranging exchange (paper 003 eq 1). t1_ns: tag sends the poll (T_t1); "
        "t2_ns: anchor receives it (T_a1); t3_ns: anchor sends the reply (T_a2); t4_ns: tag "
        "receives the reply (T_t2). Time of flight = ((t4_ns - t1_ns) - (t3_ns - t2_ns)) / 2; "
        "tag and anchor clocks are separate. Timestamps are device-clock nanoseconds (each "
        "device's own counter, not recording time), fractional allowed: UWB radios timestamp "
        "at ~15.65 ps, and 1 ns is 0.3 m of range. range_m is the reported tag-anchor distance."
    ),
    "type": "object",
    "required": ["tag", "anchor", "t1_ns", "t2_ns", "t3_ns", "t4_ns", "range_m"],
    "properties": {
        "tag": {"type": "string", "minLength": 1},
        "anchor": {"type": "string", "minLength": 1},
        "t1_ns": {"type": "number"},
        "t2_ns": {"type": "number"},
        "t3_ns": {"type": "number"},
        "t4_ns": {"type": "number"},
        "range_m": {"type": "number"},
    },
}

UWB_ANCHORS = {
    "$schema": _DRAFT,
    "title": "agvviz.UwbAnchors",
    "description": "UWB anchors and their positions in the world frame (metres).",
    "type": "object",
    "required": ["anchors"],
    "properties": {
        "anchors": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["id", "position_m"],
                "properties": {
                    "id": {"type": "string", "minLength": 1},
                    "position_m": _POINT3_M,
                },
            },
        }
    },
}

CORNER_OBSERVATIONS = {
    "$schema": _DRAFT,
    "title": "agvviz.CornerObservations",
    "description": (
        "Marker corners seen by camera cam_name without an image (Monte-Carlo studies). "
        "corners_px are pixels of the recorded (distorted) image, OpenCV pixel-centre "
        "convention, order TL, TR, BR, BL, optionally followed by the edge midpoints "
        "top, right, bottom, left (4 or 8 points). Optional, for simulated studies: cell (the "
        "study cell this trial belongs to), trial (its index in the cell), noise_sigma_px (the "
        "pixel noise sigma added), per marker points_marker_m (the marker-frame points, metres, "
        "same order) and T_cam_marker_truth (the true marker pose in the camera frame, 4x4 "
        "row-major)."
    ),
    "type": "object",
    "required": ["cam_name", "markers"],
    "properties": {
        "cam_name": {"type": "string", "minLength": 1},
        "cell": {"type": "string", "minLength": 1},
        "trial": {"type": "integer", "minimum": 0},
        "noise_sigma_px": {"type": "number", "minimum": 0},
        "markers": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["id", "corners_px"],
                "properties": {
                    "id": {"type": "string", "minLength": 1},
                    "corners_px": {
                        "type": "array",
                        "items": {
                            "type": "array",
                            "items": {"type": "number"},
                            "minItems": 2,
                            "maxItems": 2,
                        },
                        "minItems": 4,
                        "maxItems": 8,
                    },
                    "points_marker_m": {"type": "array", "items": _POINT3_M, "minItems": 4, "maxItems": 8},
                    "T_cam_marker_truth": {
                        "type": "array",
                        "items": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
                        "minItems": 4,
                        "maxItems": 4,
                    },
                },
            },
        },
    },
}

#: Schema name → JSON Schema, for every custom message a recording may hold.
SCHEMAS: dict[str, dict] = {
    "agvviz.MarkerMap": MARKER_MAP,
    "agvviz.UwbRange": UWB_RANGE,
    "agvviz.UwbAnchors": UWB_ANCHORS,
    "agvviz.CornerObservations": CORNER_OBSERVATIONS,
}


def _type_ok(expected: str, value: object) -> bool:
    if expected == "object":
        return isinstance(value, dict)
    if expected == "array":
        return isinstance(value, list)
    if expected == "string":
        return isinstance(value, str)
    if expected == "boolean":
        return isinstance(value, bool)
    if expected == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if expected == "number":
        # An int beyond the float range (JSON allows 1e400 written as digits) is not a usable
        # number: math.isfinite() would raise OverflowError on it.
        if isinstance(value, bool):
            return False
        if isinstance(value, int):
            return -_FLOAT_MAX_INT <= value <= _FLOAT_MAX_INT
        return isinstance(value, float) and math.isfinite(value)
    raise ValueError(f"schema uses unsupported type {expected!r}")


_FLOAT_MAX_INT = int(sys.float_info.max)


def _shown(value: object) -> str:
    """repr(value) cut to 40 characters; never raises (an int of more than 4300 digits has no
    repr, and a huge container is not worth printing in full)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        return f"<integer of {value.bit_length()} bits>"
    if isinstance(value, (list, dict, str)) and len(value) > 1000:
        return f"<{type(value).__name__} of length {len(value)}>"
    try:
        text = repr(value)
    except (ValueError, RecursionError):
        return f"<{type(value).__name__}>"
    return text if len(text) <= 40 else text[:37] + "..."


def validate(schema: dict, value: object, where: str = "$") -> list[str]:
    """Problems of ``value`` against ``schema`` (empty list when it conforms).

    Each problem names the JSON path (``$.markers[2].side_m``) and what was expected.
    Properties not listed in the schema are allowed.
    """
    expected = schema.get("type")
    if expected is not None and not _type_ok(expected, value):
        shown = _shown(value)
        article = "an" if expected[0] in "aeiou" else "a"
        extra = " (finite)" if expected == "number" else ""
        return [f"{where}: expected {article} {expected}{extra}, got {shown}"]
    problems: list[str] = []
    if isinstance(value, dict):
        for key in schema.get("required", []):
            if key not in value:
                problems.append(f"{where}: missing required key {key!r}")
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                problems += validate(sub, value[key], f"{where}.{key}")
    if isinstance(value, list):
        if "minItems" in schema and len(value) < schema["minItems"]:
            problems.append(f"{where}: expected at least {schema['minItems']} items, got {len(value)}")
        if "maxItems" in schema and len(value) > schema["maxItems"]:
            problems.append(f"{where}: expected at most {schema['maxItems']} items, got {len(value)}")
        if "items" in schema:
            for i, item in enumerate(value):
                problems += validate(schema["items"], item, f"{where}[{i}]")
    if isinstance(value, str) and len(value) < schema.get("minLength", 0):
        problems.append(f"{where}: expected a string of at least {schema['minLength']} characters")
    if _type_ok("number", value):
        if "minimum" in schema and value < schema["minimum"]:
            problems.append(f"{where}: expected >= {schema['minimum']}, got {_shown(value)}")
        if "exclusiveMinimum" in schema and value <= schema["exclusiveMinimum"]:
            problems.append(f"{where}: expected > {schema['exclusiveMinimum']}, got {_shown(value)}")
    return problems


def validate_payload(schema_name: str, payload: object) -> list[str]:
    """Problems of a decoded JSON ``payload`` of custom schema ``schema_name``.

    Raises ``KeyError`` naming the known schemas when ``schema_name`` is not one of them.
    """
    if schema_name not in SCHEMAS:
        raise KeyError(f"unknown agvviz schema {schema_name!r}; known: {', '.join(SCHEMAS)}")
    return validate(SCHEMAS[schema_name], payload)
