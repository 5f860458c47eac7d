"""Export the trajectories of a run ``.rrd`` for other tools (``agvviz export``).

TUM format (what ``evo_ape tum truth.tum estimate.tum`` reads): one pose per line,
``timestamp tx ty tz qx qy qz qw`` — the timestamp in seconds (the frame's recording time,
written exactly from its integer nanoseconds), the position of the AGV body frame in the world
frame in metres and its orientation as a unit quaternion (x, y, z, w) with w ≥ 0, i.e.
``T_world_agv``. Lines starting with ``#`` are comments. The estimate holds the solved frames
only; the truth every frame that has one. Rerun stores poses as float32, so positions carry
≈1 µm of rounding at 10 m.

MCAP format (to open beside the recording in Foxglove): one file ``<run>.poses.mcap`` written
with the ``foxglove-sdk`` package (the ``export`` extra), protobuf-encoded Foxglove schemas
stamped with the frames' recording times (``log_time`` and the message stamp): per trajectory a
``foxglove.PoseInFrame`` topic ``/agvviz/<which>/pose`` (the pose ``T_world_agv`` in frame
``world``) and, on ``/agvviz/tf``, a ``foxglove.FrameTransforms`` with the transform
``world`` → ``<body frame>_<which>`` (e.g. ``agv_estimate``, ``agv_truth``) at each pose, so the
3D panel draws both next to the recording's own frames. A metadata record ``agvviz`` names
the run.

A run without ground truth (most real logs) exports its estimate alone: the truth file is not
written (no ``<run>.truth.tum``, no truth topic in the MCAP) and the result's ``missing`` says
why, for the CLI to print. Only a run with nothing to export at all (no solved frame, or only
the truth asked for and none there) is an :class:`ExportError`.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agvviz.recording import outputs
from agvviz.conventions import WORLD_FRAME
from agvviz.errors import InputError, OutputError
from agvviz.geometry import se3, so3
from agvviz.viz import paths
from agvviz.viz.readback import RrdReadError, document_json, has_rows, read_rrd, split_setting, transforms

FORMATS = ("tum", "mcap")
#: Topics of the MCAP export: PoseInFrame per trajectory (format with ``which``), FrameTransforms.
MCAP_POSE_TOPIC = "/agvviz/{which}/pose"
MCAP_TF_TOPIC = "/agvviz/tf"
#: Which trajectory → the entity holding it.
TRAJECTORIES = {"estimate": paths.AGV_CAMERA, "truth": paths.AGV_TRUTH}


class ExportError(InputError):
    """An export that cannot be done (unknown format, missing trajectory, bad output path)."""


@dataclass(frozen=True)
class ExportedTrajectory:
    which: str  # "estimate" | "truth"
    path: Path
    poses: int


class Exported(list):
    """The :class:`ExportedTrajectory` items written, plus ``missing``: trajectory → why it was
    not written (e.g. the run has no truth)."""

    def __init__(self, items=(), missing: dict[str, str] | None = None):
        super().__init__(items)
        self.missing = dict(missing or {})


def tum_time(time_ns: int) -> str:
    """Seconds with nine decimals, exact (no float rounding of the nanoseconds)."""
    sign = "-" if time_ns < 0 else ""
    seconds, nanos = divmod(abs(int(time_ns)), 1_000_000_000)
    return f"{sign}{seconds}.{nanos:09d}"


def tum_lines(time_ns: np.ndarray, T_world_agv: np.ndarray) -> list[str]:
    """TUM lines of poses (N,) stamps and (N, 4, 4) transforms (rotations re-orthonormalised)."""
    lines = []
    for t, T in zip(time_ns, T_world_agv):
        q = se3.to_quaternion_xyzw(so3.project_to_so3(T[:3, :3]))
        x, y, z = T[:3, 3]
        lines.append(f"{tum_time(int(t))} {x:.9g} {y:.9g} {z:.9g} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}")
    return lines


def export_run(
    run_path: str | os.PathLike,
    fmt: str = "tum",
    out_dir: str | os.PathLike | None = None,
    which: tuple[str, ...] = ("estimate", "truth"),
) -> Exported:
    """Write ``<run stem>.<which>.tum`` for each trajectory in ``which`` (``fmt="tum"``), or one
    ``<run stem>.poses.mcap`` holding them (``fmt="mcap"``); returns what was written, and in
    ``missing`` what was not (the truth of a run without one). Every trajectory is read before
    anything is written.

    Parameters
    ----------
    run_path : path
        A run ``.rrd``, or one setting of a sweep ``.rrd`` (``sweep.rrd#ippe``): then the files
        are named ``<sweep stem>-<label>.*``.
    fmt : str
        One of :data:`FORMATS`.
    out_dir : path, optional
        Default: the run's folder. Created if missing.
    which : tuple of str
        Keys of :data:`TRAJECTORIES`.

    Raises
    ------
    ExportError, RrdReadError
        Unknown format or trajectory, the run cannot be read, or it holds none of the
        trajectories asked for (no frame solved).
    OutputError
        An output would be the run itself (also through a link), or cannot be written; no
        temporary file is left and existing outputs are untouched.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; supported: {', '.join(FORMATS)}")
    unknown = [w for w in which if w not in TRAJECTORIES]
    if unknown or not which:
        raise ExportError(f"unknown trajectory {unknown}; choose from: {', '.join(TRAJECTORIES)}")
    # A setting of a sweep .rrd (FILE#SETTING): its files are named <sweep stem>-<label>.*
    run_file, setting = split_setting(run_path)
    contents = read_rrd(run_path) if setting is not None else None
    stem = run_file.stem if contents is None else f"{run_file.stem}-{contents.setting}"
    shown = run_file.name if contents is None else f"{run_file.name}#{contents.setting}"
    run_path = run_file
    out_dir = Path(out_dir) if out_dir is not None else run_path.parent
    if fmt == "mcap":
        targets = {key: out_dir / f"{stem}.poses.mcap" for key in which}
    else:
        targets = {key: out_dir / f"{stem}.{key}.{fmt}" for key in which}
    for target in dict.fromkeys(targets.values()):  # before any work: never over the run, nor a folder
        outputs.check_not_input(target, (run_path,), option="the export")
        if target.is_dir():
            raise OutputError(f"cannot write {target}: it is an existing folder; remove it or choose another --out-dir")
    contents = contents if contents is not None else read_rrd(run_path)
    manifest = document_json(contents, paths.RUN_MANIFEST) if paths.RUN_MANIFEST in contents.entity_paths else {}
    name = manifest.get("recording_name", run_path.stem)
    trajectories = {}  # which → (stamps ns, T_world_agv), all read before anything is written
    missing = {}
    for key in which:
        entity = TRAJECTORIES[key]
        try:
            present = has_rows(contents, entity, "Transform3D:translation")
        except RrdReadError as exc:
            raise ExportError(f"{run_path}: cannot read the {key} trajectory: {exc}") from exc
        if not present:
            if key == "truth" and len(which) > 1:
                missing[key] = "the run has no ground truth (the recording gave none, or none at the frames' times)"
                if fmt != "mcap" and targets[key].exists():
                    missing[key] += f"; {targets[key]} is from an earlier export and was left as it was"
                continue
            what = "no frame was solved" if key == "estimate" else "the run has no ground truth"
            raise ExportError(f"{run_path} has no {key} trajectory ({entity}): {what}")
        try:
            _, time_ns, T = transforms(contents, entity)
        except RrdReadError as exc:
            raise ExportError(f"{run_path}: cannot read the {key} trajectory: {exc}") from exc
        trajectories[key] = (time_ns, T)
    if not trajectories:
        raise ExportError(f"{run_path} has none of the trajectories asked for ({', '.join(which)})")
    outputs.prepare_dir(out_dir, option="--out-dir")
    if fmt == "mcap":
        data = mcap_bytes(trajectories, body_frame=str(manifest.get("body_frame") or "agv"), run_name=name)
        out_path = outputs.atomic_write_bytes(targets[which[0]], data, inputs=(run_path,))
        return Exported([ExportedTrajectory(key, out_path, len(T)) for key, (_, T) in trajectories.items()], missing)
    written = Exported(missing=missing)
    for key, (time_ns, T) in trajectories.items():
        header = [
            f"# agvviz {key} trajectory of run {name} ({shown}): T_world_agv",
            "# timestamp[s] tx[m] ty[m] tz[m] qx qy qz qw",
        ]
        out_path = targets[key]
        outputs.atomic_write_text(out_path, "\n".join(header + tum_lines(time_ns, T)) + "\n", inputs=(run_path,))
        written.append(ExportedTrajectory(key, out_path, len(T)))
    return written


def mcap_bytes(trajectories: dict[str, tuple[np.ndarray, np.ndarray]], *, body_frame: str, run_name: str) -> bytes:
    """An MCAP file (its bytes) of ``trajectories`` (which → ((N,) stamps in ns, (N, 4, 4)
    ``T_world_agv``)) as Foxglove ``PoseInFrame`` and ``FrameTransforms`` messages in time order
    (see the module docstring). Needs the ``foxglove-sdk`` package: :class:`ExportError` naming
    the extra to install when it is missing."""
    try:
        import foxglove
        from foxglove.channels import FrameTransformsChannel, PoseInFrameChannel
        from foxglove.messages import FrameTransform, FrameTransforms, Pose, PoseInFrame, Quaternion, Timestamp, Vector3
    except ImportError:
        raise ExportError("--format mcap needs the foxglove-sdk package: pip install 'agvviz[export]'") from None
    messages = []  # (time ns, trajectory order, channel key, message)
    for order, (key, (time_ns, T_world_agv)) in enumerate(trajectories.items()):
        for t, T in zip(time_ns, T_world_agv):
            t = int(t)
            if t < 0:
                raise ExportError(f"the {key} trajectory has a negative time stamp ({t} ns); MCAP times are ≥ 0")
            q = se3.to_quaternion_xyzw(so3.project_to_so3(T[:3, :3]))
            x, y, z = (float(v) for v in T[:3, 3])
            stamp = Timestamp(t // 1_000_000_000, t % 1_000_000_000)
            orientation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
            messages.append((t, order, key, PoseInFrame(
                timestamp=stamp, frame_id=WORLD_FRAME, pose=Pose(position=Vector3(x=x, y=y, z=z), orientation=orientation),
            )))
            messages.append((t, order, "tf", FrameTransforms(transforms=[FrameTransform(
                timestamp=stamp, parent_frame_id=WORLD_FRAME, child_frame_id=f"{body_frame}_{key}",
                translation=Vector3(x=x, y=y, z=z), rotation=orientation,
            )])))
    messages.sort(key=lambda m: (m[0], m[1]))
    context = foxglove.Context()  # not the SDK's global one: only these channels go to this file
    buffer = io.BytesIO()
    writer = foxglove.open_mcap(buffer, context=context)
    try:
        channels = {key: PoseInFrameChannel(MCAP_POSE_TOPIC.format(which=key), context=context) for key in trajectories}
        channels["tf"] = FrameTransformsChannel(MCAP_TF_TOPIC, context=context)
        for t, _, key, message in messages:
            channels[key].log(message, log_time=t)
        writer.write_metadata("agvviz", {
            "run": run_name, "pose": "T_world_agv (metres, quaternion x y z w)", "trajectories": ",".join(trajectories),
        })
    finally:
        writer.close()
    return buffer.getvalue()
