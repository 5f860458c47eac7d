"""agvviz command line: parse, build a frozen settings object, call one library function.

Every command prints where its output went. Errors are handled in one place
(:func:`handle_errors`, on every command): an :class:`~agvviz.errors.AgvvizError`, an
``OSError`` from writing, ``MemoryError`` or an interrupt becomes one line ``error: <message>``
on stderr and the exit code of its kind (:mod:`agvviz.errors`: 2 bad input, 3 output not
written, 130 interrupted). The console script is :func:`agvviz.__main__.main`, which installs the
signal handlers before this module is imported.
"""

from __future__ import annotations

import errno
import functools
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from agvviz import __version__
from agvviz.recording import outputs
from agvviz.errors import EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_OUTPUT, AgvvizError, InputError
from agvviz.settings import RunSettings, apply_overrides, describe


class _Command(typer.core.TyperCommand):
    """A command whose ``--help`` lists on/off options as flags: typer's help would print a
    value type (``--cache/--no-cache <bool>``, ``--help <bool>``) as if they took a value."""

    def format_help(self, ctx, formatter):
        _flags_without_type(self, ctx)
        return super().format_help(ctx, formatter)


class _Group(typer.core.TyperGroup):
    """The ``agvviz`` group, its ``--help`` flag shown without a value type (see :class:`_Command`)."""

    def format_help(self, ctx, formatter):
        _flags_without_type(self, ctx)
        return super().format_help(ctx, formatter)


def _flags_without_type(command, ctx) -> None:
    for param in command.get_params(ctx):
        if getattr(param, "is_flag", False) and param.metavar is None:
            param.metavar = ""  # typer shows an option's metavar in place of its type


app = typer.Typer(
    cls=_Group,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    help="agvviz — record, replay and inspect fiducial-marker localisation in Rerun.\n\n"
    "Quick start:  agvviz demo   (records qr_floor, runs the lm solver, writes an .rrd).\n\n"
    "Exit codes: 0 ok, 1 a condition held (diff --fail-if) or a contract was violated (inspect), "
    "2 bad input, 3 output could not be written, 130 interrupted.",
)
console = Console()
err_console = Console(stderr=True, soft_wrap=True)

SET_HELP = "key=value (repeatable); see `agvviz scenarios` / `agvviz run --help` for keys"

#: errno values of an ``OSError`` that mean "could not write" (exit 3) rather than bad input.
WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG}


def error_line(message: str) -> None:
    """Print ``error: <message>`` as one line on stderr (no markup is interpreted)."""
    text = " ".join(str(message).split()) or "unknown error"
    err_console.print(Text.assemble(("error:", "bold red"), " ", text), soft_wrap=True, highlight=False)


def exit_for(exc: BaseException) -> tuple[int, str]:
    """The exit code and the one-line message for an exception reaching the CLI."""
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_INTERRUPTED, "interrupted; unfinished outputs were removed"
    if isinstance(exc, AgvvizError):
        return exc.exit_code, str(exc)
    if isinstance(exc, MemoryError):
        return EXIT_BAD_INPUT, "out of memory; try a shorter recording, fewer settings or --no-images"
    if isinstance(exc, OSError):
        target = exc.filename or "a file"
        if exc.errno in WRITE_ERRNOS:
            return EXIT_OUTPUT, str(outputs.output_error(exc, target))
        return EXIT_BAD_INPUT, f"cannot use {target}: {exc.strerror or exc}"
    raise TypeError(f"not an error the CLI reports: {type(exc).__name__}")


def handle_errors(command):
    """Decorator of every command: the one place that turns errors into a line and a code."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except BrokenPipeError:  # stdout closed by the reader (`agvviz diff … | head`): typer's to handle
            raise
        except (AgvvizError, OSError, MemoryError, KeyboardInterrupt) as exc:
            if isinstance(exc, KeyboardInterrupt):
                outputs.remove_live_temps()
            code, message = exit_for(exc)
            error_line(message)
            raise typer.Exit(code=code) from None

    return wrapper


def _fail(message: str) -> None:
    raise InputError(message)


def _progress() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeRemainingColumn(),
        console=err_console,
        transient=False,
    )


# -- scenarios / record -------------------------------------------------------------------
@app.command(cls=_Command)
@handle_errors
def scenarios() -> None:
    """List every scenario with its options and defaults."""
    from agvviz import scenarios as scenario_registry

    for name, module in scenario_registry.available().items():
        table = Table(title=f"{name} — {module.DESCRIPTION}", title_justify="left")
        for col in ("option", "type", "default", "help"):
            table.add_column(col)
        for row in describe(module.Options):
            table.add_row(*row)
        console.print(table)
    console.print("Record one with: agvviz record qr_floor --seed 1 --set duration_s=10")


def _record(scenario: str, seed: int, sets: list[str], out: Path) -> Path:
    from agvviz import scenarios as scenario_registry

    scenario_registry.build_options(scenario, sets)  # validate before any work
    with _progress() as progress:
        task = progress.add_task(f"recording {scenario}", total=None, rate="")

        def on_frame(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        scenario_registry.record(scenario, out, seed=seed, overrides=sets, progress=on_frame)
    console.print(f"recording written: [bold]{out}[/]")
    return out


@app.command(cls=_Command)
@handle_errors
def record(
    scenario: str = typer.Argument("qr_floor", metavar="SCENARIO", help="scenario name (see `agvviz scenarios`)"),
    seed: int = typer.Option(0, "--seed", help="fixes all randomness; same seed ⇒ same recording"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help=SET_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help="output .mcap (default: recordings/<scenario>.mcap)"),
) -> None:
    """Simulate SCENARIO and write an MCAP recording.

    Example: agvviz record qr_floor --seed 1 --set duration_s=10 --set speed_mps=1.5
    """
    out = out or Path("recordings") / f"{scenario}.mcap"
    if out.suffix != ".mcap":
        _fail(f"--out must end in .mcap, got {out}")
    _record(scenario, seed, set_, out)


# -- run ------------------------------------------------------------------------------------
def _run_help() -> str:
    rows = "\n".join(f"  {n} ({t}, default {d}): {h}" for n, t, d, h in describe(RunSettings))
    return (
        "Replay the localisation pipeline over RECORDING (an agvviz .mcap, a ROS 2 bag directory "
        "or .mcap, a ROS 1 .bag, a Foxglove MCAP) and write a run .rrd. Exits 2, writing nothing, when no frame "
        "can be used (one line per cause).\n\n"
        "Example: agvviz run recordings/qr_floor.mcap --solver lm --set objective=pixel\n\n"
        "Example: agvviz run robot_bag/ --topic truth=/vicon/agv/pose --markers map.yaml "
        "--set body_frame=base_link\n\n"
        "Settings (--set key=value). One that cannot act on the recording (fusion and uwb settings "
        "without UWB ranges, correction without odometry, camera_select with one camera) or under the "
        "other settings (kalman_gate_chi2, camera_sigma_m without fusion=kalman) is ignored with a "
        "warning and left out of the run name:\n\n" + rows.replace("\n", "\n\n")
    )


def _print_summary(summary: dict, timing: dict, title: str) -> None:
    from agvviz.evaluation.summary_table import summary_rows

    table = Table(title=title, title_justify="left")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for metric, value in summary_rows(summary, timing):
        table.add_row(metric, value)
    console.print(table)
    for problem in summary.get("recording_damage", []):
        err_console.print(f"[yellow]recording damage:[/] {escape(problem)}")
    for warning in summary.get("warnings", []):
        err_console.print(f"[yellow]warning:[/] {escape(warning)}")


TOPIC_HELP = (
    "ROLE=TOPIC (repeatable): which topic plays which role, over the inferred role map "
    "(`agvviz inspect` prints it); e.g. --topic truth=/vicon/agv/pose --topic "
    "front.image=/camera/image_raw/compressed. Roles: <cam>.image, <cam>.calibration, truth, "
    "odometry, markers, tf_static, tf, uwb.range, uwb.anchors, corners"
)
ROLES_HELP = "a roles file (YAML role: topic, written by `agvviz inspect --write-roles FILE`); only its roles are used"
MARKERS_HELP = "marker map side file (agvviz.MarkerMap JSON/YAML); overrides the recording's map"
CALIBRATION_HELP = "CAM=FILE (repeatable): camera calibration side file; overrides the recording's calibration of CAM"
EXTRINSIC_HELP = (
    "CAM=x,y,z,qx,qy,qz,qw (repeatable): the camera's pose in the body frame (T_body_cam, metres, "
    "quaternion x y z w; camera frame OpenCV/ROS optical); overrides the recording's transforms"
)


def _side_inputs(markers: Optional[Path], calibration: list[str], extrinsic: list[str], body_frame: str):
    """Side-file values (agvviz.recording.sidefiles) for the replay; InputError on bad input."""
    from agvviz.errors import InputError
    from agvviz.recording import sidefiles
    from agvviz.replay.run import SideInputs

    side = SideInputs()
    if markers is not None:
        side.marker_map = sidefiles.load_marker_map(markers)
    for pair, what in [(p, "calibration") for p in calibration] + [(p, "extrinsic") for p in extrinsic]:
        cam, sep, value = pair.partition("=")
        cam, value = cam.strip(), value.strip()
        if not sep or not cam or not value:
            example = "front=calib.yaml" if what == "calibration" else "front=0.1,0,0.3,-0.5,0.5,-0.5,0.5"
            raise InputError(f"--{what} {pair!r}: expected CAM={'FILE' if what == 'calibration' else 'x,y,z,qx,qy,qz,qw'}, e.g. {example}")
        if what == "calibration":
            side.calibrations[cam] = sidefiles.load_calibration(cam, Path(value))
        else:
            side.extrinsics[cam] = sidefiles.parse_extrinsic(cam, value, body_frame)
    return side


JOBS_HELP = "detection worker processes (default: one per CPU; 1 = detect in this process); results do not depend on it"
CACHE_HELP = (
    "reuse and store detections (corners, ids, payloads) per recording and detection settings, so a "
    "run that only changes solve/fusion/correction settings skips detection"
)
BUDGET_HELP = (
    "add the error budget (an agvviz recording under a non-ideal realism profile): the share of the "
    "position error each error source causes, found by re-recording the scenario with that source off "
    "(minutes: once per source); in the summary and the .rrd (same as `agvviz budget`)"
)
CACHE_DIR_HELP = "detection cache folder (default: $AGVVIZ_CACHE_DIR, else ~/.cache/agvviz/detections)"


def _check_detect_jobs(jobs: Optional[int]) -> None:
    """Refuse a detection ``--jobs`` outside 1..256 (None: one per CPU)."""
    if jobs is not None and not 1 <= jobs <= 256:
        _fail(f"--jobs must lie in 1..256 (or be left out for one per CPU), got {jobs}")


def _run(
    recording: Path, solver: Optional[str], sets: list[str], out: Optional[Path],
    topics: list[str] = (), roles: Optional[Path] = None, markers: Optional[Path] = None,
    calibration: list[str] = (), extrinsic: list[str] = (), jobs: Optional[int] = None,
    cache_dir=None, budget: bool = False,
) -> Path:
    from agvviz.recording.roles import parse_topic_options
    from agvviz.recording.source import require_recording_path
    from agvviz.replay.run import NoUsableFrameError, run_recording

    _check_detect_jobs(jobs)
    require_recording_path(recording)  # one line, before a progress bar is drawn
    settings = apply_overrides(RunSettings(), ([f"solver={solver}"] if solver else []) + list(sets))
    if budget and (topics or roles or markers or calibration or extrinsic):
        _fail("--budget re-records the scenario of an agvviz recording with each error source off; "
              "--topic, --roles, --markers, --calibration and --extrinsic do not apply to it")
    topic_map = parse_topic_options(list(topics))
    side = _side_inputs(markers, list(calibration), list(extrinsic), settings.body_frame)
    error_budget = None
    if budget:
        if out is not None:
            outputs.prepare_output(out, inputs=[recording])  # fail before minutes of work, not after
        error_budget = _error_budget_with_progress(recording, settings, None, jobs, cache_dir)
    # The bar appears once the frames are counted: an input refused while the recording is
    # prepared (e.g. frames of a marker family without a map) prints only its error line.
    progress = _progress()
    task = progress.add_task(f"replaying {recording.name}", total=None, rate="")

    def on_total(total: int) -> None:
        progress.start()
        progress.update(task, total=total)

    def on_frame(done: int) -> None:
        progress.start()
        elapsed = progress.tasks[task].elapsed or 0.0
        rate = f"{done / elapsed:.1f} frames/s" if elapsed > 0 else ""
        # the total is the busiest camera's image count: cameras that do not share every time
        # stamp make more frames than that (auv_under_ice: 201 of "200")
        total = progress.tasks[task].total
        progress.update(task, completed=done, rate=rate, **({"total": done} if total is not None and done > total else {}))

    try:
        outcome = run_recording(
            recording, settings, out, progress=on_frame, topics=topic_map, roles_file=roles,
            side=side, on_total=on_total, jobs=jobs, cache_dir=cache_dir, error_budget=error_budget,
        )
    except NoUsableFrameError as exc:
        _stop_started(progress)
        for cause in exc.causes:  # one line per cause, then the one-line error
            err_console.print(Text.assemble(("cause:", "bold"), " ", cause), soft_wrap=True, highlight=False)
        raise
    finally:
        _stop_started(progress)
    # The run's .rrd is complete and in place: an interrupt from here on would only make the exit
    # code say it failed (the robustness campaign's "output of a failed command").
    from agvviz.__main__ import outputs_complete

    outputs_complete()
    for name, item in outcome.manifest.get("ignored_settings", {}).items():
        text = f" {name}={item['value']} does not apply: {item['reason']}; ignored (not in the run name)"
        err_console.print(Text.assemble(("warning:", "yellow"), text), soft_wrap=True, highlight=False)
    _print_summary(outcome.summary, outcome.timing, f"run {outcome.manifest['recording_name']}")
    if error_budget is None:
        _budget_hint(outcome.manifest.get("scenario"))
    console.print(f"run written: [bold]{outcome.out_path}[/]")
    console.print(f"open it with: [bold]agvviz view {outcome.out_path}[/]")
    return outcome.out_path


def _stop_started(progress: Progress) -> None:
    """Stop a bar that was started (Rich prints a blank line when stopping on a non-terminal)."""
    if progress.live.is_started:
        progress.stop()


def _budget_hint(scenario: Optional[dict]) -> None:
    """Say that ``run --budget`` can share this run's error out, when the recording has error
    sources on (an agvviz recording under a non-ideal realism profile)."""
    from agvviz.evaluation.error_budget import sources_on

    options = (scenario or {}).get("options") or {}
    try:
        on = sources_on(options, scenario.get("name")) if "realism" in options else []
    except (ValueError, InputError):  # options or a scenario this agvviz does not know: no hint
        on = []
    if on:
        console.print(f"error sources on in this recording ({options['realism']}): {', '.join(on)} — "
                      "[bold]--budget[/] adds the share of the position error each one causes (re-records once per source)")


def _error_budget_with_progress(recording: Path, settings: RunSettings, work_dir: Optional[Path],
                                jobs: Optional[int], cache_dir):
    """:func:`agvviz.evaluation.error_budget.error_budget` under a progress bar."""
    from agvviz.evaluation.error_budget import error_budget

    # The bar appears with the first step, so an input refused at once prints only its error.
    progress, task = _progress(), None

    def on_step(done: int, total: int, what: str) -> None:
        nonlocal task
        if task is None:
            progress.start()
            task = progress.add_task(f"error budget of {recording.name}", total=None, rate="")
        progress.update(task, completed=done, total=total, **({"rate": what} if what else {}))

    try:
        result = error_budget(recording, settings, work_dir=work_dir, progress=on_step, jobs=jobs,
                              cache_dir=cache_dir)
        if task is not None:
            progress.update(task, rate="done")
    finally:
        progress.stop()
    for warning in result.warnings:
        err_console.print(f"[yellow]warning:[/] {escape(warning)}")
    return result


@app.command(help=_run_help(), cls=_Command)
@handle_errors
def run(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="recording: an .mcap file, a rosbag2 directory or a ROS 1 .bag (or folder of them)"),
    solver: Optional[str] = typer.Option(None, "--solver", help="shortcut for --set solver=NAME"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help=SET_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help="output .rrd (default: runs/<recording>-<settings>.rrd)"),
    topic: List[str] = typer.Option([], "--topic", metavar="ROLE=TOPIC", help=TOPIC_HELP),
    roles: Optional[Path] = typer.Option(None, "--roles", help=ROLES_HELP),
    markers: Optional[Path] = typer.Option(None, "--markers", help=MARKERS_HELP),
    calibration: List[str] = typer.Option([], "--calibration", metavar="CAM=FILE", help=CALIBRATION_HELP),
    extrinsic: List[str] = typer.Option([], "--extrinsic", metavar="CAM=POSE", help=EXTRINSIC_HELP),
    jobs: Optional[int] = typer.Option(None, "--jobs", help=JOBS_HELP),
    cache: bool = typer.Option(True, "--cache/--no-cache", help=CACHE_HELP),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help=CACHE_DIR_HELP),
    budget: bool = typer.Option(False, "--budget", help=BUDGET_HELP),
) -> None:
    _run(recording, solver, set_, out, topic, roles, markers, calibration, extrinsic,
         jobs=jobs, cache_dir=(cache_dir if cache else False), budget=budget)


# -- inspect / view / demo ---------------------------------------------------------------
@app.command(cls=_Command)
@handle_errors
def inspect(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="recording: an .mcap file, a rosbag2 directory or a ROS 1 .bag (or folder of them)"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="run settings that change what a run can use (body_frame, time_source, ...)"),
    topic: List[str] = typer.Option([], "--topic", metavar="ROLE=TOPIC", help=TOPIC_HELP),
    roles: Optional[Path] = typer.Option(None, "--roles", help=ROLES_HELP),
    write_roles: Optional[Path] = typer.Option(None, "--write-roles", help="write the role map to this file (edit it, then run --roles FILE)"),
    write_markers: Optional[Path] = typer.Option(None, "--write-markers", help="write a marker map skeleton (YAML, for --markers) with every marker id the frames show; fill in each marker's side_m and pose (docs/starting-without-a-map.md)"),
    markers: Optional[Path] = typer.Option(None, "--markers", help=MARKERS_HELP),
    calibration: List[str] = typer.Option([], "--calibration", metavar="CAM=FILE", help=CALIBRATION_HELP),
    extrinsic: List[str] = typer.Option([], "--extrinsic", metavar="CAM=POSE", help=EXTRINSIC_HELP),
) -> None:
    """Print topics, counts, time span, cameras, calibration, the role map and whether a run can use the frames; check agvviz recordings against the recording contract.

    Exits with code 1 when the file violates the contract, is damaged, or holds no frame a run could use (the causes are listed, as `run` would give them).

    Marker families: without a marker map, sampled frames (up to 20 per camera) are scanned for QR, ArUco and AprilTag families and each camera's families, ids, counts and apparent sizes are listed; frames of ArUco/AprilTag markers with no map (or a map of another family) make it exit 1. --write-markers FILE writes a map skeleton to fill in (docs/starting-without-a-map.md).

    Example: agvviz inspect rosbag2_dir --topic truth=/vicon/agv/pose --write-roles roles.yaml

    Example: agvviz inspect robot.mcap --write-markers map.yaml
    """
    from agvviz.recording.contract import format_report, inspect_recording
    from agvviz.recording.roles import parse_topic_options
    from agvviz.replay.run import prepare

    settings = apply_overrides(RunSettings(), list(set_))
    topic_map = parse_topic_options(list(topic))
    if write_markers is not None:  # before minutes of reading: never over an input
        outputs.check_not_input(write_markers, [p for p in (recording, markers, roles) if p is not None], option="--write-markers")
    side = _side_inputs(markers, list(calibration), list(extrinsic), settings.body_frame)
    prepared = prepare(recording, settings, topic_map, roles, side)
    report = inspect_recording(recording, roles=prepared.roles, time_source=settings.time_source)
    console.print(format_report(report), highlight=False, markup=False, soft_wrap=True)
    lines = ["", f"roles (body frame {prepared.body_frame}, time from {prepared.time_source}; override with --topic ROLE=TOPIC):"]
    lines += prepared.roles.lines() or ["  none"]
    marker_lines, family_problem = _marker_scan_lines(recording, prepared, markers, write_markers)
    if family_problem:
        lines.append(f"replay: {family_problem}")
        lines.append("replay: a run would fail (`agvviz run` exits 2 naming the family)")
    elif prepared.usable_cameras:
        lines.append(f"replay: frames of camera(s) {', '.join(prepared.usable_cameras)} can be used")
    for cause in prepared.causes:
        lines.append(f"replay: {cause}")
    for note in prepared.replay.sync.notes.values():
        lines.append(f"replay: warning: {note}")
    if not prepared.can_run:
        lines.append("replay: a run would fail (no frame can be used; `agvviz run` exits non-zero)")
    lines += marker_lines
    console.print("\n".join(lines), highlight=False, markup=False, soft_wrap=True)
    if write_roles is not None:
        outputs.atomic_write_text(write_roles, prepared.roles.to_yaml(), inputs=[recording])
        console.print(f"roles written: {write_roles} (use it with --roles {write_roles})", highlight=False,
                      markup=False, soft_wrap=True)
    if not report.ok or not prepared.can_run or family_problem:
        raise typer.Exit(code=1)


def _marker_scan_lines(recording: Path, prepared, markers: Optional[Path], write_markers: Optional[Path]) -> tuple[list[str], str]:
    """inspect's marker families (issue 23): without a map (or with --write-markers) the sampled
    frames are scanned for every common family; with a map, for its family first, and for the
    others only when the map's is not seen. Writes the map skeleton when asked. Returns the
    lines and, when a run would refuse the frames' family (no map, or another map), why."""
    from agvviz.replay.detect.family_scan import map_problem, map_skeleton_yaml, mismatch_line, scan_lines, scan_recording
    from agvviz.markers.scan import MIN_FRAMES, SCAN_FAMILIES

    if not prepared.roles.cameras():
        if write_markers is not None:
            raise InputError(f"--write-markers: {recording} has no camera images to find markers in; no map written")
        return [], ""
    marker_map = prepared.replay.ctx.marker_map
    family = marker_map.get("dictionary") if isinstance(marker_map, dict) else None
    lines = [""]
    broken = map_problem(prepared)
    if broken:
        lines.append(f"markers: the marker map cannot be used: {broken.removeprefix('marker map: ')}")
        if write_markers is None:
            return lines, f"the marker map cannot be used ({broken.removeprefix('marker map: ')})"
    map_seen = False
    if family is not None:
        quick = scan_recording(prepared, families=(family,),
                               stop=lambda s: any(f.frames_seen >= MIN_FRAMES for f in s.found()))
        map_seen = bool(quick.found())
        if map_seen and write_markers is None:
            return lines + [f"markers: the map's family ({family}) is seen in the sampled frames"], ""
    scan = scan_recording(prepared, families=SCAN_FAMILIES)
    lines.append("markers seen in sampled frames (no map needed to list them; family, ids ×frames, apparent side):")
    lines += scan_lines(scan)
    mismatch = None if map_seen else mismatch_line(prepared, scan)
    problem = ""
    found = scan.found()
    if mismatch:
        lines.append(f"markers: {mismatch}")
        problem = mismatch
    elif family is None and found and all(f.family != "qr" for f in found):
        lines.append(f"markers: no marker map — write one with `agvviz inspect {recording} --write-markers map.yaml`, "
                     f"fill it in, then `agvviz run {recording} --markers map.yaml`")
        problem = f"the frames show {found[0].dictionary} markers and no marker map places them"
    if write_markers is not None:
        text = map_skeleton_yaml(scan, prepared.recording.name)
        outputs.atomic_write_text(write_markers, text, inputs=[recording] + ([markers] if markers else []))
        lines.append(f"marker map skeleton written: {write_markers} (fill in side_m and pose of each marker, then "
                     f"agvviz run {recording} --markers {write_markers})")
    return lines, problem


WEB_PORT = 9090  # Rerun's web viewer (HTTP) default
GRPC_PORT = 9876  # Rerun's viewer / proxy (gRPC) default


def _rerun_executable() -> str:
    """The ``rerun`` viewer installed with this Python's rerun-sdk (the same version), else on PATH."""
    beside = Path(sys.executable).with_name("rerun")
    rerun_bin = str(beside) if beside.exists() else shutil.which("rerun")
    if rerun_bin is None:
        _fail("the `rerun` viewer executable was not found next to this Python; reinstall rerun-sdk")
    return rerun_bin


def viewer_url(address: str) -> str:
    """A running viewer's gRPC URL from ``--connect``: a port (``9876``), ``host:port`` or a
    ``rerun+http://host:port/proxy`` URL (schemes ``rerun``, ``rerun+http``, ``rerun+https``)."""
    from urllib.parse import urlsplit

    text = address.strip()
    if text.isdigit():
        text = f"127.0.0.1:{text}"
    if "://" not in text:
        text = f"rerun+http://{text}/proxy"
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        parts, port = None, None
    if (parts is None or parts.scheme not in ("rerun", "rerun+http", "rerun+https") or not parts.hostname
            or parts.path != "/proxy" or not port):
        _fail(f"--connect {address!r}: expected a port, HOST:PORT or a URL like rerun+http://HOST:{GRPC_PORT}/proxy")
    return text


def _send_to_viewer(run_file: Path, address: str) -> str:
    """Send the run (its recording and blueprint) to the Rerun viewer at ``address``; returns its URL."""
    import socket
    from urllib.parse import urlsplit

    import rerun as rr
    from rerun.chunk import RrdReader

    url = viewer_url(address)
    parts = urlsplit(url)
    try:  # the SDK would wait for an absent viewer for ever: ask first
        socket.create_connection((parts.hostname, parts.port), timeout=5).close()
    except OSError as exc:
        _fail(f"no Rerun viewer answers at {url} ({exc.strerror or exc}); start one there with `rerun` "
              f"(it listens on port {GRPC_PORT}) or give its address to --connect")
    try:
        recordings = RrdReader(run_file).recordings()
    except (RuntimeError, ValueError, OSError) as exc:
        _fail(f"cannot read {run_file}: {' '.join(str(exc).split())}; write it again with `agvviz run`")
    if not recordings:
        _fail(f"{run_file} holds no recording; write it again with `agvviz run`")
    entry = recordings[0]
    # The run's own application and recording id: the viewer shows the run, not an empty sender.
    stream = rr.RecordingStream(entry.application_id, recording_id=entry.recording_id)
    try:
        stream.connect_grpc(url)
        stream.log_file_from_path(run_file)  # the .rrd as it is: recording and blueprint
        stream.flush(timeout_sec=120)
    except (RuntimeError, ValueError) as exc:
        _fail(f"sending {run_file} to {url} failed: {' '.join(str(exc).split())}")
    finally:
        stream.disconnect()
    return url


def _port_free(bind: str, port: int, option: str) -> None:
    import socket

    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((bind, port))
        except OSError as exc:
            _fail(f"cannot listen on {bind} port {port} ({exc.strerror or exc}); choose another with {option}")


def _stop_group(process: subprocess.Popen) -> None:
    """SIGTERM to the process group ``process`` leads (started with ``start_new_session``), then
    SIGKILL after 10 s."""
    import signal

    for sig, wait_s in ((signal.SIGTERM, 10), (signal.SIGKILL, None)):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            break
        try:
            process.wait(timeout=wait_s)
            break
        except subprocess.TimeoutExpired:
            continue


def _serve_web(run_file: Path, bind: str, web_port: int, grpc_port: int) -> None:
    """Serve the run in Rerun's web viewer until Ctrl-C (exit 130)."""
    import socket
    from urllib.parse import quote

    for port, option in ((web_port, "--port"), (grpc_port, "--grpc-port")):
        if not 1 <= port <= 65535:
            _fail(f"{option} must lie in 1..65535, got {port}")
        _port_free(bind, port, option)
    host = socket.gethostname() if bind in ("0.0.0.0", "::") else bind
    command = [_rerun_executable(), "--web-viewer", "--bind", bind, "--web-viewer-port", str(web_port),
               "--port", str(grpc_port), str(run_file)]
    # Its own process group: the `rerun` script runs the viewer binary as a child, and both must
    # stop with us (Ctrl-C, SIGTERM), whoever gets the signal.
    server = subprocess.Popen(command, env={**os.environ, "RUST_LOG": "warn"}, start_new_session=True)
    try:
        def url(at: str) -> str:
            return f"http://{at}:{web_port}/?url={quote(f'rerun+http://{at}:{grpc_port}/proxy', safe='')}"

        local = f"; on this machine: {url('127.0.0.1')}" if host != "127.0.0.1" else ""
        console.print(f"serving {run_file} in Rerun's web viewer; open in a browser:\n  {url(host)}\n"
                      f"(Ctrl-C stops it{local})", highlight=False, markup=False, soft_wrap=True)
        code = server.wait()
    except KeyboardInterrupt:
        _stop_group(server)
        err_console.print("web viewer stopped", highlight=False)
        raise typer.Exit(code=EXIT_INTERRUPTED) from None
    _fail(f"the Rerun web viewer stopped with exit code {code} (see its message above)")


@app.command(cls=_Command)
@handle_errors
def view(
    run_file: Path = typer.Argument(..., metavar="RUN", help="run .rrd"),
    web: bool = typer.Option(False, "--web", help="serve the run in Rerun's web viewer (for a machine without a "
                             "screen: open the printed URL in a browser elsewhere); Ctrl-C stops it"),
    connect: Optional[str] = typer.Option(None, "--connect", metavar="ADDRESS", help="send the run to a running "
                                          f"Rerun viewer: a port, HOST:PORT or rerun+http://HOST:{GRPC_PORT}/proxy"),
    port: int = typer.Option(WEB_PORT, "--port", help="--web: the web viewer's HTTP port"),
    grpc_port: int = typer.Option(GRPC_PORT, "--grpc-port", help="--web: the port the browser fetches the run from"),
    bind: str = typer.Option("0.0.0.0", "--bind",
                             help="--web: the address to listen on (127.0.0.1: this machine only)"),
) -> None:
    """Open a run in the Rerun viewer (with its default layout); --web serves it to a browser, --connect sends it to a viewer elsewhere.

    Example: agvviz view runs/qr_floor-lm.rrd

    Example (on a robot without a screen): agvviz view runs/qr_floor-lm.rrd --web

    Example: agvviz view runs/qr_floor-lm.rrd --connect laptop:9876
    """
    from agvviz.viz.rrd_file import looks_complete

    if not run_file.is_file():
        _fail(f"no such file: {run_file}")
    if not looks_complete(run_file):
        _fail(f"{run_file} is not a complete .rrd file (no Rerun header or footer); write it again with `agvviz run`")
    if web and connect is not None:
        _fail("give --web (serve it here) or --connect (send it to a viewer elsewhere), not both")
    if connect is not None:
        url = _send_to_viewer(run_file, connect)
        console.print(f"sent {run_file} to the Rerun viewer at {url}", highlight=False, markup=False, soft_wrap=True)
        return
    if web:
        _serve_web(run_file, bind, port, grpc_port)
        return
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        _fail(f"no display to open the viewer on (DISPLAY and WAYLAND_DISPLAY are unset): serve it to a browser "
              f"with `agvviz view {run_file} --web`, or send it to a viewer elsewhere with "
              f"`agvviz view {run_file} --connect HOST:{GRPC_PORT}`")
    code = subprocess.call([_rerun_executable(), str(run_file)])
    if code != 0:
        _fail(f"the Rerun viewer could not open {run_file} (it exited with code {code}; see its messages above)")


@app.command(cls=_Command)
@handle_errors
def demo(
    seed: int = typer.Option(0, "--seed", help="scenario seed"),
    solver: str = typer.Option("lm", "--solver", help="pose solver"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="scenario options key=value"),
) -> None:
    """The main job: record the default scenario qr_floor, replay it, write the .rrd.

    Example: agvviz demo --set duration_s=10
    """
    recording = _record("qr_floor", seed, set_, Path("recordings") / "qr_floor.mcap")
    _run(recording, solver, [], None)


@app.command(cls=_Command)
@handle_errors
def version() -> None:
    """Print the agvviz version."""
    console.print(__version__)


# -- diff / sweep / export --------------------------------------------------------------------
@app.command(cls=_Command)
@handle_errors
def diff(
    a: Path = typer.Argument(..., metavar="A", help="run A .rrd (the reference)"),
    b: Path = typer.Argument(..., metavar="B", help="run B .rrd (compared with A)"),
    out: Optional[Path] = typer.Option(None, "--out", help="write the overlay .rrd (both runs on one clock) here"),
    fail_if: Optional[str] = typer.Option(
        None, "--fail-if",
        help="exit 1 when this condition holds, e.g. \"B.position_rmse_mm > 1.05*A.position_rmse_mm\" "
        "(metrics of A and B, numbers, + - * /, comparisons, and/or, parentheses)",
    ),
    align: str = typer.Option("none", "--align", help="APE alignment: none | se3 | se2 | yaw"),
    rpe_delta: int = typer.Option(1, "--rpe-delta", help="RPE pair distance in frames"),
    time_offset: bool = typer.Option(False, "--time-offset", help="also estimate each run's time offset to truth"),
    images: bool = typer.Option(True, "--images/--no-images", help="copy A's camera images into the overlay"),
    seed: int = typer.Option(0, "--seed", help="bootstrap seed"),
    all_metrics: bool = typer.Option(False, "--all", help="print every metric (default: the main ones)"),
) -> None:
    """Compare run B with run A: a verdict first, then the metrics, B − A, a paired test and a confidence interval.

    Frames are matched by time; error metrics are over the frames both runs solved.
    Exit codes: 0 fine, 1 the --fail-if condition holds, 2 bad input, 3 the overlay could not be written (never over A or B).

    Example: agvviz diff runs/lm.rrd runs/p4p.rrd --out runs/diff.rrd --fail-if "B.position_rmse_mm > 1.05*A.position_rmse_mm"
    """
    from agvviz.app.compare import diff as diff_runs, diff_table, diff_table_title, diff_verdict

    outcome = diff_runs(
        a, b, overlay_path=out, fail_if=fail_if, align=align, rpe_delta=rpe_delta,
        time_offset=time_offset, images=images, seed=seed,
    )
    c = outcome.comparison
    verdict = diff_verdict(c)
    console.print(f"[bold]{escape(verdict.headline)}[/]")
    for line in verdict.lines[1:]:
        console.print(escape(line))
    header, rows = diff_table(c, all_metrics)
    table = Table(title=escape(diff_table_title(c, all_metrics)), title_justify="left")
    for col in header:
        table.add_column(col, justify="left" if col == "metric" else "right", no_wrap=True)
    for row in rows:
        table.add_row(*row)
    # Wide enough for every metric name and interval even when stdout is not a terminal.
    Console(width=max(console.width, 100)).print(table)
    if c.settings_changed:
        console.print("settings that differ: " + ", ".join(
            f"{name} {va!r} → {vb!r}" for name, (va, vb) in c.settings_changed.items()))
    if c.largest:
        console.print("frames where the estimates differ most: " + "; ".join(
            f"frame {d.frame_a}: {d.separation_mm:.2f} mm apart (error A {d.position_a_mm:.2f} mm, "
            f"B {d.position_b_mm:.2f} mm)" for d in c.largest))
    else:
        console.print("the two runs' estimates are identical on every frame both solved")
    if c.solved_only_by_a or c.solved_only_by_b:
        console.print(f"solved only by A: {len(c.solved_only_by_a)} frames {c.solved_only_by_a[:10]}; "
                      f"only by B: {len(c.solved_only_by_b)} frames {c.solved_only_by_b[:10]}")
    for note in c.notes:
        err_console.print(f"[yellow]note:[/] {note}")
    if outcome.overlay_path is not None:
        console.print(f"overlay written: [bold]{outcome.overlay_path}[/]  (agvviz view {outcome.overlay_path})")
    if outcome.failed:
        err_console.print(f"[bold red]--fail-if holds:[/] {fail_if}")
        raise typer.Exit(code=1)
    if fail_if is not None:
        console.print(f"--fail-if does not hold: {fail_if}")


@app.command(cls=_Command)
@handle_errors
def sweep(
    recordings: List[Path] = typer.Argument(..., metavar="RECORDING", help="recordings (.mcap or rosbag2 folders)"),
    set_: List[str] = typer.Option(
        [], "--set", metavar="KEY=V1,V2", help="setting=value1,value2,... (repeatable); the sweep runs every combination",
    ),
    jobs: Optional[int] = typer.Option(None, "--jobs", help="worker processes of the local cluster (default: "
                                       "number of CPUs)"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="address of an existing Dask cluster's "
                                            "scheduler (tcp://host:8786) to run on instead of a local cluster"),
    out_dir: Optional[Path] = typer.Option(None, "--out-dir", help="default runs/sweep-<recording>; with several "
                                           "recordings one folder per recording under it (default runs/sweep)"),
    rank_by: str = typer.Option("position_rmse_mm", "--rank-by", help="metric to rank by (lower is better, "
                                "except solved / solved_pct)"),
    align: str = typer.Option("none", "--align", help="APE alignment: none | se3 | se2 | yaw"),
    images: bool = typer.Option(True, "--images/--no-images", help="camera images in the overlay"),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help=CACHE_DIR_HELP),
) -> None:
    """Replay each RECORDING under every combination of the --set values on a Dask cluster; rank each recording's runs.

    Each recording is detected once per detection settings; every setting then only solves.
    Writes one .rrd per setting, overlay.rrd, ranking.csv and ranking.md into --out-dir (with
    several recordings, into --out-dir/<recording name>/). A setting that fails is reported and
    the others go on. Names are the run settings of `agvviz run --help` (lm.max_iters is accepted
    for lm_max_iterations). Needs Dask: pip install 'agvviz\\[distributed]'.

    Example: agvviz sweep recordings/qr_floor.mcap --set solver=p4p,lm,ippe --set lm_max_iterations=3,10
    """
    from agvviz.app.compare import grid_settings, parse_grid, ranking_rows
    from agvviz.app.compare import sweep as sweep_runs

    if jobs is not None and jobs < 1:
        _fail(f"--jobs must be ≥ 1 (or left out for one per CPU), got {jobs}")
    grid = parse_grid(set_)
    n_runs = len(grid_settings(grid)) * len(recordings)
    what = f"{n_runs} runs" if len(recordings) > 1 else f"{n_runs} settings"
    with _progress() as progress:
        task = progress.add_task(f"sweeping {what}", total=None, rate="starting")

        def on_total(frames: int) -> None:
            progress.update(task, total=frames or None)

        def on_progress(frames_done: int, runs_done: int) -> None:
            progress.update(task, completed=frames_done, rate=f"{runs_done}/{n_runs} done")

        outcome = sweep_runs(
            recordings[0] if len(recordings) == 1 else recordings, grid, out_dir=out_dir, jobs=jobs,
            rank_by=rank_by, align=align, images=images, progress=on_progress, on_total=on_total,
            scheduler=scheduler, cache_dir=cache_dir,
        )
    wanted = ["rank", "setting", outcome.rank_by, "solved", "position_p95_mm",
              "heading_rmse_deg", "p_vs_best", "time_per_frame_ms", "status"]
    for result in outcome.recordings:
        header, rows = ranking_rows(result.entries, outcome.rank_by)
        table = Table(title=f"sweep of {result.recording.name}, ranked by {outcome.rank_by} "
                      f"(every column in {result.markdown_path.name})", title_justify="left")
        shown = [header.index(h) for h in dict.fromkeys(wanted)]
        for i in shown:
            table.add_column(header[i], justify="left" if header[i] in ("setting", "status") else "right",
                             no_wrap=True, min_width=6 if header[i] == "status" else None)
        for row in rows:
            table.add_row(*[row[i] if not row[i].startswith("failed") else "failed" for i in shown])
        Console(width=max(console.width, 160)).print(table)
        for entry in result.entries:
            if not entry.ok:
                where = f" of {result.recording.name}" if len(outcome.recordings) > 1 else ""
                err_console.print(f"[bold red]setting {escape(entry.label)}{escape(where)} failed:[/] "
                                  f"{escape(entry.error)}")
        console.print(f"runs in [bold]{escape(str(result.out_dir))}[/]; table: {result.csv_path.name}, "
                      f"{result.markdown_path.name}" + (f"; overlay: [bold]{escape(str(result.overlay_path))}[/]"
                                                        if result.overlay_path else ""))
    console.print(f"sweep took {outcome.wall_time_s:.1f} s")
    if not any(entry.ok for entry in outcome.entries):  # nothing to rank: say so in the exit code
        all_output = all(entry.error.startswith("OutputError") for entry in outcome.entries)
        error_line("every setting failed; see the messages above")
        raise typer.Exit(code=EXIT_OUTPUT if all_output else EXIT_BAD_INPUT)

@app.command(cls=_Command)
@handle_errors
def budget(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="an agvviz .mcap recorded under a non-ideal realism profile"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="run setting (repeatable), as for `agvviz run`"),
    out: Optional[Path] = typer.Option(None, "--out", help="output .rrd (default: runs/<recording>-budget.rrd)"),
    work_dir: Optional[Path] = typer.Option(None, "--work-dir", help="keep the re-recorded worlds and their runs "
                                            "here (default: a temporary folder, removed afterwards)"),
) -> None:
    """Error budget: the share of the position error each error source causes.

    Each error source that is on in RECORDING is switched off in turn: the scenario is recorded
    again with the same seed and options plus realism_off=<source> (every source draws from its
    own random stream, so only that source changes), replayed with the same run settings and
    compared. share = (RMSE_all² − RMSE_off²) / RMSE_all²; the shares need not sum to 100 %
    (interaction/other is the rest); the floor is every source off.

    Example: agvviz budget recordings/qr_floor_typical.mcap --out runs/budget.rrd

    `agvviz run RECORDING --budget` puts the same budget into the run's summary and .rrd.
    """
    from agvviz.viz.log_budget import write_budget_rrd

    settings = apply_overrides(RunSettings(), list(set_))
    out = out or Path("runs") / f"{recording.stem}-budget.rrd"
    if out.suffix != ".rrd":
        _fail(f"--out must end in .rrd, got {out}")
    outputs.prepare_output(out, inputs=[recording])  # fail before the work, not after
    result = _error_budget_with_progress(recording, settings, work_dir, jobs=1, cache_dir=False)
    written = write_budget_rrd(out, result)
    table = Table(title=f"error budget of {recording.name} ({result.scenario}, seed {result.seed}, "
                  f"realism {result.profile}): position RMSE {result.rmse_all_mm:.3f} mm", title_justify="left")
    table.add_column("source")
    table.add_column("RMSE with it off (mm)", justify="right")
    table.add_column("share %", justify="right")
    for row in result.rows():
        table.add_row(*row)
    console.print(table)
    if work_dir is not None:
        console.print(f"re-recorded worlds and runs in [bold]{escape(str(work_dir))}[/]")
    console.print(f"budget written: [bold]{escape(str(written))}[/]  (agvviz view {escape(str(written))})")


@app.command(cls=_Command)
@handle_errors
def audit(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="recording: an .mcap file or a rosbag2 directory"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="audit setting (agvviz/evaluation/audit/problem.py AuditSettings: "
                                   "k_sigma, min_position_m, sigma_px, map_sigma_m, …) or run setting (repeatable)"),
    out: Optional[Path] = typer.Option(None, "--out", help="output .rrd (default: runs/<recording>-audit.rrd); the corrected "
                                       "map <out>-markers.yaml and extrinsic <out>-extrinsic.txt are written beside it"),
    markers: Optional[Path] = typer.Option(None, "--markers", help=MARKERS_HELP),
    calibration: List[str] = typer.Option([], "--calibration", metavar="CAM=FILE", help=CALIBRATION_HELP),
    extrinsic: List[str] = typer.Option([], "--extrinsic", metavar="CAM=POSE", help=EXTRINSIC_HELP),
    correct: str = typer.Option("flagged", "--correct", help="markers moved in the corrected map: flagged or all (estimated)"),
    jobs: Optional[int] = typer.Option(None, "--jobs", help=JOBS_HELP),
    cache: bool = typer.Option(True, "--cache/--no-cache", help=CACHE_HELP),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help=CACHE_DIR_HELP),
) -> None:
    """Audit a map and a calibration: which markers are misplaced, is the camera where the calibration says.

    A bundle adjustment over every frame (vehicle poses, camera extrinsic corrections, marker
    placement corrections, odometry scale and drift) from every detected corner, the odometry and
    the floor, with the recorded map and calibration as priors. A marker is flagged when its error
    exceeds k_sigma·σ and the minimum size (min_position_m, min_angle_deg, min_scale); markers seen
    too little are listed, never flagged. Writes a table, an .rrd, a corrected marker map
    (agvviz run --markers) and the extrinsic option (agvviz run --extrinsic "$(cat FILE)").

    Example: agvviz audit recordings/qr_floor.mcap --set k_sigma=3 --out runs/audit.rrd
    """
    from agvviz.app import audit as audit_lib
    from agvviz.evaluation.audit import report
    from agvviz.evaluation.audit.problem import AuditSettings
    from agvviz.recording.source import require_recording_path

    if correct not in ("flagged", "all"):
        _fail(f"--correct must be flagged or all, got {correct!r}")
    _check_detect_jobs(jobs)
    audit_pairs, run_pairs = audit_lib.split_settings(list(set_))
    from agvviz.settings import field_types

    for pair in run_pairs:
        key = pair.partition("=")[0].strip()
        if key and key not in field_types(RunSettings):
            _fail(f"unknown setting {key!r}; audit settings: {', '.join(sorted(audit_lib.audit_setting_names()))}; "
                  f"run settings: {', '.join(sorted(field_types(RunSettings)))}")
    require_recording_path(recording)  # one line, before a progress bar is drawn
    settings = apply_overrides(AuditSettings(), audit_pairs)
    run_settings = apply_overrides(RunSettings(), run_pairs)
    if out is not None and out.suffix != ".rrd":
        _fail(f"--out must end in .rrd, got {out}")
    paths = audit_lib.default_paths(recording, out)
    inputs = [recording] + ([markers] if markers else [])
    for path in paths.values():  # fail before the work, not after
        outputs.prepare_output(path, inputs=inputs)
    side = _side_inputs(markers, list(calibration), list(extrinsic), run_settings.body_frame)
    with _progress() as progress:
        task = progress.add_task(f"auditing {recording.name}", total=None, rate="")
        result = audit_lib.audit_recording(recording, run_settings, settings, side=side, jobs=jobs,
                                           cache_dir=cache_dir if cache else False,
                                           progress=lambda done: progress.update(task, completed=done))
        progress.update(task, rate="solved")
    written = audit_lib.write_outputs(result, paths, correct)
    est = result.estimate
    cams = Table(title=f"{result.title}: cameras (correction recorded → estimated, AGV frame)", title_justify="left")
    for column in report.CAMERA_COLUMNS:
        cams.add_column(column, justify="left" if column in ("camera", "status", "why") else "right")
    for row in report.camera_rows(est):
        cams.add_row(*row, style="bold red" if row[1] == "flagged" else None)
    table = Table(title=f"{result.title}: markers (placement error, true − mapped)", title_justify="left")
    for column in report.MARKER_COLUMNS:
        table.add_column(column, justify="left" if column in ("marker", "status", "other", "why") else "right")
    for row in report.marker_rows(est):
        table.add_row(*row, style="bold red" if row[1] == "flagged" else ("dim" if row[1] == "seen too little" else None))
    wide = Console(width=max(console.width, 160))
    wide.print(cams)
    wide.print(table)
    for line in report.summary_lines(est):
        console.print(escape(line))
    for warning in result.collected.warnings:
        err_console.print(f"[yellow]warning:[/] {escape(warning)}")
    console.print(f"audit written: [bold]{escape(str(written['rrd']))}[/]  (agvviz view {escape(str(written['rrd']))})")
    if "markers" in written:
        console.print(f"corrected marker map: [bold]{escape(str(written['markers']))}[/]  (agvviz run --markers)")
    console.print(f"extrinsic: [bold]{escape(str(written['extrinsic']))}[/]  "
                  f"(agvviz run --extrinsic \"$(cat {escape(str(written['extrinsic']))})\")")
    for key, path in written.items():
        if key.startswith("calibration "):
            console.print(f"{key}: [bold]{escape(str(path))}[/]  (agvviz run --calibration {key.split(' ', 1)[1]}={escape(str(path))})")
    console.print(f"audit took {result.total_s:.1f} s (collect {result.collect_s:.1f} s, solve {est.solve_s:.1f} s)")


@app.command(cls=_Command)
@handle_errors
def export(
    run_file: Path = typer.Argument(..., metavar="RUN", help="run .rrd"),
    format_: str = typer.Option("tum", "--format", help="output format: tum (evo, TUM tools) or mcap (Foxglove)"),
    out_dir: Optional[Path] = typer.Option(None, "--out-dir",
                                           help="output folder, created if missing (default: the run's folder)"),
) -> None:
    """Write the run's estimated and true trajectories (T_world_agv) for other tools.

    tum: `<run>.estimate.tum` and `<run>.truth.tum`, lines `t tx ty tz qx qy qz qw`. A run without ground truth exports its estimate alone and says so (no truth file is written). See docs/export.md.

    mcap: `<run>.poses.mcap`, Foxglove PoseInFrame on /agvviz/estimate/pose and /agvviz/truth/pose and FrameTransforms (world → agv_estimate, agv_truth) on /agvviz/tf, stamped with the recording's times: open it beside the recording in Foxglove. Needs pip install 'agvviz\\[export]'.

    Example: agvviz export runs/qr_floor-lm.rrd --format tum && evo_ape tum runs/qr_floor-lm.truth.tum runs/qr_floor-lm.estimate.tum

    Example: agvviz export runs/qr_floor-lm.rrd --format mcap --out-dir exports
    """
    from agvviz.app.export import export_run

    written = export_run(run_file, format_, out_dir)
    for item in written:
        console.print(f"{item.which}: {item.poses} poses → [bold]{escape(str(item.path))}[/]", soft_wrap=True)
    for which, why in written.missing.items():
        console.print(f"{which}: not written — {escape(why)}", soft_wrap=True, highlight=False)


if __name__ == "__main__":
    from agvviz.__main__ import main

    sys.exit(main())
