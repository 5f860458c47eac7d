"""Library API behind ``agvviz sweep``: returns values, prints nothing.

:func:`sweep` replays one or several recordings under the cross product of setting values
(:func:`parse_grid`, :func:`grid_settings`) on a local pool or a Dask cluster
(:mod:`agvviz.app.cluster`; each recording detected once per detection settings, by its first
setting's run), ranks each recording's runs (:func:`ranking_rows`), and writes per recording one
sweep ``.rrd`` and the ranking as CSV and markdown (issue 27). The sweep ``.rrd``
(:func:`agvviz.viz.overlay.write_overlay` with ``layers``) holds the frames and the static world once, each setting's layers under
``settings/<key>/`` (its layers-only run, copied as chunks), the ranking with p-values and the
verdict (:func:`agvviz.app.sweep_report.ranking_markdown`) and a layout that overlays the
settings; ``FILE#LABEL`` reads one setting back. Self-contained per-setting ``.rrd`` runs are
written only with ``keep_runs``.
"""

from __future__ import annotations

import csv
import io
import itertools
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from agvviz.recording import outputs
from agvviz.recording.source import open_recording
from agvviz.evaluation import statistics
from agvviz.evaluation.comparison import QUANTITIES, RunSeries, match_frames, metric_names, quantity_values, run_metrics
from agvviz.evaluation.trajectory import ALIGNMENTS, EvaluationError
from agvviz.settings import RunSettings, SettingsError, apply_overrides, field_types
from agvviz.app.diff import CompareError, format_number, format_p
from agvviz.app import run_series
from agvviz.app.sweep_report import HIGHER_IS_BETTER, ranking_markdown
from agvviz.replay.run import recording_images
from agvviz.viz import paths
from agvviz.viz.overlay import OverlayRun, write_overlay
from agvviz.viz.readback import SETTING_SEPARATOR, RrdContents, RrdReadError, read_rrd

#: The sweep ``.rrd`` of a recording, in its folder.
SWEEP_FILE = "sweep.rrd"
#: A setting's layers-only run waits in the recording's folder under this name (hidden) until it
#: is copied into the sweep ``.rrd``; removed then.
LAYERS_NAME = ".{stem}-{label}.layers.rrd"

#: Spellings of run settings accepted by ``sweep --set`` besides the setting names themselves.
SETTING_ALIASES = {"lm.max_iters": "lm_max_iterations", "lm.max_iterations": "lm_max_iterations"}


# -- sweep -----------------------------------------------------------------------------------
def parse_grid(pairs: list[str] | tuple[str, ...]) -> dict[str, list[str]]:
    """``["solver=p4p,lm", "lm_max_iterations=3,10"]`` → ``{"solver": ["p4p", "lm"], ...}``.

    Names are run settings (``agvviz run --help``); :data:`SETTING_ALIASES` are accepted too.
    Values are split at commas, duplicates dropped (order kept).
    """
    names = field_types(RunSettings)
    grid: dict[str, list[str]] = {}
    for pair in pairs:
        key, sep, values = pair.partition("=")
        key = SETTING_ALIASES.get(key.strip(), key.strip())
        if not sep or not key:
            raise CompareError(f"--set {pair!r}: expected key=value1,value2,...")
        if key not in names:
            raise CompareError(f"unknown setting {key!r}; valid settings: {', '.join(sorted(names))}")
        if key in grid:
            raise CompareError(f"setting {key!r} given twice; list all its values once: {key}=a,b,c")
        items = [v.strip() for v in values.split(",")]
        if any(not v for v in items):
            raise CompareError(f"--set {pair!r}: empty value in the list")
        grid[key] = list(dict.fromkeys(items))
    return grid


def grid_settings(grid: dict[str, list[str]], base: RunSettings = RunSettings()) -> list[RunSettings]:
    """Every combination of ``grid`` applied to ``base``, validated, in grid order.

    Raises
    ------
    CompareError
        A value is not valid for its setting, or two combinations give the same settings.
    """
    combos = itertools.product(*[[f"{k}={v}" for v in values] for k, values in grid.items()])
    result = []
    for combo in combos:
        try:
            result.append(apply_overrides(base, list(combo)))
        except SettingsError as exc:
            raise CompareError(f"sweep setting {' '.join(combo)}: {exc}") from None
    labels = [s.label() for s in result]
    duplicates = sorted({label for label in labels if labels.count(label) > 1})
    if duplicates:
        raise CompareError(f"the grid gives the same settings more than once: {', '.join(duplicates)}")
    return result


@dataclass
class SweepEntry:
    """One setting of a sweep over one recording, and how it went."""

    label: str
    settings: RunSettings
    out_path: Path  # where to read the run: ``<sweep.rrd>#<label>``, or its own .rrd (keep_runs)
    error: str | None = None  # why the setting failed, None when it ran
    metrics: dict = field(default_factory=dict)
    timing: dict = field(default_factory=dict)  # wall-clock figures (not in the .rrd)
    p_vs_best: float | None = None  # Wilcoxon p of the ranking quantity vs the best setting
    rank: int | None = None  # 1 = best among its recording's settings; None when failed
    recording: Path | None = None  # the recording replayed
    run_path: Path | None = None  # the .rrd its run writes: its kept run or its layers-only run
    key: str = ""  # its subtree in the sweep .rrd: settings/<key>
    run: RrdContents | None = None  # its run, opened once as it ended (read back, drawn, copied)

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class RecordingSweep:
    """One recording of a sweep: its ranked entries (best first, failed last) and its files;
    ``overlay_path`` is its sweep ``.rrd`` (None when no setting ran)."""

    recording: Path
    out_dir: Path
    entries: list[SweepEntry]
    overlay_path: Path | None
    csv_path: Path
    markdown_path: Path


@dataclass
class SweepOutcome:
    """Ranked entries and the files written.

    ``entries`` holds every recording's entries, each recording's ranked (best first, failed
    last), recordings in the order given; ``overlay_path``, ``csv_path`` and ``markdown_path``
    are the first recording's (the only one's in a sweep of one recording); ``recordings`` has
    each recording's own.
    """

    entries: list[SweepEntry]
    rank_by: str
    overlay_path: Path | None
    csv_path: Path
    markdown_path: Path
    wall_time_s: float
    recordings: list[RecordingSweep] = field(default_factory=list)


def _rank_quantity(rank_by: str) -> str:
    """The per-frame quantity behind a metric (position for the counts)."""
    matches = [q.key for q in QUANTITIES if rank_by.startswith(f"{q.key}_") and rank_by.endswith(f"_{q.unit}")]
    return matches[0] if matches else "position"


def sweep_out_dirs(recordings: Sequence[Path], out_dir: str | os.PathLike | None) -> list[Path]:
    """Where each recording's runs go: ``out_dir`` (default ``runs/sweep-<stem>``) for one
    recording; ``<out_dir>/<stem>`` (default ``runs/sweep/<stem>``) for several.

    Raises
    ------
    CompareError
        A recording is given twice, or two recordings have the same file stem.
    """
    if len(recordings) == 1:
        return [Path(out_dir) if out_dir is not None else Path("runs") / f"sweep-{recordings[0].stem}"]
    seen: dict[str, Path] = {}
    for recording in recordings:
        if recording.stem in seen:
            same = outputs.same_file(recording, seen[recording.stem])
            raise CompareError(
                f"recording {recording} is given twice" if same else
                f"recordings {seen[recording.stem]} and {recording} have the same name "
                f"{recording.stem!r}; their runs would share the folder {recording.stem}/: rename one"
            )
        seen[recording.stem] = recording
    root = Path(out_dir) if out_dir is not None else Path("runs") / "sweep"
    return [root / recording.stem for recording in recordings]


def _count_frames(recording: Path) -> int:
    """Frames of ``recording`` for the progress bar; 0 when it cannot be counted (a bag folder,
    a damaged file: its runs report why)."""
    from agvviz.errors import AgvvizError
    from agvviz.recording.reader import count_image_times

    if not recording.is_file():
        return 0
    try:
        return count_image_times(recording)
    except (AgvvizError, OSError, ValueError):
        return 0


def sweep(
    recording: str | os.PathLike | Sequence[str | os.PathLike],
    grid: dict[str, list[str]],
    *,
    base: RunSettings = RunSettings(),
    out_dir: str | os.PathLike | None = None,
    jobs: int | None = None,
    rank_by: str = "position_rmse_mm",
    align: str = "none",
    rpe_delta: int = 1,
    images: bool = True,
    progress: Callable[[int, int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    scheduler: str | None = None,
    cache_dir: str | os.PathLike | None = None,
    keep_runs: bool = False,
) -> SweepOutcome:
    """Replay every recording under every combination of ``grid``, locally or on a Dask cluster.

    Parameters
    ----------
    recording : path or sequence of paths
        One recording (an ``.mcap`` or a rosbag2 folder) or several.
    grid : dict
        Setting name → values (strings, as on the command line); see :func:`parse_grid`.
    base : RunSettings
        Settings the grid values are applied to.
    out_dir : path, optional
        See :func:`sweep_out_dirs`. Each recording's folder gets ``sweep.rrd`` (every setting,
        the frames once), ``ranking.csv`` and ``ranking.md``; with ``keep_runs`` also
        ``<stem>-<label>.rrd`` per setting (a self-contained run).
    jobs : int, optional
        Processes of the local pool (default: one per CPU), which detect and then solve.
    rank_by : str
        Metric to rank by (lower is better, except ``solved``/``solved_pct``).
    progress : callable, optional
        ``progress(frames_done, runs_finished)`` summed over all runs (``on_total(frames)`` is
        called first with the total).
    scheduler : str, optional
        Address of an existing Dask cluster's scheduler; None runs on a local pool.
    cache_dir : path, optional
        Detection cache folder (default: :func:`agvviz.replay.detect.cache.default_cache_dir`).
    keep_runs : bool
        Also keep each setting's self-contained run ``.rrd`` (``--keep-runs``); without it each
        setting runs layers-only into a temporary folder and lives in ``sweep.rrd`` alone.

    Each recording is detected once per distinct detection settings of the grid: the first such
    setting (its lead) detects on every core and solves in one pass, as ``agvviz run`` does, and
    the others then only solve, from the detection cache (:mod:`agvviz.app.cluster`); each run
    is read back as it ends, while the others solve. A run that fails is reported in its
    entry (``error``) and ranked last; the others go on. ``scheduler`` needs Dask (``agvviz[distributed]``).

    Raises
    ------
    RecordingError
        A recording is missing or is no recording (an ``.rrd``, a text file): the error
        ``agvviz run`` gives, before any setting starts and before anything is written.
    CompareError
        A bad grid, metric, alignment, ``jobs`` or output folder.
    """
    single = isinstance(recording, (str, os.PathLike))
    recordings = [Path(recording)] if single else [Path(r) for r in recording]
    if not recordings:
        raise CompareError("nothing to sweep: give at least one recording")
    if rank_by not in metric_names():
        raise CompareError(f"unknown metric {rank_by!r} to rank by; known: {', '.join(metric_names())}")
    if align not in ALIGNMENTS:
        raise CompareError(f"unknown alignment {align!r}; choose one of: {', '.join(ALIGNMENTS)}")
    if not grid:
        raise CompareError("nothing to sweep: give at least one --set key=value1,value2,...")
    if jobs is not None and (isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1):
        raise CompareError(f"--jobs must be a whole number ≥ 1 (or left out for one per CPU), got {jobs}")
    if jobs is not None and scheduler is not None:
        raise CompareError("--jobs sets the processes of the local pool; with --scheduler the cluster's own "
                           "workers run the sweep: give one or the other")
    settings_list = grid_settings(grid, base)
    for path in recordings:
        # What is no recording (a missing path, an .rrd, a text file) is refused here with the
        # one line `agvviz run` gives, before any setting starts or anything is written.
        open_recording(path)
    out_dirs = sweep_out_dirs(recordings, out_dir)
    from agvviz.app import cluster

    if scheduler is None:
        # The fork server that the pool is forked from imports agvviz's replay and the .rrd
        # logger (≈0.8 s): started
        # first, it does so while this process imports it.
        cluster.start_fork_server()
    else:
        from agvviz.app import dask_engine

        dask_engine.require_distributed()  # without Dask: one line, before anything is written
    per_recording = []
    for path, folder in zip(recordings, out_dirs):
        entries = []
        for index, s in enumerate(settings_list):
            kept = folder / f"{path.stem}-{s.label()}.rrd"
            run_path = kept if keep_runs else folder / LAYERS_NAME.format(stem=path.stem, label=s.label())
            out_path = kept if keep_runs else Path(f"{folder / SWEEP_FILE}{SETTING_SEPARATOR}{s.label()}")
            entries.append(SweepEntry(s.label(), s, out_path, recording=path, run_path=run_path,
                                      key=_entity_key(index, s.label())))
        targets = [e.run_path for e in entries if keep_runs]
        for target in targets + [folder / n for n in (SWEEP_FILE, "ranking.csv", "ranking.md")]:
            outputs.check_not_input(target, recordings, option="the sweep output")
        per_recording.append(entries)
    t_start = time.perf_counter()
    all_entries = [e for entries in per_recording for e in entries]
    series: dict[int, RunSeries] = {}  # index in all_entries → its run, read back as it ends
    tasks = [cluster.RunTask(e.recording, e.settings, e.run_path, images=keep_runs, scratch=not keep_runs)
             for e in all_entries]
    # Every core: the leads detect on the pool (a sweep of one setting too); processes that
    # have nothing left to do end early (cluster.LocalEngine).
    workers = jobs or os.cpu_count() or 1
    cache = Path(cache_dir) if cache_dir is not None else None

    def prepare_dirs() -> None:
        # Once the scheduler answered (an unreachable one leaves nothing behind), or once the
        # local pool's reaper runs (it removes the temporaries of a killed sweep).
        for folder in out_dirs:
            outputs.prepare_dir(folder, option="--out-dir")

    # Frames for the progress bar are counted while the runs start (a read of each file).
    # What the threads will run is imported first, here: two threads importing one module at
    # once can deadlock on its import lock.
    import agvviz.recording.reader  # noqa: F401

    if scheduler is None:
        import agvviz.app.run  # noqa: F401
    frames: dict[Path, int] = {}
    counter = None
    if progress is not None or on_total is not None:
        counter = threading.Thread(
            target=lambda: frames.update({path: _count_frames(path) for path in recordings}),
            name="agvviz count frames", daemon=True,
        )
        counter.start()
    if scheduler is None:
        engine_context = cluster.local_engine(tasks, jobs=workers, cache_dir=cache, before_start=prepare_dirs,
                                              temp_folders=[folder.resolve() for folder in out_dirs])
    else:
        engine_context = dask_engine.connect(scheduler, tasks, cache, before_start=prepare_dirs)
    with engine_context as engine:

        def counted() -> dict[Path, int]:  # once the leads run
            if counter is not None:
                counter.join()
                if on_total is not None:
                    on_total(cluster.progress_total(tasks, frames))
            return frames

        cluster.run_sweep_tasks(
            engine, tasks, frames=counted, progress=progress,
            on_result=lambda i, result: _read_back(all_entries[i], result, series, i, align, rpe_delta),
        )
    try:
        done, first = [], 0
        for path, folder, entries in zip(recordings, out_dirs, per_recording):
            own = {i - first: run for i, run in series.items() if first <= i < first + len(entries)}
            done.append(_finish_recording(path, folder, entries, own, rank_by, align, rpe_delta, images, cache))
            first += len(entries)
    finally:
        if not keep_runs:
            for entry in all_entries:
                entry.run_path.unlink(missing_ok=True)
    return SweepOutcome(
        entries=[e for r in done for e in r.entries], rank_by=rank_by, overlay_path=done[0].overlay_path,
        csv_path=done[0].csv_path, markdown_path=done[0].markdown_path,
        wall_time_s=time.perf_counter() - t_start, recordings=done,
    )


def _read_back(
    entry: SweepEntry, result, series: dict[int, RunSeries], index: int, align: str, rpe_delta: int,
) -> None:
    """A setting's run has ended (``result``, a :class:`agvviz.app.cluster.TaskResult`): its
    timing or error, and, when it ran, its run read back into ``series[index]`` and its metrics,
    while the other settings still solve."""
    entry.timing, entry.error = result.timing, result.error
    if not entry.ok:
        return
    try:
        entry.run = read_rrd(entry.run_path)
        series[index] = run_series.load_run(entry.run)
        entry.metrics = run_metrics(series[index], align=align, rpe_delta=rpe_delta)
    except (RrdReadError, EvaluationError) as exc:
        series.pop(index, None)
        entry.error = f"{type(exc).__name__}: {exc}"


def _finish_recording(
    recording: Path, out_dir: Path, entries: list[SweepEntry], series: dict[int, RunSeries], rank_by: str,
    align: str, rpe_delta: int, images: bool, cache_dir: Path | None = None,
) -> RecordingSweep:
    """Rank one recording's runs (``series``: each that ran, read back by its index in
    ``entries``), write its tables and its sweep ``.rrd``."""
    _rank(entries, series, rank_by, align, rpe_delta)
    ranked = sorted(entries, key=lambda e: (e.rank is None, e.rank or 0))
    csv_path, markdown_path = _write_tables(out_dir, ranked, rank_by)
    overlay_path = None
    ok = [e for e in ranked if e.ok]
    if ok:
        overlay_path = _write_sweep_file(out_dir / SWEEP_FILE, recording, ranked, series, entries, rank_by, images,
                                         cache_dir)
    return RecordingSweep(recording, out_dir, ranked, overlay_path, csv_path, markdown_path)


def _rank(entries: list[SweepEntry], series: dict[int, RunSeries], rank_by: str, align: str, rpe_delta: int) -> None:
    sign = -1.0 if rank_by in HIGHER_IS_BETTER else 1.0
    ok = [i for i, e in enumerate(entries) if e.ok]

    def key(i: int):
        value = entries[i].metrics.get(rank_by)
        return (value is None, sign * value if value is not None else 0.0, entries[i].label)

    order = sorted(ok, key=key)
    for rank, i in enumerate(order, start=1):
        entries[i].rank = rank
    if not order:
        return
    best = order[0]
    quantity = _rank_quantity(rank_by)
    for i in order[1:]:
        ia, ib = match_frames(series[best].time_ns, series[i].time_ns)
        both = series[best].solved[ia] & series[i].solved[ib]
        x = quantity_values(series[best], ia[both], align, rpe_delta)[quantity][ia[both]]
        y = quantity_values(series[i], ib[both], align, rpe_delta)[quantity][ib[both]]
        finite = np.isfinite(x) & np.isfinite(y)
        entries[i].p_vs_best = statistics.wilcoxon_paired(x[finite], y[finite]) if np.any(finite) else None


#: Columns of the ranking tables: (header, metric or attribute).
TABLE_METRICS = (
    "solved", "frames", "position_rmse_mm", "position_median_mm", "position_p95_mm",
    "heading_rmse_deg", "pitch_rmse_deg", "roll_rmse_deg", "reproj_median_px",
    "ape_trans_rmse_mm", "rpe_trans_rmse_mm", "rpe_rot_rmse_deg",
)


def ranking_rows(entries: list[SweepEntry], rank_by: str) -> tuple[list[str], list[list[str]]]:
    """Header and rows (strings) of the ranking table, as written to CSV and markdown."""
    metrics = list(dict.fromkeys([rank_by, *TABLE_METRICS]))
    header = ["rank", "setting", *metrics, "p_vs_best", "time_per_frame_ms", "status", "file"]
    rows = []
    for e in entries:
        rows.append([
            str(e.rank) if e.rank else "—",
            e.label,
            *[format_number(e.metrics.get(m)) for m in metrics],
            format_p(e.p_vs_best),
            format_number(e.timing.get("time_per_frame_ms")),
            "ok" if e.ok else f"failed: {e.error}",
            e.out_path.name if e.ok and e.out_path is not None else "",
        ])
    return header, rows


def _atomic_write(path: Path, text: str) -> None:
    outputs.atomic_write_text(path, text)


def _write_tables(out_dir: Path, entries: list[SweepEntry], rank_by: str) -> tuple[Path, Path]:
    header, rows = ranking_rows(entries, rank_by)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    csv_path = out_dir / "ranking.csv"
    _atomic_write(csv_path, buffer.getvalue())
    direction = "higher" if rank_by in HIGHER_IS_BETTER else "lower"
    lines = [
        f"Ranked by `{rank_by}` ({direction} is better); p_vs_best: Wilcoxon signed-rank of the "
        "per-frame errors against the best setting, on the frames both solved.",
        "",
        "| " + " | ".join(header) + " |",
        "| " + " | ".join("---" for _ in header) + " |",
    ]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]
    markdown_path = out_dir / "ranking.md"
    _atomic_write(markdown_path, "\n".join(lines) + "\n")
    return csv_path, markdown_path


def _entity_key(index: int, label: str) -> str:
    return f"s{index + 1}_" + re.sub(r"[^A-Za-z0-9_-]+", "_", label)


def _reprojected_reader(run: RrdContents, cams: list[str], to_first: dict[int, int]):
    """A function reading a setting's reprojected corners (its ``run``), its frames mapped
    onto the sweep's clock (``to_first``): called by the writer when it draws that setting, so
    one setting's corners are in memory at a time."""
    def read() -> dict[str, dict[int, np.ndarray]]:
        return {
            cam: {to_first[f]: pts for f, pts in per.items() if f in to_first}
            for cam, per in run_series.reprojected_corners(run, cams).items()
        }
    return read


def _write_sweep_file(
    out: Path, recording: Path, ranked: list[SweepEntry], series: dict[int, RunSeries],
    entries: list[SweepEntry], rank_by: str, images: bool, cache_dir: Path | None = None,
) -> Path:
    """The sweep ``.rrd``: the settings that ran drawn together on the best one's clock, each
    one's layers under ``settings/<key>/``, the frames once (from the recording, or copied from
    the best setting's kept run), the ranking document and the index. ``cache_dir``: the runs'
    cache folder (None: the default), whose scan of the recording says whether it is intact."""
    index_of = {id(e): i for i, e in enumerate(entries)}
    ok = [e for e in ranked if e.ok]
    first = series[index_of[id(ok[0])]]
    first_contents = ok[0].run
    cams = run_series.cameras_of(first_contents) if images else []
    frames = None
    if cams and not paths.camera_images(first_contents.entity_paths):  # layers-only runs: frames from the recording
        frames = (
            recording_images(recording, first.manifest.get("roles", {}), first.manifest.get("time_source", "log"),
                             cache_dir),
            run_series.image_clocks(first_contents),
        )
    runs = []
    for entry in ok:
        s = series[index_of[id(entry)]]
        ia, ib = match_frames(first.time_ns, s.time_ns)
        to_first = {int(s.frames[j]): int(first.frames[i]) for i, j in zip(ia, ib)}
        runs.append(OverlayRun(
            entry.key, f"#{entry.rank} {entry.label}",
            first.frames[ia], first.time_ns[ia], s.T_est[ib], run_series.overlay_errors(s, ib),
            _reprojected_reader(entry.run, cams, to_first) if images else {},
            T_truth=None if s.T_truth is None else s.T_truth[ib], short_label=f"#{entry.rank}",
        ))
    index = [
        {"key": e.key, "label": e.label, "rank": e.rank, "settings": series[index_of[id(e)]].settings}
        for e in ok
    ]
    return write_overlay(
        out,
        recording_name=f"sweep {recording.stem}",
        runs=runs,
        truth=run_series.overlay_truth(first),
        source=ok[0].run,
        cam_names=cams,
        fixed_cams=run_series.fixed_cameras_of(first_contents) & set(cams),
        report_markdown=ranking_markdown(recording.name, ranked, rank_by),
        inputs=(recording, *[e.run_path for e in ok]),
        layers={e.key: e.run for e in ok},
        index=index,
        frames=frames,
    )
