"""One truth for each figure: docs/BENCHMARKS.md's generated table ("Current figures", written by
``scmbridge bench figures --write``) is the only place a figure it holds is stated.

The prose documents that readers check figures in (README.md, docs/PAPER.md, docs/FLEET.md, docs/OPERATING.md and
BENCHMARKS.md outside its table) must not state one of the table's figures with another value. The ways those
documents have stated them (the demo's time, deviation and SC-mapped count, one SC point, the default MPC solver's
median, the estop on a slow disk, the fleet's memory and CPU per robot-tick, the paper's MPC and grid ratios) are
recognised by the patterns below; a pattern is checked against the sentences it was written for, so that it cannot
silently match nothing. Every other BENCHMARKS section is dated (or says its date was not recorded) and names the
command that measures it again, or says it is stale.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "docs" / "BENCHMARKS.md"
DOCS = [ROOT / "README.md", *(ROOT / "docs" / f for f in ("PAPER.md", "FLEET.md", "OPERATING.md", "BENCHMARKS.md"))]
BEGIN = "<!-- figures:begin"
END = "<!-- figures:end -->"
NUM = r"(\d+(?:\.\d+)?)"


@dataclass(frozen=True)
class Statement:
    """How a doc states one of the table's figures: ``pattern``'s first group is the value, in ``scale`` x the
    table's unit (cm for a figure the table holds in m: 100)."""

    figure: str
    pattern: str
    scale: float = 1.0
    #: the number of the table's value to compare: 0 the value itself (or a median), 1 and 2 a range's ends
    part: int = 0


STATEMENTS = [
    Statement("demo_driving_s", rf"`scmbridge demo`(?:[^.]|\.\d)*?goal\s+reached\s+in\s+{NUM}\s+s\s+of\s+driving"),
    Statement("demo_driving_s", rf"no\s+change:\s+{NUM}\s+s\s+of\s+driving"),
    Statement("demo_mean_dev_m", rf"`scmbridge demo`[^|]*?goal\s+reached[^|]*?mean\s+deviation\s+{NUM}\s+cm", 100),
    Statement("demo_mean_dev_m", rf"no\s+change:[^)]*?mean\s+deviation\s+{NUM}\s+cm", 100),
    Statement("demo_mean_dev_m", rf"\(no\s+change:\s+{NUM}\s+cm\)", 100),
    Statement("demo_methods", rf"`scmbridge demo`[^|]*?goal\s+reached[^|]*?commands\s+{NUM}\s+scm\b"),
    Statement("demo_raw_pairs", rf"`scmbridge demo`[^|]*?goal\s+reached[^|]*?{NUM}\s+raw\s+/"),
    Statement("scm_point_median", rf"one\s+point\s+through\s+a\s+built\s+`QuadTransfer`\s+\|\s+{NUM}\s+us"),
    Statement("scm_build_median", rf"build\s+one\s+quadrilateral's\s+map\s+\|\s+{NUM}\s+ms", 1e-3),
    Statement("mpc_rti-qpoases_N20_median", rf"`rti-qpoases`\s+\(default\)\s+\|\s+\**{NUM}\s+ms"),
    Statement("mpc_guided_time_ratio", rf"\|\s+guided\s+\|\s+{NUM}x\s+\[[^|]*\|[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s+19-21"),
    Statement("mpc_guided_dev_ratio", rf"\|\s+guided\s+\|[^|]*\|\s+\**{NUM}x\**\s+\["
              r"[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s+19-21"),
    Statement("mpc_paper_time_ratio", rf"\|\s+paper\s+\|\s+{NUM}x\s+\[[^|]*\|[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s+52-99"),
    Statement("mpc_guided_dev_ratio#2", rf"--seeds\s+10-19\s+--policy\s+guided`\):\s+time[^,]*,\s+deviation\s+{NUM}x"),
    Statement("grid_scm_to_baseline", rf"on\s+the\s+SCM\s+region\s+\**{NUM}x"),
    Statement("estop_fsync_0.5s_max", rf"median\s+[\d.]+\s+ms,\s+max\s+{NUM}\s+ms,\s+latch\s+confirmed"),
    Statement("fleet_100_station_rss_mb_total", rf"\b{NUM}\s+MB\s+for\s+both\b"),
    Statement("fleet_100_station_cpu_ms_per_tick", rf"held\s+a\s+hundred\s+robots[^.]*?{NUM}(?:-[\d.]+)?\s+ms\s+of\s+"
              r"station\s+CPU"),
    Statement("fleet_100_station_cpu_ms_per_tick", rf"hundred\s+robots\s+are\s+held[^.]*?{NUM}(?:-[\d.]+)?\s+ms\s+of\s+"
              r"station\s+CPU"),
    Statement("fleet_50_station_rss_mb_total", rf"added\s+robot\s+costs\s+about\s+[\d.]+\s+MB\s+"
              rf"\({NUM}\s+MB\s+at\s+50\b"),
    Statement("fleet_100_station_rss_mb_total", rf"added\s+robot\s+costs\s+about\s+[\d.]+\s+MB\s+"
              rf"\([\d.]+\s+MB\s+at\s+50,\s+{NUM}\s+MB\s+at\s+100\b"),
    Statement("demo_refined_pairs", rf"`scmbridge demo`[^|]*?goal\s+reached[^|]*?raw\s+/\s+{NUM}\s+refined"),
]
#: the table's figures no doc restates in prose, so no pattern looks for them: a figure the table gains is put in
#: STATEMENTS (where a doc states it) or here, by a person who checked the docs
ONLY_IN_TABLE = {
    "transfer_hit_median", "transfer_rebuild_p99", "transfer_stream_median", "bridge_can_median", "bridge_can_p99",
    "bridge_udp_median", "bridge_udp_p99", "bridge_mavlink_median", "bridge_mavlink_p99", "estop_fsync_0s_max",
    "demo_reached_goal", "demo_time_s", "demo_missed_deadlines", "mpc_paper_dev_ratio",
    "mpc_paper_collided_or_missed", "mpc_guided_collided_or_missed", "mpc_guided_time_ratio#2",
    "mpc_guided_collided_or_missed#2", "grid_scm_region_fraction", "fleet_robots_held", "fleet_50_missed_worst",
    "fleet_50_station_cpu_ms_per_tick", "fleet_50_tick_p99_ms_worst", "fleet_100_missed_worst",
    "fleet_100_tick_p99_ms_worst",
}

#: the statements the patterns were written for, each as a doc once had it
STATED_BEFORE = {
    "demo_driving_s": ["`scmbridge demo` (the figures' table above, \"Current figures\", 2026-11-27 12:27 UTC, quiet "
                       "machine, load 1.3): goal reached in 39.6 s of driving (from the first executed command",
                       "Every run reached the goal without a collision (no change: 39.6 s of driving, mean deviation "
                       "9.6 cm, BENCHMARKS \"The demo\"):"],
    "demo_mean_dev_m": ["`scmbridge demo` (...): goal reached in 39.6 s of driving, 388 raw / 17 refined pairs "
                        "learned, commands 21 scm / 222 barycentric, mean deviation 9.6 cm (the start",
                        "mean deviation 9.1 and 8.7 cm over the whole run (no change: 9.6 cm) in"],
    "demo_methods": ["`scmbridge demo` (...): goal reached in 39.5 s of driving, 388 raw / 17 refined pairs learned, "
                     "commands 21 scm / 222 barycentric"],
    "scm_point_median": ["| one point through a built `QuadTransfer` | 55 us (88) | <= 50 us |"],
    "mpc_rti-qpoases_N20_median": ["| `rti-qpoases` (default) | **0.26 ms** | **0.52 ms** | 0.12 ms |"],
    "mpc_guided_dev_ratio": ["| guided | 1.063x [1.055-1.066] (4) | **1.32x** [1.10-1.39] (7) | 10.0 % [9.2-10.7] (5) "
                             "| 0 of 10 | <= 1.6e-7 | 19-21 |"],
    "mpc_guided_dev_ratio#2": ["On seeds the tests do not use (`scmbridge sim mpc --seeds 10-19 --policy guided`): "
                               "time 1.061x [1.055-1.063], deviation 1.26x [1.16-1.50] (worst seed 16)"],
    "estop_fsync_0.5s_max": ["the host confirms the latch once it is on disk): median 6.8 ms, max 7.9 ms, latch "
                             "confirmed 1.9 s after (4 fsyncs delayed)"],
    "fleet_100_station_rss_mb_total": ["deadline missed (tick p99 5-7 ms, 0.91-0.98 ms of station CPU per "
                                       "robot-tick, 663 MB for both)"],
    "fleet_100_station_cpu_ms_per_tick": ["two processes of 50 held a hundred robots in 3 of 3 runs with no "
                                          "deadline missed (tick p99 5-7 ms, 0.91-0.98 ms of station CPU per "
                                          "robot-tick, 663 MB",
                                          "A hundred robots are held in 3 of 3 runs with no deadline missed, at "
                                          "0.91-0.98 ms of station CPU per robot-tick (the"],
    "fleet_50_station_rss_mb_total": ["Each added robot costs about 2.2 MB (557 MB at 50, 663 MB at 100)."],
    "demo_refined_pairs": ["`scmbridge demo` (...): goal reached in 39.6 s of driving, 388 raw / 16 refined pairs "
                           "learned"],
}


def table(text: str) -> dict[str, str]:
    """The generated block's figures by name; a name measured again by a later command of the table (the guided
    policy's ratios on the seeds the tests do not use) is kept as ``name#2``."""
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    out: dict[str, str] = {}
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 2 and cells[0] and not cells[0].startswith(("figure", "---")):
            name, n = cells[0], 1
            while name in out:
                n += 1
                name = f"{cells[0]}#{n}"
            out[name] = cells[1]
    return out


def numbers(value: str, figure: str) -> list[float]:
    """The table's value as numbers: a median and its range's ends, or the SC-mapped count of the method mix."""
    if figure == "demo_methods":  # the mix lists only the methods that mapped a command: none named, none SC-mapped
        m = re.search(r"\bscm=(\d+)", value)
        return [float(m.group(1))] if m else ([0.0] if "=" in value else [])
    return [float(x) for x in re.findall(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", value)]


def same(stated: str, held: float, scale: float) -> bool:
    """The stated figure equals the table's to the coarser of the two precisions (39.5 s is not 39.6 s; 9.4 cm is
    0.0943 m; 1.063x is the table's 1.06)."""
    held = held * scale
    decimals = len(stated.split(".", 1)[1]) if "." in stated else 0
    shown = f"{held:.3g}"  # the table prints three significant figures (bench/figures.py, _fmt)
    if "e" not in shown:
        decimals = min(decimals, len(shown.split(".", 1)[1]) if "." in shown else 0)
    return round(float(stated), decimals) == round(held, decimals)


def prose(path: Path) -> str:
    text = path.read_text()
    if path == BENCH:
        head, rest = text.split(BEGIN, 1)
        text = head + rest.split(END, 1)[1]
    return text


def contradictions(text: str, held: dict[str, str], where: str) -> list[str]:
    bad = []
    for st in STATEMENTS:
        if st.figure not in held:
            continue
        values = numbers(held[st.figure], st.figure)
        if len(values) <= st.part:
            continue
        for m in re.finditer(st.pattern, text):
            if not same(m.group(1), values[st.part], st.scale):
                line = text.count("\n", 0, m.start()) + 1
                bad.append(f"{where}:{line}: states {st.figure} as {m.group(1)}, the table holds {held[st.figure]}")
    return bad


def test_the_table_holds_the_figures_the_patterns_name():
    held = table(BENCH.read_text())
    missing = sorted({st.figure for st in STATEMENTS} - set(held))
    assert not missing, f"the generated table has no {missing}: rename the pattern or regenerate the table"


def test_every_figure_of_the_table_is_looked_for_or_known_to_be_stated_nowhere_else():
    """A figure the table gains is not left unguarded: either a pattern looks for it in the docs, or a person
    checked that no doc restates it (:data:`ONLY_IN_TABLE`); a name the table lost leaves that list."""
    held = set(table(BENCH.read_text()))
    patterned = {st.figure for st in STATEMENTS}
    unguarded = sorted(held - patterned - ONLY_IN_TABLE)
    assert not unguarded, f"figures of the table no pattern looks for: {unguarded} (STATEMENTS or ONLY_IN_TABLE)"
    assert not ONLY_IN_TABLE & patterned, ONLY_IN_TABLE & patterned
    gone = sorted(ONLY_IN_TABLE - held)
    assert not gone, f"ONLY_IN_TABLE names figures the table does not hold: {gone}"


def _moved(held: dict[str, str]) -> dict[str, str]:
    """The table with every number in it moved (x3 + 1), so that no statement can agree with it by chance."""
    return {k: re.sub(r"\d+(?:\.\d+)?", lambda m: f"{float(m.group()) * 3 + 1:g}", v) for k, v in held.items()}


@pytest.mark.parametrize("figure", sorted(STATED_BEFORE))
def test_a_pattern_recognises_each_way_a_figure_was_stated(figure):
    held = _moved(table(BENCH.read_text()))
    for sentence in STATED_BEFORE[figure]:
        found = [b for b in contradictions(sentence, held, "example") if f"states {figure} " in b]
        assert found, f"no pattern recognises {figure} in {sentence!r}"


def test_a_statement_equal_to_the_table_is_no_contradiction():
    held = table(BENCH.read_text())
    dev_cm = f"{float(held['demo_mean_dev_m']) * 100:.1f}"
    ok = f"Every run reached the goal (no change: {held['demo_driving_s']} s of driving, mean deviation {dev_cm} cm)"
    assert contradictions(ok, held, "example") == []


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_doc_states_a_figure_the_table_holds_differently(path):
    held = table(BENCH.read_text())
    bad = contradictions(prose(path), held, str(path.relative_to(ROOT)))
    assert not bad, "link to docs/BENCHMARKS.md \"Current figures\" instead of restating:\n" + "\n".join(bad)


def test_every_other_benchmarks_section_is_dated_and_says_how_it_is_measured_again():
    text = BENCH.read_text()
    sections = re.split(r"^## ", text, flags=re.M)[1:]
    bad = []
    for sec in sections:
        title, body = sec.split("\n", 1)
        if title.startswith("Current figures"):
            continue
        if "`" not in title and "stale" not in body.lower():
            bad.append(f"{title}: its heading names no command and it is not marked stale")
        if not re.search(r"\b20\d\d-\d\d-\d\d\b", body) and "not recorded" not in body:
            bad.append(f"{title}: no date (nor says its date was not recorded)")
    assert not bad, "\n".join(bad)
