"""The commands that make recordings and runs: ``scenarios``, ``record``, ``run``, ``demo`` and
``version``; each parses its options and calls the library (:mod:`agvviz.scenarios`,
:func:`agvviz.app.run.run_recording`), then prints where its output went.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from agvviz import __version__
from agvviz.cli import interrupts
from agvviz.cli.common import console, err_console, fail, handle_errors, progress_bar, stop_progress
from agvviz.cli import options
from agvviz.errors import InputError
from agvviz.recording import outputs
from agvviz.settings import RunSettings, apply_overrides, describe


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
    with progress_bar() as progress:
        task = progress.add_task(f"recording {scenario}", total=None, rate="")

        def on_frame(done: int, total: int) -> None:
            progress.update(task, completed=done, total=total)

        scenario_registry.record(scenario, out, seed=seed, overrides=sets, progress=on_frame)
    console.print(f"recording written: [bold]{out}[/]")
    return out


@handle_errors
def record(
    scenario: str = typer.Argument("qr_floor", metavar="SCENARIO", help="scenario name (see `agvviz scenarios`)"),
    seed: int = typer.Option(0, "--seed", help="fixes all randomness; same seed ⇒ same recording"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help=options.SET_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help="output .mcap (default: recordings/<scenario>.mcap)"),
) -> None:
    """Simulate SCENARIO and write an MCAP recording.

    Example: agvviz record qr_floor --seed 1 --set duration_s=10 --set speed_mps=1.5
    """
    out = out or Path("recordings") / f"{scenario}.mcap"
    if out.suffix != ".mcap":
        fail(f"--out must end in .mcap, got {out}")
    _record(scenario, seed, set_, out)


# -- run ------------------------------------------------------------------------------------
def run_help() -> str:
    """``agvviz run --help``: what it does, examples, and every run setting with its default."""
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


def _print_summary(outcome) -> None:
    """The run's summary table (the rows the library built, :meth:`RunOutcome.summary_rows`),
    then its recording damage and warnings."""
    table = Table(title=f"run {outcome.manifest['recording_name']}", title_justify="left")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for metric, value in outcome.summary_rows():
        table.add_row(metric, value)
    console.print(table)
    summary = outcome.summary
    _print_stretches(summary, outcome.recording_start_ns)
    for problem in summary.get("recording_damage", []):
        err_console.print(f"[yellow]recording damage:[/] {escape(problem)}")
    for warning in summary.get("warnings", []):
        err_console.print(f"[yellow]warning:[/] {escape(warning)}")


def _print_stretches(summary: dict, start_ns) -> None:
    """The suspect stretches after the summary table (at most
    :data:`~agvviz.evaluation.suspect_report.MAX_STRETCH_ROWS`, then "… and N more"); nothing
    when there are none."""
    from agvviz.evaluation import suspect_report

    rows, more = suspect_report.stretch_rows(summary, start_ns)
    if not rows:
        return
    console.print("[bold]suspect stretches[/] — solved poses that disagree with what else the log knows "
                  "(frames, seconds since the recording's start):")
    for frames, time_s, cause, where, max_sigma, finding, next_step in rows:
        console.print(f"[yellow]  frames {escape(frames)}, {escape(time_s)} s — {escape(cause)}"
                      f"{' (' + escape(where) + ')' if where else ''}, up to {escape(max_sigma)}σ[/]")
        console.print(f"    {escape(finding)}")
        if next_step:
            console.print(f"    next: {escape(next_step)}")
    if more:
        console.print(f"… and {more} more (every suspect frame: the suspects log in the .rrd)")


def _gates(outcome, fail_if: list[str], junit_xml: Optional[Path], recording: Path) -> None:
    """Evaluate ``run --fail-if`` on the run's summary, write ``--junit-xml``, print each verdict;
    exit 1 when a condition holds, 2 when one could not be evaluated (a metric without a value)."""
    from agvviz.app.run import gate_run
    from agvviz.evaluation.expression import ExpressionError

    verdicts = gate_run(outcome, fail_if, junit_xml, inputs=[recording, outcome.out_path])
    if junit_xml is not None:
        console.print(f"JUnit verdict written: [bold]{escape(str(junit_xml))}[/]")
    for gate in verdicts:
        if gate.holds:
            err_console.print(f"[bold red]--fail-if holds:[/] {escape(gate.shown)}")
        elif gate.holds is False:
            console.print(f"--fail-if does not hold: {escape(gate.shown)}")
    errors = [gate for gate in verdicts if gate.holds is None]
    if errors:
        raise ExpressionError("; ".join(gate.message for gate in errors))
    if any(gate.holds for gate in verdicts):
        raise typer.Exit(code=1)


def _run(
    recording: Path, solver: Optional[str], sets: list[str], out: Optional[Path],
    topics: list[str] = (), roles: Optional[Path] = None, markers: Optional[Path] = None,
    calibration: list[str] = (), extrinsic: list[str] = (), jobs: Optional[int] = None,
    cache_dir=None, budget: bool = False, fail_if: list[str] = (), junit_xml: Optional[Path] = None,
    images: str = "all",
) -> Path:
    # The fork server of the .rrd writer and the detection workers: their imports run on
    # another core while this one starts up. `agvviz run` started it before its command line
    # was imported (agvviz.cli.early); here for `demo` and a call of main(argv) in process.
    from agvviz.cli.early import start_run_fork_server

    start_run_fork_server()
    from agvviz.recording.roles import parse_topic_options
    from agvviz.recording.source import require_recording_path
    from agvviz.app.run import run_recording
    from agvviz.replay.run import NoUsableFrameError

    from agvviz.app.run import check_gates

    options.check_detect_jobs(jobs)
    if images not in ("all", "none"):
        fail(f"--images {images!r}: choose all (the frames in the .rrd) or none (the layers only)")
    require_recording_path(recording)  # one line, before a progress bar is drawn
    if junit_xml is not None and not fail_if:
        fail("--junit-xml writes the verdict of --fail-if conditions; give at least one --fail-if")
    check_gates(fail_if, junit_xml, inputs=[recording] + ([out] if out is not None else []))
    settings = apply_overrides(RunSettings(), ([f"solver={solver}"] if solver else []) + list(sets))
    if budget and (topics or roles or markers or calibration or extrinsic):
        fail("--budget re-records the scenario of an agvviz recording with each error source off; "
             "--topic, --roles, --markers, --calibration and --extrinsic do not apply to it")
    topic_map = parse_topic_options(list(topics))
    side = options.side_inputs(markers, list(calibration), list(extrinsic), settings.body_frame)
    error_budget = None
    if budget:
        if out is not None:
            outputs.prepare_output(out, inputs=[recording])  # fail before minutes of work, not after
        error_budget = error_budget_with_progress(recording, settings, None, jobs, cache_dir)
    # The bar appears once the frames are counted: an input refused while the recording is
    # prepared (e.g. frames of a marker family without a map) prints only its error line.
    progress = progress_bar()
    task = progress.add_task(f"replaying {recording.name}", total=None, rate="")

    def on_total(total: int) -> None:
        progress.start()
        progress.update(task, total=total)

    def on_frame(done: int) -> None:
        progress.start()
        elapsed = progress.tasks[task].elapsed or 0.0
        # units per second: frames, or a corner-only correction run's corner messages (run_recording)
        rate = f"{done / elapsed:.1f}/s" if elapsed > 0 else ""
        # the total is the busiest camera's image count: cameras that do not share every time
        # stamp make more frames than that (auv_under_ice: 201 of "200")
        total = progress.tasks[task].total
        progress.update(task, completed=done, rate=rate, **({"total": done} if total is not None and done > total else {}))

    try:
        outcome = run_recording(
            recording, settings, out, progress=on_frame, topics=topic_map, roles_file=roles,
            side=side, on_total=on_total, jobs=jobs, cache_dir=cache_dir, error_budget=error_budget,
            images=images == "all", on_published=interrupts.outputs_complete,
        )
    except NoUsableFrameError as exc:
        stop_progress(progress)
        for cause in exc.causes:  # one line per cause, then the one-line error
            err_console.print(Text.assemble(("cause:", "bold"), " ", cause), soft_wrap=True, highlight=False)
        raise
    finally:
        stop_progress(progress)
    # The run's .rrd is in place: outputs_complete was called the moment it was (on_published),
    # with no signal handled in between; an interrupt from then on would only make the exit code
    # say it failed (the robustness campaign's "output of a failed command").
    for name, item in outcome.manifest.get("ignored_settings", {}).items():
        text = f" {name}={item['value']} does not apply: {item['reason']}; ignored (not in the run name)"
        err_console.print(Text.assemble(("warning:", "yellow"), text), soft_wrap=True, highlight=False)
    _print_summary(outcome)
    if error_budget is None:
        _budget_hint(outcome.manifest.get("scenario"))
    console.print(f"run written: [bold]{outcome.out_path}[/]")
    console.print(f"open it with: [bold]agvviz view {outcome.out_path}[/]")
    if fail_if:
        _gates(outcome, list(fail_if), junit_xml, recording)
    return outcome.out_path


def _budget_hint(scenario: Optional[dict]) -> None:
    """Say that ``run --budget`` can share this run's error out, when the recording has error
    sources on (an agvviz recording under a non-ideal realism profile)."""
    from agvviz.app.budget import sources_on

    options = (scenario or {}).get("options") or {}
    try:
        on = sources_on(options, scenario.get("name")) if "realism" in options else []
    except (ValueError, InputError):  # options or a scenario this agvviz does not know: no hint
        on = []
    if on:
        console.print(f"error sources on in this recording ({options['realism']}): {', '.join(on)} — "
                      "[bold]--budget[/] adds the share of the position error each one causes (re-records once per source)")


def error_budget_with_progress(recording: Path, settings: RunSettings, work_dir: Optional[Path],
                                jobs: Optional[int], cache_dir):
    """:func:`agvviz.app.budget.error_budget` under a progress bar."""
    from agvviz.app.budget import error_budget

    # The bar appears with the first step, so an input refused at once prints only its error.
    progress, task = progress_bar(), None

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


@handle_errors
def run(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="recording: an .mcap file, a rosbag2 directory or a ROS 1 .bag (or folder of them)"),
    solver: Optional[str] = typer.Option(None, "--solver", help="shortcut for --set solver=NAME"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help=options.SET_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help="output .rrd (default: runs/<recording>-<settings>.rrd)"),
    topic: List[str] = typer.Option([], "--topic", metavar="ROLE=TOPIC", help=options.TOPIC_HELP),
    roles: Optional[Path] = typer.Option(None, "--roles", help=options.ROLES_HELP),
    markers: Optional[Path] = typer.Option(None, "--markers", help=options.MARKERS_HELP),
    calibration: List[str] = typer.Option([], "--calibration", metavar="CAM=FILE", help=options.CALIBRATION_HELP),
    extrinsic: List[str] = typer.Option([], "--extrinsic", metavar="CAM=POSE", help=options.EXTRINSIC_HELP),
    jobs: Optional[int] = typer.Option(None, "--jobs", help=options.JOBS_HELP),
    cache: bool = typer.Option(True, "--cache/--no-cache", help=options.CACHE_HELP),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help=options.CACHE_DIR_HELP),
    budget: bool = typer.Option(False, "--budget", help=options.BUDGET_HELP),
    fail_if: List[str] = typer.Option([], "--fail-if", metavar="CONDITION", help=options.RUN_FAIL_IF_HELP),
    junit_xml: Optional[Path] = typer.Option(None, "--junit-xml", metavar="FILE", help=options.JUNIT_XML_HELP),
    images: str = typer.Option("all", "--images", metavar="all|none",
                               help="none: leave the camera images out of the .rrd (the layers only, for long logs); "
                                    "`agvviz view` adds them from the recording"),
) -> None:
    _run(recording, solver, set_, out, topic, roles, markers, calibration, extrinsic,
         jobs=jobs, cache_dir=(cache_dir if cache else False), budget=budget, fail_if=fail_if, junit_xml=junit_xml,
         images=images)


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


@handle_errors
def version() -> None:
    """Print the agvviz version."""
    console.print(__version__)
