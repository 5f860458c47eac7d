"""The commands that compare and report on runs and recordings: ``diff`` (two runs), ``sweep``
(a grid of settings, ranked), ``budget`` (the error budget), ``audit`` (map and calibration) and
``export`` (trajectories for other tools); each calls its library function
(:mod:`agvviz.app.diff`, :mod:`agvviz.app.sweep`, :mod:`agvviz.app.budget`,
:mod:`agvviz.app.audit`, :mod:`agvviz.app.export`) and prints its result.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from agvviz.cli.common import console, err_console, error_line, fail, handle_errors, progress_bar, stop_progress
from agvviz.cli import options
from agvviz.cli.record_run import error_budget_with_progress
from agvviz.errors import EXIT_BAD_INPUT, EXIT_OUTPUT
from agvviz.recording import outputs
from agvviz.settings import RunSettings, apply_overrides


@handle_errors
def diff(
    a: Path = typer.Argument(..., metavar="A", help="run A .rrd (the reference), or a setting of a sweep .rrd: "
                             "sweep.rrd#LABEL or sweep.rrd#NAME=VALUE"),
    b: Path = typer.Argument(..., metavar="B", help="run B .rrd (compared with A), or sweep.rrd#LABEL"),
    out: Optional[Path] = typer.Option(None, "--out", help="write the overlay .rrd (both runs on one clock) here"),
    fail_if: List[str] = typer.Option(
        [], "--fail-if", metavar="CONDITION",
        help="exit 1 when this condition holds, e.g. \"B.position_rmse_mm > 1.05*A.position_rmse_mm\" or "
        "\"B.suspects > A.suspects\" (repeatable: exit 1 when any holds; metrics of A and B — the table's "
        "metrics and each run's suspect counts suspects, suspects_pct, suspect_stretches, suspects.<cause> — "
        "numbers, + - * /, comparisons, and/or, parentheses)",
    ),
    junit_xml: Optional[Path] = typer.Option(None, "--junit-xml", metavar="FILE", help=options.JUNIT_XML_HELP),
    align: str = typer.Option("none", "--align", help="APE alignment: none | se3 | se2 | yaw"),
    rpe_delta: int = typer.Option(1, "--rpe-delta", help="RPE pair distance in frames"),
    time_offset: bool = typer.Option(False, "--time-offset", help="also estimate each run's time offset to truth"),
    images: bool = typer.Option(True, "--images/--no-images", help="copy A's camera images into the overlay"),
    seed: int = typer.Option(0, "--seed", help="bootstrap seed"),
    all_metrics: bool = typer.Option(False, "--all", help="print every metric (default: the main ones)"),
) -> None:
    """Compare run B with run A: a verdict first, then the metrics, B − A, a paired test and a confidence interval.

    Frames are matched by time; error metrics are over the frames both runs solved.
    Exit codes: 0 fine, 1 a --fail-if condition holds, 2 bad input (or a condition on a metric without a value), 3 the overlay or --junit-xml could not be written (never over A or B).

    Example: agvviz diff runs/lm.rrd runs/p4p.rrd --out runs/diff.rrd --fail-if "B.position_rmse_mm > 1.05*A.position_rmse_mm"
    """
    from agvviz.app.diff import diff as diff_runs, diff_table, diff_table_title, diff_verdict

    outcome = diff_runs(
        a, b, overlay_path=out, fail_if=fail_if, junit_path=junit_xml, align=align, rpe_delta=rpe_delta,
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
    if outcome.junit_path is not None:
        console.print(f"JUnit verdict written: [bold]{escape(str(outcome.junit_path))}[/]")
    for gate in outcome.gates:
        if gate.holds:
            err_console.print(f"[bold red]--fail-if holds:[/] {escape(gate.shown)}")
        else:
            console.print(f"--fail-if does not hold: {escape(gate.shown)}")
    if outcome.failed:
        raise typer.Exit(code=1)


@handle_errors
def sweep(
    recordings: List[Path] = typer.Argument(..., metavar="RECORDING", help="recordings (.mcap or rosbag2 folders)"),
    set_: List[str] = typer.Option(
        [], "--set", metavar="KEY=V1,V2", help="setting=value1,value2,... (repeatable); the sweep runs every combination",
    ),
    jobs: Optional[int] = typer.Option(None, "--jobs", help="processes of the local pool that detects and solves "
                                       "(default: number of CPUs)"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="address of an existing Dask cluster's "
                                            "scheduler (tcp://host:8786) to run on instead of the local pool"),
    out_dir: Optional[Path] = typer.Option(None, "--out-dir", help="default runs/sweep-<recording>; with several "
                                           "recordings one folder per recording under it (default runs/sweep)"),
    rank_by: str = typer.Option("position_rmse_mm", "--rank-by", help="metric to rank by (lower is better, "
                                "except solved / solved_pct)"),
    align: str = typer.Option("none", "--align", help="APE alignment: none | se3 | se2 | yaw"),
    images: bool = typer.Option(True, "--images/--no-images", help="the camera frames in the sweep .rrd (once)"),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help=options.CACHE_DIR_HELP),
    keep_runs: bool = typer.Option(False, "--keep-runs", help="also write each setting's self-contained run "
                                   ".rrd (<recording>-<setting>.rrd; each holds every frame again)"),
) -> None:
    """Replay each RECORDING under every combination of the --set values; rank each recording's runs.

    Each recording is detected once per detection settings; every setting then only solves.
    Writes sweep.rrd (the frames once, each setting's layers under settings/<key>/, the ranking
    and a layout that overlays the settings), ranking.csv and ranking.md into --out-dir (with
    several recordings, into --out-dir/<recording name>/); --keep-runs adds one run .rrd per
    setting. `agvviz diff sweep.rrd#lm sweep.rrd#ippe` compares two settings. A setting that fails is reported and
    the others go on. Names are the run settings of `agvviz run --help` (lm.max_iters is accepted
    for lm_max_iterations). Runs on a pool of --jobs processes, or on an existing Dask cluster
    with --scheduler (needs pip install 'agvviz\\[distributed]').

    Example: agvviz sweep recordings/qr_floor.mcap --set solver=p4p,lm,ippe --set lm_max_iterations=3,10
    """
    if scheduler is None:  # `agvviz sweep` started it already (agvviz.cli.early); main(argv) in process not
        from agvviz.app.cluster import start_fork_server

        start_fork_server()
    from agvviz.app.sweep import grid_settings, parse_grid, ranking_rows
    from agvviz.app.sweep import sweep as sweep_runs

    if jobs is not None and jobs < 1:
        fail(f"--jobs must be ≥ 1 (or left out for one per CPU), got {jobs}")
    grid = parse_grid(set_)
    n_runs = len(grid_settings(grid)) * len(recordings)
    what = f"{n_runs} runs" if len(recordings) > 1 else f"{n_runs} settings"
    # The bar appears once the runs start (as `run`'s): an input refused first prints its line only.
    progress = progress_bar()
    task = progress.add_task(f"sweeping {what}", total=None, rate="starting")

    def on_total(frames: int) -> None:
        progress.start()
        progress.update(task, total=frames or None)

    def on_progress(frames_done: int, runs_done: int) -> None:
        progress.start()
        progress.update(task, completed=frames_done, rate=f"{runs_done}/{n_runs} done")

    try:
        outcome = sweep_runs(
            recordings[0] if len(recordings) == 1 else recordings, grid, out_dir=out_dir, jobs=jobs,
            rank_by=rank_by, align=align, images=images, progress=on_progress, on_total=on_total,
            scheduler=scheduler, cache_dir=cache_dir, keep_runs=keep_runs,
        )
    finally:
        stop_progress(progress)
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
        console.print(f"written in [bold]{escape(str(result.out_dir))}[/]: "
                      + (f"[bold]{escape(result.overlay_path.name)}[/] (open it with: agvviz view "
                         f"{escape(str(result.overlay_path))}), " if result.overlay_path else "")
                      + f"{result.csv_path.name}, {result.markdown_path.name}")
    console.print(f"sweep took {outcome.wall_time_s:.1f} s")
    if not any(entry.ok for entry in outcome.entries):  # nothing to rank: say so in the exit code
        all_output = all(entry.error.startswith("OutputError") for entry in outcome.entries)
        error_line("every setting failed; see the messages above")
        raise typer.Exit(code=EXIT_OUTPUT if all_output else EXIT_BAD_INPUT)


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
        fail(f"--out must end in .rrd, got {out}")
    outputs.prepare_output(out, inputs=[recording])  # fail before the work, not after
    result = error_budget_with_progress(recording, settings, work_dir, jobs=1, cache_dir=False)
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


@handle_errors
def audit(
    recording: Path = typer.Argument(..., metavar="RECORDING", help="recording: an .mcap file or a rosbag2 directory"),
    set_: List[str] = typer.Option([], "--set", metavar="KEY=VALUE", help="audit setting (agvviz/evaluation/audit/problem.py AuditSettings: "
                                   "k_sigma, min_position_m, sigma_px, map_sigma_m, …) or run setting (repeatable)"),
    out: Optional[Path] = typer.Option(None, "--out", help="output .rrd (default: runs/<recording>-audit.rrd); the corrected "
                                       "map <out>-markers.yaml and extrinsic <out>-extrinsic.txt are written beside it"),
    markers: Optional[Path] = typer.Option(None, "--markers", help=options.MARKERS_HELP),
    calibration: List[str] = typer.Option([], "--calibration", metavar="CAM=FILE", help=options.CALIBRATION_HELP),
    extrinsic: List[str] = typer.Option([], "--extrinsic", metavar="CAM=POSE", help=options.EXTRINSIC_HELP),
    correct: str = typer.Option("flagged", "--correct", help="markers moved in the corrected map: flagged or all (estimated)"),
    jobs: Optional[int] = typer.Option(None, "--jobs", help=options.JOBS_HELP),
    cache: bool = typer.Option(True, "--cache/--no-cache", help=options.CACHE_HELP),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help=options.CACHE_DIR_HELP),
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
        fail(f"--correct must be flagged or all, got {correct!r}")
    options.check_detect_jobs(jobs)
    audit_pairs, run_pairs = audit_lib.split_settings(list(set_))
    from agvviz.settings import field_types

    for pair in run_pairs:
        key = pair.partition("=")[0].strip()
        if key and key not in field_types(RunSettings):
            fail(f"unknown setting {key!r}; audit settings: {', '.join(sorted(audit_lib.audit_setting_names()))}; "
                 f"run settings: {', '.join(sorted(field_types(RunSettings)))}")
    require_recording_path(recording)  # one line, before a progress bar is drawn
    settings = apply_overrides(AuditSettings(), audit_pairs)
    run_settings = apply_overrides(RunSettings(), run_pairs)
    if out is not None and out.suffix != ".rrd":
        fail(f"--out must end in .rrd, got {out}")
    paths = audit_lib.default_paths(recording, out)
    inputs = [recording] + ([markers] if markers else [])
    for path in paths.values():  # fail before the work, not after
        outputs.prepare_output(path, inputs=inputs)
    side = options.side_inputs(markers, list(calibration), list(extrinsic), run_settings.body_frame)
    with progress_bar() as progress:
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


@handle_errors
def export(
    run_file: Path = typer.Argument(..., metavar="RUN", help="run .rrd, or a setting of a sweep .rrd: sweep.rrd#LABEL"),
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
