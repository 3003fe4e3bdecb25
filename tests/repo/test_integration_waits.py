"""The integration tests wait on events, not on time (docs/ARCHITECTURE.md, "Threads and clocks"): a fixed sleep before
an assertion fails on a machine that stalls the process it waits for, and wastes time on one that does not. So every
``sleep`` left in tests/integration/ says, in a comment on its line or on a comment line just above it, which of the
few kinds that cannot wait on an event it is:

- *pacing*: a simulated sender's period (a 50 Hz mocap, a telemetry source);
- *window* (or *absence*): a span in which something must *not* happen (absence is observed only over time);
- *stall*: a process or its messages held still on purpose (to trip a deadman, a watchdog, a freshness check);
- *poll*: the step of a bounded wait for a state no event announces (tests/wait.py ``until`` is the usual form).

The kind is a word of a comment (``# pacing: the 50 Hz mocap``, ``# a simulated stall: ...``).

A sleep without its kind is a wait to turn into an event wait (``until(fn, timeout)``)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
KINDS = ("pacing", "window", "absence", "stall", "poll")
TAG = re.compile(r"#.*\b(" + "|".join(KINDS) + r")\b")


def _sleeps(source: str) -> list[int]:
    """Line numbers of every call of a function named ``sleep`` (``time.sleep``, ``sleep``, ``asyncio.sleep``)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name == "sleep":
                out.append(node.lineno)
    return sorted(out)


def _untagged(path: Path, root: Path = ROOT) -> list[str]:
    text = path.read_text()
    lines = text.splitlines()
    bad = []
    for n in _sleeps(text):
        here, above = lines[n - 1], lines[n - 2] if n >= 2 else ""
        if not (TAG.search(here) or (above.lstrip().startswith("#") and TAG.search(above))):
            bad.append(f"{path.relative_to(root)}:{n}: {here.strip()}")
    return bad


def test_every_sleep_in_the_integration_tests_says_why_it_cannot_be_an_event_wait() -> None:
    files = sorted((ROOT / "tests" / "integration").rglob("*.py"))
    assert len(files) > 20, files
    bad = [b for p in files for b in _untagged(p)]
    assert not bad, ("wait on the event instead (tests/wait.py until), or tag the sleep with its kind "
                     f"({', '.join('# ' + k for k in KINDS)}):\n" + "\n".join(bad))


def test_the_scan_finds_sleeps_and_reads_their_tags(tmp_path: Path) -> None:
    (tmp_path / "tests" / "integration").mkdir(parents=True)
    src = ("import time, asyncio\nfrom time import sleep\n"
           "time.sleep(1)\n"
           "sleep(0.02)  # pacing: the 50 Hz sender\n"
           "time.sleep(0.5)  # give it time to settle\n"
           "# window: nothing may drive for 3 s\n"
           "time.sleep(3)\n"
           "asyncio.sleep(0.1)\n"
           "x.sleepy(1)\n")
    assert _sleeps(src) == [3, 4, 5, 7, 8]
    p = tmp_path / "tests" / "integration" / "t.py"
    p.write_text(src)
    bad = _untagged(p, tmp_path)
    assert [b.split(":")[1] for b in bad] == ["3", "5", "8"]
