"""The tests assert behaviour, never how long something took: a wall-clock bound fails on
a loaded machine (timings live in ``benchmarks/``, as pytest-benchmark groups)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

TIMING_NAME = re.compile(r"seconds|elapsed|duration|perf_counter|monotonic|^time$", re.I)


def _timed_assertions(source: str) -> list[int]:
    """Line numbers of the ``assert`` statements that compare a timing (a name such as
    ``seconds`` or ``elapsed``, or a clock call) with ``<``, ``<=``, ``>`` or ``>=``."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Assert):
            continue
        for compare in (n for n in ast.walk(node.test) if isinstance(n, ast.Compare)):
            if not any(isinstance(op, (ast.Lt, ast.LtE, ast.Gt, ast.GtE)) for op in compare.ops):
                continue
            names = [n.attr if isinstance(n, ast.Attribute) else n.id
                     for n in ast.walk(compare) if isinstance(n, (ast.Attribute, ast.Name))]
            if any(TIMING_NAME.search(name) for name in names):
                lines.append(node.lineno)
    return lines


def test_the_check_finds_a_timed_assertion():
    assert _timed_assertions("assert run.seconds < 30\nassert len(x) < 30\n") == [1]
    assert _timed_assertions("assert time.perf_counter() - start < 5") == [1]


@pytest.mark.parametrize("path", sorted(Path(__file__).parent.rglob("*.py")),
                         ids=lambda p: str(p.relative_to(Path(__file__).parent)))
def test_no_assertion_on_elapsed_time(path):
    assert _timed_assertions(path.read_text()) == [], path
