"""The small, safe grammar of ``agvviz diff --fail-if`` and ``agvviz run --fail-if``. Never
handed to ``eval``.

::

    condition  := conjunction ("or" conjunction)*
    conjunction:= comparison ("and" comparison)*
    comparison := sum ("<" | "<=" | ">" | ">=" | "==" | "!=") sum
                | "(" condition ")"
    sum        := product (("+" | "-") product)*
    product    := unary (("*" | "/") unary)*
    unary      := "-" unary | atom
    atom       := NUMBER | METRIC | "(" sum ")"
    METRIC     := ("A" | "B") "." name          diff: e.g. B.position_rmse_mm, B.suspects.map_entry
                | name                          run (``runs=()``): e.g. suspects, suspects.map_entry
    name       := word ("." word)*
    NUMBER     := decimal, optional exponent    e.g. 1.05, 2e-3 (ASCII digits only)

Only ASCII is accepted: a full-width digit ``１``, a non-breaking space or any other
non-ASCII character is an error naming its column (Python's ``float`` and a regex digit
class would otherwise read ``１`` as 1).

A number must be a finite double: ``1e999`` is an error, not infinity (a condition against
infinity could never hold or always would); so is arithmetic on finite values whose result
overflows (``1e308 * 10``).

The whole expression must be a condition (true/false); arithmetic works on numbers,
``and``/``or`` on conditions. A metric name that is not known is an error listing the known
ones; a metric without a value (e.g. no common frames), a division by zero, or a chained
comparison (``a < b < c``; write ``a < b and b < c``) is an error too.
"""

from __future__ import annotations

from agvviz.errors import InputError

import math
import re
from dataclasses import dataclass
from typing import Iterable, Mapping, Union

#: Longest accepted expression (characters) and deepest parenthesis nesting.
MAX_LENGTH = 1000
MAX_DEPTH = 32

_TOKEN = re.compile(
    r"[ \t\r\n\f\v]*(?:"
    r"(?P<number>(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)"
    r"|(?P<metric>[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)+)"
    r"|(?P<word>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<op><=|>=|==|!=|<|>|\+|-|\*|/|\(|\))"
    r")",
    re.ASCII,
)
_BLANK = " \t\r\n\f\v"
_COMPARISONS = ("<", "<=", ">", ">=", "==", "!=")
RUNS = ("A", "B")
_KEYWORDS = ("and", "or")


class ExpressionError(InputError):
    """A ``--fail-if`` expression that does not parse or cannot be evaluated."""


@dataclass(frozen=True)
class _Token:
    kind: str  # number | metric | word | op | end
    text: str
    column: int  # 1-based


@dataclass(frozen=True)
class Number:
    value: float


@dataclass(frozen=True)
class Metric:
    run: str  # "A" | "B"; "" for a single run's metric (``agvviz run --fail-if``)
    name: str

    @property
    def qualified(self) -> str:
        """The metric as written: ``B.suspects`` or ``suspects``."""
        return f"{self.run}.{self.name}" if self.run else self.name


@dataclass(frozen=True)
class Negate:
    operand: "Node"


@dataclass(frozen=True)
class Arithmetic:
    op: str
    left: "Node"
    right: "Node"


@dataclass(frozen=True)
class Comparison:
    op: str
    left: "Node"
    right: "Node"


@dataclass(frozen=True)
class Logical:
    op: str  # "and" | "or"
    left: "Node"
    right: "Node"


Node = Union[Number, Metric, Negate, Arithmetic, Comparison, Logical]


def _tokenize(text: str) -> list[_Token]:
    for index, char in enumerate(text):
        if not char.isascii():
            raise ExpressionError(
                f"non-ASCII character {char!r} (U+{ord(char):04X}) at column {index + 1}; "
                "write numbers, metrics and operators in ASCII"
            )
    tokens, pos = [], 0
    while pos < len(text):
        if text[pos:].strip(_BLANK) == "":
            break
        match = _TOKEN.match(text, pos)
        if match is None or match.end() == pos:
            column = len(text) - len(text[pos:].lstrip(_BLANK)) + 1
            raise ExpressionError(f"unexpected character {text[column - 1]!r} at column {column}")
        kind = match.lastgroup
        tokens.append(_Token(kind, match.group(kind), match.start(kind) + 1))
        pos = match.end()
    tokens.append(_Token("end", "", len(text) + 1))
    return tokens


class _Parser:
    def __init__(self, text: str, known: frozenset[str], runs: tuple[str, ...] = RUNS):
        self.tokens = _tokenize(text)
        self.pos = 0
        self.known = known
        self.runs = tuple(runs)
        self.depth = 0

    # -- helpers ------------------------------------------------------------------------
    def peek(self) -> _Token:
        return self.tokens[self.pos]

    def take(self) -> _Token:
        token = self.tokens[self.pos]
        self.pos += 1
        return token

    def at(self, kind: str, *texts: str) -> bool:
        token = self.peek()
        return token.kind == kind and (not texts or token.text in texts)

    def fail(self, message: str, token: _Token | None = None) -> ExpressionError:
        token = token or self.peek()
        where = "at the end" if token.kind == "end" else f"at column {token.column} ({token.text!r})"
        return ExpressionError(f"{message} {where}")

    def enter(self) -> None:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.fail(f"parentheses nested deeper than {MAX_DEPTH}")

    # -- grammar ------------------------------------------------------------------------
    def condition(self) -> Node:
        node = self.conjunction()
        while self.at("word", "or"):
            self.take()
            node = Logical("or", node, self.conjunction())
        return node

    def conjunction(self) -> Node:
        node = self.comparison()
        while self.at("word", "and"):
            self.take()
            node = Logical("and", node, self.comparison())
        return node

    def comparison(self) -> Node:
        if self.at("op", "(") and self._parenthesised_condition():
            self.take()
            self.enter()
            node = self.condition()
            if not self.at("op", ")"):
                raise self.fail("expected ')'")
            self.take()
            self.depth -= 1
            return node
        left = self.sum()
        if not self.at("op", *_COMPARISONS):
            raise self.fail("expected a comparison (<, <=, >, >=, ==, !=)")
        op = self.take().text
        right = self.sum()
        if self.at("op", *_COMPARISONS):
            raise self.fail("chained comparison; write 'x < y and y < z'")
        return Comparison(op, left, right)

    def _parenthesised_condition(self) -> bool:
        """Whether the '(' at the cursor opens a condition (contains a comparison or and/or
        at its own nesting level) rather than an arithmetic group."""
        depth = 0
        for token in self.tokens[self.pos :]:
            if token.kind == "op" and token.text == "(":
                depth += 1
            elif token.kind == "op" and token.text == ")":
                depth -= 1
                if depth == 0:
                    return False
            elif depth >= 1 and (
                (token.kind == "op" and token.text in _COMPARISONS)
                or (token.kind == "word" and token.text in ("and", "or"))
            ):
                return True
        return False

    def sum(self) -> Node:
        node = self.product()
        while self.at("op", "+", "-"):
            op = self.take().text
            node = Arithmetic(op, node, self.product())
        return node

    def product(self) -> Node:
        node = self.unary()
        while self.at("op", "*", "/"):
            op = self.take().text
            node = Arithmetic(op, node, self.unary())
        return node

    def unary(self) -> Node:
        if self.at("op", "-"):
            self.take()
            self.enter()
            node = Negate(self.unary())
            self.depth -= 1
            return node
        return self.atom()

    def atom(self) -> Node:
        token = self.peek()
        if token.kind == "number":
            self.take()
            value = float(token.text)
            if not math.isfinite(value):
                raise self.fail("number out of range (largest is 1.8e308)", token)
            return Number(value)
        if token.kind == "metric" or (token.kind == "word" and not self.runs and token.text not in _KEYWORDS):
            self.take()
            if self.runs:
                run, _, name = token.text.partition(".")
                if run not in self.runs:
                    raise self.fail(f"metrics belong to run {' or '.join(self.runs)}, not {run!r}", token)
            else:
                run, name = "", token.text
            if name not in self.known:
                raise ExpressionError(
                    f"unknown metric {name!r} at column {token.column}; known metrics: "
                    + ", ".join(sorted(self.known))
                )
            return Metric(run, name)
        if token.kind == "op" and token.text == "(":
            self.take()
            self.enter()
            node = self.sum()
            if not self.at("op", ")"):
                raise self.fail("expected ')'")
            self.take()
            self.depth -= 1
            return node
        if token.kind == "word":
            example = "A.position_rmse_mm" if self.runs else "suspects"
            raise self.fail(f"expected a number or a metric such as {example}, got a bare word")
        raise self.fail("expected a number, a metric or '('")


def parse(text: str, known_metrics: Iterable[str], runs: tuple[str, ...] = RUNS) -> Node:
    """Parse a ``--fail-if`` condition over the metric names ``known_metrics``.

    ``runs``: the run names a metric is prefixed with (``A.``, ``B.`` for ``diff``); empty for
    the metrics of a single run (``agvviz run --fail-if "suspects > 0"``), written bare.

    Raises
    ------
    ExpressionError
        With the column of the problem, or the list of known metrics for an unknown one.
    """
    if not isinstance(text, str) or not text.strip(_BLANK):
        raise ExpressionError("empty expression; e.g. 'B.position_rmse_mm > 1.05 * A.position_rmse_mm'")
    if len(text) > MAX_LENGTH:
        raise ExpressionError(f"expression longer than {MAX_LENGTH} characters")
    parser = _Parser(text, frozenset(known_metrics), runs)
    node = parser.condition()
    if not parser.at("end"):
        raise parser.fail("unexpected text")
    return node


def evaluate(node: Node, metrics: Mapping[str, Mapping[str, float | None]]) -> bool | float:
    """Value of a parsed expression given ``metrics = {"A": {name: value}, "B": {...}}`` (a single
    run's metrics under the run name ``""``)."""
    if isinstance(node, Number):
        return node.value
    if isinstance(node, Metric):
        value = metrics.get(node.run, {}).get(node.name)
        if value is None:
            raise ExpressionError(f"{node.qualified} has no value in this {'comparison' if node.run else 'run'}")
        return float(value)
    if isinstance(node, Negate):
        return -evaluate(node.operand, metrics)
    if isinstance(node, Arithmetic):
        left, right = evaluate(node.left, metrics), evaluate(node.right, metrics)
        if node.op == "+":
            result = left + right
        elif node.op == "-":
            result = left - right
        elif node.op == "*":
            result = left * right
        elif right == 0.0:
            raise ExpressionError("division by zero")
        else:
            result = left / right
        if not math.isfinite(result) and math.isfinite(left) and math.isfinite(right):
            raise ExpressionError(f"overflow: {left!r} {node.op} {right!r} is beyond ±1.8e308")
        return result
    if isinstance(node, Comparison):
        left, right = evaluate(node.left, metrics), evaluate(node.right, metrics)
        return {
            "<": left < right, "<=": left <= right, ">": left > right,
            ">=": left >= right, "==": left == right, "!=": left != right,
        }[node.op]
    if isinstance(node, Logical):
        left = evaluate(node.left, metrics)
        if node.op == "and":
            return bool(left) and bool(evaluate(node.right, metrics))
        return bool(left) or bool(evaluate(node.right, metrics))
    raise ExpressionError(f"unknown expression node {type(node).__name__}")


def check(text: str, metrics: Mapping[str, Mapping[str, float | None]]) -> bool:
    """Parse ``text`` against the metric names of run A and evaluate it on ``metrics``."""
    node = parse(text, metrics.get("A", {}).keys() | metrics.get("B", {}).keys())
    return bool(evaluate(node, metrics))


def metrics_of(node: Node) -> list[Metric]:
    """The metrics a parsed expression reads, in order of appearance, each once."""
    found: dict[Metric, None] = {}

    def walk(n: Node) -> None:
        if isinstance(n, Metric):
            found[n] = None
        elif isinstance(n, Negate):
            walk(n.operand)
        elif isinstance(n, (Arithmetic, Comparison, Logical)):
            walk(n.left)
            walk(n.right)

    walk(node)
    return list(found)
