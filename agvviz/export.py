"""Export the trajectories of a run ``.rrd`` for other tools (``agvviz export``).

TUM format (what ``evo_ape tum truth.tum estimate.tum`` reads): one pose per line,
``timestamp tx ty tz qx qy qz qw`` — the timestamp in seconds (the frame's recording time,
written exactly from its integer nanoseconds), the position of the AGV body frame in the world
frame in metres and its orientation as a unit quaternion (x, y, z, w) with w ≥ 0, i.e.
``T_world_agv``. Lines starting with ``#`` are comments. The estimate holds the solved frames
only; the truth every frame that has one. Rerun stores poses as float32, so positions carry
≈1 µm of rounding at 10 m.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agvviz import outputs
from agvviz.errors import InputError
from agvviz.geometry import se3, so3
from agvviz.viz import paths
from agvviz.viz.readback import RrdReadError, document_json, read_rrd, transforms

FORMATS = ("tum",)
#: Which trajectory → the entity holding it.
TRAJECTORIES = {"estimate": paths.AGV_CAMERA, "truth": paths.AGV_TRUTH}


class ExportError(InputError):
    """An export that cannot be done (unknown format, missing trajectory, bad output path)."""


@dataclass(frozen=True)
class ExportedTrajectory:
    which: str  # "estimate" | "truth"
    path: Path
    poses: int


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
) -> list[ExportedTrajectory]:
    """Write ``<run stem>.<which>.tum`` for each trajectory in ``which``; returns what was written.

    Parameters
    ----------
    run_path : path
        A run ``.rrd``.
    fmt : str
        One of :data:`FORMATS`.
    out_dir : path, optional
        Default: the run's folder. Created if missing.
    which : tuple of str
        Keys of :data:`TRAJECTORIES`.

    Raises
    ------
    ExportError, RrdReadError
        Unknown format or trajectory, or the run cannot be read.
    OutputError
        An output would be the run itself (also through a link), or cannot be written; no
        temporary file is left and existing outputs are untouched.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; supported: {', '.join(FORMATS)}")
    unknown = [w for w in which if w not in TRAJECTORIES]
    if unknown or not which:
        raise ExportError(f"unknown trajectory {unknown}; choose from: {', '.join(TRAJECTORIES)}")
    run_path = Path(run_path)
    out_dir = Path(out_dir) if out_dir is not None else run_path.parent
    targets = {key: out_dir / f"{run_path.stem}.{key}.{fmt}" for key in which}
    for target in targets.values():  # before any work: never over the run itself
        outputs.check_not_input(target, (run_path,), option="the export")
    contents = read_rrd(run_path)
    outputs.prepare_dir(out_dir, option="--out-dir")
    name = document_json(contents, paths.RUN_MANIFEST).get("recording_name", run_path.stem) \
        if paths.RUN_MANIFEST in contents.entity_paths else run_path.stem
    written = []
    for key in which:
        entity = TRAJECTORIES[key]
        if entity not in contents.entity_paths:
            raise ExportError(f"{run_path} has no {key} trajectory ({entity}): nothing was solved or no truth")
        try:
            _, time_ns, T = transforms(contents, entity)
        except RrdReadError as exc:
            raise ExportError(f"{run_path}: cannot read the {key} trajectory: {exc}") from exc
        header = [
            f"# agvviz {key} trajectory of run {name} ({run_path.name}): T_world_agv",
            "# timestamp[s] tx[m] ty[m] tz[m] qx qy qz qw",
        ]
        out_path = targets[key]
        outputs.atomic_write_text(out_path, "\n".join(header + tum_lines(time_ns, T)) + "\n", inputs=(run_path,))
        written.append(ExportedTrajectory(key, out_path, len(T)))
    return written
