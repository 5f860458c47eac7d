"""Robustness harness for issue 10: run agvviz as a hostile user would and classify each attempt.

Every case is one real ``agvviz`` subprocess (its own session, so a timeout kills the whole
process group) with a declared expectation. Inputs are snapshotted (sha256, inode, size,
mtime) before and after; declared outputs are checked for completeness and for leftover
``*.tmp`` files beside them. Each attempt gets exactly one class:

===============  ==========================================================================
class            meaning
===============  ==========================================================================
clean error      an expected nonzero exit code, exactly one ``error:`` line, no traceback
ok               success where success is right (and the output is complete and right)
crash            a traceback, a signal, an unexpected exit code or a malformed error message
hang             the process did not finish within the timeout (its group was killed)
partial output   an output target that exists but is incomplete, a target created by a
                 failed command, or a leftover ``*.tmp`` beside it
input modified   an input file's content, inode or mtime changed
silent wrong     exit 0 where the input should have been refused or warned about, or a
                 success whose result is wrong (e.g. salvage replayed the wrong frames)
===============  ==========================================================================

Priority when several apply: hang, input modified, crash, partial output, silent wrong.
Every problem found is kept in ``Result.problems``; the class is the first by priority.

Everything random is drawn from ``random.Random(seed)`` with a fixed seed per case, so the
campaign is deterministic. The cases themselves live in :mod:`robustness_cases`.
"""

from __future__ import annotations

import hashlib
import os
import signal
import stat
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

REPO = Path(__file__).resolve().parents[2]

CLASSES = (
    "clean error", "ok", "crash", "hang", "partial output", "input modified", "silent wrong",
)
#: Classes that must never occur (the campaign asserts zero of each).
FORBIDDEN = ("crash", "hang", "input modified", "silent wrong")
#: Exit codes agvviz may use at all (agvviz/errors.py).
KNOWN_CODES = {0, 1, 2, 3, 130}
DEFAULT_TIMEOUT_S = 120.0
#: Address-space cap for cases that try to make agvviz allocate absurdly (MemoryError,
#: not the OOM killer).
MEMORY_CAP_BYTES = 4 << 30


def agvviz_command() -> list[str]:
    """The installed ``agvviz`` console script next to this Python (or ``python -m``)."""
    script = Path(sys.executable).parent / "agvviz"
    if script.exists():
        return [str(script)]
    return [sys.executable, "-m", "agvviz"]


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env.update({
        "COLUMNS": "200",  # rich wraps at 80 columns when not on a terminal
        "TERM": "dumb",
        "NO_COLOR": "1",
        "PYTHONHASHSEED": "0",
        "PYTHONDONTWRITEBYTECODE": "1",
    })
    return env


# -- snapshots ------------------------------------------------------------------------------
@dataclass(frozen=True)
class FileState:
    exists: bool
    sha256: str = ""
    inode: int = 0
    size: int = 0
    mtime_ns: int = 0
    link_target: str = ""  # for a symlink: where it points


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def snapshot(path: Path) -> FileState:
    """State of ``path`` (following a symlink for the content, remembering where it points)."""
    path = Path(path)
    link = os.readlink(path) if path.is_symlink() else ""
    if not path.exists():
        return FileState(False, link_target=link)
    st = path.stat()
    if path.is_dir():
        names = sorted(os.listdir(path))
        return FileState(True, "dir:" + ",".join(names), st.st_ino, 0, st.st_mtime_ns, link)
    if not stat.S_ISREG(st.st_mode):  # a FIFO or a device: never read it (a FIFO would block)
        return FileState(True, f"mode:{stat.S_IFMT(st.st_mode):o}", st.st_ino, 0, st.st_mtime_ns, link)
    return FileState(True, _sha256(path), st.st_ino, st.st_size, st.st_mtime_ns, link)


def tmp_files(folders: Sequence[Path]) -> set[Path]:
    found = set()
    for folder in folders:
        if Path(folder).is_dir():
            found |= {p for p in Path(folder).iterdir() if p.name.endswith(".tmp")}
    return found


# -- cases and results ----------------------------------------------------------------------
@dataclass
class Run:
    """What one subprocess did."""

    argv: list[str]
    returncode: Optional[int]
    stdout: str
    stderr: str
    seconds: float
    timed_out: bool
    cwd: Path
    orphans: bool = False  # processes of its group still running 3 s after it exited


@dataclass
class Case:
    """One hostile attempt and what it must do.

    ``expect``: ``"error"`` (refuse: a nonzero code in ``codes``), ``"ok"`` (succeed),
    ``"error_or_ok"`` (either is right; ``check`` decides whether the success is right, e.g.
    it carries a warning). ``check(run, case)`` returns problems of a successful (or, with
    ``check_errors``, of any) run as ``[(class, text)]``; an empty list means fine.
    ``inputs`` must not change; ``outputs`` are targets: complete when they exist after a
    success (``validate_output``), absent (or unchanged when they pre-existed) after a failure.
    ``setup(case)`` runs first (make the files); ``drive(popen, case)`` interacts with the
    running process (e.g. sends a signal) and returns nothing.
    """

    category: str
    name: str
    args: list[str]
    expect: str = "error"
    codes: tuple[int, ...] = (2,)
    inputs: list[Path] = field(default_factory=list)
    outputs: list[Path] = field(default_factory=list)
    cwd: Optional[Path] = None
    timeout_s: float = DEFAULT_TIMEOUT_S
    memory_cap: bool = False
    error_line: bool = True  # a refusal must print exactly one "error:" line
    check: Optional[Callable[["Run", "Case"], list]] = None
    check_errors: bool = False
    setup: Optional[Callable[["Case"], None]] = None
    drive: Optional[Callable[[subprocess.Popen, "Case"], None]] = None
    expected_signal_exit: Optional[int] = None  # e.g. -9 when the case kills it on purpose
    skip_reason: Optional[str] = None
    teardown: Optional[Callable[["Case"], None]] = None
    note: str = ""
    driven: Optional[bool] = None  # set by ``drive``: False when it could not do its part
    program: Optional[list[str]] = None  # instead of agvviz (the harness's own tests)

    @property
    def id(self) -> str:
        return f"{self.category}/{self.name}"

    def command(self) -> list[str]:
        return (self.program or agvviz_command()) + [str(a) for a in self.args]


@dataclass
class Result:
    case: Case
    klass: str  # one of CLASSES, or "skipped"
    problems: list[tuple[str, str]]
    run: Optional[Run]

    @property
    def failed(self) -> bool:
        return self.klass in FORBIDDEN or self.klass == "partial output"

    def describe(self) -> str:
        lines = [f"[{self.klass}] {self.case.id}"]
        if self.run is not None:
            lines.append(f"  command: (cd {self.run.cwd} && {' '.join(_quote(a) for a in self.run.argv)})")
            lines.append(f"  exit: {self.run.returncode}  ({self.run.seconds:.1f} s)")
        if self.case.note:
            lines.append(f"  note: {self.case.note}")
        for klass, text in self.problems:
            lines.append(f"  {klass}: {text}")
        if self.run is not None and self.run.stderr.strip():
            tail = "\n".join(self.run.stderr.strip().splitlines()[-6:])
            lines.append("  stderr tail:\n    " + tail.replace("\n", "\n    "))
        if self.case.skip_reason:
            lines.append(f"  skipped: {self.case.skip_reason}")
        return "\n".join(lines)


def _quote(arg: str) -> str:
    import shlex

    return shlex.quote(arg)


#: Sets RLIMIT_AS in the child, then execs the command: the same effect as a preexec_fn
#: calling ``resource.setrlimit``, without forking a multi-threaded harness into Python code.
_CAPPED = (
    "import os, resource, sys; "
    "resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[1]), int(sys.argv[1]))); "
    "os.execv(sys.argv[2], sys.argv[2:])"
)


def _start(case: Case, argv: list[str], cwd: Path) -> subprocess.Popen:
    if case.memory_cap:
        argv = [sys.executable, "-c", _CAPPED, str(MEMORY_CAP_BYTES), *argv]
    return subprocess.Popen(
        argv,
        cwd=cwd,
        env=child_env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        errors="replace",
        start_new_session=True,  # own process group: a timeout kills everything it started
    )


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def run_process(case: Case) -> Run:
    cwd = Path(case.cwd or REPO)
    argv = case.command()
    t0 = time.monotonic()
    proc = _start(case, argv, cwd)
    timed_out = False
    try:
        if case.drive is not None:
            case.drive(proc, case)
        stdout, stderr = proc.communicate(timeout=max(1.0, case.timeout_s - (time.monotonic() - t0)))
    except subprocess.TimeoutExpired:
        timed_out = True
        _kill_group(proc)
        stdout, stderr = proc.communicate()
    finally:
        if proc.poll() is None:
            _kill_group(proc)
            proc.communicate()
    # anything it started must end with it (sweep workers, viewers)
    orphans = False
    deadline = time.monotonic() + 3.0
    while True:
        try:
            os.killpg(proc.pid, 0)
        except (ProcessLookupError, PermissionError):
            break
        if time.monotonic() > deadline:
            orphans = True
            _kill_group(proc)
            break
        time.sleep(0.05)
    run = Run(argv, proc.returncode, stdout or "", stderr or "", time.monotonic() - t0, timed_out, cwd)
    run.orphans = orphans
    return run


def error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip().startswith("error:")]


# -- output validation ----------------------------------------------------------------------
def validate_output(path: Path) -> Optional[str]:
    """Why the finished output ``path`` is incomplete, or ``None`` when it is complete."""
    path = Path(path)
    if path.is_dir():
        return None
    try:
        if path.stat().st_size == 0:
            return "is empty"
        if path.suffix == ".rrd":
            from agvviz.viz.readback import read_rrd

            contents = read_rrd(path)
            if not contents.entity_paths:
                return "holds no entity"
        elif path.suffix == ".mcap":
            from agvviz.recording.mcap_stream import iter_raw
            from agvviz.recording.raw import ReadReport

            report = ReadReport()
            for _ in iter_raw(path, report=report):
                pass
            if report.problems:
                return "; ".join(report.problems[:2])
        elif path.suffix == ".tum":
            for n, line in enumerate(path.read_text().splitlines()):
                if line.startswith("#") or not line.strip():
                    continue
                if len(line.split()) != 8:
                    return f"line {n + 1} has {len(line.split())} fields, not 8"
                [float(v) for v in line.split()]
    except Exception as exc:  # noqa: BLE001 — any failure to read it back means incomplete
        return f"cannot be read back ({type(exc).__name__}: {str(exc)[:200]})"
    return None


def run_summary(path: Path) -> Optional[dict]:
    """The ``run/summary`` JSON of a run ``.rrd`` (``None`` when unreadable)."""
    try:
        from agvviz.viz.readback import document_json

        return document_json(path, "run/summary")
    except Exception:  # noqa: BLE001
        return None


# -- classification -------------------------------------------------------------------------
def classify(case: Case, run: Run, before: dict, tmp_before: set[Path]) -> tuple[str, list]:
    problems: list[tuple[str, str]] = []
    code = run.returncode
    if run.timed_out:
        problems.append(("hang", f"no exit within {case.timeout_s:.0f} s; process group killed"))

    for path, state in before.items():
        after = snapshot(path)
        if after != state:
            changed = [
                name for name in ("exists", "sha256", "inode", "size", "mtime_ns", "link_target")
                if getattr(after, name) != getattr(state, name)
            ]
            problems.append(("input modified", f"{path}: {', '.join(changed)} changed"))

    if not run.timed_out:
        if "Traceback (most recent call last)" in run.stderr or "Traceback" in run.stdout:
            problems.append(("crash", "a Python traceback on " + ("stderr" if "Traceback" in run.stderr else "stdout")))
        if code is not None and code < 0 and code != case.expected_signal_exit:
            problems.append(("crash", f"killed by signal {-code} ({signal.Signals(-code).name})"))
        elif code is not None and code not in KNOWN_CODES and code != case.expected_signal_exit:
            problems.append(("crash", f"exit code {code} is not one agvviz documents (0, 1, 2, 3, 130)"))

    if run.orphans and not run.timed_out:
        problems.append(("crash", "processes it started were still running 3 s after it exited (killed)"))

    success = code == 0 and not run.timed_out
    refused = code not in (0, None) and code != case.expected_signal_exit and not run.timed_out

    # outputs: complete after success, absent (or unchanged) after a failure; no *.tmp left
    out_folders = sorted({Path(p).parent for p in case.outputs} | ({Path(run.cwd)} if case.cwd else set()))
    for p in case.outputs:
        p = Path(p)
        pre = before.get(p)
        if success:
            if p.exists():
                why = validate_output(p)
                if why:
                    problems.append(("partial output", f"{p} {why}"))
        else:
            now = snapshot(p) if p.exists() else FileState(False)
            if pre is None and now.exists:
                why = validate_output(p)
                problems.append(("partial output", f"{p} was created by a command that failed (exit {code})"
                                 + (f" and {why}" if why else "")))
    leftovers = tmp_files(out_folders) - tmp_before
    if leftovers and not run.timed_out:
        problems.append(("partial output", "temporary file(s) left behind: " + ", ".join(sorted(str(p) for p in leftovers))))

    # expectation
    if not run.timed_out and code is not None and code >= 0:
        if refused:
            if case.expect == "ok":
                problems.append(("crash", f"unexpected exit code {code} where success was right"))
            elif code not in case.codes:
                problems.append(("crash", f"exit code {code}, expected {' or '.join(map(str, case.codes))}"))
            elif case.error_line and code != 1:  # exit 1 is a report (inspect) or a condition (diff)
                n = len(error_lines(run.stderr))
                if n != 1:
                    problems.append(("crash", f"{n} 'error:' lines on stderr (exactly one expected)"))
                if error_lines(run.stdout):
                    problems.append(("crash", "an 'error:' line on stdout"))
        if success and case.expect == "error":
            problems.append(("silent wrong", "exit 0 where the input should have been refused"))
        if case.check is not None and (success or case.check_errors):
            problems += case.check(run, case)

    order = {k: i for i, k in enumerate(("hang", "input modified", "crash", "partial output", "silent wrong"))}
    bad = sorted((p for p in problems if p[0] in order), key=lambda p: order[p[0]])
    if bad:
        return bad[0][0], problems
    if refused:
        return "clean error", problems
    if code == case.expected_signal_exit and code is not None:
        return ("clean error" if case.expect == "error" else "ok"), problems
    return "ok", problems


def run_case(case: Case) -> Result:
    if case.skip_reason:
        return Result(case, "skipped", [], None)
    try:
        if case.setup is not None:
            case.setup(case)
        if case.skip_reason:  # setup may find the fault cannot be made here
            return Result(case, "skipped", [], None)
        if case.cwd is not None:
            Path(case.cwd).mkdir(parents=True, exist_ok=True)
        before = {Path(p): snapshot(p) for p in case.inputs}
        for p in case.outputs:
            if Path(p).exists() and Path(p) not in before:
                before[Path(p)] = snapshot(p)  # a pre-existing target must survive a failure
        folders = sorted({Path(p).parent for p in case.outputs} | ({Path(case.cwd)} if case.cwd else set()))
        tmp_before = tmp_files(folders)
        run = run_process(case)
        if case.cwd is not None:  # keep what it said beside the case's files
            for name, text in (("_stdout.txt", run.stdout), ("_stderr.txt", run.stderr)):
                try:
                    (Path(case.cwd) / name).write_text(text)
                except OSError:
                    pass
        if case.driven is False:
            case.skip_reason = case.skip_reason or "the fault could not be injected in time (the command ended first)"
            return Result(case, "skipped", [], run)
        klass, problems = classify(case, run, before, tmp_before)
        return Result(case, klass, problems, run)
    finally:
        if case.teardown is not None:
            case.teardown(case)


def run_cases(cases: Sequence[Case], jobs: int = 1, progress: Optional[Callable[[Result], None]] = None) -> list[Result]:
    """Run every case (``jobs`` at a time); results in case order whatever the scheduling."""
    if jobs <= 1:
        results = []
        for case in cases:
            results.append(run_case(case))
            if progress:
                progress(results[-1])
        return results
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(run_case, c) for c in cases]
        results = []
        for f in futures:
            results.append(f.result())
            if progress:
                progress(results[-1])
        return results


# -- report ---------------------------------------------------------------------------------
def table(results: Sequence[Result], group: Callable[[Result], str] = lambda r: r.case.category,
          label: str = "category") -> str:
    """Markdown table: category (or ``group``) × tried / each class (skipped counted apart)."""
    categories = list(dict.fromkeys(group(r) for r in results))
    header = [label, "tried", *CLASSES, "skipped"]
    rows = []
    totals = [0] * (len(header) - 1)
    for cat in categories:
        rs = [r for r in results if group(r) == cat]
        tried = [r for r in rs if r.klass != "skipped"]
        counts = [len(tried)] + [sum(r.klass == k for r in tried) for k in CLASSES] + [len(rs) - len(tried)]
        totals = [a + b for a, b in zip(totals, counts)]
        rows.append([cat, *map(str, counts)])
    rows.append(["**total**", *(f"**{v}**" for v in totals)])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def report(results: Sequence[Result], title: str = "agvviz robustness campaign", command: str = "") -> str:
    failing = [r for r in results if r.failed]
    skipped = [r for r in results if r.klass == "skipped"]
    parts = [f"# {title}", ""]
    if command:
        parts += [f"Command: `{command}`", ""]
    parts += [table(results), ""]
    damaged = [r for r in results if r.case.category == "damaged files"]
    if damaged:
        parts += ["Damaged files by kind of damage and command:", "",
                  table(damaged, lambda r: (r.case.note.split(" (")[0] or "not MCAP at all") + " / " + r.case.args[0],
                        "damage / command"), ""]
    if failing:
        parts += [f"## Failing cases ({len(failing)})", "", "```"]
        parts += [r.describe() + "\n" for r in failing]
        parts += ["```", ""]
    if skipped:
        parts += ["## Skipped", ""] + [f"- {r.case.id}: {r.case.skip_reason}" for r in skipped] + [""]
    parts += ["## Every case", "", "| case | class | exit | s | note |", "|---|---|---|---|---|"]
    for r in results:
        exit_code = "" if r.run is None else str(r.run.returncode)
        secs = "" if r.run is None else f"{r.run.seconds:.1f}"
        parts.append(f"| {r.case.id} | {r.klass} | {exit_code} | {secs} | {r.case.note} |")
    return "\n".join(parts) + "\n"
