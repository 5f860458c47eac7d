"""Render agvviz's views in the real Rerun viewer, headless, into ``docs/images/``.

One *group* per thing a user opens: the four scenarios' default runs (seed 0, default settings;
``auv_under_ice`` with ``correction=cnoem``, its default recording holding corner observations
only; the study with 100 trials a cell), a ``diff`` of two solvers on one recording, a
``sweep`` over four solvers, an ``audit`` of a map with two markers laid wrong on purpose, and an
error ``budget``. Each group builds its files once in the work folder (kept with ``--work``;
small recordings, so a group takes a few minutes), then screenshots them at chosen times and,
where a picture is of a tab the layout does not open on, with that tab shown. The docs show
these pictures; rerun this whenever a layout changes, and look at every image.

    python docs/make_pictures.py                              # every group → docs/images/
    python docs/make_pictures.py --only diff,sweep --work /tmp/w    # some groups; keep the files
    python docs/make_pictures.py --list                       # the groups and their pictures
    python docs/make_pictures.py --rrd run.rrd --at 50 --out-dir /tmp/pics   # any file, frame 50
    python docs/make_pictures.py --rrd run.rrd --timeline elapsed --at 6.0 --out-dir /tmp/pics  # at 6 s
    python docs/make_pictures.py --rrd run.rrd --at 6.0 --timeline elapsed --tab "summary (JSON)" --out-dir /tmp/pics

A tab is picked by name (whole, or the start of one name: ``--tab "paper figures"``): the
viewer's layout of the file is read back (``ViewerClient.get_blueprint``), the tab and every tab
around it made active (:func:`agvviz.viz.blueprints.with_active_tab`) and the layout sent back
(``set_blueprint``). A bad name lists the layout's tabs.

The viewer runs headless (``rerun --headless``; it needs a Vulkan driver, e.g. Debian's
``mesa-vulkan-drivers``) and is driven through ``rerun.experimental.ViewerClient``: open the
file, pick the tab, put the time cursor, screenshot. A screenshot is retaken until two in a row
are equal, since images decode after the first paint. The viewer dies with this script.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent
#: This checkout's agvviz, for this script and the commands it runs (not another installed copy).
REPO = DOCS.parent
sys.path.insert(0, str(REPO))
WINDOW_SIZE = "1600x1000"
#: A short qr_floor at a small image size (as the tests record): the diff, sweep and audit.
SMALL_QR = ("duration_s=6", "width_px=640", "height_px=512", "focal_px=500.0", "supersample=2")
#: The audit's world: a code 5 cm off and a code turned 90° (tests/test_audit.py's seed 3 track sees both).
AUDIT_INJECT = "marker:Q034:dx_m=0.05;marker:Q015:yaw_deg=90"
SWEEP_SOLVERS = "lm,ippe,p4p,sqpnp"


@dataclass(frozen=True)
class Shot:
    """One picture of a group's file: ``<name>.png``, the time cursor at ``at`` — a value on
    ``timeline`` (seconds on a duration timeline such as ``elapsed``, nanoseconds since the epoch
    on a timestamp one such as ``time``) or, with no timeline, a
    fraction of the layout's own timeline (0 its start, 1 its end) — and ``tab`` shown (None:
    the tab the layout opens on). ``caption``: the point the picture shows; ``doc``: the page
    that shows it (tests/test_pictures.py checks both against the docs)."""

    name: str
    at: float
    timeline: str | None = None
    tab: str | None = None
    caption: str = ""
    doc: str = "README.md"


@dataclass(frozen=True)
class Group:
    """Files a user opens: ``build(work)`` writes them (or finds them in ``work``) and returns
    their paths, in the order of ``shots``, each file's pictures."""

    name: str
    build: Callable[[Path], list[Path]]
    shots: tuple[tuple[Shot, ...], ...]


# -- building the files (agvviz's own CLI, each file once per work folder) ---------------------------
def _agvviz(*args: str) -> None:
    command = [sys.executable, "-m", "agvviz", *args]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    result = subprocess.run(command, capture_output=True, text=True, env=env)
    if result.returncode not in (0, 1):  # 1: a --fail-if verdict or a contract finding, the file is written
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")


def _sets(values) -> list[str]:
    return [a for s in values for a in ("--set", s)]


def _record(work: Path, name: str, scenario: str, sets=(), seed: int = 0) -> Path:
    path = work / f"{name}.mcap"
    if not path.exists():
        _agvviz("record", scenario, "--seed", str(seed), "--out", str(path), *_sets(sets))
    return path


def _run(work: Path, name: str, recording: Path, sets=(), *extra: str) -> Path:
    path = work / f"{name}.rrd"
    if not path.exists():
        _agvviz("run", str(recording), "--out", str(path), *_sets(sets), *extra)
    return path


def _scenario(name: str, record_sets=(), run_sets=()) -> Callable[[Path], list[Path]]:
    """A scenario's default recording (seed 0) and its run."""
    return lambda work: [_run(work, name, _record(work, name, name, record_sets), run_sets)]


def _diff(work: Path) -> list[Path]:
    recording = _record(work, "qr_small", "qr_floor", SMALL_QR)
    a = _run(work, "qr_small-lm", recording, ("solver=lm",))
    b = _run(work, "qr_small-p4p", recording, ("solver=p4p",))
    overlay = work / "diff.rrd"
    if not overlay.exists():
        _agvviz("diff", str(a), str(b), "--out", str(overlay))
    return [overlay]


def _sweep(work: Path) -> list[Path]:
    recording = _record(work, "qr_small", "qr_floor", SMALL_QR)
    out = work / "sweep"
    if not (out / "sweep.rrd").exists():
        _agvviz("sweep", str(recording), "--set", f"solver={SWEEP_SOLVERS}", "--out-dir", str(out), "--jobs", "2")
    return [out / "sweep.rrd"]


def _audit(work: Path) -> list[Path]:
    recording = _record(work, "qr_audit", "qr_floor", (*SMALL_QR, f"inject={AUDIT_INJECT}"), seed=3)
    out = work / "audit.rrd"
    if not out.exists():
        _agvviz("audit", str(recording), "--out", str(out))
    return [out]


def _budget(work: Path) -> list[Path]:
    # 3 s: a budget records the world again once per error source (twice here: budget, run --budget).
    recording = _record(work, "qr_budget", "qr_floor", ("duration_s=3", "width_px=640", "height_px=512", "focal_px=500.0"))
    out = work / "budget.rrd"
    if not out.exists():
        _agvviz("budget", str(recording), "--out", str(out))
    return [out, _run(work, "qr_budget-run", recording, (), "--budget")]


END = 1.0  # with no timeline: the cursor at the end of the file's own timeline
GROUPS = (
    Group("qr_floor", _scenario("qr_floor"), ((
        Shot("qr_floor", 10.0, "elapsed", caption="a run at 10 s: 3D view, image, this frame's solve, errors against seconds, summary table"),
        Shot("qr_floor-summary-json", 10.0, "elapsed", tab="summary (JSON)", doc="docs/run-contract.md",
             caption="the whole summary as JSON, unrounded, in a tab behind the summary table"),
    ),)),
    Group("uwb_room", _scenario("uwb_room"), ((
        Shot("uwb_room", 15.0, "elapsed", caption="15 s: the code hidden from every camera, fusion on UWB"),
    ),)),
    Group("auv_under_ice", _scenario("auv_under_ice", run_sets=("correction=cnoem",)), ((
        Shot("auv_under_ice", 40, "frame", caption="frame 40: a correction cycle"),
    ),)),
    # 100 trials a cell keep it quick (the lines and bands read the same as with the default 1000).
    Group("p4p_monte_carlo", _scenario("p4p_monte_carlo", record_sets=("trials=100",)), ((
        Shot("p4p_monte_carlo", END, caption="paper 000's figures 9–11: a line per solver with its 95 % CI against σ"),
        Shot("p4p_monte_carlo-rmse", END, tab="RMSE per solver", doc="docs/uncertainty.md",
             caption="RMSE per solver with its 95 % CI and the CRLB, one plot per cell group"),
        Shot("p4p_monte_carlo-crlb", END, tab="RMSE ÷ CRLB", doc="docs/uncertainty.md",
             caption="RMSE ÷ CRLB per solver, one plot per cell group: 1 is the bound"),
        Shot("p4p_monte_carlo-report", END, tab="report (paper vs ours", doc="docs/uncertainty.md",
             caption="the paper-vs-ours table with an agree/disagree verdict per figure"),
    ),)),
    Group("diff", _diff, ((
        Shot("diff", 0.5, doc="docs/comparing-runs.md",
             caption="lm (A) against p4p (B) on one recording: magnified errors, both runs' corners, errors and B − A, the verdict"),
    ),)),
    Group("sweep", _sweep, ((
        Shot("sweep", 0.5, doc="docs/comparing-runs.md",
             caption=f"solver={SWEEP_SOLVERS}: each setting in its colour, the ranking with p vs best in the viewer"),
        Shot("sweep-lm-steps", 0.5, tab="LM trial steps", doc="docs/comparing-runs.md",
             caption="each iterating setting's LM trial steps per frame"),
    ),)),
    Group("audit", _audit, ((
        Shot("audit", END, doc="docs/audit.md",
             caption="Q034 laid 5 cm off and Q015 turned 90°: flagged, with an arrow and a label, the whole map with ids"),
    ),)),
    Group("budget", _budget, (
        (Shot("budget", END, doc="docs/realism.md",
              caption="each source's share of the position error with its 95 % CI; negative: interaction"),),
        (Shot("budget-run", END, tab="error budget:", doc="docs/realism.md",
              caption="run --budget: the budget's whole layout in a tab of its own beside the run's"),),
    )),
)


# -- the headless viewer -----------------------------------------------------------------------------
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:
    """In the viewer's process, before exec: on Linux, ask for SIGKILL when this script dies (the viewer holds nothing to save), so a
    killed script (a timeout, Ctrl-C in a pipeline) leaves no headless viewer running."""
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def _viewer_binary() -> str:
    """The Rerun viewer's own executable. The ``rerun`` on PATH is a Python script that runs it as
    a child: stopping the script (or its parent dying) left the viewer running, so start the
    binary itself (where ``rerun_cli`` keeps it, or ``RERUN_CLI_PATH``)."""
    if path := os.environ.get("RERUN_CLI_PATH"):
        return path
    try:
        import rerun_cli
    except ImportError:
        rerun_cli = None
    if rerun_cli is not None and (binary := Path(rerun_cli.__file__).parent / "rerun").is_file():
        return str(binary)
    found = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if found is None:
        raise SystemExit("the rerun executable is not on PATH: pip install rerun-sdk")
    return found


class HeadlessViewer:
    """A headless Rerun viewer process and a client driving it (a context manager)."""

    def __init__(self, rerun_exe: str, window_size: str = WINDOW_SIZE):
        self.port = _free_port()
        self.process = subprocess.Popen(
            [rerun_exe, "--headless", "--bind", "127.0.0.1", "--port", str(self.port),
             "--window-size", window_size, "--hide-welcome-screen"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=_die_with_parent,
        )
        try:
            self.client = self._connect()
        except BaseException:
            self.__exit__()
            raise

    def _connect(self, timeout_s: float = 30.0):
        from rerun.experimental import ViewerClient

        deadline = time.monotonic() + timeout_s
        while True:
            if self.process.poll() is not None:
                raise SystemExit(f"the Rerun viewer exited: {self.process.stderr.read().decode()[-500:]}")
            try:
                client = ViewerClient.connect(f"rerun+http://127.0.0.1:{self.port}/proxy")
                client.get_state()
                return client
            except Exception as exc:  # noqa: BLE001 — not listening yet
                if time.monotonic() > deadline:
                    raise SystemExit(f"cannot reach the headless Rerun viewer: {exc}") from None
                time.sleep(0.2)

    def _open(self, rrd: Path, timeout_s: float = 120.0):
        """Open ``rrd`` and wait until it has loaded; its recording's state."""
        result = self.client.open(str(rrd.resolve()))
        deadline = time.monotonic() + timeout_s
        while (state := self.client.get_state()).loading:
            if time.monotonic() > deadline:
                raise SystemExit(f"the viewer is still loading {rrd} after {timeout_s:g} s")
            time.sleep(0.5)
        store_id = result.store_ids[0] if result.store_ids else state.active_recording
        return next(r for r in state.recordings if r.store_id == store_id)

    def screenshots(self, rrd: Path, shots: list[Shot]) -> None:
        """Open ``rrd`` and save one screenshot per shot into each shot's path (``shot.name`` is a path here)."""
        from agvviz.errors import InputError
        from agvviz.viz.blueprints import with_active_tab

        recording = self._open(rrd)
        layout = self.client.get_blueprint(store_id=recording.store_id).blueprint
        own_timeline = layout.get("/time_panel", {}).get("TimePanelBlueprint", {}).get("timeline") or recording.current_timeline
        timelines = {t.name: t for t in recording.timelines}
        picked = None
        for shot in shots:
            if shot.tab != picked:  # the file's own layout, with the shot's tab shown
                try:
                    tabbed = layout if shot.tab is None else with_active_tab(layout, shot.tab)
                except InputError as exc:
                    raise SystemExit(f"{rrd}: {exc}") from None
                self.client.set_blueprint(tabbed, store_id=recording.store_id)
                picked = shot.tab
            name = shot.timeline or own_timeline
            if name not in timelines:
                raise SystemExit(f"{rrd} has no timeline {name!r}; its timelines: {', '.join(timelines)}")
            timeline = timelines[name]
            value = shot.at
            if shot.timeline is None:  # a fraction of the timeline's range, in its own units
                if timeline.start is None or timeline.end is None:
                    raise SystemExit(f"{rrd}: its timeline {name!r} holds no data")
                value = timeline.start + shot.at * (timeline.end - timeline.start)
                if timeline.time_type == "duration":
                    value = value / 1e9
            if timeline.time_type == "duration":  # seconds
                self.client.set_time(name, duration=float(value), play_state="paused")
            elif timeline.time_type == "timestamp":
                self.client.set_time(name, timestamp=np.datetime64(int(value), "ns"), play_state="paused")
            else:
                self.client.set_time(name, sequence=int(round(value)), play_state="paused")
            self._settled_screenshot(Path(shot.name))
            print(f"  {shot.name}" + (f"  [tab {shot.tab}]" if shot.tab else ""))

    def _settled_screenshot(self, out: Path) -> None:
        import cv2

        previous = None
        for _ in range(6):  # until two shots in a row are equal (images decode late)
            time.sleep(0.5)
            self.client.save_screenshot(str(out.resolve()))
            image = cv2.imread(str(out))
            if previous is not None and image is not None and np.array_equal(image, previous):
                break
            previous = image
        if image is not None:  # the same pixels, compressed harder (about 40 % smaller than the viewer's PNG)
            cv2.imwrite(str(out), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])

    def __enter__(self) -> "HeadlessViewer":
        return self

    def __exit__(self, *exc) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()


def _retimed(shots, at: list[float] | None, timeline: str) -> list[Shot]:
    """``--at`` given: each shot at each of those times on ``timeline`` instead (named ``<name>-<time>``)."""
    if at is None:
        return list(shots)
    return [Shot(f"{s.name}-{v:g}", v, timeline, s.tab, s.caption, s.doc) for s in shots for v in at]


def _slug(text: str) -> str:
    """``"summary (JSON)"`` → ``summary-json``."""
    return re.sub(r"[^0-9a-z]+", "-", text.lower()).strip("-")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-dir", type=Path, default=DOCS / "images", help="where the PNGs go")
    parser.add_argument("--work", type=Path, default=None, help="folder for recordings and runs (kept; a file there is reused)")
    parser.add_argument("--only", default=None, help=f"comma-separated groups: {', '.join(g.name for g in GROUPS)}")
    parser.add_argument("--list", action="store_true", help="print the groups, their pictures and captions, and stop")
    parser.add_argument("--at", default=None, help="comma-separated times on --timeline, instead of each picture's")
    parser.add_argument("--timeline", default="frame", help="the timeline of --at (seconds on elapsed) [default: frame]")
    parser.add_argument("--tab", default=None, help="with --rrd: show this tab of the file's layout (its name or its start)")
    parser.add_argument("--rrd", type=Path, default=None,
                        help="screenshot this file instead of the groups (without --at: at the end of its own timeline)")
    args = parser.parse_args()

    if args.list:
        for group in GROUPS:
            print(group.name)
            for shot in (s for shots in group.shots for s in shots):
                print(f"  {shot.name}.png ({shot.doc}){f'  [tab {shot.tab}]' if shot.tab else ''}: {shot.caption}")
        return
    groups = {g.name: g for g in GROUPS}
    wanted = args.only.split(",") if args.only else list(groups)
    if unknown := [w for w in wanted if w not in groups]:
        raise SystemExit(f"--only: no group {', '.join(unknown)}; groups: {', '.join(groups)}")
    rerun_exe = _viewer_binary()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    try:
        at = [float(v) for v in args.at.split(",")] if args.at else None
    except ValueError:
        raise SystemExit(f"--at: comma-separated numbers, not {args.at!r}") from None

    def place(shot: Shot) -> Shot:  # the picture's file under --out-dir
        return Shot(str(args.out_dir / f"{shot.name}.png"), shot.at, shot.timeline, shot.tab, shot.caption, shot.doc)

    if args.rrd is not None:
        if not args.rrd.exists():
            raise SystemExit(f"--rrd: no file {args.rrd}")
        name = args.rrd.stem + (f"-{_slug(args.tab)}" if args.tab else "")
        shots = _retimed([Shot(name, END, None, args.tab)], at, args.timeline) if at else [Shot(f"{name}-end", END, None, args.tab)]
        with HeadlessViewer(rerun_exe) as viewer:
            viewer.screenshots(args.rrd, [place(s) for s in shots])
        return
    work = args.work or Path(tempfile.mkdtemp(prefix="agvviz-pictures-"))
    work.mkdir(parents=True, exist_ok=True)
    for name in wanted:
        group = groups[name]
        print(f"{name} (work: {work})")
        started = time.monotonic()
        files = group.build(work)
        built = time.monotonic()
        for rrd, shots in zip(files, group.shots):
            # A fresh viewer per file: a viewer keeps the layout it showed for the application id,
            # so a second file would be drawn in the first one's layout instead of its own.
            with HeadlessViewer(rerun_exe) as viewer:
                viewer.screenshots(rrd, [place(s) for s in _retimed(shots, at, args.timeline)])
        print(f"  {name}: {time.monotonic() - started:.0f} s ({built - started:.0f} s building the files)")


if __name__ == "__main__":
    main()
