"""Property-based tests (hypothesis) of the parsers and validators that read untrusted input:
the QR payload codec, the ``--fail-if`` grammar, ``--set key=value`` settings, and the
marker-map validators. Each either accepts its input and returns something valid, or raises
its one documented error — never another exception.

Every test is derandomized (the same examples on every run and machine) with a fixed example
budget; the whole file runs in well under 20 s.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings, strategies as st

from agvviz import scenarios as scenario_registry
from agvviz.errors import InputError
from agvviz.evaluation import expression
from agvviz.evaluation.expression import ExpressionError
from agvviz.geometry import se3, so3
from agvviz.markers.aruco import ArucoMap, parse_aruco_map
from agvviz.markers.types import ArucoError
from agvviz.markers.payload import (
    MAX_ABS_COORD_MM,
    MAX_PAYLOAD_CHARS,
    PayloadError,
    QrPayload,
    encode_payload,
    parse_payload,
)
from agvviz.recording.schemas import SCHEMAS, validate_payload
from agvviz.settings import RunSettings, SettingsError, apply_overrides, field_types, validate

RESOLUTION_MM = 0.1


def budget(n: int):
    """Reproducible hypothesis settings: derandomized, ``n`` examples, no deadline (shared CI
    cores make per-example timing meaningless), no example database."""
    return settings(
        max_examples=n,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    )


# =============================================================================================
# (a) QR payload codec
# =============================================================================================

IDS = st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True)


@st.composite
def code_points(draw) -> np.ndarray:
    """Feature points (4|8, 3) of a square code of random side, position and attitude."""
    side_m = draw(st.floats(0.01, 5.0))
    corners = np.array([[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]], float) * side_m / 2
    if draw(st.booleans()):
        corners = np.vstack([corners, (corners + np.roll(corners, -1, axis=0)) / 2])
    if draw(st.booleans()):  # 3-D attitude; 3-D text is longer, so stay within 100 m
        R = so3.exp(np.array(draw(st.tuples(*[st.floats(-3.0, 3.0)] * 3))))
        t = np.array(draw(st.tuples(*[st.floats(-100.0, 100.0)] * 3)))
    else:
        R = so3.exp(np.array([0.0, 0.0, draw(st.floats(-math.pi, math.pi))]))
        t = np.array([*draw(st.tuples(st.floats(-9000.0, 9000.0), st.floats(-9000.0, 9000.0))), 0.0])
    return se3.transform_points(se3.make(R, t), corners)


def _check_parsed(parsed: QrPayload) -> None:
    points = parsed.points_world_m
    assert points.shape in ((4, 3), (8, 3))
    assert np.all(np.isfinite(points))
    assert np.all(np.abs(points) <= MAX_ABS_COORD_MM / 1000.0)


@budget(100)
@given(IDS, code_points())
def test_payload_encode_parse_round_trip_within_resolution(marker_id, points):
    try:
        text = encode_payload(QrPayload(marker_id, points))
    except PayloadError as exc:
        # Only the documented refusals: too long (8 3-D points far out) or degenerate after rounding.
        assert "too long" in str(exc) or "degenerate" in str(exc), exc
        return
    assert len(text) <= MAX_PAYLOAD_CHARS
    parsed = parse_payload(text)
    assert parsed.marker_id == marker_id
    assert parsed.points_world_m.shape == points.shape
    # Rounding to the 0.1 mm grid moves a coordinate by at most 0.05 mm.
    np.testing.assert_allclose(parsed.points_world_m, points, rtol=0, atol=(RESOLUTION_MM / 2 + 1e-9) / 1000)
    # The text is canonical: encoding the parsed payload gives the same text.
    assert encode_payload(parsed) == text
    assert parse_payload(text.encode("ascii")).marker_id == marker_id


PAYLOAD_ALPHABET = "AGV1;id=mm,.-0123456789_ABxyz \t\u00e9\uff11"


@budget(300)
@given(st.one_of(st.text(max_size=300), st.text(alphabet=PAYLOAD_ALPHABET, max_size=300), st.binary(max_size=300)))
def test_any_text_parses_or_raises_payload_error(text):
    try:
        parsed = parse_payload(text)
    except PayloadError:
        return
    _check_parsed(parsed)


def _mutate(text: str, edits) -> str:
    for kind, position, char in edits:
        i = position % (len(text) + 1)
        if kind == "delete" and text:
            text = text[: min(i, len(text) - 1)] + text[min(i, len(text) - 1) + 1 :]
        elif kind == "insert":
            text = text[:i] + char + text[i:]
        elif kind == "replace" and text:
            j = min(i, len(text) - 1)
            text = text[:j] + char + text[j + 1 :]
        elif kind == "duplicate":
            text = text[:i] + text[i : i + 12] + text[i:]
        elif kind == "swap_fields":
            fields = text.split(";")
            a, b = i % len(fields), (i + 1 + ord(char)) % len(fields)
            fields[a], fields[b] = fields[b], fields[a]
            text = ";".join(fields)
    return text


EDITS = st.lists(
    st.tuples(
        st.sampled_from(["delete", "insert", "replace", "duplicate", "swap_fields"]),
        st.integers(0, 400),
        st.sampled_from(list("0123456789-.,;=mAGVid9 \x00\u00e9\uff11")),
    ),
    min_size=1,
    max_size=6,
)


@budget(200)
@given(IDS, code_points(), EDITS)
def test_mutated_valid_payloads_parse_or_raise_payload_error(marker_id, points, edits):
    try:
        text = encode_payload(QrPayload(marker_id, points))
    except PayloadError:
        assume(False)
    mutated = _mutate(text, edits)
    try:
        parsed = parse_payload(mutated)
    except PayloadError:
        return
    _check_parsed(parsed)
    # Whatever the parser accepts, the encoder writes back (canonically) and re-reads equal.
    again = parse_payload(encode_payload(parsed))
    assert again.marker_id == parsed.marker_id
    np.testing.assert_array_equal(again.points_world_m, parsed.points_world_m)


# =============================================================================================
# (b) the --fail-if grammar
# =============================================================================================

KNOWN = ("position_rmse_mm", "heading_rmse_deg", "solved")
METRICS = {
    "A": {"position_rmse_mm": 2.5, "heading_rmse_deg": 0.0, "solved": 10.0},
    "B": {"position_rmse_mm": 3.0, "heading_rmse_deg": -1.5, "solved": 0.0},
}

NUMBER_TEXT = st.from_regex(r"(?:[0-9]{1,4}\.?[0-9]{0,3}|\.[0-9]{1,3})(?:[eE][+-]?[0-9]{1,3})?", fullmatch=True)


def _leaf():
    number = NUMBER_TEXT.map(lambda t: (t, f"F({t!r})"))
    metric = st.tuples(st.sampled_from(expression.RUNS), st.sampled_from(KNOWN)).map(
        lambda rn: (f"{rn[0]}.{rn[1]}", f"M[{rn[0]!r}][{rn[1]!r}]")
    )
    return st.one_of(number, metric)


def _sums(leaf):
    def extend(children):
        binary = st.tuples(children, st.sampled_from(["+", "-", "*", "/"]), children).map(
            lambda t: (f"{t[0][0]} {t[1]} {t[2][0]}", f"{t[0][1]} {t[1]} {t[2][1]}")
        )
        negate = children.map(lambda c: (f"- {c[0]}", f"- {c[1]}"))
        group = children.map(lambda c: (f"( {c[0]} )", f"( {c[1]} )"))
        return st.one_of(binary, negate, group)

    return st.recursive(leaf, extend, max_leaves=8)


SUMS = _sums(_leaf())
COMPARISONS = st.tuples(SUMS, st.sampled_from(["<", "<=", ">", ">=", "==", "!="]), SUMS).map(
    lambda t: (f"{t[0][0]} {t[1]} {t[2][0]}", f"{t[0][1]} {t[1]} {t[2][1]}")
)
CONDITIONS = st.recursive(
    COMPARISONS,
    lambda children: st.one_of(
        st.tuples(children, st.sampled_from(["and", "or"]), children).map(
            lambda t: (f"{t[0][0]} {t[1]} {t[2][0]}", f"{t[0][1]} {t[1]} {t[2][1]}")
        ),
        children.map(lambda c: (f"( {c[0]} )", f"( {c[1]} )")),
    ),
    max_leaves=4,
)


class F(float):
    """A float whose arithmetic refuses to overflow, as the grammar does: a finite result of
    finite operands or OverflowError (division by zero stays ZeroDivisionError)."""

    def __new__(cls, value):
        return super().__new__(cls, _finite(float(value), value))

    def __add__(self, other):
        return F(_finite(float(self) + float(other), self, other))

    def __sub__(self, other):
        return F(_finite(float(self) - float(other), self, other))

    def __mul__(self, other):
        return F(_finite(float(self) * float(other), self, other))

    def __truediv__(self, other):
        return F(_finite(float(self) / float(other), self, other))

    def __neg__(self):
        return F(-float(self))


def _finite(result, *_operands):
    """F values are always finite, so a non-finite result of them is an overflow."""
    if not math.isfinite(result):
        raise OverflowError(result)
    return result


REFERENCE_METRICS = {run: {k: F(v) for k, v in values.items()} for run, values in METRICS.items()}


def _reference(python_text: str):
    """Python's own evaluation of the same expression: same precedence (unary minus over
    * / over + - over comparisons over and over or), same IEEE arithmetic with overflow refused
    (class F), same left-to-right order and short-circuit. The text is built by the strategies
    above from F('number'), M[...] and operators only. A literal that is not a finite double
    (1e999) is refused by the grammar when parsing, wherever it stands."""
    if any(not math.isfinite(float(t)) for t in re.findall(r"F\('([^']*)'\)", python_text)):
        return SyntaxError
    try:
        return eval(python_text, {"__builtins__": {}, "F": F}, {"M": REFERENCE_METRICS})  # noqa: S307
    except (ZeroDivisionError, OverflowError) as exc:
        return type(exc)


_EXPECTED_MESSAGE = {SyntaxError: "out of range", ZeroDivisionError: "division by zero", OverflowError: "overflow"}


@budget(200)
@given(CONDITIONS)
def test_grammar_expressions_evaluate_like_python(pair):
    text, python_text = pair
    expected = _reference(python_text)
    if len(text) > expression.MAX_LENGTH:
        with pytest.raises(ExpressionError):
            expression.parse(text, KNOWN)
        return
    try:
        value = expression.evaluate(expression.parse(text, KNOWN), METRICS)
    except ExpressionError as exc:
        if "nested deeper" in str(exc):
            return  # the generator may nest more than MAX_DEPTH; refusing it is documented
        assert expected in _EXPECTED_MESSAGE, (text, exc)
        assert _EXPECTED_MESSAGE[expected] in str(exc), (text, exc, expected)
        return
    assert expected not in _EXPECTED_MESSAGE, (text, expected)
    assert isinstance(value, bool) and value == bool(expected), (text, value, expected)


@budget(150)
@given(SUMS)
def test_arithmetic_matches_python_exactly(pair):
    text, python_text = pair
    expected = _reference(python_text)
    try:
        node = expression.parse(f"{text} == 0", KNOWN)
        value = expression.evaluate(node.left, METRICS)
    except ExpressionError as exc:
        if "nested deeper" in str(exc):
            return
        assert expected in _EXPECTED_MESSAGE and _EXPECTED_MESSAGE[expected] in str(exc), (text, exc, expected)
        return
    assert expected not in _EXPECTED_MESSAGE, (text, expected)
    assert math.isfinite(value) and value == expected, (text, value, expected)


EXPRESSION_ALPHABET = "AB.position_rmse_mm solved 0123456789eE+-*/()<>=!andor \t\u00a0\uff11\u0661"


@budget(300)
@given(st.one_of(st.text(max_size=200), st.text(alphabet=EXPRESSION_ALPHABET, max_size=200)))
def test_any_text_parses_or_raises_expression_error(text):
    try:
        node = expression.parse(text, KNOWN)
    except ExpressionError:
        return
    assert text.isascii()
    try:
        value = expression.evaluate(node, METRICS)
    except ExpressionError:
        return
    assert isinstance(value, bool)


UNICODE_SPACES = "\u00a0\u2003\u3000\u202f\u0085"


@budget(100)
@given(CONDITIONS, st.integers(0, 10_000), st.characters(min_codepoint=0x80, max_codepoint=0x10FFFF), st.data())
def test_any_non_ascii_character_is_an_error(pair, position, char, data):
    """A valid expression with one character made non-ASCII — a digit turned full-width
    (``1`` → ``１``, which ``float`` reads as 1), a space turned into a Unicode space (which
    ``str.strip`` and regex ``\\s`` skip), or any character inserted — is an error."""
    text = pair[0]
    digits = [i for i, c in enumerate(text) if c.isdigit()]
    spaces = [i for i, c in enumerate(text) if c == " "]
    how = data.draw(st.sampled_from(["full-width digit", "unicode space", "insert"]))
    if how == "full-width digit" and digits:
        i = digits[position % len(digits)]
        changed = text[:i] + chr(ord(text[i]) + 0xFEE0) + text[i + 1 :]
    elif how == "unicode space" and spaces:
        i = spaces[position % len(spaces)]
        changed = text[:i] + UNICODE_SPACES[position % len(UNICODE_SPACES)] + text[i + 1 :]
    else:
        i = position % (len(text) + 1)
        changed = text[:i] + char + text[i:]
    with pytest.raises(ExpressionError):
        expression.parse(changed, KNOWN)


@pytest.mark.parametrize(
    "text, message",
    [
        ("B.position_rmse_mm > 1e999", "number out of range"),
        ("B.position_rmse_mm > -1e999", "number out of range"),
        ("1e308 * 10 > B.solved", "overflow"),
        ("A.position_rmse_mm * 1e308 * 1e308 > 0", "overflow"),
    ],
)
def test_numbers_and_arithmetic_beyond_the_double_range_are_errors(text, message):
    """1e999 used to become inf, so 'B.x > 1e999' could never hold and diff exited 0."""
    with pytest.raises(ExpressionError, match=message):
        expression.check(text, METRICS)
    assert expression.check("B.position_rmse_mm < 1e308 and 1e-999 == 0", METRICS)


@pytest.mark.parametrize("digit", ["\uff11", "\u0661", "\u0967", "\U0001d7cf"])  # １ ١ १ 𝟏
def test_non_ascii_digits_are_not_numbers(digit):
    with pytest.raises(ExpressionError, match="non-ASCII"):
        expression.parse(f"B.solved > {digit}", KNOWN)
    assert expression.check("B.solved < 1", METRICS)


# =============================================================================================
# (c) settings: --set key=value
# =============================================================================================

RUN_KEYS = [f.name for f in dataclasses.fields(RunSettings)]
VALUE_TEXT = st.one_of(
    st.text(max_size=30),
    st.from_regex(r"[+-]?[0-9]{0,6}\.?[0-9]{0,4}(?:[eE][+-]?[0-9]{1,4})?", fullmatch=True),
    st.sampled_from(["nan", "inf", "-inf", "1e999", "true", "no", "auto", "lm", "pixel", "\uff11", "1_0", " 3 "]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**30), 10**30).map(str),
)
PAIRS = st.lists(
    st.one_of(
        st.tuples(st.sampled_from(RUN_KEYS), VALUE_TEXT).map(lambda kv: f"{kv[0]}={kv[1]}"),
        st.text(max_size=40),
    ),
    max_size=4,
)


@budget(200)
@given(PAIRS)
def test_run_overrides_give_valid_settings_or_settings_error(pairs):
    try:
        result = apply_overrides(RunSettings(), pairs)
    except SettingsError:
        return
    assert isinstance(result, RunSettings)
    validate(result)


@budget(100)
@given(st.data())
def test_values_within_bounds_are_accepted_and_outside_refused(data):
    numeric = [f for f in dataclasses.fields(RunSettings) if field_types(RunSettings)[f.name] in (int, float)]
    f = data.draw(st.sampled_from(numeric))
    kind = field_types(RunSettings)[f.name]
    lo, hi = f.metadata["min"], f.metadata["max"]
    if kind is int:
        inside = data.draw(st.integers(lo, hi))
        outside = data.draw(st.one_of(st.integers(max_value=lo - 1), st.integers(min_value=hi + 1)))
    else:
        inside = data.draw(st.floats(lo, hi))
        outside = data.draw(st.one_of(st.floats(max_value=lo, exclude_max=True), st.floats(min_value=hi, exclude_min=True)))
    assert getattr(apply_overrides(RunSettings(), [f"{f.name}={inside!r}"]), f.name) == inside
    with pytest.raises(SettingsError, match=f.name):
        apply_overrides(RunSettings(), [f"{f.name}={outside!r}"])


SCENARIOS = sorted(scenario_registry.available())


@budget(100)
@given(st.sampled_from(SCENARIOS), st.data())
def test_scenario_overrides_give_valid_options_or_input_error(scenario, data):
    keys = [f.name for f in dataclasses.fields(scenario_registry.get(scenario).Options)]
    pairs = data.draw(
        st.lists(st.tuples(st.sampled_from(keys), VALUE_TEXT).map(lambda kv: f"{kv[0]}={kv[1]}"), max_size=3)
    )
    try:
        options = scenario_registry.build_options(scenario, pairs)
    except InputError:
        return
    validate(options)


# =============================================================================================
# (d) marker-map validators: schemas.validate_payload and aruco.parse_aruco_map
# =============================================================================================

JSON_SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.integers(-(10**400), 10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
JSON_ISH = st.recursive(
    JSON_SCALARS,
    lambda children: st.one_of(st.lists(children, max_size=5), st.dictionaries(st.text(max_size=8), children, max_size=5)),
    max_leaves=20,
)
NUMBER_ISH = st.one_of(st.floats(-20.0, 20.0), st.integers(-3, 3), JSON_SCALARS)


@st.composite
def marker_entries(draw):
    """A marker entry near the schema: valid parts mixed with wrong types and values."""
    entry = {}
    if draw(st.booleans()):
        entry["id"] = draw(st.one_of(st.integers(-2, 60).map(str), st.integers(-2, 60), st.sampled_from(["²", "٣", "07", ""]), JSON_ISH))
    if draw(st.booleans()):
        entry["side_m"] = draw(NUMBER_ISH)
    if draw(st.booleans()):
        side = draw(st.floats(0.001, 2.0))
        square = [[-side / 2, side / 2, 0.0], [side / 2, side / 2, 0.0], [side / 2, -side / 2, 0.0], [-side / 2, -side / 2, 0.0]]
        entry["corners_world_m"] = draw(
            st.one_of(
                st.just(square),
                st.lists(st.lists(NUMBER_ISH, min_size=3, max_size=3), min_size=4, max_size=4),
                st.lists(st.lists(NUMBER_ISH, max_size=4), max_size=5),
                JSON_ISH,
            )
        )
    if draw(st.booleans()):
        entry["frame"] = draw(st.one_of(st.sampled_from(["world", "agv", "odom"]), JSON_ISH))
    if draw(st.booleans()):
        entry.update(draw(st.dictionaries(st.text(max_size=6), JSON_ISH, max_size=2)))
    return entry


@st.composite
def marker_maps(draw):
    value = {}
    if draw(st.integers(0, 9)):
        value["dictionary"] = draw(st.one_of(st.sampled_from(["qr", "DICT_4X4_50", "DICT_5X5_50", "DICT_X", ""]), JSON_ISH))
    if draw(st.integers(0, 9)):
        value["markers"] = draw(st.one_of(st.lists(marker_entries(), max_size=4), JSON_ISH))
    return value


@budget(200)
@given(st.one_of(marker_maps(), JSON_ISH))
def test_marker_map_validators_accept_or_raise_their_documented_error(value):
    problems = validate_payload("agvviz.MarkerMap", value)
    assert isinstance(problems, list) and all(isinstance(p, str) for p in problems)
    try:
        parsed = parse_aruco_map(value)
    except ArucoError:
        return
    assert parsed is None or isinstance(parsed, ArucoMap)
    if parsed is not None:
        for marker in parsed.markers.values():
            assert marker.corners_m.shape == (4, 3) and np.all(np.isfinite(marker.T_frame_marker))


@budget(100)
@given(st.sampled_from(sorted(SCHEMAS)), JSON_ISH)
def test_every_schema_validator_returns_problems_never_raises(name, value):
    problems = validate_payload(name, value)
    assert isinstance(problems, list) and all(isinstance(p, str) for p in problems)


def test_unknown_schema_name_is_the_documented_key_error():
    with pytest.raises(KeyError, match="unknown agvviz schema"):
        validate_payload("agvviz.Nope", {})


def test_huge_json_integers_are_not_finite_numbers():
    problems = validate_payload(
        "agvviz.MarkerMap",
        {"dictionary": "qr", "markers": [{"id": "1", "side_m": 10**400, "corners_world_m": [[0, 0, 0]] * 4}]},
    )
    assert problems == ["$.markers[0].side_m: expected a number (finite), got <integer of 1329 bits>"]


@pytest.mark.parametrize(
    "value, message",
    [
        ([], "must be a JSON object"),
        ({"dictionary": ["DICT_4X4_50"], "markers": []}, "dictionary must be a string"),
        ({"dictionary": "DICT_4X4_50", "markers": "abc"}, "markers must be a list"),
        ({"dictionary": "DICT_4X4_50", "markers": [3]}, "must be an object"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": "²"}]}, "is not an id"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": "1", "corners_world_m": [[1e300, 0, 0]] * 4}]}, "within"),
        ({"dictionary": "DICT_4X4_50", "markers": [{"id": "1", "corners_world_m": "abcd"}]}, "4 points"),
        (
            {"dictionary": "DICT_4X4_50", "markers": [
                {"id": "1", "corners_world_m": [[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]]},
                {"id": 1, "corners_world_m": [[-1, 1, 0], [1, 1, 0], [1, -1, 0], [-1, -1, 0]]},
            ]},
            "more than once",
        ),
    ],
)
def test_marker_map_bugs_found_by_hypothesis_are_aruco_errors(value, message):
    with pytest.raises(ArucoError, match=message):
        parse_aruco_map(value)

