"""Deterministic error injection: exact map and calibration errors on top of the realism draws.

A scenario option ``inject`` names errors to put into the world on purpose, so that a test
knows exactly what an audit (:mod:`agvviz.app.audit`) must find. Syntax — items separated by ``;``,
each ``KIND:TARGET:key=value[,key=value…]``::

    marker:Q012:dx_m=0.05                   code Q012 lies 5 cm further along world x than mapped
    marker:Q020:yaw_deg=90                  code Q020 is turned 90° about its normal
    marker:Q031:scale=0.02                  code Q031 is printed 2 % too large
    camera:front:pitch_deg=1,dz_m=0.02      camera front sits 1° pitched and 2 cm higher than recorded

``marker`` keys (the :mod:`agvviz.sim.realism` ``map`` source's model: the map and the payload
keep the *mapped* placement, rendering and truth use the moved one): ``dx_m``, ``dy_m``,
``dz_m`` (world frame), ``yaw_deg`` (about the code's normal), ``tilt_x_deg``, ``tilt_y_deg``
(about the code's x and y axes), ``scale`` (printed side = mapped side · (1 + scale)). The true
pose becomes ``R_true = R_true,drawn · Rz(yaw)·Rx(tilt_x)·Ry(tilt_y)``, ``p_true = p_true,drawn
+ (dx, dy, dz)``, ``side_true = side_true,drawn · (1 + scale)``.

``camera`` keys: ``dx_m``, ``dy_m``, ``dz_m`` and ``pitch_deg``, ``roll_deg``, ``yaw_deg``
(rotations about the parent (AGV) frame's x, y and z axes: the axes of heading/pitch/roll in
:mod:`agvviz.conventions`). The camera's *true* mount is unchanged (the world renders as
before); the *recorded* extrinsic is moved so that ``R_true = Exp(φ)·R_recorded`` and
``t_true = t_recorded + (dx, dy, dz)`` with ``φ = (pitch, roll, yaw)`` in radians (left
perturbation in the parent frame) — on top of the realism ``calibration`` draw, exactly so
under ``ideal``. The correction an audit should report is therefore ``+φ`` and ``+d``.

What was injected is recorded in the draws (:class:`agvviz.sim.realism.Draws`, source
``inject``) and folded into each draw's ``true`` / ``recorded`` values, so the draws stay the
exact truth. Numpy only: no files, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from agvviz.geometry import so3
from agvviz.geometry.euler import Rx, Ry, Rz

HELP = (
    "errors injected on purpose, ';'-separated KIND:TARGET:key=value[,…], e.g. "
    "marker:Q012:dx_m=0.05;marker:Q020:yaw_deg=90;marker:Q031:scale=0.02;camera:front:pitch_deg=1,dz_m=0.02 "
    "(keys in agvviz/sim/inject.py)"
)
MARKER_KEYS = ("dx_m", "dy_m", "dz_m", "yaw_deg", "tilt_x_deg", "tilt_y_deg", "scale")
CAMERA_KEYS = ("dx_m", "dy_m", "dz_m", "pitch_deg", "roll_deg", "yaw_deg")
#: Inclusive bound of |value| per unit suffix (scale: open interval (-0.5, 0.5)).
_LIMITS = {"_m": 10.0, "_deg": 180.0}


@dataclass(frozen=True)
class Injection:
    """One target's injected error: ``kind`` "marker" or "camera", its id or camera name, and
    the values given (key → float; keys not given are 0)."""

    kind: str
    target: str
    values: dict

    def get(self, key: str) -> float:
        return float(self.values.get(key, 0.0))


@dataclass(frozen=True)
class InjectSpec:
    """The parsed ``inject`` option."""

    items: tuple[Injection, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.items)

    def markers(self) -> dict[str, Injection]:
        return {i.target: i for i in self.items if i.kind == "marker"}

    def cameras(self) -> dict[str, Injection]:
        return {i.target: i for i in self.items if i.kind == "camera"}

    def to_json(self) -> list[dict]:
        return [{"kind": i.kind, "target": i.target, "values": dict(i.values)} for i in self.items]


def parse_inject(text: str) -> InjectSpec:
    """Parse the ``inject`` option; ``ValueError`` with a one-line message naming the item."""
    if not isinstance(text, str):
        raise ValueError(f"inject must be text, got {type(text).__name__}")
    items = []
    seen = set()
    for raw in (p.strip() for p in text.split(";")):
        if not raw:
            continue
        parts = raw.split(":")
        if len(parts) != 3 or not parts[1].strip():
            raise ValueError(f"inject: {raw!r} is not KIND:TARGET:key=value[,key=value…] (e.g. marker:Q012:dx_m=0.05)")
        kind, target, body = parts[0].strip(), parts[1].strip(), parts[2]
        if kind not in ("marker", "camera"):
            raise ValueError(f"inject: {raw!r}: kind {kind!r} is not marker or camera")
        allowed = MARKER_KEYS if kind == "marker" else CAMERA_KEYS
        if (kind, target) in seen:
            raise ValueError(f"inject: {kind} {target!r} is given twice; put all its keys in one item")
        seen.add((kind, target))
        values = {}
        for pair in (p.strip() for p in body.split(",")):
            key, sep, value = pair.partition("=")
            key = key.strip()
            if not sep or key not in allowed:
                raise ValueError(f"inject: {raw!r}: {pair!r} is not key=value with a {kind} key among: {', '.join(allowed)}")
            if key in values:
                raise ValueError(f"inject: {raw!r}: {key} is given twice")
            try:
                number = float(value)
            except ValueError:
                raise ValueError(f"inject: {raw!r}: {key}={value.strip()!r} is not a number") from None
            if not math.isfinite(number):
                raise ValueError(f"inject: {raw!r}: {key} must be finite, got {value.strip()}")
            if key == "scale":
                if not -0.5 < number < 0.5:
                    raise ValueError(f"inject: {raw!r}: scale must lie in (-0.5, 0.5), got {number:g}")
            else:
                limit = next(v for suffix, v in _LIMITS.items() if key.endswith(suffix))
                if abs(number) > limit:
                    raise ValueError(f"inject: {raw!r}: |{key}| must be ≤ {limit:g}, got {number:g}")
            values[key] = number
        if not values:
            raise ValueError(f"inject: {raw!r} names no key=value")
        items.append(Injection(kind, target, values))
    return InjectSpec(tuple(items))


def check_targets(spec: InjectSpec, marker_ids, camera_names) -> None:
    """``ValueError`` when an item names a marker or camera the scenario does not have."""
    ids = set(marker_ids)
    for target in spec.markers():
        if target not in ids:
            some = ", ".join(sorted(ids)[:5])
            raise ValueError(f"inject: the scene has no marker {target!r} (ids like {some} …)")
    for target in spec.cameras():
        if target not in camera_names:
            raise ValueError(f"inject: the scenario has no camera {target!r}; its cameras: {', '.join(camera_names)}")


def apply_to_marker(draw, injection: Injection | None):
    """A :class:`agvviz.sim.realism.MarkerDraw` with ``injection`` added to its true
    placement (module docstring); ``delta`` gets the totals and an ``injected`` entry."""
    if injection is None:
        return draw
    g = injection.get
    T_true = np.array(draw.T_parent_marker_true, dtype=float)
    yaw, tilt_x, tilt_y = (math.radians(g(k)) for k in ("yaw_deg", "tilt_x_deg", "tilt_y_deg"))
    T_true[:3, :3] = T_true[:3, :3] @ Rz(yaw) @ Rx(tilt_x) @ Ry(tilt_y)
    T_true[:3, 3] = T_true[:3, 3] + np.array([g("dx_m"), g("dy_m"), g("dz_m")])
    side_true = draw.side_true_m * (1.0 + g("scale"))
    delta = dict(draw.delta)
    delta["injected"] = dict(injection.values)
    return dataclasses.replace(draw, T_parent_marker_true=T_true, side_true_m=float(side_true), delta=delta)


def apply_to_camera(draw, injection: Injection | None):
    """A :class:`agvviz.sim.realism.CameraDraw` whose *recorded* extrinsic is moved so that
    ``R_true = Exp(φ)·R_recorded``, ``t_true = t_recorded + d`` holds for the injected part
    (module docstring); ``delta`` gets an ``injected`` entry."""
    if injection is None:
        return draw
    g = injection.get
    phi = np.radians([g("pitch_deg"), g("roll_deg"), g("yaw_deg")])
    d = np.array([g("dx_m"), g("dy_m"), g("dz_m")])
    T_rec = np.array(draw.T_parent_cam_recorded, dtype=float)
    T_rec[:3, :3] = so3.exp(-phi) @ T_rec[:3, :3]
    T_rec[:3, 3] = T_rec[:3, 3] - d
    delta = dict(draw.delta)
    delta["injected"] = dict(injection.values)
    return dataclasses.replace(draw, T_parent_cam_recorded=T_rec, delta=delta)
