"""``agvviz view``: open a run in the Rerun viewer, serve it to a browser (``--web``, the
``rerun`` executable as a web server) or send it to a viewer elsewhere (``--connect``,
:func:`agvviz.viz.viewer.send_rrd`).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Optional

import typer

from agvviz.cli.common import console, err_console, fail, handle_errors
from agvviz.errors import EXIT_INTERRUPTED

WEB_PORT = 9090  # Rerun's web viewer (HTTP) default
GRPC_PORT = 9876  # Rerun's viewer / proxy (gRPC) default


def _rerun_executable() -> str:
    """The ``rerun`` viewer installed with this Python's rerun-sdk (the same version), else on PATH."""
    beside = Path(sys.executable).with_name("rerun")
    rerun_bin = str(beside) if beside.exists() else shutil.which("rerun")
    if rerun_bin is None:
        fail("the `rerun` viewer executable was not found next to this Python; reinstall rerun-sdk")
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
        fail(f"--connect {address!r}: expected a port, HOST:PORT or a URL like rerun+http://HOST:{GRPC_PORT}/proxy")
    return text


def _send_to_viewer(run_files: list[Path], address: str) -> str:
    """Send the run (its recording and blueprint; a layers-only run's frames too) to the Rerun
    viewer at ``address``; returns its URL."""
    import socket
    from urllib.parse import urlsplit

    from agvviz.viz.viewer import send_rrd

    url = viewer_url(address)
    parts = urlsplit(url)
    try:  # the SDK would wait for an absent viewer for ever: ask first
        socket.create_connection((parts.hostname, parts.port), timeout=5).close()
    except OSError as exc:
        fail(f"no Rerun viewer answers at {url} ({exc.strerror or exc}); start one there with `rerun` "
             f"(it listens on port {GRPC_PORT}) or give its address to --connect")
    for run_file in run_files:
        send_rrd(run_file, url)
    return url


def _port_free(bind: str, port: int, option: str) -> None:
    import socket

    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((bind, port))
        except OSError as exc:
            fail(f"cannot listen on {bind} port {port} ({exc.strerror or exc}); choose another with {option}")


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


def _serve_web(run_files: list[Path], bind: str, web_port: int, grpc_port: int) -> None:
    """Serve the run in Rerun's web viewer until Ctrl-C (exit 130)."""
    import socket
    from urllib.parse import quote

    for port, option in ((web_port, "--port"), (grpc_port, "--grpc-port")):
        if not 1 <= port <= 65535:
            fail(f"{option} must lie in 1..65535, got {port}")
        _port_free(bind, port, option)
    host = socket.gethostname() if bind in ("0.0.0.0", "::") else bind
    command = [_rerun_executable(), "--web-viewer", "--bind", bind, "--web-viewer-port", str(web_port),
               "--port", str(grpc_port), *map(str, run_files)]
    # Its own process group: the `rerun` script runs the viewer binary as a child, and both must
    # stop with us (Ctrl-C, SIGTERM), whoever gets the signal.
    server = subprocess.Popen(command, env={**os.environ, "RUST_LOG": "warn"}, start_new_session=True)
    try:
        def url(at: str) -> str:
            return f"http://{at}:{web_port}/?url={quote(f'rerun+http://{at}:{grpc_port}/proxy', safe='')}"

        local = f"; on this machine: {url('127.0.0.1')}" if host != "127.0.0.1" else ""
        console.print(f"serving {run_files[0]} in Rerun's web viewer; open in a browser:\n  {url(host)}\n"
                      f"(Ctrl-C stops it{local})", highlight=False, markup=False, soft_wrap=True)
        code = server.wait()
    except KeyboardInterrupt:
        _stop_group(server)
        err_console.print("web viewer stopped", highlight=False)
        raise typer.Exit(code=EXIT_INTERRUPTED) from None
    fail(f"the Rerun web viewer stopped with exit code {code} (see its message above)")


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
    recording: Optional[Path] = typer.Option(None, "--recording", help="a run written with --images none: its "
                                             "recording, whose frames are shown with it (default: the recording's "
                                             "file name beside the run, here or in recordings/)"),
) -> None:
    """Open a run in the Rerun viewer (with its default layout); --web serves it to a browser, --connect sends it to a viewer elsewhere.

    Example: agvviz view runs/qr_floor-lm.rrd

    Example (on a robot without a screen): agvviz view runs/qr_floor-lm.rrd --web

    Example: agvviz view runs/qr_floor-lm.rrd --connect laptop:9876

    A run written with `agvviz run --images none` is opened together with its recording's frames.
    """
    from agvviz.viz.rrd_file import looks_complete

    if not run_file.is_file():
        fail(f"no such file: {run_file}")
    if not looks_complete(run_file):
        fail(f"{run_file} is not a complete .rrd file (no Rerun header or footer); write it again with `agvviz run`")
    if web and connect is not None:
        fail("give --web (serve it here) or --connect (send it to a viewer elsewhere), not both")
    import tempfile

    with tempfile.TemporaryDirectory(prefix="agvviz-view-") as scratch:
        run_files = [run_file] + _frames_of_layers_only_run(run_file, recording, Path(scratch))
        _open(run_files, web, connect, port, grpc_port, bind)


def _frames_of_layers_only_run(run_file: Path, recording: Optional[Path], scratch: Path) -> list[Path]:
    """A run written with ``--images none``: its recording's frames as a second ``.rrd`` (same
    recording id) in ``scratch``; [] for a run that holds its images."""
    from agvviz.app.run import layers_only_frames

    frames = layers_only_frames(run_file, recording, scratch)
    if frames is None:
        if recording is not None:
            fail(f"--recording is for a run written with --images none; {run_file} holds its own frames")
        return []
    console.print(f"{run_file} holds the layers only: its frames come from the recording", highlight=False,
                  markup=False, soft_wrap=True)
    return [frames]


def _open(run_files: list[Path], web: bool, connect: Optional[str], port: int, grpc_port: int, bind: str) -> None:
    run_file = run_files[0]
    if connect is not None:
        url = _send_to_viewer(run_files, connect)
        console.print(f"sent {run_file} to the Rerun viewer at {url}", highlight=False, markup=False, soft_wrap=True)
        return
    if web:
        _serve_web(run_files, bind, port, grpc_port)
        return
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        fail(f"no display to open the viewer on (DISPLAY and WAYLAND_DISPLAY are unset): serve it to a browser "
             f"with `agvviz view {run_file} --web`, or send it to a viewer elsewhere with "
             f"`agvviz view {run_file} --connect HOST:{GRPC_PORT}`")
    code = subprocess.call([_rerun_executable(), *map(str, run_files)])
    if code != 0:
        fail(f"the Rerun viewer could not open {run_file} (it exited with code {code}; see its messages above)")
