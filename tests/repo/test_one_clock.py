"""One clock on the control path: the nodes' loops and the drivers tell the time only through the clock they are given
(:class:`bridge.core.clock.Clock`; docs/ARCHITECTURE.md, "Threads and clocks"), so their timing is tested on a fake
clock (tests/fakeclock.py) and a recorded run replays on the recorded one. No module of bridge/nodes/ or drivers/
calls ``time.monotonic``, ``time.time``, ``time.sleep`` or ``time.perf_counter`` itself (nor imports them by name),
except those listed in :data:`NOT_YET`, which is empty and stays so; none imports ``time`` at all (a date is
formatted with ``datetime``): ``time`` is used only by the clock's own module, :data:`CLOCK_MODULE`."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCANNED = ("bridge/nodes", "drivers")
#: a direct read of the host's clocks, or one of their functions imported by name
DIRECT = re.compile(r"\btime\.(monotonic|time|sleep|perf_counter)(_ns)?\b"
                    r"|\bfrom\s+time\s+import\s+[^\n]*\b(monotonic|time|sleep|perf_counter)\b")
#: modules still allowed a direct read: none (the driver side went onto its injected clock, bridge/core/timebase.py)
NOT_YET: set[str] = set()
#: the module that may use the time module for the nodes and the drivers: the clock's own
CLOCK_MODULE = "bridge/core/timebase.py"


def _allowed(rel: str) -> bool:
    return rel in NOT_YET or any(p.endswith("/*") and rel.startswith(p[:-1]) for p in NOT_YET)


def _offences() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for top in SCANNED:
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for n, line in enumerate(path.read_text().splitlines(), 1):
                if DIRECT.search(line):
                    out.setdefault(rel, []).append(f"{rel}:{n}: {line.strip()}")
    return out


def test_the_nodes_read_the_time_only_through_their_clock() -> None:
    bad = [line for rel, lines in _offences().items() if not _allowed(rel) for line in lines]
    assert not bad, "read the injected clock (bridge.core.clock.Clock) instead:\n" + "\n".join(bad)


def test_the_pattern_finds_what_it_is_for() -> None:
    for line in ("t = time.monotonic()", "time.sleep(0.1)", "x = time.time_ns()", "t0 = time.perf_counter()",
                 "from time import monotonic", "from time import sleep as nap"):
        assert DIRECT.search(line), line
    for line in ("t = self.clock()", "time.strftime('%H')", "clock.wait(stop, 1.0)", "uptime.monotonic_s"):
        assert not DIRECT.search(line), line


def _uses_time(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name == "time" for a in node.names):
            found.append(f"line {node.lineno}: import time")
        elif isinstance(node, ast.ImportFrom) and node.module == "time":
            found.append(f"line {node.lineno}: from time import ...")
    return found


def test_the_drivers_and_the_nodes_read_time_only_through_the_clock_module() -> None:
    offenders = {}
    for top in SCANNED:
        for p in sorted((ROOT / top).rglob("*.py")):
            found = _uses_time(p)
            if found:
                offenders[p.relative_to(ROOT).as_posix()] = found
    assert not offenders, offenders
    assert _uses_time(ROOT / CLOCK_MODULE)  # (the check sees an import where there is one)
