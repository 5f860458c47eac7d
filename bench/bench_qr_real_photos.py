"""How many of the real QR photos in ``../shared/data/zxing_qrcode/qrcode-1`` agvviz decodes.

Each photo goes through agvviz's own detection path (:func:`agvviz.markers.qr.detect_qr_codes`,
grayscale, ``refine=ecc``); a photo counts as decoded when one detection's payload equals the
photo's ``N.txt`` (line endings normalised: the ``.txt`` files use LF where some codes hold
CRLF). Prints one line per photo (decoded or not, the corner refinement applied) and the count.

    python bench/bench_qr_real_photos.py [--data DIR] [--refine ecc|subpix|none]

The photos are zxing's black-box set ``qrcode-1`` (20 phone photos, 640×480, upright).
Measured (2026-11): 12 of 20 when agvviz decoded through OpenCV's detectors (commit 7663202),
20 of 20 through zxing-cpp with OpenCV as the fallback, all 20 ECC-refined.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2

from agvviz.markers.qr import REFINE_METHODS, detect_qr_codes

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "zxing_qrcode" / "qrcode-1"


def normalise(text: str) -> str:
    """Line endings as LF, no trailing newline."""
    return text.replace("\r\n", "\n").replace("\r", "\n").rstrip("\n")


def photo_texts(data_dir: Path) -> list[tuple[Path, str]]:
    """(image path, expected payload) of every photo in ``data_dir``, by number."""
    images = sorted(
        (p for p in data_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg")),
        key=lambda p: int(p.stem) if p.stem.isdigit() else p.stem,
    )
    return [(p, p.with_suffix(".txt").read_text(encoding="utf-8")) for p in images]


def decoded_count(data_dir: Path, refine: str = "ecc", verbose: bool = False) -> tuple[int, int]:
    """(photos whose payload agvviz decodes, photos)."""
    pairs = photo_texts(data_dir)
    ok = 0
    for path, expected in pairs:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        t0 = time.perf_counter()
        detections = detect_qr_codes(gray, refine=refine)
        dt_ms = (time.perf_counter() - t0) * 1e3
        hit = next(
            (d for d in detections if d.text is not None and normalise(d.text) == normalise(expected)), None
        )
        ok += hit is not None
        if verbose:
            how = f"{hit.refine_method}{'' if hit.refine_ok else ' (fallback: ' + hit.refine_note + ')'}" if hit else ""
            print(f"{path.name:>8}  {'decoded' if hit else 'MISSED ':7}  {dt_ms:6.1f} ms  {how}")
    return ok, len(pairs)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of N.png + N.txt")
    parser.add_argument("--refine", choices=REFINE_METHODS, default="ecc")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        print(f"no data folder {args.data} (the real test data lives in ../shared/data)", file=sys.stderr)
        return 2
    ok, total = decoded_count(args.data, args.refine, verbose=True)
    print(f"decoded {ok} of {total} photos in {args.data.name} (refine={args.refine})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
