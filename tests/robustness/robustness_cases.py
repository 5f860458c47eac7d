"""The cases of the robustness campaign (issue 10), built over one small recording.

Categories:

* ``damaged files`` — a seeded corruption campaign over a small ``qr_floor`` recording
  (truncations, bit flips, zeroed blocks, duplicated chunks), each tried with ``inspect``
  (must exit 1 naming the damage, or 2 when the file is no MCAP any more) and ``run`` (must
  replay exactly the frames of the intact chunks and report the damage, or refuse when
  nothing is left); plus non-MCAP inputs.
* ``bad recordings`` — semantically wrong recordings (re-written message by message with
  ``mcap``'s Writer): a run must reject frames with a reason, warn, or refuse; never exit 0
  with nothing said.
* ``cli misuse`` — outputs onto inputs (also via a symlink and a hard link), non-.rrd and
  damaged .rrd inputs, impossible output paths, absurd options under a memory cap.
* ``faults`` — read-only and full output folders (tmpfs mounts), SIGINT / SIGTERM mid-run,
  SIGKILL then a second run into the same folder.

The expected frames of a salvage are computed here, independently of agvviz's reader, from the
pristine file's record layout: a chunk that the damage did not touch at all must be replayed;
a chunk whose record bytes (the part its CRC covers) are untouched may be; nothing else may.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import struct
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from robustness_harness import (
    DEFAULT_TIMEOUT_S,
    Case,
    Run,
    agvviz_command,
    child_env,
    run_summary,
    tmp_files,
)

#: The small recording every case starts from: 12 frames of 1280x1024, 3 chunks of ~1.2 MB.
BASE_RECORD_ARGS = ["record", "qr_floor", "--seed", "1", "--set", "duration_s=1.5", "--set", "rate_hz=8", "--set", "realism=ideal"]
CAMPAIGN_SEED = 10  # issue 10
DAMAGE_WORDS = (
    "damage", "lost", "truncat", "crc", "corrupt", "duplicate", "repeated", "magic", "footer",
    "summary", "not an mcap", "invalid", "checksum",
)
WARNING_WORDS = ("warning", "warn:", "rejected", "recording damage", "violat", "not ok", "mismatch")

# -- the workspace: base recording and run -------------------------------------------------------


@dataclass
class Workspace:
    """Folder holding the pristine inputs every case copies or reads."""

    root: Path
    base_mcap: Path = field(init=False)
    base_rrd: Path = field(init=False)
    layout: "Layout" = field(init=False)
    base_frames: int = field(init=False)

    def __post_init__(self):
        self.root = Path(self.root)
        self.base_mcap = self.root / "base" / "qr_floor.mcap"
        self.base_rrd = self.root / "base" / "qr_floor-lm.rrd"

    def build(self) -> "Workspace":
        base = self.base_mcap.parent
        base.mkdir(parents=True, exist_ok=True)
        if not self.base_mcap.exists():
            _check_call(BASE_RECORD_ARGS + ["--out", str(self.base_mcap)], base)
        if not self.base_rrd.exists():
            _check_call(["run", str(self.base_mcap), "--out", str(self.base_rrd)], base)
        summary = run_summary(self.base_rrd)
        assert summary is not None, "the base run's summary cannot be read back"
        assert summary["frames"] == summary["solved"] and not summary["rejected"], summary
        assert not summary.get("recording_damage"), summary
        assert not _summary_warnings(summary), summary
        for p in (self.base_mcap, self.base_rrd):
            os.chmod(p, 0o444)  # cases copy what they may change
        self.layout = parse_layout(self.base_mcap.read_bytes())
        self.base_frames = self.layout.frames()
        assert self.base_frames == summary["frames"], (self.base_frames, summary["frames"])
        assert len(self.layout.chunks) >= 3, "the base recording should span several chunks"
        return self

    def case_dir(self, category: str, name: str) -> Path:
        d = self.root / "cases" / category.replace(" ", "_") / name
        if d.exists():
            _force_rmtree(d)
        d.mkdir(parents=True)
        return d


def _check_call(args: list[str], cwd: Path) -> None:
    proc = subprocess.run(agvviz_command() + args, cwd=cwd, env=child_env(), capture_output=True,
                          text=True, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"agvviz {' '.join(args)} failed ({proc.returncode}): {proc.stderr[-2000:]}")


def _force_rmtree(path: Path) -> None:
    for p in Path(path).rglob("*"):
        try:
            if p.is_dir() and not p.is_symlink():
                os.chmod(p, 0o755)
            elif not p.is_symlink():
                os.chmod(p, 0o644)
        except OSError:
            pass
    shutil.rmtree(path, ignore_errors=True)


# -- MCAP layout, parsed independently of agvviz ---------------------------------------------------
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_DATA_END = 0x0F
MAGIC = b"\x89MCAP0\r\n"


@dataclass
class ChunkInfo:
    offset: int  # record start (opcode byte)
    end: int  # one past the record
    time_fields: tuple[int, int]  # message_start_time, message_end_time
    records: tuple[int, int]  # the bytes the chunk CRC covers
    channels: dict[int, str]  # channels defined inside
    images: list[tuple[int, int]]  # (channel id, log time) of every message
    setup: set = field(default_factory=set)  # "calibration" / "tf_static": what a replay needs held here


@dataclass
class Layout:
    size: int
    records: list[tuple[int, int, int]]  # (offset, opcode, end) of top-level records
    chunks: list[ChunkInfo]
    data_end: tuple[int, int]  # DataEnd record (offset, end)
    summary_channels: dict[int, str]

    def image_topic(self, topic: str) -> bool:
        return topic.startswith("/cam/") and topic.endswith("/image")

    def frames(self, present: Optional[list[bool]] = None, summary: bool = True) -> int:
        """Distinct image log times in the chunks marked present, counting only messages whose
        channel is known when they are read (from an intact summary, or a present chunk)."""
        known = dict(self.summary_channels) if summary else {}
        times = set()
        for i, chunk in enumerate(self.chunks):
            if present is not None and not present[i]:
                continue
            known.update(chunk.channels)
            for channel_id, log_time in chunk.images:
                if self.image_topic(known.get(channel_id, "")):
                    times.add(log_time)
        return len(times)


def _u(fmt: str, data: bytes, at: int):
    return struct.unpack_from(fmt, data, at)


def parse_layout(data: bytes) -> Layout:
    assert data[:8] == MAGIC
    records = []
    chunks = []
    data_end = (0, 0)
    summary_channels: dict[int, str] = {}
    offset = 8
    while offset < len(data) - 8:
        opcode, length = _u("<BQ", data, offset)
        body = offset + 9
        end = body + length
        records.append((offset, opcode, end))
        if opcode == OP_CHUNK:
            (comp_len,) = _u("<I", data, body + 28)
            rec_at = body + 32 + comp_len
            (rec_len,) = _u("<Q", data, rec_at)
            rec_start, rec_end = rec_at + 8, rec_at + 8 + rec_len
            channels, images = {}, []
            at = rec_start
            while at < rec_end:
                op, ln = _u("<BQ", data, at)
                b = at + 9
                if op == OP_CHANNEL:
                    cid, _sid, tlen = _u("<HHI", data, b)
                    channels[cid] = data[b + 8 : b + 8 + tlen].decode()
                elif op == OP_MESSAGE:
                    cid, _seq, log_time = _u("<HIQ", data, b)
                    images.append((cid, log_time))
                at = b + ln
            chunks.append(ChunkInfo(offset, end, (body, body + 16), (rec_start, rec_end), channels, images))
        elif opcode == OP_DATA_END:
            data_end = (offset, end)
        elif opcode == OP_CHANNEL:
            cid, _sid, tlen = _u("<HHI", data, body)
            summary_channels[cid] = data[body + 8 : body + 8 + tlen].decode()
        elif opcode == OP_FOOTER:
            break
        offset = end
    # keep only image messages (topic known from any definition)
    topics = dict(summary_channels)
    for c in chunks:
        topics.update(c.channels)
    for c in chunks:
        c.setup = {("calibration" if topics.get(cid, "").endswith("/calibration") else "tf_static")
                   for cid, _ in c.images
                   if topics.get(cid, "").endswith("/calibration") or topics.get(cid, "") == "/tf_static"}
        c.images = [(cid, t) for cid, t in c.images if topics.get(cid, "").startswith("/cam/")
                    and topics.get(cid, "").endswith("/image")]
    return Layout(len(data), records, chunks, data_end, summary_channels)


# -- damage ------------------------------------------------------------------------------------
@dataclass
class Damage:
    """One corruption of the pristine file: ``ranges`` of modified bytes, a truncation, or a
    chunk inserted again (``insert_chunk`` copied to ``insert_at``)."""

    kind: str
    name: str
    truncate_at: Optional[int] = None
    flips: list[tuple[int, int]] = field(default_factory=list)  # (offset, bit)
    zero: list[tuple[int, int]] = field(default_factory=list)  # (start, end)
    insert_chunk: Optional[int] = None
    insert_at: Optional[int] = None

    def apply(self, data: bytes, layout: Layout) -> bytes:
        out = bytearray(data)
        for at, bit in self.flips:
            out[at] ^= 1 << bit
        for a, b in self.zero:
            out[a:b] = bytes(b - a)
        if self.truncate_at is not None:
            del out[self.truncate_at :]
        if self.insert_chunk is not None:
            c = layout.chunks[self.insert_chunk]
            out[self.insert_at : self.insert_at] = data[c.offset : c.end]
        return bytes(out)

    def modified(self) -> list[tuple[int, int]]:
        """Ranges of pristine offsets whose bytes differ (truncation and insertion apart)."""
        return [(a, a + 1) for a, _ in self.flips] + [tuple(z) for z in self.zero]

    def expectation(self, layout: Layout) -> dict:
        """What a correct salvage gives: frames between ``lo`` (untouched chunks) and ``hi``
        (chunks whose CRC-covered bytes are untouched), whether the data section was damaged
        (a warning is due), and whether the MCAP magic survived."""
        size = layout.size if self.truncate_at is None else self.truncate_at
        mods = self.modified()

        def hit(a: int, b: int) -> bool:
            return any(x < b and a < y for x, y in mods)

        strict, content = [], []
        for c in layout.chunks:
            inside = c.end <= size
            strict.append(inside and not hit(c.offset, c.end))
            content.append(inside and not hit(*c.records))
        summary_ok = self.truncate_at is None and not hit(layout.data_end[1], layout.size)
        magic_ok = size >= 8 and not hit(0, 8)
        data_damaged = (
            hit(0, layout.data_end[1])
            or (self.truncate_at is not None and self.truncate_at < layout.size)
            or self.insert_chunk is not None
        )
        if self.insert_chunk is not None:
            lo = hi = layout.frames()
        else:
            lo = layout.frames(strict, summary_ok)
            # with an intact summary or not, the upper bound may use any surviving definition
            hi = max(layout.frames(content, summary_ok), layout.frames(content, True) if summary_ok else 0)
        first_chunk = layout.chunks[0].offset
        # Without the calibration or the camera's transform no frame can be used, and a run
        # must refuse loudly (issue 11) rather than replay frames it can only reject.
        kept = set().union(*(c.setup for c, ok in zip(layout.chunks, strict) if ok))
        return {
            "setup_lost": not {"calibration", "tf_static"} <= kept,
            "lo": lo,
            "hi": hi,
            "all": layout.frames(),
            "magic_ok": magic_ok,
            "data_damaged": data_damaged,
            # damage before the first chunk (magic, header, metadata) may make a run refuse
            "head_damaged": not magic_ok or hit(0, first_chunk) or (size < first_chunk),
        }


def _where(layout: Layout, offset: int) -> str:
    for i, c in enumerate(layout.chunks):
        if c.offset <= offset < c.end:
            if offset < c.offset + 9:
                part = "record header"
            elif c.time_fields[0] <= offset < c.time_fields[1]:
                part = "time fields"
            elif c.records[0] <= offset < c.records[1]:
                part = "records"
            else:
                part = "size/crc/compression fields"
            return f"chunk {i} {part}"
    for rec_off, opcode, end in layout.records:
        if rec_off <= offset < end:
            return f"record 0x{opcode:02x} at {rec_off}"
    return "magic" if offset < 8 or offset >= layout.size - 8 else "between records"


def corruption_campaign(layout: Layout, seed: int = CAMPAIGN_SEED, n_seeds: int = 4) -> list[Damage]:
    """Every corruption of the campaign: structural ones (each chunk's fields and edges, the
    other records), then per seed ``seed .. seed + n_seeds - 1`` two random truncations,
    three random bit flips, one five-byte multi-flip and one zeroed 4 KiB block. Deterministic."""
    damages: list[Damage] = []
    size = layout.size
    de_off, de_end = layout.data_end
    # truncations at structural offsets
    cuts = [0, 4, 8, 9, 20, layout.records[1][0] if len(layout.records) > 1 else 37]
    for i, c in enumerate(layout.chunks):
        if i == 1:  # every edge of one chunk; the middle and its header for the others
            cuts += [c.offset, c.offset + 1, c.offset + 9, c.records[0] + 100, (c.offset + c.end) // 2, c.end - 1, c.end]
        else:
            cuts += [c.offset + 9, (c.offset + c.end) // 2]
    cuts += [de_off, de_off + 5, de_end, (de_end + size) // 2, size - 30, size - 8, size - 1]
    for at in sorted(set(cuts)):
        damages.append(Damage("truncate", f"truncate@{at}", truncate_at=at))
    # bit flips: targeted fields of every chunk, other records, then seeded random bytes
    flips = []
    for i, c in enumerate(layout.chunks):
        body = c.offset + 9
        if i != 1:  # every field of one chunk; opcode, CRC and records for the others
            flips += [(c.offset, 1, f"chunk{i}-opcode"), (body + 24, 5, f"chunk{i}-crc"),
                      ((c.records[0] + c.records[1]) // 2, 7, f"chunk{i}-mid-records")]
            continue
        flips += [
            (c.offset, 1, f"chunk{i}-opcode"),
            (c.offset + 1, 0, f"chunk{i}-length-lsb"),
            (c.offset + 3, 4, f"chunk{i}-length+2^20"),
            (c.time_fields[0] + 2, 3, f"chunk{i}-start-time"),
            (body + 16, 0, f"chunk{i}-uncompressed-size"),
            (body + 24, 5, f"chunk{i}-crc"),
            (c.records[0] - 8, 2, f"chunk{i}-records-length"),
            (c.records[0] + 4, 6, f"chunk{i}-first-record"),
            ((c.records[0] + c.records[1]) // 2, 7, f"chunk{i}-mid-records"),
        ]
    flips += [(3, 0, "magic"), (layout.records[0][0] + 12, 1, "header"),
              (layout.records[1][0] + 20, 2, "metadata"), (de_off + 10, 0, "dataend-crc"),
              ((de_end + size) // 2, 4, "summary"), (size - 20, 1, "footer"), (size - 3, 0, "closing-magic")]
    mi = [(o, e) for o, op, e in layout.records if op == 0x07]  # message index records
    if mi:
        flips += [(mi[0][0] + 1, 0, "message-index-length"), (mi[0][0] + 3, 4, "message-index-length+2^20")]
    for at, bit, name in flips:
        damages.append(Damage("bit flip", f"flip-{name}", flips=[(at, bit)]))
    # zeroed blocks: each whole chunk, a chunk's CRC and first records, the first 64 bytes
    for i, c in enumerate(layout.chunks):
        damages.append(Damage("zeroed", f"zero-chunk{i}", zero=[(c.offset, c.end)]))
        damages.append(Damage("zeroed", f"zero-chunk{i}-crc+records", zero=[(c.offset + 9 + 24, c.records[0] + 4096)]))
    damages.append(Damage("zeroed", "zero-first-64", zero=[(0, 64)]))
    # seeded random damage
    for s in range(seed, seed + n_seeds):
        rng = random.Random(s)
        for k in range(2):
            at = rng.randrange(1, size)
            damages.append(Damage("truncate", f"s{s}-truncate@{at}", truncate_at=at))
        for k in range(3):
            at = rng.randrange(0, size)
            bit = rng.randrange(8)
            damages.append(Damage("bit flip", f"s{s}-flip@{at}.{bit}", flips=[(at, bit)]))
        multi = sorted((rng.randrange(0, size), rng.randrange(8)) for _ in range(5))
        damages.append(Damage("bit flip", f"s{s}-5flips@{multi[0][0]}", flips=multi))
        at = rng.randrange(0, size - 4096)
        damages.append(Damage("zeroed", f"s{s}-zero4k@{at}", zero=[(at, at + 4096)]))
    # duplicated chunks: right after itself, the first at the end of the data section,
    # the last before the first
    for i, c in enumerate(layout.chunks):
        damages.append(Damage("duplicated", f"dup-chunk{i}-after-itself", insert_chunk=i, insert_at=c.end))
    damages.append(Damage("duplicated", "dup-chunk0-at-end", insert_chunk=0, insert_at=de_off))
    last = len(layout.chunks) - 1
    damages.append(Damage("duplicated", f"dup-chunk{last}-before-chunk0", insert_chunk=last,
                          insert_at=layout.chunks[0].offset))
    return damages


def fast_corruptions(layout: Layout) -> list[Damage]:
    """A handful for the default test run."""
    c1 = layout.chunks[1]
    last = len(layout.chunks) - 1
    mi = [o for o, op, _ in layout.records if op == 0x07][0]  # first message index record
    return [
        Damage("truncate", "truncate@mid-chunk1", truncate_at=(c1.offset + c1.end) // 2),
        Damage("bit flip", "flip-chunk1-mid-records", flips=[((c1.records[0] + c1.records[1]) // 2, 7)]),
        Damage("bit flip", "flip-message-index-length+2^20", flips=[(mi + 3, 4)]),
        Damage("duplicated", f"dup-chunk{last}-before-chunk0", insert_chunk=last, insert_at=layout.chunks[0].offset),
    ]


# -- checks ------------------------------------------------------------------------------------
def _summary_warnings(summary: dict) -> list[str]:
    found = []
    for key, value in summary.items():
        if "warn" in key.lower() and value:
            found += value if isinstance(value, list) else [str(value)]
    return found


def _said_something(summary: Optional[dict], run: Run) -> list[str]:
    """Rejections, warnings or damage notes a run gave (summary and stderr)."""
    said = []
    if summary:
        if summary.get("rejected"):
            said.append(f"rejected {summary['rejected']}")
        if summary.get("recording_damage"):
            said.append(f"damage {summary['recording_damage'][:2]}")
        said += [f"warning {w}" for w in _summary_warnings(summary)]
    for line in run.stderr.splitlines():
        low = line.lower()
        if any(w in low for w in ("warning", "recording damage", "note:")):
            said.append(line.strip())
    return said


def _names_damage(run: Run) -> bool:
    text = (run.stdout + run.stderr).lower()
    return any(w in text for w in DAMAGE_WORDS)


def inspect_damage_check(run: Run, case: Case) -> list:
    if run.returncode in (1, 2) and not _names_damage(run):
        return [("silent wrong", f"inspect exit {run.returncode} without naming the damage")]
    return []


def run_damage_check(expect: dict, out: Path) -> Callable[[Run, Case], list]:
    def check(run: Run, case: Case) -> list:
        if run.returncode == 0:
            summary = run_summary(out)
            if summary is None:
                return [("partial output", f"{out}: no readable run/summary after exit 0")]
            frames = summary.get("frames")
            problems = []
            if not expect["lo"] <= frames <= expect["hi"]:
                want = f"{expect['lo']}" if expect["lo"] == expect["hi"] else f"{expect['lo']}..{expect['hi']}"
                problems.append(("silent wrong", f"salvage replayed {frames} frames; the intact chunks hold {want} "
                                 f"(of {expect['all']})"))
            if expect["data_damaged"] and not summary.get("recording_damage"):
                problems.append(("silent wrong", "exit 0 on a damaged recording with no damage reported in the summary"))
            return problems
        if run.returncode == 2 and expect.get("setup_lost") and "could be used" in run.stderr:
            return []  # calibration or transforms lost: "no frame could be used" is the right answer
        if run.returncode == 2 and expect["hi"] > 0 and not expect["head_damaged"]:
            return [("crash", f"refused the recording although its intact chunks hold {expect['lo']}..{expect['hi']} frames")]
        return []

    return check


def said_check(out: Optional[Path]) -> Callable[[Run, Case], list]:
    """Exit 0 is right only when the run said something: a rejection, a warning, damage."""

    def check(run: Run, case: Case) -> list:
        if run.returncode != 0:
            return []
        summary = run_summary(out) if out is not None else None
        said = _said_something(summary, run)
        if out is None:
            text = (run.stdout + run.stderr).lower()
            if any(w in text for w in WARNING_WORDS):
                said.append("a warning in the output")
        if not said:
            return [("silent wrong", "exit 0 and nothing said (no rejection, warning or damage note)")]
        return [("info", "said: " + " | ".join(said)[:300])]

    return check


# -- damaged-file cases ----------------------------------------------------------------------
def damaged_cases(ws: Workspace, damages: list[Damage], commands=("inspect", "run")) -> list[Case]:
    pristine = ws.base_mcap.read_bytes()
    cases = []
    for d in damages:
        expect = d.expectation(ws.layout)
        where = ""
        if d.flips:
            where = _where(ws.layout, d.flips[0][0])
        elif d.zero:
            where = _where(ws.layout, d.zero[0][0])
        elif d.truncate_at is not None:
            where = _where(ws.layout, max(0, d.truncate_at - 1))
        note = f"{d.kind} ({where}); intact chunks hold {expect['lo']}..{expect['hi']} of {expect['all']} frames"
        for command in commands:
            cdir = ws.case_dir("damaged files", f"{command}-{d.name}")
            rec = cdir / "damaged.mcap"

            def setup(case, d=d, rec=rec):
                rec.write_bytes(d.apply(pristine, ws.layout))

            if command == "inspect":
                cases.append(Case(
                    "damaged files", f"inspect {d.name}", ["inspect", rec], expect="error", codes=(1, 2),
                    inputs=[rec], cwd=cdir, setup=setup, check=inspect_damage_check, check_errors=True, note=note,
                ))
            else:
                out = cdir / "out.rrd"
                cases.append(Case(
                    "damaged files", f"run {d.name}", ["run", rec, "--out", out], expect="error_or_ok", codes=(2,),
                    inputs=[rec], outputs=[out], cwd=cdir, setup=setup, check=run_damage_check(expect, out),
                    check_errors=True, note=note,
                ))
    return cases


def zstd_bomb_chunk(uncompressed_bytes: int = 1 << 30) -> bytes:
    """A chunk record (opcode, length, body) whose zstd data inflates to ``uncompressed_bytes``
    zero bytes, with the right size and CRC: a few KiB on disk, 1 GiB in memory, and (zeros
    being records of opcode 0 and length 0) ~10^8 empty records inside."""
    import zlib

    import zstandard

    block = bytes(1 << 24)
    comp = zstandard.ZstdCompressor(level=1).compressobj()
    parts, crc = [], 0
    for _ in range(uncompressed_bytes // len(block)):
        parts.append(comp.compress(block))
        crc = zlib.crc32(block, crc)
    parts.append(comp.flush())
    data = b"".join(parts)
    body = struct.pack("<QQQI", 0, 0, uncompressed_bytes, crc) + struct.pack("<I", 4) + b"zstd"
    body += struct.pack("<Q", len(data)) + data
    return struct.pack("<BQ", OP_CHUNK, len(body)) + body


def bomb_cases(ws: Workspace) -> list[Case]:
    """A decompression bomb chunk appended to the data section, under the memory cap."""
    cases = []
    for command in ("inspect", "run"):
        cdir = ws.case_dir("damaged files", f"{command}-zstd-bomb")
        rec = cdir / "bomb.mcap"
        out = cdir / "out.rrd"

        def setup(case, rec=rec):
            if not rec.exists():
                data = ws.base_mcap.read_bytes()
                at = ws.layout.data_end[0]
                rec.write_bytes(data[:at] + zstd_bomb_chunk() + data[at:])

        expect = {"lo": ws.base_frames, "hi": ws.base_frames, "all": ws.base_frames, "data_damaged": True,
                  "head_damaged": False}
        note = ("decompression bomb (a zstd chunk of 1 GiB of zeros with a valid CRC, before DataEnd); "
                "a 4 MB file must be done within 60 s")
        if command == "inspect":
            cases.append(Case("damaged files", "inspect zstd-bomb", ["inspect", rec], codes=(1, 2), inputs=[rec],
                              cwd=cdir, setup=setup, memory_cap=True, check=inspect_damage_check, check_errors=True,
                              note=note, timeout_s=60))
        else:
            cases.append(Case("damaged files", "run zstd-bomb", ["run", rec, "--out", out], expect="error_or_ok",
                              codes=(2,), inputs=[rec], outputs=[out], cwd=cdir, setup=setup, memory_cap=True,
                              check=run_damage_check(expect, out), check_errors=True, note=note, timeout_s=60))
    return cases


def non_mcap_cases(ws: Workspace, commands=("inspect", "run"), which=None) -> list[Case]:
    rng = random.Random(CAMPAIGN_SEED + 1)
    makers = {
        "empty": lambda p: p.write_bytes(b""),
        "random-bytes": lambda p: p.write_bytes(bytes(rng.randrange(256) for _ in range(65536))),
        "text-file": lambda p: p.write_text("topic,time\n/cam/front/image,0\n" * 100),
        "magic-only": lambda p: p.write_bytes(MAGIC),
        "directory": lambda p: p.mkdir(),
        "fifo": lambda p: os.mkfifo(p),  # open() would block for ever waiting for a writer
        "symlink-to-dev-zero": lambda p: p.symlink_to("/dev/zero"),
        "dangling-symlink": lambda p: p.symlink_to(p.parent / "nowhere.mcap"),
    }
    cases = []
    for kind, make in makers.items():
        if which and kind not in which:
            continue
        for command in commands:
            cdir = ws.case_dir("damaged files", f"{command}-{kind}")
            target = cdir / ("input.mcap")
            make(target)
            args = [command, target] + (["--out", cdir / "out.rrd"] if command == "run" else [])
            cases.append(Case(
                "damaged files", f"{command} {kind}", args, expect="error", codes=(2,), inputs=[target],
                outputs=[cdir / "out.rrd"] if command == "run" else [], cwd=cdir,
                timeout_s=30 if kind == "fifo" else DEFAULT_TIMEOUT_S,
            ))
    return cases


# -- semantically bad recordings -----------------------------------------------------------------
def rewrite(src: Path, dst: Path, mutate: Callable) -> None:
    """Copy ``src`` to ``dst`` message by message through ``mutate(topic, schema_name, log_time,
    data) -> list of (log_time, data)`` (same schemas, channels, metadata, chunking)."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        header = reader.get_header()
        writer = Writer(f_out, chunk_size=1024 * 1024, compression=CompressionType.NONE)
        writer.start(profile=header.profile, library=header.library)
        for md in reader.iter_metadata():
            writer.add_metadata(md.name, dict(md.metadata))
        schema_ids, channel_ids = {}, {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schema_ids:
                schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channel_ids:
                channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_ids.get(channel.schema_id, 0),
                    dict(channel.metadata),
                )
            for log_time, data in mutate(channel.topic, schema.name if schema else "", message.log_time, message.data):
                writer.add_message(channel_ids[channel.id], log_time=log_time, data=data,
                                   publish_time=log_time, sequence=message.sequence)
        writer.finish()


def _image_times(src: Path) -> list[int]:
    from mcap.reader import make_reader

    with open(src, "rb") as f:
        return [m.log_time for _, c, m in make_reader(f).iter_messages(log_time_order=False)
                if c.topic.endswith("/image")]


def semantic_mutations(ws: Workspace) -> dict[str, Callable]:
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame

    times = _image_times(ws.base_mcap)
    t0, t1 = min(times), max(times)
    hour = 3600 * 10**9
    counter = {"image": 0}

    def stamp(msg, t):
        msg.timestamp.seconds, msg.timestamp.nanos = divmod(t, 10**9)

    def image(fn):
        def mutate(topic, schema, t, data):
            if schema != "foxglove.CompressedImage":
                return [(t, data)]
            msg = CompressedImage.FromString(data)
            return fn(t, msg)
        return mutate

    def reversed_times(t, msg):
        t2 = t0 + t1 - t
        stamp(msg, t2)
        return [(t2, msg.SerializeToString())]

    def one_time(t, msg):
        stamp(msg, t0)
        return [(t0, msg.SerializeToString())]

    def zero_bytes(t, msg):
        if t == times[len(times) // 2]:
            msg.data = b""
        return [(t, msg.SerializeToString())]

    def bmp(t, msg):
        msg.format = "bmp"
        return [(t, msg.SerializeToString())]

    def all_zero(topic, schema, t, data):
        return [(0, data)]

    def gt_shift(topic, schema, t, data):
        if topic != "/agv/ground_truth":
            return [(t, data)]
        msg = PoseInFrame.FromString(data)
        stamp(msg, t + hour)
        return [(t + hour, msg.SerializeToString())]

    def calibration(width, height):
        def mutate(topic, schema, t, data):
            if schema != "foxglove.CameraCalibration":
                return [(t, data)]
            msg = CameraCalibration.FromString(data)
            msg.width, msg.height = width, height
            return [(t, msg.SerializeToString())]
        return mutate

    def drop(which):
        def mutate(topic, schema, t, data):
            return [] if topic == which else [(t, data)]
        return mutate

    def gt_nan(topic, schema, t, data):
        if topic != "/agv/ground_truth":
            return [(t, data)]
        msg = PoseInFrame.FromString(data)
        msg.pose.position.x = float("nan")
        return [(t, msg.SerializeToString())]

    garbage_rng = random.Random(CAMPAIGN_SEED + 3)

    def garbage(t, msg):
        msg.data = bytes(garbage_rng.randrange(256) for _ in range(len(msg.data) // 64))
        return [(t, msg.SerializeToString())]

    def map_far(topic, schema, t, data):
        if topic != "/markers/map":
            return [(t, data)]
        value = json.loads(data)
        for m in value["markers"]:
            m["corners_world_m"] = [[x + 10_000.0, y, z] for x, y, z in m["corners_world_m"]]
        return [(t, json.dumps(value).encode())]

    return {
        "reversed-image-times": image(reversed_times),
        "images-one-time": image(one_time),
        "all-log-times-0": all_zero,
        "ground-truth-plus-1h": gt_shift,
        "calibration-640x480": calibration(640, 480),
        "calibration-width-2^32-1": calibration(2**32 - 1, 1024),
        "zero-byte-image": image(zero_bytes),
        "image-format-bmp": image(bmp),
        "map-10km-from-payloads": map_far,
        "no-calibration": drop("/cam/front/calibration"),
        "no-tf-static": drop("/tf_static"),
        "ground-truth-nan": gt_nan,
        "image-random-bytes": image(garbage),
    }


def semantic_cases(ws: Workspace, which=None, commands=("run",)) -> list[Case]:
    cases = []
    for name, mutate in semantic_mutations(ws).items():
        if which and name not in which:
            continue
        for command in commands:
            cdir = ws.case_dir("bad recordings", f"{command}-{name}")
            rec = cdir / f"{name.replace('^', '')}.mcap"

            def setup(case, rec=rec, mutate=mutate):
                if not rec.exists():
                    rewrite(ws.base_mcap, rec, mutate)

            if command == "run":
                out = cdir / "out.rrd"
                cases.append(Case(
                    "bad recordings", f"run {name}", ["run", rec, "--out", out], expect="error_or_ok", codes=(2,),
                    inputs=[rec], outputs=[out], cwd=cdir, setup=setup, check=said_check(out),
                ))
            else:
                cases.append(Case(
                    "bad recordings", f"inspect {name}", ["inspect", rec], expect="error_or_ok", codes=(1, 2),
                    inputs=[rec], cwd=cdir, setup=setup, check=said_check(None), error_line=True,
                ))
    return cases


# -- CLI misuse ------------------------------------------------------------------------------
def _copy(src: Path, dst: Path) -> Path:
    shutil.copyfile(src, dst)
    return dst


def cli_cases(ws: Workspace, fast: bool = False) -> list[Case]:
    cases = []
    rng = random.Random(CAMPAIGN_SEED + 2)
    rrd_bytes = ws.base_rrd.read_bytes()

    def diff_dir(name):
        d = ws.case_dir("cli misuse", name)
        return d, _copy(ws.base_rrd, d / "a.rrd"), _copy(ws.base_rrd, d / "b.rrd")

    # output onto an input: directly, via a symlink, via a hard link
    d, a, b = diff_dir("diff-out-is-input")
    cases.append(Case("cli misuse", "diff --out onto input A", ["diff", a, b, "--out", a], codes=(2, 3),
                      inputs=[a, b], cwd=d))
    d, a, b = diff_dir("diff-out-symlink-to-input")
    link = d / "link.rrd"
    link.symlink_to(a)
    cases.append(Case("cli misuse", "diff --out symlink to input A", ["diff", a, b, "--out", link], codes=(2, 3),
                      inputs=[a, b, link], cwd=d))
    d, a, b = diff_dir("diff-out-hardlink-to-input")
    hard = d / "hard.rrd"
    os.link(a, hard)
    cases.append(Case("cli misuse", "diff --out hard link to input A", ["diff", a, b, "--out", hard],
                      codes=(2, 3), inputs=[a, b, hard], cwd=d))
    # run --out onto its recording (via a symlink)
    d = ws.case_dir("cli misuse", "run-out-symlink-to-recording")
    rec = _copy(ws.base_mcap, d / "rec.mcap")
    (d / "rec.rrd").symlink_to(rec)
    cases.append(Case("cli misuse", "run --out symlink to the recording", ["run", rec, "--out", d / "rec.rrd"],
                      codes=(2, 3), inputs=[rec, d / "rec.rrd"], cwd=d))

    # bad .rrd inputs for export and diff
    bad_rrds = {
        "non-rrd (an .mcap)": None,
        "truncated .rrd": rrd_bytes[: len(rrd_bytes) // 2],
        "random bytes .rrd": bytes(rng.randrange(256) for _ in range(65536)),
        "empty .rrd": b"",
        "text .rrd": b"this is not a rerun file\n" * 20,
    }
    if fast:
        bad_rrds = {k: bad_rrds[k] for k in ("truncated .rrd", "empty .rrd")}
    for label, content in bad_rrds.items():
        slug = label.replace(" ", "-").replace("(", "").replace(")", "").replace(".", "")
        d = ws.case_dir("cli misuse", f"export-{slug}")
        src = _copy(ws.base_mcap, d / "run.mcap") if content is None else d / "run.rrd"
        if content is not None:
            src.write_bytes(content)
        stem = src.with_suffix("")
        cases.append(Case("cli misuse", f"export {label}", ["export", src, "--format", "tum"], codes=(2,),
                          inputs=[src], outputs=[Path(f"{stem}.estimate.tum"), Path(f"{stem}.truth.tum")], cwd=d))
        d2, a, _ = diff_dir(f"diff-{slug}")
        bad = _copy(src, d2 / src.name)
        cases.append(Case("cli misuse", f"diff with B = {label}", ["diff", a, bad, "--out", d2 / "ab.rrd"],
                          codes=(2,), inputs=[a, bad], outputs=[d2 / "ab.rrd"], cwd=d2))

    # impossible output paths
    d = ws.case_dir("cli misuse", "run-out-under-file")
    rec = _copy(ws.base_mcap, d / "rec.mcap")
    (d / "plain.txt").write_text("a file, not a folder\n")
    cases.append(Case("cli misuse", "run --out under a regular file", ["run", rec, "--out", d / "plain.txt" / "x.rrd"],
                      codes=(3,), inputs=[rec, d / "plain.txt"], cwd=d))
    d = ws.case_dir("cli misuse", "run-out-proc")
    rec = _copy(ws.base_mcap, d / "rec.mcap")
    cases.append(Case("cli misuse", "run --out /proc/x/y.rrd", ["run", rec, "--out", "/proc/x/y.rrd"], codes=(3,),
                      inputs=[rec], cwd=d))
    if not fast:
        d = ws.case_dir("cli misuse", "record-out-under-file")
        (d / "plain.txt").write_text("a file, not a folder\n")
        cases.append(Case("cli misuse", "record --out under a regular file",
                          BASE_RECORD_ARGS + ["--out", d / "plain.txt" / "x.mcap"], codes=(3,),
                          inputs=[d / "plain.txt"], cwd=d))
        d, a, b = diff_dir("diff-out-under-file")
        (d / "plain.txt").write_text("x\n")
        cases.append(Case("cli misuse", "diff --out under a regular file",
                          ["diff", a, b, "--out", d / "plain.txt" / "ab.rrd"], codes=(3,), inputs=[a, b], cwd=d))
        d = ws.case_dir("cli misuse", "export-out-dir-is-file")
        r = _copy(ws.base_rrd, d / "r.rrd")
        (d / "plain.txt").write_text("x\n")
        cases.append(Case("cli misuse", "export --out-dir is a regular file",
                          ["export", r, "--out-dir", d / "plain.txt"], codes=(3,), inputs=[r, d / "plain.txt"], cwd=d))

    if not fast:
        d = ws.case_dir("cli misuse", "run-out-is-directory")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        (d / "x.rrd").mkdir()
        cases.append(Case("cli misuse", "run --out an existing directory named x.rrd",
                          ["run", rec, "--out", d / "x.rrd"], codes=(2, 3), inputs=[rec, d / "x.rrd"], cwd=d))
        d = ws.case_dir("cli misuse", "run-out-name-too-long")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        cases.append(Case("cli misuse", "run --out a 300-character file name",
                          ["run", rec, "--out", d / ("n" * 300 + ".rrd")], codes=(2, 3), inputs=[rec], cwd=d))
        d = ws.case_dir("cli misuse", "record-out-wrong-suffix")
        cases.append(Case("cli misuse", "record --out x.txt", BASE_RECORD_ARGS + ["--out", d / "x.txt"], codes=(2,),
                          outputs=[d / "x.txt"], cwd=d))
        d = ws.case_dir("cli misuse", "export-format-csv")
        r = _copy(ws.base_rrd, d / "r.rrd")
        cases.append(Case("cli misuse", "export --format csv", ["export", r, "--format", "csv"], codes=(2,),
                          inputs=[r], outputs=[d / "r.estimate.csv", d / "r.estimate.tum"], cwd=d))
        for opts in (["--rpe-delta", "0"], ["--rpe-delta", "-5"], ["--align", "bogus"]):
            d, a, b = diff_dir("diff" + "".join(opts).replace("-", "_"))
            cases.append(Case("cli misuse", f"diff {' '.join(opts)}", ["diff", a, b, *opts, "--no-images"], codes=(2,),
                              inputs=[a, b], cwd=d))
        d = ws.case_dir("cli misuse", "sweep-unknown-setting")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        cases.append(Case("cli misuse", "sweep --set nosuch=1,2",
                          ["sweep", rec, "--set", "nosuch=1,2", "--out-dir", d / "sweep"], codes=(2,), inputs=[rec],
                          outputs=[d / "sweep"], cwd=d))

    # sweep --jobs 0 (and negative)
    for jobs in (["0"] if fast else ["0", "-1"]):
        d = ws.case_dir("cli misuse", f"sweep-jobs-{jobs}")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        cases.append(Case("cli misuse", f"sweep --jobs {jobs}",
                          ["sweep", rec, "--set", "solver=p4p", "--jobs", jobs, "--out-dir", d / "sweep"],
                          codes=(2,), inputs=[rec], outputs=[d / "sweep"], cwd=d, timeout_s=120))

    # absurd scenario options under a memory cap
    absurd = ["duration_s=1e9", "rate_hz=1e9", "width_px=100000"]
    if not fast:
        absurd += ["duration_s=nan", "rate_hz=0", "height_px=-1", "supersample=1000", "duration_s=1e-9"]
    for opt in absurd:
        d = ws.case_dir("cli misuse", f"record-{opt}")
        out = d / "x.mcap"
        cases.append(Case("cli misuse", f"record --set {opt}", ["record", "qr_floor", "--set", opt, "--out", out],
                          codes=(2,), outputs=[out], cwd=d, memory_cap=True, timeout_s=120))
    if not fast:
        for opt in ["max_reproj_px=nan", "lm_max_iterations=-1", "lm_max_iterations=10000000000", "solver="]:
            d = ws.case_dir("cli misuse", f"run-{opt}")
            rec = _copy(ws.base_mcap, d / "rec.mcap")
            cases.append(Case("cli misuse", f"run --set {opt}", ["run", rec, "--set", opt, "--out", d / "o.rrd"],
                              codes=(2,), inputs=[rec], outputs=[d / "o.rrd"], cwd=d, memory_cap=True))

    # --fail-if with a full-width digit
    exprs = ["B.position_rmse_mm > \uff11", "B.position_rmse_mm > 1e999"]
    if not fast:
        exprs += ["__import__('os')", "B.position_rmse_mm > " + "(" * 200 + "1" + ")" * 200]
    for k, expr in enumerate(exprs):
        d, a, b = diff_dir(f"diff-fail-if-{k}")
        cases.append(Case("cli misuse", f"diff --fail-if {expr[:40]!r}", ["diff", a, b, "--fail-if", expr, "--no-images"],
                          codes=(2,), inputs=[a, b], cwd=d))
    return cases


# -- faults ----------------------------------------------------------------------------------
def _mount(target: Path, options: str) -> Optional[str]:
    """Mount a tmpfs with ``options`` at ``target``; the reason when that is not possible."""
    if shutil.which("mount") is None:
        return "no mount command here"
    target.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(target)], capture_output=True, text=True)
    if proc.returncode != 0:
        return f"cannot mount a tmpfs here ({proc.stderr.strip() or proc.returncode}); needs root / CAP_SYS_ADMIN"
    return None


def _umount(target: Path) -> None:
    if os.path.ismount(target):
        if subprocess.run(["umount", str(target)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(target)], capture_output=True)


def _wait_for_tmp(folder: Path, proc: subprocess.Popen, timeout_s: float = 60.0) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if proc.poll() is not None:
            return False
        if tmp_files([folder]):
            return True
        time.sleep(0.02)
    return False


def signal_driver(signum: int, settle_s: float = 0.4, folder: Optional[Path] = None, at_start_s: Optional[float] = None):
    """Send ``signum`` to the process group once its temporary output exists (mid-run), or
    ``at_start_s`` seconds after it started (during start-up)."""

    def drive(proc: subprocess.Popen, case: Case) -> None:
        if at_start_s is not None:
            time.sleep(at_start_s)
            case.driven = proc.poll() is None
            if case.driven:
                os.killpg(proc.pid, signum)
            return
        watched = folder or Path(case.outputs[0]).parent
        case.driven = False
        if _wait_for_tmp(watched, proc):
            time.sleep(settle_s)
            if proc.poll() is None:
                os.killpg(proc.pid, signum)
                case.driven = True

    return drive


def no_tmp_check(folder: Path):
    def check(run: Run, case: Case) -> list:
        left = tmp_files([folder])
        if left:
            return [("partial output", "temporary file(s) left in the output folder: " + ", ".join(map(str, sorted(left))))]
        return []

    return check


def fault_cases(ws: Workspace, fast: bool = False) -> list[Case]:
    cases = []

    # read-only output folder: a read-only tmpfs (chmod does not stop root)
    for command in (["run"] if fast else ["run", "record"]):
        d = ws.case_dir("faults", f"{command}-read-only-folder")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        ro = d / "ro"
        out = ro / ("x.rrd" if command == "run" else "x.mcap")
        args = ["run", rec, "--out", out] if command == "run" else BASE_RECORD_ARGS + ["--out", out]

        def setup(case, ro=ro):
            why = _mount(ro, "ro,size=1m")
            if why:
                case.skip_reason = why

        cases.append(Case("faults", f"{command} --out into a read-only folder", args, codes=(3,), inputs=[rec],
                          outputs=[out], cwd=d, setup=setup, teardown=lambda case, ro=ro: _umount(ro)))

    # full disk: a 1 MiB tmpfs (the run .rrd of the base recording is ~4 MB)
    for command in (["run"] if fast else ["run", "record", "diff"]):
        d = ws.case_dir("faults", f"{command}-full-disk")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        full = d / "full"
        if command == "run":
            out = full / "x.rrd"
            args, inputs = ["run", rec, "--out", out], [rec]
        elif command == "record":
            out = full / "x.mcap"
            args, inputs = BASE_RECORD_ARGS + ["--out", out], []
        else:
            a, b = _copy(ws.base_rrd, d / "a.rrd"), _copy(ws.base_rrd, d / "b.rrd")
            out = full / "ab.rrd"
            args, inputs = ["diff", a, b, "--out", out], [a, b]

        def setup(case, full=full):
            why = _mount(full, "size=1m")
            if why:
                case.skip_reason = why

        cases.append(Case("faults", f"{command} --out onto a full disk (1 MiB tmpfs)", args, codes=(3,),
                          inputs=inputs, outputs=[out], cwd=d, setup=setup,
                          teardown=lambda case, full=full: _umount(full)))

    # SIGINT / SIGTERM mid-run: exit 130, target not created, no .tmp left
    sigs = [("SIGINT", signal.SIGINT), ("SIGTERM", signal.SIGTERM)]
    for label, signum in sigs:
        for command in (["run"] if fast else ["run", "record"]):
            d = ws.case_dir("faults", f"{command}-{label}")
            rec = _copy(ws.base_mcap, d / "rec.mcap")
            outdir = d / "out"
            outdir.mkdir()
            out = outdir / ("x.rrd" if command == "run" else "x.mcap")
            args = ["run", rec, "--out", out] if command == "run" else BASE_RECORD_ARGS + ["--out", out]
            # 130 when the signal lands mid-run; a run is fast enough now (detections cached,
            # 12 frames) that it may land after the .rrd is in place, and then the signal is
            # ignored and the run ends 0 with its complete output (agvviz.cli.interrupts.outputs_complete).
            cases.append(Case("faults", f"{label} mid-{command}", args, codes=(130,),
                              expect="error_or_ok" if command == "run" else "error", inputs=[rec], outputs=[out],
                              cwd=d, drive=signal_driver(signum, settle_s=0.1), error_line=False))

    if not fast:
        # a signal during start-up (imports), and mid-sweep (worker processes must end too)
        for label, signum in sigs:
            d = ws.case_dir("faults", f"run-{label}-at-start-up")
            rec = _copy(ws.base_mcap, d / "rec.mcap")
            out = d / "out" / "x.rrd"
            cases.append(Case("faults", f"{label} 0.3 s after start (start-up)", ["run", rec, "--out", out],
                              codes=(130,), inputs=[rec], outputs=[out], cwd=d, error_line=False,
                              drive=signal_driver(signum, at_start_s=0.3)))
            d = ws.case_dir("faults", f"sweep-{label}")
            rec = _copy(ws.base_mcap, d / "rec.mcap")
            sweep_dir = d / "sweep"
            sweep_dir.mkdir()
            cases.append(Case("faults", f"{label} mid-sweep (2 workers)",
                              ["sweep", rec, "--set", "solver=p4p,lm,ippe", "--jobs", "2", "--out-dir", sweep_dir],
                              codes=(130,), inputs=[rec], cwd=d, error_line=False,
                              drive=signal_driver(signum, folder=sweep_dir, settle_s=1.0), check=no_tmp_check(sweep_dir),
                              check_errors=True))

    # SIGKILL mid-run, then a second run into the same folder: it succeeds and the stale
    # temporary file of the killed run is cleaned up
    for command in (["run"] if fast else ["run", "record"]):
        d = ws.case_dir("faults", f"{command}-SIGKILL-then-again")
        rec = _copy(ws.base_mcap, d / "rec.mcap")
        outdir = d / "out"
        outdir.mkdir()
        out = outdir / ("x.rrd" if command == "run" else "x.mcap")
        args = ["run", rec, "--out", out] if command == "run" else BASE_RECORD_ARGS + ["--out", out]

        def setup(case, args=args, outdir=outdir, d=d):
            proc = subprocess.Popen(agvviz_command() + [str(a) for a in args], cwd=d, env=child_env(),
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
            ok = _wait_for_tmp(outdir, proc)
            if ok:
                time.sleep(0.4)
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
            if not ok or not tmp_files([outdir]):
                case.skip_reason = "the first run ended before it could be killed mid-write"

        cases.append(Case("faults", f"SIGKILL mid-{command}, then {command} again", args, expect="ok", inputs=[rec],
                          outputs=[out], cwd=d, setup=setup, check=no_tmp_check(outdir)))
    return cases


# -- the sets --------------------------------------------------------------------------------
def campaign_cases(ws: Workspace, seed: int = CAMPAIGN_SEED, n_seeds: int = 4) -> list[Case]:
    damages = corruption_campaign(ws.layout, seed=seed, n_seeds=n_seeds)
    return (
        damaged_cases(ws, damages)
        + non_mcap_cases(ws)
        + bomb_cases(ws)
        + semantic_cases(ws, commands=("run", "inspect"))
        + cli_cases(ws)
        + fault_cases(ws)
    )


#: The default (fast) set: a handful per category, ids as ``Case.id``.
FAST_IDS = (
    "damaged files/run truncate@mid-chunk1",
    "damaged files/inspect flip-chunk1-mid-records",
    "damaged files/run flip-message-index-length+2^20",
    "damaged files/run dup-chunk2-before-chunk0",
    "damaged files/inspect empty",
    "bad recordings/run reversed-image-times",
    "bad recordings/run calibration-640x480",
    "cli misuse/diff --out onto input A",
    "cli misuse/diff --out hard link to input A",
    "cli misuse/export truncated .rrd",
    "cli misuse/run --out under a regular file",
    "cli misuse/sweep --jobs 0",
    "cli misuse/record --set width_px=100000",
    "cli misuse/diff --fail-if 'B.position_rmse_mm > \uff11'",
    "cli misuse/diff --fail-if 'B.position_rmse_mm > 1e999'",
    "faults/run --out into a read-only folder",
    "faults/run --out onto a full disk (1 MiB tmpfs)",
    "faults/SIGINT mid-run",
    "faults/SIGTERM mid-run",
    "faults/SIGKILL mid-run, then run again",
)


def fast_cases(ws: Workspace) -> list[Case]:
    cases = (
        damaged_cases(ws, fast_corruptions(ws.layout))
        + non_mcap_cases(ws, which=("empty",), commands=("inspect",))
        + semantic_cases(ws, which=("reversed-image-times", "calibration-640x480"))
        + cli_cases(ws, fast=True)
        + fault_cases(ws, fast=True)
    )
    by_id = {c.id: c for c in cases}
    missing = [i for i in FAST_IDS if i not in by_id]
    assert not missing, f"fast cases not built: {missing}"
    return [by_id[i] for i in FAST_IDS]


def run_campaign(root: Path, *, jobs: int = 2, seed: int = CAMPAIGN_SEED, n_seeds: int = 4,
                 report_path: Optional[Path] = None, fast: bool = False, echo: Callable[[str], None] = print,
                 only: Optional[str] = None):
    """Build the workspace under ``root``, run every case, write the markdown report.

    Returns (results, report text)."""
    from robustness_harness import report, run_cases

    t0 = time.monotonic()
    ws = Workspace(root).build()
    cases = fast_cases(ws) if fast else campaign_cases(ws, seed=seed, n_seeds=n_seeds)
    if only:
        cases = [c for c in cases if only in c.id]
    echo(f"robustness campaign: {len(cases)} cases, {jobs} at a time, corruption seeds {seed}.."
         f"{seed + n_seeds - 1}, workspace {root}")
    done = {"n": 0}

    def progress(result):
        done["n"] += 1
        if result.failed:
            echo(f"  [{done['n']}/{len(cases)}] {result.klass}: {result.case.id}")
        elif done["n"] % 25 == 0:
            echo(f"  [{done['n']}/{len(cases)}] {time.monotonic() - t0:.0f} s")

    results = run_cases(cases, jobs=jobs, progress=progress)
    command = "python bench/robustness_campaign.py" + (" --fast" if fast else f" --seed {seed} --seeds {n_seeds}")
    command += f" --jobs {jobs}" + (f" --only {only!r}" if only else "")
    text = report(results, title="agvviz robustness campaign (issue 10)", command=command)
    text += f"\nWall time: {time.monotonic() - t0:.0f} s; {jobs} jobs.\n"
    if report_path is not None:
        Path(report_path).parent.mkdir(parents=True, exist_ok=True)
        Path(report_path).write_text(text)
    return results, text
