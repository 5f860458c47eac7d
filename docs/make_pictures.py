"""Render each scenario's default run in the real Rerun viewer, headless, into ``docs/images/``.

For every scenario this records the default recording (seed 0), replays it with the default
settings (``auv_under_ice`` needs ``correction=cnoem``: its default recording holds corner
observations only), and screenshots the viewer at a telling moment of the run — the pictures
shown in the README. Rerun them whenever a layout changes, and look at every image.

    python docs/make_pictures.py                     # all scenarios → docs/images/<scenario>.png
    python docs/make_pictures.py --only qr_floor --at 20,100,180 --out-dir /tmp/pics
    python docs/make_pictures.py --rrd run.rrd --at 50 --out-dir /tmp/pics   # any run
    python docs/make_pictures.py --rrd run.rrd --timeline elapsed --at 6.0 --out-dir /tmp/pics  # at 6 s

The viewer runs headless (``rerun --headless``; it needs a Vulkan driver, e.g. Debian's
``mesa-vulkan-drivers``) and is driven through ``rerun.experimental.ViewerClient``: open the
file, put the time cursor on the ``frame`` timeline (or the one given), screenshot. A screenshot
is retaken until two in a row are equal, since images decode after the first paint.
"""

from __future__ import annotations

import argparse
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

DOCS = Path(__file__).resolve().parent
WINDOW_SIZE = "1600x1000"


@dataclass(frozen=True)
class Picture:
    """A scenario's default run and where on its timeline to look at it."""

    scenario: str
    run_sets: tuple[str, ...] = ()
    timeline: str = "frame"
    at: tuple[float, ...] = (100,)  # values on ``timeline`` (seconds on elapsed); the first is the README's
    record_sets: tuple[str, ...] = field(default=())


PICTURES = (
    # On ``elapsed`` (seconds, 10 frames a second), the timeline a run opens on: plots read in seconds.
    Picture("qr_floor", timeline="elapsed", at=(10.0, 2.0, 18.0)),
    Picture("uwb_room", timeline="elapsed", at=(15.0, 2.0, 28.0)),
    Picture("auv_under_ice", run_sets=("correction=cnoem",), at=(40, 5, 70)),
    # The study opens on σ (milli-pixels); the cursor past the last σ shows every cell. 100 trials a
    # cell keep the picture quick (the lines and bands read the same as with the default 1000).
    Picture("p4p_monte_carlo", timeline="sigma_mpx", at=(100000,), record_sets=("trials=100",)),
)


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

    def screenshots(self, rrd: Path, timeline: str, at: list[float], out_paths: list[Path]) -> None:
        """Open ``rrd`` and save one screenshot per time in ``at``."""
        import cv2

        self.client.open(str(rrd.resolve()))
        for value, out in zip(at, out_paths):
            if timeline == "elapsed":  # seconds since the recording's start (a duration timeline)
                self.client.set_time(timeline, duration=float(value), play_state="paused")
            else:
                self.client.set_time(timeline, sequence=int(value), play_state="paused")
            previous = None
            for _ in range(6):  # until two shots in a row are equal (images decode late)
                time.sleep(0.5)
                self.client.save_screenshot(str(out.resolve()))
                image = cv2.imread(str(out))
                if previous is not None and image is not None and np.array_equal(image, previous):
                    break
                previous = image
            print(f"  {out}")

    def __enter__(self) -> "HeadlessViewer":
        return self

    def __exit__(self, *exc) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()


def _agvviz(*args: str) -> None:
    command = [sys.executable, "-m", "agvviz", *args]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-2000:]}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out-dir", type=Path, default=DOCS / "images", help="where the PNGs go")
    parser.add_argument("--work", type=Path, default=None, help="folder for recordings and runs (kept)")
    parser.add_argument("--only", default=None, help="comma-separated scenarios")
    parser.add_argument("--at", default=None, help="comma-separated times on the timeline (overrides)")
    parser.add_argument("--timeline", default=None, help="timeline for --at (default: the picture's)")
    parser.add_argument("--rrd", type=Path, default=None, help="screenshot this run instead of the scenarios")
    parser.add_argument("--all-times", action="store_true", help="every time of each picture, not the first")
    args = parser.parse_args()

    rerun_exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if rerun_exe is None:
        raise SystemExit("the rerun executable is not on PATH: pip install rerun-sdk")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    work = args.work or Path(tempfile.mkdtemp(prefix="agvviz-pictures-"))
    work.mkdir(parents=True, exist_ok=True)
    # Sequence values (frame, trial); seconds on ``--timeline elapsed`` (what a run opens on).
    at_override = [float(v) if args.timeline == "elapsed" else int(v) for v in args.at.split(",")] if args.at else None

    # A fresh viewer per run: a viewer keeps the layout it showed for the application id, so a
    # second run would be drawn in the first one's layout instead of its own.
    if args.rrd is not None:
        at = at_override or [0]
        with HeadlessViewer(rerun_exe) as viewer:
            viewer.screenshots(args.rrd, args.timeline or "frame", at, [args.out_dir / f"{args.rrd.stem}-{v}.png" for v in at])
        return
    wanted = set(args.only.split(",")) if args.only else None
    for picture in PICTURES:
        if wanted is not None and picture.scenario not in wanted:
            continue
        print(picture.scenario)
        recording = work / f"{picture.scenario}.mcap"
        if not recording.exists():
            _agvviz("record", picture.scenario, "--out", str(recording),
                    *[a for s in picture.record_sets for a in ("--set", s)])
        run = work / f"{picture.scenario}.rrd"
        _agvviz("run", str(recording), "--out", str(run), *[a for s in picture.run_sets for a in ("--set", s)])
        at = at_override or (list(picture.at) if args.all_times else [picture.at[0]])
        names = [picture.scenario] if len(at) == 1 and at_override is None else [
            f"{picture.scenario}-{v}" for v in at
        ]
        with HeadlessViewer(rerun_exe) as viewer:
            viewer.screenshots(run, args.timeline or picture.timeline, at, [args.out_dir / f"{n}.png" for n in names])


if __name__ == "__main__":
    main()
