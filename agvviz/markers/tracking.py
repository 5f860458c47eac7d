"""Follow decoded QR codes from frame to frame instead of searching every frame ("track,
don't search"). numpy/OpenCV only: no I/O, no Rerun, no printing.

Full detection (:func:`agvviz.markers.qr.detect_qr_codes`) finds and decodes every code with
zxing-cpp, picks each code's template (its module grid) and aligns it by ECC from zxing's
integer corners. Once a code is known, a :class:`CodeTracker` skips the search and the template
choice: it predicts the code's corners in the next frame and aligns the same template by ECC
directly from the prediction, with the same ECC (:func:`agvviz.markers.ecc.align_symbol_ecc`,
the same convergence criterion and correlation threshold), so a tracked code's corners are full
detection's ECC optimum to within ECC's stopping tolerance (a few thousandths of a pixel on
``qr_floor``). From a good prediction ECC needs fewer iterations (≈3 against ≈5 from zxing's
corners on ``qr_floor``).

Predictions, per code, tried in this order until one passes every check below:

1. the caller's predicted corners for its payload (``motion_hint`` as a mapping,
   :meth:`CodeTracker.detect`);
2. the code's own motion: the homography that took its corners from the frame before the last
   to the last frame, applied once more (a constant frame-to-frame homography: exact for a
   plane moving at constant velocity and turn rate; on ``qr_floor`` it predicts the corners to
   ≈0.01 module, median, except in the two frames after the AGV enters or leaves a turn);
   for a code seen in one frame only (new at the last keyframe), the least-squares homography
   of every code that has its own motion (all codes on one plane — a floor — share it);
3. the caller's homography (``motion_hint`` as a 3×3 array, e.g. the floor's motion from
   odometry): the only prediction of a code without a motion of its own (the frame after a
   tracker's first, a code new at the last keyframe), and the second chance of one whose own
   motion failed (a turn begins or ends). Odometry is noisier than a code's own motion
   (≈1.2 px median on ``qr_floor``, against ≈0.02 px), so it does not come first, and a wrong
   odometry costs no more than having none.

A code without any prediction (the first frames of a tracker, without a hint) is not tracked:
that frame is a keyframe.

A code whose predicted corners are not all inside the image is leaving the view: its track
ends without a keyframe (a cut symbol does not decode, so full detection would not report it
either; the ECC template's light border may leave the image earlier — ECC masks what lies
outside). Checks on every other tracked code — any failure makes the frame a keyframe (full
detection) and ``fallback_reason`` names the code and the check:

* the prediction and the result are convex and the result lies inside the image;
* ECC converges with correlation ≥ :data:`~agvviz.markers.ecc.ECC_MIN_CORRELATION`;
* no corner moves more than :data:`~agvviz.markers.ecc.MAX_REFINE_SHIFT_MODULES` module from the
  prediction (ECC is not trusted beyond its convergence basin: a whole-module slip of the
  template would otherwise go unnoticed);
* it is still the same code (:func:`~agvviz.markers.qr.module_agreement` at the new corners):
  the image at the module centres correlates with the template at
  ≥ :data:`~agvviz.markers.qr.TEMPLATE_GOOD_CORRELATION`, and at most
  :data:`TRACK_MAX_MODULE_MISMATCH` of the modules read the other way. The correlation alone
  does not tell payloads apart: neighbouring ``qr_floor`` codes (Q014, Q015: same version and
  mask) differ in only 9 % of their modules, and a symbol differing in 9 % (payload Q014 →
  Z999) still correlates at 0.81.

Keyframes: the first frame; every ``keyframe_every``-th frame since the last keyframe; a frame
with nothing to track (none found, or every code left the view: tracking would return nothing,
and new codes should be found at once); a frame after a keyframe that found a code which cannot
be tracked (undecoded, or its ECC refinement fell back); a frame without a prediction; a frame
where a check fails. With ``refine`` other than ``"ecc"`` every frame is a keyframe (tracking
aligns by ECC).

The cost of tracking: a code that *enters* the view while others are tracked is found at the
next keyframe, at most ``keyframe_every - 1`` frames later (a frame without tracked codes is a
keyframe, so an empty view finds new codes at once).

State is small (per code: the last detection, its template and the corners one frame earlier)
and picklable; a tracker is cheap to create, one per camera and per contiguous run of frames.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import cv2
import numpy as np

from agvviz.errors import InputError
from agvviz.markers.ecc import MAX_REFINE_SHIFT_MODULES, align_symbol_ecc, ecc_crop_box, mean_side_px
from agvviz.markers.qr import (
    REFINE_METHODS,
    TEMPLATE_GOOD_CORRELATION,
    QrDetection,
    _is_convex,
    check_gray,
    detect_qr_codes,
    module_agreement,
)

#: ``refine_note`` of a tracked detection.
TRACKED_NOTE = "tracked"
#: Largest share of modules a tracked code may read differently from its template. Measured at
#: ECC-refined corners: 0 on every code of qr_floor (module ≥ 4.7 px), at most one module on
#: 19 of zxing's 20 real photos and 2.0 % on the last (3.6 px modules, uneven lighting); two
#: different codes of the qr_floor scene differ in ≥ 6.8 % of their modules.
TRACK_MAX_MODULE_MISMATCH = 0.03

#: A predicted-corners hint: corners (4, 2) TL, TR, BR, BL per payload (``QrDetection.text``,
#: or ``payload_bytes`` for a payload that is not UTF-8).
CornersHint = Mapping[str | bytes, np.ndarray]


@dataclass(frozen=True)
class TrackOutcome:
    """What :meth:`CodeTracker.detect` found in one frame.

    Attributes
    ----------
    detections : list of QrDetection
        As :func:`~agvviz.markers.qr.detect_qr_codes` returns them. Tracked ones carry the
        track's ``text``, ``payload_bytes``, ``n_modules`` and ``symbol``;
        ``raw_corners_px`` is the prediction, ``refine_method`` ``"ecc"`` and ``refine_note``
        :data:`TRACKED_NOTE`.
    keyframe : bool
        Full detection was run on this frame.
    tracked : int
        Codes tracked (0 on a keyframe).
    fallback_reason : str
        Why this frame could not be tracked ("" when it was tracked, or was a keyframe by
        schedule: first frame, every K-th, nothing to track, ``refine`` not ``"ecc"``).
    """

    detections: list[QrDetection]
    keyframe: bool
    tracked: int
    fallback_reason: str = ""


@dataclass(frozen=True)
class _Track:
    """One code being followed: its last detection and its corners one frame step earlier."""

    detection: QrDetection
    previous_corners_px: np.ndarray | None


class CodeTracker:
    """Follows the QR codes of one camera over consecutive frames (module docstring).

    Parameters
    ----------
    refine : {"ecc", "subpix", "none"}
        Corner refinement of full detection; tracking needs ``"ecc"`` (any other value makes
        every frame a keyframe).
    keyframe_every : int ≥ 1
        Full detection at least every this many frames (1: every frame, exactly
        :func:`~agvviz.markers.qr.detect_qr_codes`).

    Raises
    ------
    InputError
        ``refine`` unknown or ``keyframe_every`` not a positive integer.
    """

    def __init__(self, refine: str = "ecc", keyframe_every: int = 10):
        if refine not in REFINE_METHODS:
            raise InputError(f"refine must be one of {REFINE_METHODS}, got {refine!r}")
        if isinstance(keyframe_every, bool) or not isinstance(keyframe_every, (int, np.integer)) or keyframe_every < 1:
            raise InputError(f"keyframe_every must be an integer ≥ 1, got {keyframe_every!r}")
        self.refine = refine
        self.keyframe_every = int(keyframe_every)
        self._tracks: list[_Track] = []
        self._untrackable: str = ""  # why a code of the last frame cannot be tracked
        self._frame_shape: tuple[int, int] | None = None
        self._last_index: int | None = None
        self._step: int | None = None  # frames between the last two observations
        self._last_keyframe_index: int | None = None

    def detect(
        self,
        gray: np.ndarray,
        frame_index: int,
        motion_hint: np.ndarray | CornersHint | None = None,
        full_image: Callable[[], np.ndarray] | None = None,
    ) -> TrackOutcome:
        """The codes in frame ``frame_index``, tracked when possible, else fully detected.

        Parameters
        ----------
        gray : np.ndarray, shape (H, W), uint8
            Undistorted grayscale frame.
        frame_index : int
            Position of the frame in the camera's sequence; strictly increasing from call to
            call. A gap (a skipped frame) is allowed: image-space prediction then needs the
            same gap between the last two observations, else the frame is a keyframe.
        motion_hint : None, np.ndarray (3, 3) or mapping
            Optional prediction supplied by the caller (e.g. from odometry and the last pose):
            a homography ``H_frame_previous`` taking pixels of the previous frame given to
            this tracker to this frame's (valid for codes on one plane, e.g. the floor), or
            a mapping from payload (``QrDetection.text``, or ``payload_bytes``) to predicted
            corners (4, 2) TL, TR, BR, BL in this frame. Codes it does not cover (and codes
            whose payload is tracked twice) are predicted from their image motion. A hint
            only predicts: the checks are the same, and it finds no new code.
        full_image : callable, optional
            When given, ``gray`` need hold only the :meth:`regions` of this frame (the rest
            may be anything), and ``full_image()`` returns the whole frame for a keyframe's
            full detection.

        Raises
        ------
        InputError
            ``frame_index`` does not increase, or ``motion_hint`` has the wrong form.
        ValueError
            ``gray`` is not a 2-D uint8 image (as :func:`~agvviz.markers.qr.detect_qr_codes`).
        """
        check_gray(gray)
        frame_index = int(frame_index)
        if self._last_index is not None and frame_index <= self._last_index:
            raise InputError(
                f"frames must be given in order: frame {frame_index} after frame {self._last_index}"
            )
        hint_H, hint_corners = _parse_hint(motion_hint)
        reason = self._why_not_track(gray.shape, frame_index)
        tracked = None
        if reason is None:
            tracked, reason = self._track_all(gray, frame_index, hint_H, hint_corners)
        if tracked:  # not None (a check failed) nor empty (every code left the view)
            self._advance(tracked, frame_index)
            return TrackOutcome(detections=[t.detection for t in tracked], keyframe=False, tracked=len(tracked))
        if full_image is not None:
            gray = full_image()
            check_gray(gray)
        detections = detect_qr_codes(gray, refine=self.refine)
        self._restart(detections, gray.shape, frame_index)
        return TrackOutcome(detections=detections, keyframe=True, tracked=0, fallback_reason=reason)

    def regions(
        self, shape: tuple[int, int], frame_index: int, motion_hint: np.ndarray | CornersHint | None = None
    ) -> list[tuple[int, int, int, int]] | None:
        """The parts of frame ``frame_index`` (an image of ``shape``, (H, W)) that
        :meth:`detect` reads when it tracks the frame, as boxes ``(x0, y0, x1, y1)``
        (``gray[y0:y1, x0:x1]``): for each code, the crop ECC aligns it in from each of its
        predictions (:func:`~agvviz.markers.ecc.ecc_crop_box`; the module check reads only
        inside the corners, which ECC may move by at most one module). None when the frame
        is a keyframe by schedule or has a code without a prediction: :meth:`detect` then
        reads the whole frame. The same arguments as :meth:`detect`, which must follow."""
        frame_index = int(frame_index)
        if self._last_index is not None and frame_index <= self._last_index:
            return None  # detect() refuses it
        hint_H, hint_corners = _parse_hint(motion_hint)
        if self._why_not_track(tuple(shape), frame_index) is not None:
            return None
        boxes = []
        for track, predictions in self._predictions(frame_index, hint_H, hint_corners):
            if not predictions:
                return None
            n = len(track.detection.symbol)
            for predicted in predictions:
                if np.all(np.isfinite(predicted)) and _is_convex(predicted):
                    boxes.append(ecc_crop_box(predicted, n, shape))
        return boxes

    # -- keyframe policy ------------------------------------------------------------------------
    def _why_not_track(self, shape: tuple[int, int], frame_index: int) -> str | None:
        """None when this frame may be tracked; else the fallback reason ("" for a keyframe by
        schedule)."""
        if self.refine != "ecc" or self._last_keyframe_index is None:
            return ""
        if frame_index - self._last_keyframe_index >= self.keyframe_every:
            return ""
        if shape != self._frame_shape:
            return f"frame size changed from {self._frame_shape} to {shape}"
        if self._untrackable:
            return self._untrackable
        if not self._tracks:
            return ""
        return None

    # -- tracking -------------------------------------------------------------------------------
    def _track_all(
        self, gray: np.ndarray, frame_index: int, hint_H: np.ndarray | None, hint_corners: dict
    ) -> tuple[list[_Track] | None, str]:
        """Every code tracked into this frame, or (None, why not)."""
        tracked = []
        for track, predictions in self._predictions(frame_index, hint_H, hint_corners):
            detection = track.detection
            if not predictions:
                return None, f"no motion known yet for {_label(detection)} (seen in one frame only)"
            corners_px, predicted, problem = _first_alignment(gray, detection, predictions)
            if problem:
                return None, problem
            if corners_px is None:
                continue  # leaving the view: its track ends (full detection would not decode it either)
            tracked.append(
                _Track(
                    detection=replace(
                        detection, corners_px=corners_px, raw_corners_px=predicted, refine_method="ecc",
                        refine_ok=True, refine_note=TRACKED_NOTE,
                    ),
                    previous_corners_px=detection.corners_px,
                )
            )
        return tracked, ""

    def _predictions(
        self, frame_index: int, hint_H: np.ndarray | None, hint_corners: dict
    ) -> list[tuple[_Track, list[np.ndarray]]]:
        """Each track with its predicted corners in frame ``frame_index``, in order of
        preference (module docstring); an empty list when there is none."""
        gap = frame_index - self._last_index
        has_motion = self._step is not None and gap == self._step
        H_common = self._common_step_homography() if has_motion else None
        counts = Counter(_payload_key(t.detection) for t in self._tracks)
        out = []
        for track in self._tracks:
            detection = track.detection
            key = _payload_key(detection)
            predictions = []
            if key in hint_corners and counts[key] == 1:
                predictions.append(hint_corners[key])
            if has_motion and track.previous_corners_px is not None:
                predictions.append(_apply(_step_homography(track.previous_corners_px, detection.corners_px), detection.corners_px))
            elif H_common is not None:
                predictions.append(_apply(H_common, detection.corners_px))
            if hint_H is not None:
                predictions.append(_apply(hint_H, detection.corners_px))
            out.append((track, predictions))
        return out

    def _common_step_homography(self) -> np.ndarray | None:
        """Least-squares frame-to-frame homography of every code with its own motion (codes
        on one plane share it), None when no code has any."""
        pairs = [(t.previous_corners_px, t.detection.corners_px) for t in self._tracks if t.previous_corners_px is not None]
        if not pairs:
            return None
        previous = np.concatenate([p for p, _ in pairs]).astype(np.float64)
        last = np.concatenate([c for _, c in pairs]).astype(np.float64)
        try:
            H, _ = cv2.findHomography(previous, last, 0)
        except cv2.error:
            return None
        return H if H is not None and np.all(np.isfinite(H)) else None

    # -- state ----------------------------------------------------------------------------------
    def _advance(self, tracked: list[_Track], frame_index: int) -> None:
        self._tracks = tracked
        self._step = frame_index - self._last_index
        self._last_index = frame_index

    def _restart(self, detections: list[QrDetection], shape: tuple[int, int], frame_index: int) -> None:
        """New tracks from a keyframe's detections; a code also seen in the previous frame
        keeps its motion (matched by payload, when the payload is unique in both frames)."""
        previous = {}
        if self._last_index is not None and shape == self._frame_shape:
            previous = _unique_by_payload([t.detection for t in self._tracks])
        counts = Counter(_payload_key(d) for d in detections)
        self._tracks, self._untrackable = [], ""
        for detection in detections:
            problem = _untrackable(detection)
            if problem:
                self._untrackable = self._untrackable or problem
                continue
            key = _payload_key(detection)
            before = previous.get(key) if counts[key] == 1 else None
            self._tracks.append(_Track(detection, before.corners_px if before is not None else None))
        self._step = frame_index - self._last_index if self._last_index is not None else None
        self._frame_shape = shape
        self._last_index = frame_index
        self._last_keyframe_index = frame_index


def _first_alignment(
    gray: np.ndarray, detection: QrDetection, predictions: list[np.ndarray]
) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """``(corners, prediction, "")`` of the first prediction ECC aligns with every check
    passed; ``(None, None, "")`` when the first usable prediction leaves the image (the code is
    leaving the view); else ``(None, None, why the first failed)``."""
    problem = ""
    for predicted in predictions:
        if not (np.all(np.isfinite(predicted)) and _is_convex(predicted)):
            problem = problem or f"{_label(detection)}: prediction is not a convex quadrilateral"
            continue
        if not _inside(predicted, gray.shape):
            if not problem:
                return None, None, ""
            continue
        corners_px, why = _align(gray, detection.symbol, predicted)
        if corners_px is not None:
            return corners_px, predicted, ""
        problem = problem or f"{_label(detection)}: {why}"
    return None, None, problem


def _align(gray: np.ndarray, symbol: np.ndarray, predicted_px: np.ndarray) -> tuple[np.ndarray | None, str]:
    """ECC-aligned corners of ``symbol`` from ``predicted_px`` with every check passed, or
    (None, the failed check)."""
    n = len(symbol)
    corners_px, note = align_symbol_ecc(gray, symbol, predicted_px)
    if corners_px is None:
        return None, f"ECC {note}"
    if not _is_convex(corners_px):
        return None, "ECC corners not convex"
    if not _inside(corners_px, gray.shape):
        return None, "ECC corners outside the image"
    module_px = mean_side_px(corners_px) / n
    shift_px = float(np.max(np.linalg.norm(corners_px - predicted_px, axis=1)))
    if shift_px > MAX_REFINE_SHIFT_MODULES * module_px:
        return None, f"ECC moved a corner {shift_px / module_px:.2f} modules from the prediction > {MAX_REFINE_SHIFT_MODULES}"
    correlation, mismatch = module_agreement(gray, symbol, corners_px)
    if correlation < TEMPLATE_GOOD_CORRELATION:
        return None, f"module correlation {correlation:.2f} < {TEMPLATE_GOOD_CORRELATION} (not the same code)"
    if mismatch > TRACK_MAX_MODULE_MISMATCH:
        return None, f"{mismatch:.1%} of the modules read differently > {TRACK_MAX_MODULE_MISMATCH:.0%} (not the same code)"
    return corners_px, ""


def _inside(corners_px: np.ndarray, shape: tuple[int, int]) -> bool:
    """Every corner of the (convex) symbol lies inside the image, so every module centre
    :func:`~agvviz.markers.qr.module_agreement` samples does (half a module inside)."""
    height, width = shape
    return bool(
        np.all(corners_px >= 0.0) and np.all(corners_px[:, 0] <= width - 1.0) and np.all(corners_px[:, 1] <= height - 1.0)
    )


def _step_homography(from_px: np.ndarray, to_px: np.ndarray) -> np.ndarray:
    """The homography taking the 4 points ``from_px`` to ``to_px``."""
    return cv2.getPerspectiveTransform(from_px.astype(np.float32), to_px.astype(np.float32))


def _apply(H: np.ndarray, points_px: np.ndarray) -> np.ndarray:
    return cv2.perspectiveTransform(np.asarray(points_px, dtype=np.float64).reshape(1, -1, 2), np.asarray(H, dtype=np.float64)).reshape(-1, 2)


def _parse_hint(motion_hint) -> tuple[np.ndarray | None, dict]:
    """(homography or None, corners per payload)."""
    if motion_hint is None:
        return None, {}
    if isinstance(motion_hint, np.ndarray):
        if motion_hint.shape != (3, 3) or not np.all(np.isfinite(motion_hint)):
            raise InputError(f"motion_hint homography must be a finite 3×3 array, got shape {motion_hint.shape}")
        return motion_hint.astype(np.float64), {}
    if isinstance(motion_hint, Mapping):
        corners = {}
        for key, value in motion_hint.items():
            value = np.asarray(value, dtype=np.float64)
            if value.shape != (4, 2) or not np.all(np.isfinite(value)):
                raise InputError(f"motion_hint corners of {key!r} must be a finite (4, 2) array, got shape {value.shape}")
            corners[key] = value
        return None, corners
    raise InputError(
        f"motion_hint must be None, a 3×3 homography or a mapping payload → (4, 2) corners, got {type(motion_hint).__name__}"
    )


def _payload_key(detection: QrDetection) -> str | bytes | None:
    return detection.text if detection.text is not None else detection.payload_bytes


def _unique_by_payload(detections: list[QrDetection]) -> dict:
    counts = Counter(_payload_key(d) for d in detections)
    return {_payload_key(d): d for d in detections if counts[_payload_key(d)] == 1}


def _untrackable(detection: QrDetection) -> str:
    """Why ``detection`` cannot be tracked, "" when it can."""
    if _payload_key(detection) is None:
        return "an undecoded code cannot be tracked"
    if detection.refine_method != "ecc" or detection.symbol is None:
        return f"{_label(detection)} was not ECC-refined at the last detection ({detection.refine_note or detection.refine_method})"
    return ""


def _label(detection: QrDetection) -> str:
    """A short name of a code for messages: the start of its payload."""
    key = _payload_key(detection)
    text = key if isinstance(key, str) else repr(key)
    return repr(text if len(text) <= 24 else text[:23] + "…")
