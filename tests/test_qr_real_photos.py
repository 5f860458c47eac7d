"""QR decoding through zxing-cpp (OpenCV as the fallback): real photos, the corner convention,
and payloads that are not agvviz text.

Real photos: zxing's black-box set ``qrcode-1`` (``../shared/data/zxing_qrcode/qrcode-1``, 20
upright phone photos, 640×480). Through OpenCV's detectors agvviz decoded 12 of them; through
zxing-cpp it decodes all 20 (``python bench/bench_qr_real_photos.py``).
"""

from pathlib import Path

import cv2
import numpy as np
import pytest
import zxingcpp

from agvviz.markers import qr
from agvviz.markers.payload import PayloadError, parse_payload
from agvviz.markers.qr import ZXING_TO_OPENCV_PX, detect_qr_codes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
QRCODE_1 = DATA / "zxing_qrcode" / "qrcode-1"
AGV_TEXT = "AGV1;id=A17;mm=1000,2000;1500,2000;1500,1500;1000,1500"


def _normalise(text: str) -> str:
    # MANIFEST: the N.txt files use LF where some codes hold CRLF.
    return text.replace("\r\n", "\n").replace("\r", "\n").rstrip("\n")


@pytest.fixture(scope="module")
def real_photos():
    if not QRCODE_1.is_dir():
        pytest.skip(f"real QR photos not found at {QRCODE_1} (see ../shared/data/MANIFEST.md)")
    out = []
    for index in range(1, 21):
        gray = cv2.imread(str(QRCODE_1 / f"{index}.png"), cv2.IMREAD_GRAYSCALE)
        expected = _normalise((QRCODE_1 / f"{index}.txt").read_bytes().decode("utf-8"))
        out.append((index, expected, detect_qr_codes(gray)))
    return out


def test_every_real_photo_decodes_and_is_ecc_refined(real_photos):
    decoded, ecc = 0, 0
    for index, expected, detections in real_photos:
        texts = [_normalise(d.text) for d in detections if d.text is not None]
        assert all(text == expected for text in texts), index  # never a wrong decode
        decoded += bool(texts)
        ecc += any(d.refine_method == "ecc" and d.refine_ok for d in detections)
    # zxing-cpp decodes all 20 (DESIGN §9); OpenCV's detectors decoded 12.
    assert decoded == 20
    # These codes come from other encoders: ECC aligns the module grid sampled from the image
    # (measured: all 20 refined).
    assert ecc >= 18


def test_zxing_corners_are_shifted_to_the_pixel_centre_convention(real_photos):
    """zxing-cpp's corners (pixel-corner convention, whole pixels) minus 0.5 px against the
    ECC-refined corners of the same codes: no bias. Measured mean (−0.02, −0.05) px over 80
    corners, RMS 0.6 px per axis (standard error of the mean ≈0.07 px); without the shift the
    mean would be ≈ +0.5 px."""
    offsets = np.concatenate(
        [d.raw_corners_px - d.corners_px for _, _, ds in real_photos for d in ds if d.refine_method == "ecc"]
    )
    assert len(offsets) >= 72
    assert np.all(np.abs(offsets.mean(axis=0)) < 0.2)
    assert np.max(np.linalg.norm(offsets, axis=1)) < 4.0  # within the refiner's shift bound


def _zxing_code_image(content, scale: int = 8, margin_px: int = 40) -> np.ndarray:
    """A QR symbol made by zxing-cpp's encoder, ``scale`` px per module, no blur: symbol corner
    (pixel-corner convention) at ``margin_px``."""
    barcode = zxingcpp.create_barcode(content, zxingcpp.BarcodeFormat.QRCode)
    symbol = np.array(zxingcpp.write_barcode_to_image(barcode, scale=scale, add_quiet_zones=False))
    return cv2.copyMakeBorder(symbol, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)


def test_corner_convention_on_an_exact_image():
    image = _zxing_code_image(AGV_TEXT)
    side = image.shape[0] - 2 * 40
    # OpenCV convention: the symbol's outer edge at pixel-corner 40 is at 39.5.
    truth = np.array([[40, 40], [40 + side, 40], [40 + side, 40 + side], [40, 40 + side]], float) - 0.5
    (raw,) = detect_qr_codes(image, refine="none")
    assert raw.text == AGV_TEXT
    np.testing.assert_allclose(raw.raw_corners_px, truth, atol=1e-9)
    assert ZXING_TO_OPENCV_PX == -0.5
    (ecc,) = detect_qr_codes(image, refine="ecc")
    assert ecc.refine_method == "ecc" and ecc.refine_ok
    np.testing.assert_allclose(ecc.corners_px, truth, atol=0.05)


@pytest.mark.parametrize(
    "content, expected_bytes",
    [
        (b"\x8d\xa1\x93x\x82\xcc\xff\x00", b"\x8d\xa1\x93x\x82\xcc\xff\x00"),  # binary, not UTF-8
        ("AGV1;id=\uff11;mm=0,0;1,0;1,1;0,1", None),  # full-width digit: zxing encodes it as Shift-JIS
    ],
    ids=["binary", "full-width-digit"],
)
def test_payload_that_is_not_utf8_text_is_kept_as_bytes_and_refused(content, expected_bytes):
    detections = detect_qr_codes(_zxing_code_image(content))  # never raises
    assert len(detections) == 1
    (detection,) = detections
    assert detection.text is None and detection.payload_bytes
    if expected_bytes is not None:
        assert detection.payload_bytes == expected_bytes
    # The corners are still refined from the module grid read off the image.
    assert detection.refine_method == "ecc"
    with pytest.raises(PayloadError):
        parse_payload(detection.payload_bytes)


def test_non_ascii_utf8_payload_is_refused_by_the_parser():
    text = "AGV1;id=Ä17;mm=1000,2000;1500,2000;1500,1500;1000,1500"
    (detection,) = detect_qr_codes(_zxing_code_image(text.encode("utf-8")))
    assert detection.text == text
    with pytest.raises(PayloadError, match="printable ASCII|character"):
        parse_payload(detection.text)


def test_opencv_is_the_fallback_when_zxing_decodes_nothing(monkeypatch):
    image = _zxing_code_image(AGV_TEXT)
    monkeypatch.setattr(qr, "_run_zxing", lambda gray: [])
    (detection,) = detect_qr_codes(image)
    assert detection.text == AGV_TEXT
    assert detect_qr_codes(image, fallback_detectors=False) == []
