"""Issue 13, item 8: the CLI as a stranger meets it — on/off options shown as flags in every
``--help``, a setting that does not apply to the recording warned about and kept out of the run
name, ``view --web`` (served until Ctrl-C, exit 130), ``view --connect`` (the run arrives in a
real Rerun gRPC server), the headless hint, and ``inspect`` times relative and human."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
import warnings
from pathlib import Path

import pytest
from typer.testing import CliRunner

from agvviz import scenarios as scenario_registry
from agvviz.cli.main import app
from agvviz.cli.viewer import viewer_url
from agvviz.errors import InputError
from agvviz.app.run import run_recording
from agvviz.settings import RunSettings
from agvviz.viz.readback import document_json, read_rrd
from agvviz.viz import paths

TINY = ["duration_s=0.4", "rate_hz=5", "realism=ideal"]  # 2 frames
AGVVIZ = [sys.executable, "-m", "agvviz"]  # = the console script agvviz.__main__:main
RERUN = str(Path(sys.executable).with_name("rerun"))
COMMANDS = ["scenarios", "record", "run", "inspect", "view", "demo", "version", "diff", "sweep", "export"]


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("views")
    recording = tmp / "qr.mcap"
    scenario_registry.record("qr_floor", recording, seed=2, overrides=TINY)
    run = run_recording(recording, RunSettings(solver="ippe"), tmp / "qr-ippe.rrd").out_path
    return recording, run


def _invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_listening(port: int, process: subprocess.Popen, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"the server exited with {process.returncode} before listening on {port}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"nothing listens on port {port} after {timeout_s} s")


# -- --help -------------------------------------------------------------------------------------
@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help_shows_flags_without_a_value_type(command):
    result = _invoke(*([command] if command else []), "--help")
    assert result.exit_code == 0, result.output
    assert "<bool>" not in result.output
    assert "--help" in result.output and "list[str]" not in result.output


def test_help_names_both_sides_of_a_switch():
    text = _invoke("run", "--help").output
    assert "--cache" in text and "--no-cache" in text
    assert "KEY=VALUE" in text and "ROLE=TOPIC" in text


# -- a setting that does not apply --------------------------------------------------------------
def test_a_setting_without_data_is_a_warning_and_stays_out_of_the_name(recorded, tmp_path, monkeypatch):
    recording, _ = recorded
    monkeypatch.chdir(tmp_path)  # the default output runs/<name>.rrd
    result = _invoke("run", recording, "--solver", "ippe", "--set", "fusion=kalman", "--set", "refine=subpix",
                     "--no-cache")
    assert result.exit_code == 0, result.output
    warnings_ = [line for line in result.output.splitlines() if line.startswith("warning: fusion")]
    assert warnings_ == ["warning: fusion=kalman does not apply: the recording has no UWB ranges (no uwb.range "
                         "topic); ignored (not in the run name)"]
    out = tmp_path / "runs" / "qr-ippe-refine=subpix.rrd"  # refine applies: in the name; fusion not
    assert out.is_file(), sorted(p.name for p in (tmp_path / "runs").iterdir())
    manifest = document_json(read_rrd(out), paths.RUN_MANIFEST)
    assert manifest["recording_name"] == "qr_floor-ippe-refine=subpix"
    assert manifest["settings"]["fusion"] == RunSettings().fusion
    assert manifest["ignored_settings"] == {
        "fusion": {"value": "kalman", "reason": "the recording has no UWB ranges (no uwb.range topic)"}}


# -- view ---------------------------------------------------------------------------------------
def test_view_without_a_display_says_what_to_do(recorded, monkeypatch):
    _, run = recorded
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    result = _invoke("view", run)
    assert result.exit_code == 2, result.output
    (line,) = [line for line in result.output.splitlines() if line.strip()]
    assert line.startswith("error: no display") and "--web" in line and "--connect" in line


@pytest.mark.parametrize("address, url", [
    ("9876", "rerun+http://127.0.0.1:9876/proxy"),
    ("robot.local:9877", "rerun+http://robot.local:9877/proxy"),
    ("rerun+https://viewer.example:443/proxy", "rerun+https://viewer.example:443/proxy"),
])
def test_connect_addresses(address, url):
    assert viewer_url(address) == url


@pytest.mark.parametrize("address", ["http://host:9876/proxy", "rerun+http://host:9876/other", "host:", "a:b:c"])
def test_connect_refuses_other_addresses(address):
    with pytest.raises(InputError, match="--connect"):
        viewer_url(address)


def test_view_connect_without_a_viewer_is_one_line(recorded):
    _, run = recorded
    result = _invoke("view", run, "--connect", str(_free_port()))
    assert result.exit_code == 2, result.output
    (line,) = [line for line in result.output.splitlines() if line.strip()]
    assert line.startswith("error: no Rerun viewer answers at rerun+http://127.0.0.1:")


def test_view_connect_sends_the_run_and_its_blueprint(recorded, tmp_path):
    """A real Rerun gRPC server saving what it receives: the run arrives whole, under its own
    recording id, with its blueprint."""
    from rerun.chunk import RrdReader

    _, run = recorded
    port, received = _free_port(), tmp_path / "received.rrd"
    server = subprocess.Popen([RERUN, "--serve-grpc", "--bind", "127.0.0.1", "--port", str(port), "--save",
                               str(received)], env={**os.environ, "RUST_LOG": "warn"}, start_new_session=True)
    try:
        _wait_listening(port, server)
        result = _invoke("view", run, "--connect", f"127.0.0.1:{port}")
        assert result.exit_code == 0, result.output
        assert f"sent {run} to the Rerun viewer at rerun+http://127.0.0.1:{port}/proxy" in result.output
        with warnings.catch_warnings():  # the saved stream has no footer: read it whole
            warnings.simplefilter("ignore")
            want = set(RrdReader(run).stream().collect().schema().entity_paths())
            deadline, got = time.monotonic() + 60, set()
            while got != want and time.monotonic() < deadline:  # the server writes as it receives
                time.sleep(0.5)
                try:
                    got = set(RrdReader(received).stream().collect().schema().entity_paths())
                except (RuntimeError, ValueError, OSError):  # caught mid-write
                    continue
            assert got == want
            assert RrdReader(received).recordings() == RrdReader(run).recordings()  # the run's own id
            assert [b.application_id for b in RrdReader(received).blueprints()] == ["agvviz"]
    finally:
        os.killpg(server.pid, signal.SIGINT)
        server.wait(timeout=30)


def test_view_web_serves_until_ctrl_c(recorded):
    """The console script serves the web viewer, prints a URL that answers, and stops — with its
    viewer process group — on SIGINT, exit 130, no traceback."""
    _, run = recorded
    web_port, grpc_port = _free_port(), _free_port()
    proc = subprocess.Popen(
        AGVVIZ + ["view", str(run), "--web", "--bind", "127.0.0.1", "--port", str(web_port),
                  "--grpc-port", str(grpc_port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        first = proc.stdout.readline()
        assert first.startswith(f"serving {run} in Rerun's web viewer"), first
        url = proc.stdout.readline().strip()
        assert url == f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"
        _wait_listening(web_port, proc)
        _wait_listening(grpc_port, proc)
        with urllib.request.urlopen(url, timeout=10) as response:
            assert response.status == 200
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "web viewer stopped" in err
    for port in (web_port, grpc_port):  # the viewer is gone: its ports are free again
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
            except OSError:
                break
            assert time.monotonic() < deadline, f"port {port} still answers after the stop"
            time.sleep(0.2)


def test_view_web_on_a_busy_port_is_one_line(recorded):
    _, run = recorded
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = _invoke("view", run, "--web", "--bind", "127.0.0.1", "--port", port)
    assert result.exit_code == 2, result.output
    (line,) = [line for line in result.output.splitlines() if line.strip()]
    assert line.startswith(f"error: cannot listen on 127.0.0.1 port {port}") and "--port" in line


# -- inspect: times relative and human ----------------------------------------------------------
def test_inspect_prints_a_date_a_duration_and_relative_topic_times(recorded):
    recording, _ = recorded
    result = _invoke("inspect", recording)
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    # qr_floor starts at 1_700_000_000 s (2023-11-14 22:13:20 UTC); 2 frames at 5 Hz: 0.2 s.
    assert "time span: start 2023-11-14 22:13:20.000 UTC, duration 0.200 s" in lines
    image_row = next(line for line in lines if line.startswith("/cam/front/image"))
    assert image_row.split()[-4:] == ["+0.000", "s", "+0.200", "s"]
    assert "1700000000" not in result.output


@pytest.mark.parametrize("first_ns, last_ns, text", [
    (1_700_000_000 * 10**9, 1_700_000_072_400_000_000, "start 2023-11-14 22:13:20.000 UTC, duration 1 min 12.4 s"),
    (0, 3_725_500_000_000, "start 0.000 s, duration 1 h 02 min 05.5 s"),
    (5 * 10**9, 5 * 10**9 + 123_456_789, "start 5.000 s, duration 0.123 s"),
])
def test_span_texts(first_ns, last_ns, text):
    from agvviz.recording.checks import span_text

    assert span_text(first_ns, last_ns) == text


def test_relative_stamps():
    from agvviz.recording.checks import format_ns

    assert format_ns(1_700_000_072_400_000_000, 1_700_000_000 * 10**9) == "+72.400 s"
    assert format_ns(10**9 - 5 * 10**6, 10**9) == "-0.005 s"
    assert format_ns(None, 0) == "-"
