"""The sweep .rrd is written streaming (issue 27, peak memory): each setting's layers copied
entity by entity, its reprojected corners read only when it is drawn, the frames flushed as they
are logged, the elapsed origin read from one entity. The file equals the one the eager writer
gave (layers in one stream, every setting's corners read first, no flushes, a scan of every
per-frame chunk) — `rerun rrd compare --unordered`. One small recording (3 s at 10 Hz, 640×512),
two solvers, layers-only runs as a sweep makes them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import rerun as rr

from agvviz import scenarios as scenario_registry
from agvviz.app import sweep as sweep_module
from agvviz.app.run import run_recording
from agvviz.app.run_series import load_run
from agvviz.settings import RunSettings
from agvviz.viz import overlay, paths, rrd_file
from agvviz.viz.readback import points2d, read_rrd

SMALL = ["duration_s=3", "rate_hz=10", "width_px=640", "height_px=512", "focal_px=500", "realism=typical"]


def _eager_copy_layers(rec, key, run):
    """The writer before: a run's layers in one stream."""
    store = run.store
    entities = [p.lstrip("/") for p in store.schema().entity_paths()]
    left_out = ["/__properties/**", *[f"/{e}" for e in paths.camera_images(entities)]]
    prefix = "/" + paths.sweep_setting(key)
    rec.send_chunks(store.stream().drop(content=left_out).map(lambda c: c.with_entity_path(prefix + c.entity_path)))
    return set(entities)


def test_the_streamed_sweep_file_equals_the_eager_one(tmp_path, monkeypatch):
    cli = Path(sys.executable).parent / "rerun"
    if not cli.is_file():
        pytest.skip(f"rerun CLI not found next to {sys.executable}; needed for `rerun rrd compare`")
    recording = tmp_path / "qr.mcap"
    scenario_registry.record("qr_floor", recording, seed=4, overrides=SMALL)
    entries, series = [], {}
    for index, solver in enumerate(("lm", "ippe")):
        settings = RunSettings(solver=solver)
        layers = run_recording(recording, settings, tmp_path / f"{solver}.layers.rrd", jobs=1, images=False).out_path
        entry = sweep_module.SweepEntry(solver, settings, tmp_path / "sweep.rrd", recording=recording, run_path=layers,
                                        key=sweep_module._entity_key(index, solver), run=read_rrd(layers))
        entry.rank = index + 1
        entries.append(entry)
        series[index] = load_run(layers)

    def write(out: Path) -> Path:
        return sweep_module._write_sweep_file(out, recording, entries, series, entries, "position_rmse_mm", True)

    # Streamed, flushed after every image: the batcher cuts a chunk at every image of this
    # recording (≥ 8 kB), as at the default resolution (≈300 kB each) with its default 256 kB.
    monkeypatch.setattr(rrd_file, "BATCHER_FLUSH_NUM_BYTES", 8 << 10)
    monkeypatch.setattr(overlay, "FLUSH_IMAGE_BYTES", 1)
    flushes = []
    flush = rr.RecordingStream.flush
    monkeypatch.setattr(rr.RecordingStream, "flush", lambda self, *a, **k: flushes.append(1) or flush(self, *a, **k))
    read_when_drawn = []
    reader = sweep_module._reprojected_reader
    monkeypatch.setattr(sweep_module, "_reprojected_reader",
                        lambda *args: lambda: read_when_drawn.append(args[0]) or reader(*args)())
    streamed = write(tmp_path / "streamed" / "sweep.rrd")
    assert read_when_drawn == [e.run for e in entries]  # each setting's corners, once, when drawn
    assert len(flushes) >= len(series[0].frames)  # paced: a flush per frame (and per layers entity)
    # Eager, as before.
    monkeypatch.setattr(overlay, "FLUSH_IMAGE_BYTES", 1 << 62)
    monkeypatch.setattr(overlay, "_copy_layers", _eager_copy_layers)
    monkeypatch.setattr(overlay, "_first_temporal_entity", lambda store: None)
    monkeypatch.setattr(sweep_module, "_reprojected_reader", lambda *args: reader(*args)())
    eager = write(tmp_path / "eager" / "sweep.rrd")

    same = subprocess.run([cli, "rrd", "compare", "--unordered", streamed, eager], capture_output=True, text=True,
                          timeout=120, check=False)
    assert same.returncode == 0, same.stdout + same.stderr
    # The comparison can fail: the corners drawn are the settings' own, and differ between them.
    drawn = {e.label: points2d(streamed, paths.overlay_reprojected("front", e.key)) for e in entries}
    assert drawn["lm"].keys() == drawn["ippe"].keys() and len(drawn["lm"]) == len(series[0].frames)
    assert any(len(a) and (a.shape != b.shape or (abs(a - b) > 1e-6).any())
               for a, b in zip(drawn["lm"].values(), drawn["ippe"].values()))
    for entry in entries:
        own = points2d(entry.run_path, paths.reprojected("front", False))
        assert all((drawn[entry.label][f] == pts).all() for f, pts in own.items())
