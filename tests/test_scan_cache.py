"""Issue 27: a recording's scan and sha256 kept in the cache folder (agvviz.recording.scan_cache).

The reference is a fresh scan of the file (agvviz.recording.source.scan) and hashlib over its
bytes: a cached scan must equal it field by field; a changed file, or an entry that is damaged
or belongs to another file, must never be used.
"""

from __future__ import annotations

import hashlib
import os
import shutil

import pytest

from agvviz.recording import raw, scan_cache
from agvviz.recording.raw import ReadReport
from agvviz.recording.source import open_recording, scan
from agvviz.scenarios import record

QR_SMALL = ["duration_s=1.5", "width_px=640", "height_px=512", "focal_px=500"]


@pytest.fixture(scope="module")
def recording_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("scan") / "qr.mcap"
    record("qr_floor", path, seed=3, overrides=QR_SMALL)
    return path


def _fresh(path):
    raw._SHA256_CACHE.clear()  # the process-wide memo would hide a missed hash
    return open_recording(path)


def _same_scan(a, b) -> None:
    assert a.topics == b.topics and a.first_ns == b.first_ns and a.last_ns == b.last_ns
    assert a.first_problem == b.first_problem and a.tf_frames == b.tf_frames
    assert a.metadata == b.metadata
    assert a.context == b.context  # RawMessage equality: every field, payload bytes included


def _read_count(monkeypatch) -> list[int]:
    """How many times the recording's messages are read (Recording.iter_raw called)."""
    calls = [0]
    original = raw.Recording.iter_raw

    def counted(self, *args, **kwargs):
        calls[0] += 1
        return original(self, *args, **kwargs)

    monkeypatch.setattr(raw.Recording, "iter_raw", counted)
    return calls


def test_a_second_scan_reads_the_cache_not_the_file(recording_file, tmp_path, monkeypatch):
    reference = scan(_fresh(recording_file), ReadReport())
    assert reference.context, "the recording has context messages (odometry, calibration)"
    sha256 = hashlib.sha256(recording_file.read_bytes()).hexdigest()
    first = scan_cache.cached_scan(_fresh(recording_file), tmp_path)
    _same_scan(first, reference)
    assert len(list((tmp_path / "scans").iterdir())) == 1
    calls = _read_count(monkeypatch)
    recording = _fresh(recording_file)
    second = scan_cache.cached_scan(recording, tmp_path)
    _same_scan(second, reference)
    assert recording.sha256() == sha256
    assert calls[0] == 0  # neither scanned nor hashed again (sha256() would also read it)


def test_a_changed_file_is_scanned_again(recording_file, tmp_path, monkeypatch):
    path = tmp_path / "copy.mcap"
    shutil.copyfile(recording_file, path)
    scan_cache.cached_scan(_fresh(path), tmp_path / "cache")
    # the same bytes, touched: mtime differs, so the entry is not this file's any more
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    calls = _read_count(monkeypatch)
    scan_cache.cached_scan(_fresh(path), tmp_path / "cache")
    assert calls[0] == 1
    # other bytes of the same size, with the old mtime put back: the inode's ctime still moves
    data = bytearray(path.read_bytes())
    st = os.stat(path)
    data[-1] ^= 0xFF  # the MCAP trailer's magic byte: another file, equally long
    path.write_bytes(bytes(data))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    recording = _fresh(path)
    scan_cache.cached_scan(recording, tmp_path / "cache")
    assert calls[0] == 2
    assert recording.sha256() == hashlib.sha256(bytes(data)).hexdigest()
    # a file replaced by another one (a new inode) at the same path
    replacement = tmp_path / "other.mcap"
    shutil.copyfile(recording_file, replacement)
    os.replace(replacement, path)
    scan_cache.cached_scan(_fresh(path), tmp_path / "cache")
    assert calls[0] == 3


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "foreign"])
def test_a_damaged_or_foreign_entry_is_ignored(recording_file, tmp_path, monkeypatch, damage):
    reference = scan(_fresh(recording_file), ReadReport())
    scan_cache.cached_scan(_fresh(recording_file), tmp_path)
    (entry,) = (tmp_path / "scans").iterdir()
    blob = entry.read_bytes()
    if damage == "truncated":
        entry.write_bytes(blob[: len(blob) - 100])
    elif damage == "garbage":
        entry.write_bytes(blob[:40] + b"\xff" * 200 + blob[240:])
    elif damage == "empty":
        entry.write_bytes(b"")
    else:  # another file's entry copied under this file's name: its key names other files
        other = tmp_path / "other.mcap"
        shutil.copyfile(recording_file, other)
        scan_cache.cached_scan(_fresh(other), tmp_path / "elsewhere")
        (foreign,) = (tmp_path / "elsewhere" / "scans").iterdir()
        shutil.copyfile(foreign, entry)
    calls = _read_count(monkeypatch)
    recording = _fresh(recording_file)
    again = scan_cache.cached_scan(recording, tmp_path)
    assert calls[0] == 1  # scanned, not read from the entry
    _same_scan(again, reference)
    assert recording.sha256() == hashlib.sha256(recording_file.read_bytes()).hexdigest()
    # and the entry was rewritten: the next scan is a hit again
    scan_cache.cached_scan(_fresh(recording_file), tmp_path)
    assert calls[0] == 1


def test_an_unwritable_cache_folder_only_costs_the_scan(recording_file, tmp_path):
    blocked = tmp_path / "file-not-folder"
    blocked.write_text("x")
    reference = scan(_fresh(recording_file), ReadReport())
    _same_scan(scan_cache.cached_scan(_fresh(recording_file), blocked), reference)


def test_a_file_changed_during_the_scan_is_not_stored(recording_file, tmp_path, monkeypatch):
    from agvviz.recording import source

    path = tmp_path / "copy.mcap"
    shutil.copyfile(recording_file, path)
    original = source.scan

    def scan_then_touch(recording, report=None):
        result = original(recording, report)
        st = os.stat(path)
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1))  # written to while it was read
        return result

    monkeypatch.setattr(source, "scan", scan_then_touch)
    scan_cache.cached_scan(_fresh(path), tmp_path / "cache")
    assert not (tmp_path / "cache" / "scans").exists() or not list((tmp_path / "cache" / "scans").iterdir())


# -- a recording found intact is read again without its CRC checks ---------------------------------
def _crc_bytes(monkeypatch) -> list[int]:
    """How many bytes the MCAP reader computes CRCs of from now on."""
    import zlib

    from agvviz.recording import mcap_records, mcap_stream

    calls = [0]

    class Counting:
        @staticmethod
        def crc32(data, *args):
            calls[0] += len(data)
            return zlib.crc32(data, *args)

    monkeypatch.setattr(mcap_records, "zlib", Counting)
    monkeypatch.setattr(mcap_stream, "zlib", Counting)
    return calls


def _messages(recording) -> tuple[list, ReadReport]:
    report = ReadReport()
    items = [(m.topic, m.log_time_ns, m.data) for m in recording.iter_raw(report) if isinstance(m, raw.RawMessage)]
    return items, report


@pytest.mark.parametrize("cached", [True, False], ids=["from the cache entry", "scanned, no cache folder"])
def test_an_intact_recording_is_read_again_without_its_crc_checks(recording_file, tmp_path, monkeypatch, cached):
    """A scan that read every byte and found no damage marks the recording verified: a later
    read of it computes no CRC of its data (only of the small summary section, whose schemas and
    channels the read takes) and yields exactly what a checked read yields. A touched file is
    checked again: the data section, each chunk and each message, so more than the file."""
    path = tmp_path / "copy.mcap"
    shutil.copyfile(recording_file, path)
    reference, reference_report = _messages(_fresh(path))
    assert not reference_report.problems and reference_report.chunks_ok > 0
    cache = tmp_path / "cache" if cached else None
    scan_cache.cached_scan(_fresh(path), cache)
    recording = _fresh(path)
    scan_cache.cached_scan(recording, cache)
    assert recording.verified()
    size = path.stat().st_size
    crc_bytes = _crc_bytes(monkeypatch)
    items, report = _messages(recording)
    assert crc_bytes[0] < 0.01 * size
    assert items == reference
    assert (report.problems, report.chunks_ok, report.chunks_lost) == ([], reference_report.chunks_ok, 0)
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1))  # the same bytes, touched
    assert not recording.verified()
    crc_bytes[0] = 0
    items, report = _messages(recording)
    assert crc_bytes[0] > size and items == reference and not report.problems


def test_a_damaged_recording_is_checked_at_every_read(recording_file, tmp_path, monkeypatch):
    """A recording whose scan found damage (here a bit flip only the data section's CRC can
    tell) is never marked verified: a read from its cache entry reports the damage again."""
    from agvviz.recording.mcap_records import DATA_SECTION_CRC_PROBLEM

    data = bytearray(recording_file.read_bytes())
    at = data.index(b"seed\x01\x00\x00\x003") + 8  # the seed's value "3" in the metadata record
    data[at] ^= 0x01  # "3" -> "2": still a valid seed
    bad = tmp_path / "seed_flip.mcap"
    bad.write_bytes(bytes(data))
    scan_cache.cached_scan(_fresh(bad), tmp_path / "cache")
    recording = _fresh(bad)
    scan_cache.cached_scan(recording, tmp_path / "cache")
    assert not recording.verified()
    crc_bytes = _crc_bytes(monkeypatch)
    _, report = _messages(recording)
    assert crc_bytes[0] > bad.stat().st_size and DATA_SECTION_CRC_PROBLEM in report.problems
