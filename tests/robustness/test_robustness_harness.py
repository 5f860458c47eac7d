"""The robustness harness classifies what it sees correctly (fake commands, no agvviz), and
the independent salvage expectation of the corruption campaign is right on a synthetic MCAP."""

from __future__ import annotations

import sys

import pytest

from robustness_cases import Damage, parse_layout
from robustness_harness import Case, run_case


def _py(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def _case(tmp_path, code, **kw) -> Case:
    kw.setdefault("cwd", tmp_path)
    return Case("self test", "x", [], program=_py(code), **kw)


@pytest.mark.parametrize(
    "code, expect, klass",
    [
        ("import sys; print('error: bad input', file=sys.stderr); sys.exit(2)", "error", "clean error"),
        ("pass", "ok", "ok"),
        ("raise ValueError('boom')", "error", "crash"),  # traceback, exit 1
        ("import sys; print('error: a', file=sys.stderr); print('error: b', file=sys.stderr); sys.exit(2)",
         "error", "crash"),  # two error lines
        ("import sys; print('error: x', file=sys.stderr); sys.exit(3)", "error", "crash"),  # code not expected
        ("import sys; sys.exit(7)", "error", "crash"),  # undocumented exit code
        ("import os, signal; os.kill(os.getpid(), signal.SIGSEGV)", "error", "crash"),
        ("pass", "error", "silent wrong"),  # exit 0 where a refusal was right
        ("import sys; print('error: no', file=sys.stderr); sys.exit(2)", "ok", "crash"),  # wrongful refusal
        ("import time; time.sleep(30)", "error", "hang"),
    ],
)
def test_classification(tmp_path, code, expect, klass):
    result = run_case(_case(tmp_path, code, expect=expect, timeout_s=2))
    assert result.klass == klass, result.describe()


def test_input_modified_and_leftovers(tmp_path):
    src = tmp_path / "in.mcap"
    src.write_bytes(b"abc")
    touched = run_case(_case(tmp_path, f"open({str(src)!r}, 'ab').write(b'x')", expect="ok", inputs=[src]))
    assert touched.klass == "input modified", touched.describe()
    out = tmp_path / "out" / "x.rrd"
    out.parent.mkdir()
    left = run_case(_case(
        tmp_path,
        f"import sys; open({str(out.parent / '.x.rrd.123.tmp')!r}, 'w').write('half'); "
        "print('error: disk full', file=sys.stderr); sys.exit(3)",
        codes=(3,), outputs=[out],
    ))
    assert left.klass == "partial output", left.describe()
    created = run_case(_case(
        tmp_path, f"import sys; open({str(out)!r}, 'w').write('half'); print('error: x', file=sys.stderr); sys.exit(3)",
        codes=(3,), outputs=[tmp_path / "out" / "x.rrd"],
    ))
    assert created.klass == "partial output", created.describe()


def _synthetic_mcap(path):
    """Three chunks of two image messages each (plus a pose per chunk)."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as f:
        w = Writer(f, chunk_size=3000, compression=CompressionType.NONE)
        w.start()
        sid = w.register_schema("foxglove.CompressedImage", "protobuf", b"x")
        img = w.register_channel("/cam/front/image", "protobuf", sid)
        pose = w.register_channel("/agv/ground_truth", "protobuf", sid)
        for k in range(6):
            w.add_message(img, log_time=k, data=bytes(1400), publish_time=k)
            w.add_message(pose, log_time=k, data=bytes(10), publish_time=k)
        w.finish()
    return path.read_bytes()


def test_salvage_expectation(tmp_path):
    data = _synthetic_mcap(tmp_path / "s.mcap")
    layout = parse_layout(data)
    assert len(layout.chunks) == 3 and layout.frames() == 6
    c0, c1, c2 = layout.chunks
    per = [len({t for _, t in c.images}) for c in layout.chunks]
    cut = Damage("truncate", "t", truncate_at=(c1.offset + c1.end) // 2).expectation(layout)
    assert (cut["lo"], cut["hi"]) == (per[0], per[0]) and cut["data_damaged"]
    rec = Damage("bit flip", "r", flips=[((c1.records[0] + c1.records[1]) // 2, 3)]).expectation(layout)
    assert (rec["lo"], rec["hi"]) == (per[0] + per[2], per[0] + per[2])
    # a flip outside the CRC-covered bytes may or may not lose the chunk
    hdr = Damage("bit flip", "h", flips=[(c1.time_fields[0], 0)]).expectation(layout)
    assert (hdr["lo"], hdr["hi"]) == (per[0] + per[2], 6)
    # without the summary, chunk 0's loss takes the channel definitions with it
    lost0 = Damage("truncate", "t0", truncate_at=c2.end).expectation(layout)
    assert lost0["hi"] == 6
    both = Damage("zeroed", "z", zero=[(c0.records[0], c0.records[0] + 8)], truncate_at=c2.end).expectation(layout)
    assert both["hi"] == 0, both  # channels were defined in chunk 0 only
    dup = Damage("duplicated", "d", insert_chunk=1, insert_at=c1.end)
    assert dup.expectation(layout)["lo"] == 6
    assert len(dup.apply(data, layout)) == len(data) + (c1.end - c1.offset)
