"""Detect stage: camera frame → marker corners, ids and payloads (no pose). Work in progress."""

from __future__ import annotations

from agvviz.settings import RunSettings

#: The run settings that change what the detect stage outputs; every other setting (solver,
#: fusion, correction, …) reuses a recording's stored detections.
DETECTION_SETTINGS = ("refine", "feature_points", "tracking", "keyframe_every")


def detection_settings(settings: RunSettings) -> dict:
    """The detection-relevant part of ``settings`` (equal dicts ⇒ equal detections)."""
    return {name: getattr(settings, name) for name in DETECTION_SETTINGS}
