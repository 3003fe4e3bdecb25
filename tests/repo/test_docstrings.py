"""Docstrings say what the code is for, not how it came about: no issue numbers and no measured figures in the
product's docstrings (bridge/, drivers/, transfer/, sim_learner/, bench/) nor in docs/CLI.md, which shows the
commands' module docstrings to users as their help. Issue numbers belong to CHANGELOG.md; measured figures to
docs/BENCHMARKS.md (with the command that measures them) or docs/PAPER.md.

A measured figure is recognised where a sentence says it is one (measured, a finding, found here, before/after a
change) and holds a number with a unit of time, memory, a ratio or a share: ``9.0 ms median``, ``1.02 s after``,
``1.5x``, ``35 %``. A sentence that only says how something is measured ("measured from the poses every 0.1 s") or
states a design value, a target or a limit is not one.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("bridge", "drivers", "transfer", "sim_learner", "bench")
ISSUE = re.compile(r"\bissues?\s*#?\s*\d+", re.I)
#: a number with a unit of time, memory, a ratio or a share
FIGURE = re.compile(r"(?<![\w.])\d+(?:\.\d+)?(?:\s?(?:ms|us|µs|s|MB|kB|GB|%)|x)(?![\w])")
#: words that make a sentence's figure a measurement (not how it is measured: "measured from", "measured by")
MEASURED = re.compile(r"\b(?:measured(?!\s+(?:from|by|as|at|on|in|with|over|against|per)\b)|finding|found here"
                      r"|was\s+\d|were\s+\d)\b", re.I)


def _sentences(text: str) -> list[str]:
    flat = " ".join(text.split())
    return [s for s in re.split(r"(?<=[.;!?])\s+(?=[A-Z(`*])", flat) if s]


def figures_and_issues(text: str) -> list[str]:
    """The sentences of ``text`` that name an issue by number or state a measured figure."""
    bad = []
    for s in _sentences(text):
        if ISSUE.search(s):
            bad.append(f"issue number: {s[:160]}")
        elif MEASURED.search(s) and FIGURE.search(s):
            bad.append(f"measured figure: {s[:160]}")
    return bad


def _docstrings(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                out.append((getattr(node, "lineno", 1), doc))
    return out


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


@pytest.mark.parametrize("example", [
    "The host is the wiring (issue 34: one job per class): Zenoh callbacks -> the pure pieces.",
    "Finding (``scmbridge bench bridge``): a command waited out the rest of the gap (9.0 ms median).",
    "A stop never waits for the disk (measured: with each fsync delayed 0.5 s the first stop came 1.02 s after).",
    "Measured (docs/PAPER.md): no alarm in 90 unchanged runs, 5 in 60 000 at 3 %.",
])
def test_the_check_recognises_what_it_forbids(example: str) -> None:
    assert figures_and_issues(example), example


@pytest.mark.parametrize("example", [
    "Deviation is measured from the poses of the run, every 0.1 s.",
    "The deadman stops the vehicle when no fresh command arrived within cmd_timeout (0.3 s).",
    "One point through a built map: 50 us median (the target).",
    "Its figures are in docs/BENCHMARKS.md, with the command that measures them.",
])
def test_the_check_lets_design_values_and_pointers_be(example: str) -> None:
    assert not figures_and_issues(example), example


def test_no_issue_number_or_measured_figure_in_a_product_docstring() -> None:
    bad = []
    for path in _modules():
        for line, doc in _docstrings(path):
            bad += [f"{path.relative_to(ROOT)}:{line}: {b}" for b in figures_and_issues(doc)]
    assert not bad, "move it to CHANGELOG.md or docs/BENCHMARKS.md and point there:\n" + "\n".join(bad)


def test_no_issue_number_or_measured_figure_in_the_cli_reference() -> None:
    bad = figures_and_issues((ROOT / "docs" / "CLI.md").read_text())
    assert not bad, "the CLI's help is its modules' docstrings (fix them, then regenerate docs/CLI.md):\n" + \
        "\n".join(bad)
