"""Deterministic error injection: exact map, payload, calibration and timing faults on top of
the realism draws.

A scenario option ``inject`` names faults to put into the world on purpose, so that a test or a
bench knows exactly what an audit (:mod:`agvviz.app.audit`) or the replay's checks must find.
Syntax — items separated by ``;``, each ``KIND:TARGET:key=value[,key=value…]``::

    marker:Q012:dx_m=0.05                   code Q012 lies 5 cm further along world x than mapped
    marker:Q020:yaw_deg=90                  code Q020 is turned 90° about its normal
    marker:Q031:scale=0.02                  code Q031 is printed 2 % too large
    payload:Q014:dx_m=0.2                   code Q014's QR text says it lies 20 cm further along x
    camera:front:pitch_deg=1,dz_m=0.02      camera front sits 1° pitched and 2 cm higher than recorded
    camera:front:pitch_deg=1,dz_m=0.02,from_s=10   … from 10 s on: the camera got knocked
    timing:front:offset_ms=30               camera front's images are stamped 30 ms after they were taken

``marker`` keys (the :mod:`agvviz.sim.realism` ``map`` source's model: the map and the payload
keep the *mapped* placement, rendering and truth use the moved one): ``dx_m``, ``dy_m``,
``dz_m`` (world frame), ``yaw_deg`` (about the code's normal), ``tilt_x_deg``, ``tilt_y_deg``
(about the code's x and y axes), ``scale`` (printed side = mapped side · (1 + scale)). The true
pose becomes ``R_true = R_true,drawn · Rz(yaw)·Rx(tilt_x)·Ry(tilt_y)``, ``p_true = p_true,drawn
+ (dx, dy, dz)``, ``side_true = side_true,drawn · (1 + scale)``.

``payload`` keys (QR codes whose payload carries coordinates: ``qr_floor``): ``dx_m``, ``dy_m``,
``dz_m`` (world frame, multiples of the payload's 0.1 mm). The code's printed QR text carries
its feature points moved by (dx, dy, dz); the map (``/markers/map``, its corners and payload
text) and the code's true placement stay right. The replay compares a payload with the map
(:func:`agvviz.recording.checks.payload_map_problem`): a shift beyond its 10 mm tolerance is
refused there (``payload_map_mismatch``, the frame loses that code), one within it moves the
pose by about the shift. Record with ``write_map=false`` to leave the map out: then the payload
is the only source of the code's coordinates and any shift moves the pose by the shift.

``camera`` keys: ``dx_m``, ``dy_m``, ``dz_m`` and ``pitch_deg``, ``roll_deg``, ``yaw_deg``
(rotations about the parent (AGV) frame's x, y and z axes: the axes of heading/pitch/roll in
:mod:`agvviz.conventions`), and ``from_s``. Without ``from_s`` the camera's *true* mount is
unchanged (the world renders as before) and the *recorded* extrinsic is moved so that ``R_true =
Exp(φ)·R_recorded`` and ``t_true = t_recorded + (dx, dy, dz)`` with ``φ = (pitch, roll, yaw)``
in radians (left perturbation in the parent frame) — on top of the realism ``calibration``
draw, exactly so under ``ideal``. With ``from_s`` the recorded extrinsic stays as drawn and the
camera's *true* mount moves, ``R_true,after = Exp(φ)·R_true``, ``t_true,after = t_true + d``,
for every frame captured ``from_s`` seconds or more after the recording's first stamp (a frame
is rendered whole with the mount of its capture instant: the knock falls between exposures).
Either way the correction an audit should report for the affected frames is ``+φ`` and ``+d``.

``timing`` key: ``offset_ms``. Every image of the camera is stamped ``offset_ms`` later than the
instant it shows (the world rendered at t, stamped t + offset), on top of the realism
``timing`` draw: the recorded delay (stamp − capture, :class:`agvviz.sim.realism.CameraTiming`)
is the drawn one plus the offset. A scenario bounds |offset| + the drawn reach below half a
frame period (:func:`check_frame_times`).

What was injected is recorded in the draws (:class:`agvviz.sim.realism.Draws`, source
``inject``: one entry per item, :meth:`InjectSpec.to_json`, with the scenario's exact truth of
what each item affects — frames by stamp, the moved mount, the payload written) and folded into
each draw's ``true`` / ``recorded`` values, so the draws stay the exact truth. Numpy only: no
files, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from agvviz.geometry import se3, so3
from agvviz.geometry.euler import Rx, Ry, Rz
from agvviz.markers.payload import QrPayload, encode_payload, parse_payload

HELP = (
    "errors injected on purpose, ';'-separated KIND:TARGET:key=value[,…], e.g. "
    "marker:Q012:dx_m=0.05;marker:Q020:yaw_deg=90;marker:Q031:scale=0.02;payload:Q014:dx_m=0.2;"
    "camera:front:pitch_deg=1,dz_m=0.02[,from_s=10];timing:front:offset_ms=30 "
    "(keys in agvviz/sim/inject.py)"
)
MARKER_KEYS = ("dx_m", "dy_m", "dz_m", "yaw_deg", "tilt_x_deg", "tilt_y_deg", "scale")
CAMERA_KEYS = ("dx_m", "dy_m", "dz_m", "pitch_deg", "roll_deg", "yaw_deg", "from_s")
PAYLOAD_KEYS = ("dx_m", "dy_m", "dz_m")
TIMING_KEYS = ("offset_ms",)
#: Keys of each kind, in the order the messages list them.
KEYS = {"marker": MARKER_KEYS, "payload": PAYLOAD_KEYS, "camera": CAMERA_KEYS, "timing": TIMING_KEYS}
#: Inclusive bound of |value| per unit suffix (scale: open interval (-0.5, 0.5); from_s: 0..3600).
_LIMITS = {"_m": 10.0, "_deg": 180.0, "_ms": 1000.0}
#: Largest ``from_s`` (the longest recording a scenario makes, s).
MAX_FROM_S = 3600.0
#: A payload's coordinates are written at 0.1 mm (:mod:`agvviz.markers.payload`): payload shifts
#: must be multiples of it, so the code says exactly what was injected.
PAYLOAD_STEP_M = 1e-4


@dataclass(frozen=True)
class Injection:
    """One target's injected error: ``kind`` (a key of :data:`KEYS`), its marker id or camera
    name, and the values given (key → float; keys not given are 0, ``from_s`` absent: None)."""

    kind: str
    target: str
    values: dict

    def get(self, key: str) -> float:
        return float(self.values.get(key, 0.0))

    @property
    def from_s(self) -> float | None:
        """``camera``'s ``from_s`` (s after the recording's first stamp), None when not given."""
        return self.values.get("from_s")


@dataclass(frozen=True)
class InjectSpec:
    """The parsed ``inject`` option."""

    items: tuple[Injection, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.items)

    def _of(self, kind: str) -> dict[str, Injection]:
        return {i.target: i for i in self.items if i.kind == kind}

    def markers(self) -> dict[str, Injection]:
        return self._of("marker")

    def payloads(self) -> dict[str, Injection]:
        return self._of("payload")

    def cameras(self) -> dict[str, Injection]:
        return self._of("camera")

    def timings(self) -> dict[str, Injection]:
        return self._of("timing")

    def to_json(self, details: dict | None = None) -> list[dict]:
        """One entry per item: kind, target, values, and the scenario's ``details[(kind,
        target)]`` (what the item affects: frames by stamp, the moved mount, the payload …)."""
        details = details or {}
        return [
            {"kind": i.kind, "target": i.target, "values": dict(i.values), **details.get((i.kind, i.target), {})}
            for i in self.items
        ]


def _number(raw: str, kind: str, key: str, value: str) -> float:
    """``value`` of ``key`` as a float within its bounds; ``ValueError`` naming the key and range."""
    try:
        number = float(value)
    except ValueError:
        raise ValueError(f"inject: {raw!r}: {key}={value.strip()!r} is not a number") from None
    if not math.isfinite(number):
        raise ValueError(f"inject: {raw!r}: {key} must be finite, got {value.strip()}")
    if key == "scale":
        if not -0.5 < number < 0.5:
            raise ValueError(f"inject: {raw!r}: scale must lie in (-0.5, 0.5), got {number:g}")
    elif key == "from_s":
        if not 0.0 <= number <= MAX_FROM_S:
            raise ValueError(f"inject: {raw!r}: from_s must lie in 0..{MAX_FROM_S:g} s, got {number:g}")
    else:
        limit = next(v for suffix, v in _LIMITS.items() if key.endswith(suffix))
        if abs(number) > limit:
            raise ValueError(f"inject: {raw!r}: |{key}| must be ≤ {limit:g}, got {number:g}")
    if kind == "payload" and abs(number / PAYLOAD_STEP_M - round(number / PAYLOAD_STEP_M)) > 1e-6:
        raise ValueError(f"inject: {raw!r}: payload {key} must be a multiple of 0.0001 m (the payload's 0.1 mm), got {number:g}")
    return number


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
        if kind not in KEYS:
            raise ValueError(f"inject: {raw!r}: kind {kind!r} is not one of: {', '.join(KEYS)}")
        allowed = KEYS[kind]
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
            values[key] = _number(raw, kind, key, value)
        if not values:
            raise ValueError(f"inject: {raw!r} names no key=value")
        if set(values) == {"from_s"}:
            raise ValueError(f"inject: {raw!r}: from_s alone moves nothing; give the camera's dx_m … yaw_deg too")
        items.append(Injection(kind, target, values))
    return InjectSpec(tuple(items))


def check_targets(spec: InjectSpec, marker_ids, camera_names, payload_ids=None) -> None:
    """``ValueError`` when an item names a marker or camera the scenario does not have;
    ``payload_ids`` (None: ``marker_ids``) are the markers whose payload carries coordinates
    (empty: the scenario has none, so ``payload`` items are refused)."""
    ids = set(marker_ids)
    payload_ids = ids if payload_ids is None else set(payload_ids)
    for target in spec.markers():
        if target not in ids:
            some = ", ".join(sorted(ids)[:5])
            raise ValueError(f"inject: the scene has no marker {target!r} (ids like {some} …)")
    for target in spec.payloads():
        if not payload_ids:
            raise ValueError("inject: payload needs markers whose payload carries coordinates (qr_floor with marker_family=qr)")
        if target not in payload_ids:
            some = ", ".join(sorted(payload_ids)[:5])
            raise ValueError(f"inject: the scene has no QR code {target!r} (ids like {some} …)")
    for kind, targets in (("camera", spec.cameras()), ("timing", spec.timings())):
        for target in targets:
            if target not in camera_names:
                raise ValueError(f"inject: {kind}: the scenario has no camera {target!r}; its cameras: {', '.join(camera_names)}")


def check_frame_times(spec: InjectSpec, timing_reach_s: float, frame_period_s: float, last_frame_s: float) -> None:
    """``ValueError`` unless every ``timing`` offset keeps a frame's capture between its
    neighbours' stamps (|offset| + ``timing_reach_s``, the realism draw's |latency| + 5σ jitter,
    below half a frame period) and every ``from_s`` affects a frame (≤ ``last_frame_s``, the last
    frame's time after the first)."""
    for name, item in spec.timings().items():
        limit_ms = (frame_period_s / 2.0 - timing_reach_s) * 1e3
        if not abs(item.get("offset_ms")) < limit_ms:
            raise ValueError(
                f"inject: timing:{name}: |offset_ms| must be < {limit_ms:g} ms (half the frame period less the "
                f"realism timing's reach), got {item.get('offset_ms'):g}; lower it or the frame rate"
            )
    for name, item in spec.cameras().items():
        if item.from_s is not None and not item.from_s <= last_frame_s:
            raise ValueError(
                f"inject: camera:{name}: from_s must lie in 0..{last_frame_s:g} s (the last frame's time), got {item.from_s:g}"
            )


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


def _camera_motion(injection: Injection) -> tuple[np.ndarray, np.ndarray]:
    """``(φ rad (3,), d m (3,))`` of a ``camera`` item."""
    g = injection.get
    return np.radians([g("pitch_deg"), g("roll_deg"), g("yaw_deg")]), np.array([g("dx_m"), g("dy_m"), g("dz_m")])


def apply_to_camera(draw, injection: Injection | None):
    """A :class:`agvviz.sim.realism.CameraDraw` whose *recorded* extrinsic is moved so that
    ``R_true = Exp(φ)·R_recorded``, ``t_true = t_recorded + d`` holds for the injected part
    (module docstring); ``delta`` gets an ``injected`` entry. An item with ``from_s`` moves
    the true mount from then on instead (:func:`knocked_mount`): the draw is returned with just
    the ``injected`` entry."""
    if injection is None:
        return draw
    delta = dict(draw.delta)
    delta["injected"] = dict(injection.values)
    if injection.from_s is not None:
        return dataclasses.replace(draw, delta=delta)
    phi, d = _camera_motion(injection)
    T_rec = np.array(draw.T_parent_cam_recorded, dtype=float)
    T_rec[:3, :3] = so3.exp(-phi) @ T_rec[:3, :3]
    T_rec[:3, 3] = T_rec[:3, 3] - d
    return dataclasses.replace(draw, T_parent_cam_recorded=T_rec, delta=delta)


def knocked_mount(T_parent_cam_true: np.ndarray, injection: Injection | None) -> np.ndarray:
    """The true ``T_parent_cam`` after a ``from_s`` item's knock: ``R = Exp(φ)·R_true``,
    ``t = t_true + d``; ``T_parent_cam_true`` itself without such an item."""
    if injection is None or injection.from_s is None:
        return T_parent_cam_true
    phi, d = _camera_motion(injection)
    T = np.array(T_parent_cam_true, dtype=float)
    T[:3, :3] = so3.exp(phi) @ T[:3, :3]
    T[:3, 3] = T[:3, 3] + d
    return T


def knocked(injection: Injection | None, capture_s: float) -> bool:
    """Whether a frame captured ``capture_s`` seconds after the recording's first stamp has the
    knocked mount of ``injection`` (a ``from_s`` item)."""
    return injection is not None and injection.from_s is not None and capture_s >= injection.from_s


def apply_to_timing(timing, injection: Injection | None):
    """A :class:`agvviz.sim.realism.CameraTiming` whose delays (stamp − capture) carry the
    item's ``offset_ms`` on top of the drawn ones."""
    if injection is None:
        return timing
    offset_ns = int(round(injection.get("offset_ms") * 1e6))
    return dataclasses.replace(timing, delay_ns=np.asarray(timing.delay_ns, dtype=np.int64) + offset_ns)


def apply_to_payload(code, injection: Injection | None):
    """A QR :class:`agvviz.sim.render.FloorCode` whose payload text — and so its printed
    modules — carries its feature points moved by the item's (dx, dy, dz); placement, size and
    id unchanged. The code itself without an item."""
    if injection is None:
        return code
    from agvviz.sim.qr_texture import qr_symbol_modules  # cv2: only when a payload is injected

    mapped = parse_payload(code.payload)
    shift = np.array([injection.get("dx_m"), injection.get("dy_m"), injection.get("dz_m")])
    text = encode_payload(QrPayload(mapped.marker_id, mapped.points_world_m + shift))
    return dataclasses.replace(code, payload=text, modules=qr_symbol_modules(text))


def frames_in_view(camera, T_world_cam_per_frame, points_world_m: np.ndarray, stamps_ns) -> list[int]:
    """The stamps of the frames whose camera (the true :class:`PinholeCamera`, at each frame's
    true ``T_world_cam``) sees every one of ``points_world_m`` ((N, 3), or (frames, N, 3) for a
    marker that moves) in front of it and inside the image: the frames an injected marker or
    payload can affect."""
    points = np.asarray(points_world_m, dtype=float)
    out = []
    for k, (T_world_cam, stamp) in enumerate(zip(T_world_cam_per_frame, stamps_ns)):
        p = se3.transform_points(se3.inverse(T_world_cam), points[k] if points.ndim == 3 else points)
        if np.any(p[:, 2] <= 0.0):
            continue
        px = camera.project(p)
        if np.all((px >= -0.5) & (px <= np.array([camera.width_px, camera.height_px]) - 0.5)):
            out.append(int(stamp))
    return out
