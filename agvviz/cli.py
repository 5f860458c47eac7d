"""agvviz command line: parse, build a frozen settings object, call one library function.

Every command prints where its output went; errors are one clear line and exit code 2.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from agvviz import __version__
from agvviz.settings import RunSettings, SettingsError, apply_overrides, describe

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="agvviz — record, replay and inspect fiducial-marker localisation in Rerun.\n\n"
    "Quick start:  agvviz demo   (records qr_floor, runs the lm solver, writes an .rrd).",
)
console = Console()
err_console = Console(stderr=True, soft_wrap=True)

SET_HELP = "key=value (repeatable); see `agvviz scenarios` / `agvviz run --help` for keys"


def _fail(message: str) -> None:
    err_console.print(f"[bold red]error:[/] {message}")
    raise typer.Exit(code=2)


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
@app.command()
def scenarios() -> None:
    """List every scenario with its options and defaults."""
    from agvviz import scenario_registry

    for name, module in scenario_registry.available().items():
        table = Table(title=f"{name} — {module.DESCRIPTION}", title_justify="left")
        for col in ("option", "type", "default", "help"):
            table.add_column(col)
        for row in describe(module.Options):
            table.add_row(*row)
        console.print(table)
    console.print("Record one with: agvviz record qr_floor --seed 1 --set duration_s=10")


def _record(scenario: str, seed: int, sets: list[str], out: Path) -> Path:
    from agvviz import scenario_registry

    try:
        scenario_registry.build_options(scenario, sets)  # validate before any work
        with _progress() as progress:
            task = progress.add_task(f"recording {scenario}", total=None, rate="")

            def on_frame(done: int, total: int) -> None:
                progress.update(task, completed=done, total=total)

            scenario_registry.record(scenario, out, seed=seed, overrides=sets, progress=on_frame)
    except scenario_registry.ScenarioError as exc:
        _fail(str(exc))
    console.print(f"recording written: [bold]{out}[/]")
    return out


@app.command()
def record(
    scenario: str = typer.Argument("qr_floor", help="scenario name (see `agvviz scenarios`)"),
    seed: int = typer.Option(0, "--seed", help="fixes all randomness; same seed ⇒ same recording"),
    set_: List[str] = typer.Option([], "--set", help=SET_HELP),
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
        "Replay the localisation pipeline over RECORDING and write a run .rrd.\n\n"
        "Example: agvviz run recordings/qr_floor.mcap --solver lm --set objective=pixel\n\n"
        "Settings (--set key=value):\n\n" + rows.replace("\n", "\n\n")
    )


def _print_summary(summary: dict, title: str) -> None:
    table = Table(title=title, title_justify="left")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_row("frames", str(summary["frames"]))
    table.add_row("solved", str(summary["solved"]))
    for reason, count in summary["rejected"].items():
        table.add_row(f"rejected: {reason}", str(count))
    pos = summary["position_error_mm"]
    hdg = summary["heading_error_deg"]
    fmt = lambda v, p=2: "—" if v is None else f"{v:.{p}f}"  # noqa: E731
    table.add_row("position RMSE / median / p95 (mm)", f"{fmt(pos['rmse'])} / {fmt(pos['median'])} / {fmt(pos['p95'])}")
    table.add_row("heading RMSE / median / p95 (deg)", f"{fmt(hdg['rmse'], 3)} / {fmt(hdg['median'], 3)} / {fmt(hdg['p95'], 3)}")
    table.add_row("reprojection RMS median (px)", fmt(summary["reproj_rms_px"]["median"], 3))
    table.add_row("time per frame (ms): total / detect / solve",
                  f"{fmt(summary['time_per_frame_ms'], 1)} / {fmt(summary['detect_ms'], 1)} / {fmt(summary['solve_ms'], 2)}")
    if "frames_per_s" in summary:
        table.add_row("throughput (frames/s, incl. logging)", fmt(summary["frames_per_s"], 1))
    console.print(table)
    for problem in summary.get("recording_damage", []):
        err_console.print(f"[yellow]recording damage:[/] {problem}")


def _run(recording: Path, solver: Optional[str], sets: list[str], out: Optional[Path]) -> Path:
    from agvviz.recording.reader import RecordingError, count_messages
    from agvviz.runner import RunError, run_recording

    try:
        settings = apply_overrides(RunSettings(), ([f"solver={solver}"] if solver else []) + list(sets))
    except SettingsError as exc:
        _fail(str(exc))
    try:
        total = count_messages(recording, topic_prefix="/cam/", topic_suffix="/image")
        with _progress() as progress:
            task = progress.add_task(f"replaying ({settings.label()})", total=total, rate="")

            def on_frame(done: int) -> None:
                elapsed = progress.tasks[task].elapsed or 0.0
                rate = f"{done / elapsed:.1f} frames/s" if elapsed > 0 else ""
                progress.update(task, completed=done, rate=rate)

            outcome = run_recording(recording, settings, out, progress=on_frame)
    except (RunError, RecordingError) as exc:
        _fail(str(exc))
    _print_summary(outcome.summary, f"run {outcome.manifest['recording_name']}")
    console.print(f"run written: [bold]{outcome.out_path}[/]")
    console.print(f"open it with: [bold]agvviz view {outcome.out_path}[/]")
    return outcome.out_path


@app.command(help=_run_help())
def run(
    recording: Path = typer.Argument(..., help="recording .mcap"),
    solver: Optional[str] = typer.Option(None, "--solver", help="shortcut for --set solver=NAME"),
    set_: List[str] = typer.Option([], "--set", help=SET_HELP),
    out: Optional[Path] = typer.Option(None, "--out", help="output .rrd (default: runs/<recording>-<settings>.rrd)"),
) -> None:
    _run(recording, solver, set_, out)


# -- inspect / view / demo ---------------------------------------------------------------
@app.command()
def inspect(recording: Path = typer.Argument(..., help="recording .mcap")) -> None:
    """Print topics, counts, time span, cameras and calibration; check the recording contract.

    Exits with code 1 when the file violates the contract or is damaged.
    Example: agvviz inspect recordings/qr_floor.mcap
    """
    from agvviz.recording.contract import format_report, inspect_recording
    from agvviz.recording.reader import RecordingError

    try:
        report = inspect_recording(recording)
    except RecordingError as exc:
        _fail(str(exc))
    console.print(format_report(report), highlight=False, markup=False)
    if not report.ok:
        raise typer.Exit(code=1)


@app.command()
def view(run_file: Path = typer.Argument(..., help="run .rrd")) -> None:
    """Open a run in the Rerun viewer (with its default layout).

    Example: agvviz view runs/qr_floor-lm.rrd
    """
    if not run_file.is_file():
        _fail(f"no such file: {run_file}")
    rerun_bin = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    if not Path(rerun_bin).exists():
        _fail("the `rerun` viewer executable was not found next to this Python; reinstall rerun-sdk")
    raise typer.Exit(code=subprocess.call([rerun_bin, str(run_file)]))


@app.command()
def demo(
    seed: int = typer.Option(0, "--seed", help="scenario seed"),
    solver: str = typer.Option("lm", "--solver", help="pose solver"),
    set_: List[str] = typer.Option([], "--set", help="scenario options key=value"),
) -> None:
    """The main job: record the default scenario qr_floor, replay it, write the .rrd.

    Example: agvviz demo --set duration_s=10
    """
    recording = _record("qr_floor", seed, set_, Path("recordings") / "qr_floor.mcap")
    _run(recording, solver, [], None)


@app.command()
def version() -> None:
    """Print the agvviz version."""
    console.print(__version__)


if __name__ == "__main__":
    app()
