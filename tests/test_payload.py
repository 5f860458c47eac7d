"""QR payload codec: round trips at the format's resolution and a table of hostile inputs."""

from pathlib import Path

import numpy as np
import pytest

from agvviz.geometry import se3, so3
from agvviz.markers.payload import (
    MAX_PAYLOAD_CHARS,
    PAYLOAD_PREFIX,
    PayloadError,
    QrPayload,
    encode_payload,
    parse_payload,
)

ZXING = Path(__file__).resolve().parents[2] / "shared" / "data" / "zxing_qrcode" / "qrcode-1"

RESOLUTION_M = 1e-4  # the text carries millimetres with one decimal
VALID = "AGV1;id=A17;mm=1000,2000;1500,2000;1500,1500;1000,1500"
SQUARE = "1000,2000;1500,2000;1500,1500;1000,1500"
MIDPOINTS = "1250,2000;1500,1750;1250,1500;1000,1750"


def random_code_points(rng, with_midpoints: bool, three_d: bool) -> np.ndarray:
    """Feature points of a square code of random side, position and (3-D) attitude, (4|8, 3)."""
    side_m = rng.uniform(0.05, 1.0)
    corners = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], float) * side_m / 2
    if with_midpoints:
        corners = np.vstack([corners, (corners + np.roll(corners, -1, axis=0)) / 2])
    if three_d:
        R = so3.exp(rng.normal(0.0, 1.0, 3))
        t = rng.uniform(-100.0, 100.0, 3)  # 8 3-D points far beyond 100 m can exceed 256 chars
    else:
        R = so3.exp(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))
        t = np.array([*rng.uniform(-9000.0, 9000.0, 2), 0.0])
    return se3.transform_points(se3.make(R, t), corners)


@pytest.mark.parametrize("with_midpoints", [False, True])
@pytest.mark.parametrize("three_d", [False, True])
def test_round_trip_within_resolution(with_midpoints, three_d):
    rng = np.random.default_rng(100 + 2 * with_midpoints + three_d)
    for _ in range(50):
        points = random_code_points(rng, with_midpoints, three_d)
        text = encode_payload(QrPayload("code_7-B", points))
        assert text.startswith(f"{PAYLOAD_PREFIX};id=code_7-B;mm=")
        assert len(text) <= MAX_PAYLOAD_CHARS
        assert (text.count(",") == 2 * len(points)) is three_d  # 2-D written when all z are 0
        parsed = parse_payload(text)
        assert parsed.marker_id == "code_7-B"
        assert parsed.points_world_m.shape == (len(points), 3)
        # Rounding to 0.1 mm moves each coordinate by at most half the resolution.
        np.testing.assert_allclose(parsed.points_world_m, points, rtol=0, atol=RESOLUTION_M / 2 + 1e-9)
        # Idempotent: the parsed values are on the grid, so re-encoding reproduces the text.
        assert encode_payload(parsed) == text
        assert parse_payload(text.encode("ascii")).points_world_m.tolist() == parsed.points_world_m.tolist()


def test_known_payload_values():
    parsed = parse_payload(f"AGV1;id=A17;mm={SQUARE};{MIDPOINTS}")
    assert parsed.marker_id == "A17"
    np.testing.assert_array_equal(parsed.points_world_m[:4], [[1, 2, 0], [1.5, 2, 0], [1.5, 1.5, 0], [1, 1.5, 0]])
    np.testing.assert_array_equal(parsed.points_world_m[7], [1.0, 1.75, 0.0])
    three_d = parse_payload("AGV1;id=w;mm=0,0,2000.5;500,0,2000.5;500,0,1500.5;0,0,1500.5")
    np.testing.assert_allclose(three_d.points_world_m[0], [0.0, 0.0, 2.0005], rtol=0, atol=1e-12)
    with pytest.raises(ValueError):  # parsed arrays are read-only
        three_d.points_world_m[0, 0] = 1.0


def test_lenient_number_forms_are_normalised():
    parsed = parse_payload("AGV1;id=z;mm=-0,0;100.0,0;100,-100;-0.0,-100")
    assert not np.any(np.signbit(parsed.points_world_m[[0, 3], 0]))  # -0 becomes +0
    assert encode_payload(parsed) == "AGV1;id=z;mm=0,0;100,0;100,-100;0,-100"


COLLINEAR = "0,0;1000,0;3000,0;1500,0"
HOSTILE = [
    ("A" * 10_000, "payload too long: 10000 chars > 256"),
    ("A" * 1_000_000, "payload too long: 1000000 chars"),
    (b"B" * 10_000, "payload too long: 10000 bytes"),
    (VALID[:20] + "\x00" + VALID[21:], "forbidden character U+0000"),
    (VALID.replace("1000,2000", "１000,2000"), "forbidden character U+FF11"),
    (VALID.encode("utf-8").replace(b"A17", b"A\xc3\xa97"), "not ASCII"),
    (VALID.replace("1000,2000", "1e400,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "nan,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "inf,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "0x10,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "+1000,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "01000,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "1000.25,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "1000.,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "123456789,2000"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "10000001,2000"), "out of range"),
    (VALID.replace("1000,2000", "1000,2000,0,0"), "point 0 is malformed"),
    (VALID.replace("1000,2000", "1_000,2000"), "point 0 is malformed"),
    ("AGV1;id=__import__('os');mm=" + SQUARE, "invalid marker id"),
    ("__import__('os').system('ls')", "not an agvviz payload"),
    ("AGV1;id=A17;mm=__import__('os'),0;1,0;1,1;0,1", "point 0 is malformed"),
    ("AGV1;id=" + "x" * 33 + ";mm=" + SQUARE, "invalid marker id"),
    ("AGV1;id=;mm=" + SQUARE, "invalid marker id"),
    ("AGV1;id=a.b;mm=" + SQUARE, "invalid marker id"),
    (VALID + ";x=1", "unexpected field 'x'"),
    (VALID + ";id=B", "duplicate field 'id'"),
    (VALID + ";mm=1,2", "duplicate field 'mm'"),
    ("AGV1;id=A;id=B;mm=" + SQUARE, "duplicate field 'id'"),
    ("AGV1;mm=" + SQUARE + ";id=A", "field 1 must be 'id', got 'mm'"),
    ("AGV1;mm=" + SQUARE, "field 1 must be 'id', got 'mm'"),
    ("AGV1;id=A17", "missing fields"),
    ("AGV1;id=A17;" + SQUARE, "field 2 must be 'mm=...'"),
    ("AGV1;id=A17;mm=1000,2000;1500,2000;1500,1500", "expected 4 or 8 points, got 3"),
    (VALID + ";1200,1200", "expected 4 or 8 points, got 5"),
    (VALID + ";" + MIDPOINTS + ";1200,1200", "expected 4 or 8 points, got 9"),
    (VALID + ";", "expected 4 or 8 points, got 5"),
    ("AGV1;id=A17;mm=1000,2000;1500,2000,0;1500,1500;1000,1500", "mixed 2-D and 3-D"),
    ("AGV1;id=A17;mm=1000,2000;1500,2000;1000,2000;1000,1500", "duplicate points: point 0 equals point 2"),
    ("AGV1;id=A17;mm=" + COLLINEAR, "collinear"),
    ("AGV1;id=A17;mm=0,0;1000,0;1000,0.5;0,0.5", "0.5 mm long"),
    ("AGV1;id=A17;mm=0,1000;1000,1000;200,0;1000,100", "convex quadrilateral"),  # bow tie
    ("AGV1;id=A17;mm=0,1000;1000,1000;500,800;0,0", "convex quadrilateral"),  # arrow head
    ("AGV1;id=A17;mm=0,0,0;1000,0,0;1000,1000,0;0,1000,50", "not coplanar"),
    (f"AGV1;id=A17;mm={SQUARE};1250,2000;1500,1750;1250,1600;1000,1750", "bottom midpoint (point 6)"),
    (f"AGV1;id=A17;mm={SQUARE};1500,1750;1250,1500;1000,1750;1250,2000", "midpoint"),
    (" " + VALID, "forbidden character U+0020 at position 0"),
    (VALID + " ", "forbidden character U+0020"),
    (VALID + "\n", "forbidden character U+000A"),
    (VALID.replace(";", "\r\n;", 1), "forbidden character U+000D"),
    (VALID.replace("AGV1", "AGV9"), "unsupported payload version 'AGV9'"),
    (VALID.replace("AGV1", "AGV2"), "unsupported payload version 'AGV2'"),
    (VALID.replace("AGV1", "AGV10"), "unsupported payload version 'AGV10'"),
    (VALID.replace("AGV1", "agv1"), "not an agvviz payload"),
    (VALID.replace("AGV1", "AGV1x"), "not an agvviz payload"),
    ("", "not an agvviz payload"),
    ("MEBKM:URL:http\\://en.wikipedia.org/wiki/Main_Page;;", "not an agvviz payload"),
]


@pytest.mark.parametrize("text, reason", HOSTILE, ids=[f"{i:02d}" for i in range(len(HOSTILE))])
def test_hostile_inputs_are_rejected_with_their_reason(text, reason):
    with pytest.raises(PayloadError) as caught:
        parse_payload(text)
    assert reason in str(caught.value)
    assert isinstance(caught.value, ValueError)


def test_non_text_input_is_rejected():
    with pytest.raises(PayloadError, match="must be str or bytes"):
        parse_payload(12345)


# A valid 1 m code with midpoints, 9 km away on every axis: 24 numbers like "-9000000.1" make
# the text longer than MAX_PAYLOAD_CHARS.
FAR_AWAY_3D = parse_payload(f"AGV1;id=A17;mm={SQUARE};{MIDPOINTS}").points_world_m - 9_000.0001


@pytest.mark.parametrize(
    "payload, reason",
    [
        (QrPayload("bad id!", parse_payload(VALID).points_world_m), "invalid marker id"),
        (QrPayload("A", np.zeros((5, 3))), "shape (4, 3) or (8, 3)"),
        (QrPayload("A", np.zeros((4, 2))), "shape (4, 3) or (8, 3)"),
        (QrPayload("A", np.full((4, 3), np.nan)), "NaN or inf"),
        (QrPayload("A", parse_payload(VALID).points_world_m + 20_000.0), "out of range"),
        # 20 µm edges collapse to duplicate points at the 0.1 mm resolution.
        (QrPayload("A", np.array([[0, 2e-5, 0], [2e-5, 2e-5, 0], [2e-5, 0, 0], [0, 0, 0]])), "duplicate points"),
        (QrPayload("x" * 32, FAR_AWAY_3D), "payload too long"),
    ],
)
def test_encode_rejects_what_it_cannot_represent(payload, reason):
    with pytest.raises(PayloadError) as caught:
        encode_payload(payload)
    assert reason in str(caught.value)


def test_real_zxing_payloads_are_rejected():
    texts = sorted(ZXING.glob("[0-9]*.txt")) if ZXING.is_dir() else []
    texts = [path for path in texts if path.stem.isdigit()]
    if len(texts) != 20:
        pytest.skip(f"the 20 zxing QR payloads are not at {ZXING} (see shared/data/MANIFEST.md)")
    for path in texts:
        with pytest.raises(PayloadError):
            parse_payload(path.read_bytes())
