"""The docs' commands are real: every ``scmbridge ...`` line in a fenced block of README.md, deploy/README.md,
deploy/ROBOT.md and the prose documents of docs/ (not the generated CLI.md, nor ARCHITECTURE.md, whose diagrams are
fenced too) names a command that exists and parses with that command's own parser, and the ones that need neither a
robot nor a running lab run here (in a temporary state and config directory). The ones that need a running lab
(engage, mission, status, estop, doctor through the router) are what tests/integration/test_lab_in_a_box.py runs;
the ones that need hardware or root (systemctl, useradd, pip into /opt, ip link, doctor on a CAN bus) are listed by
name below, so a new command in the docs must be put in one of the three groups."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from bridge.tools import cli

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "deploy" / "README.md", ROOT / "deploy" / "ROBOT.md",
        *(ROOT / "docs" / f for f in ("OPERATING.md", "PAPER.md", "FLEET.md", "SECURITY.md",
                                      "RELIABILITY.md", "BENCHMARKS.md"))]
#: run here, offline
RUN_HERE = {"config show", "config check", "deploy certs", "deploy lab", "deploy acl", "deploy client", "keys udp",
            "keys mavlink", "driver"}
#: need a running lab: tests/integration/test_lab_in_a_box.py runs them (``mission send`` and ``mission start`` as
#: the docs show them: tests/integration/test_operator_truths.py; deploy/README.md's lab on one machine, the router
#: and the station too: tests/integration/test_lab_local.py); ``pairs show --store``, ``report`` and ``replay``
#: of a file run here
NEEDS_LAB = {"doctor", "engage", "mission start", "mission send", "status", "estop", "demo", "pairs show",
             "pairs plot", "record", "replay", "report", "calibrate", "mission place", "router", "station"}
#: need a robot, root, the network or ArduPilot's SITL for an hour: not run here (``bench sitl``'s runs are
#: tests/integration/test_sitl_profiles.py's, marked ``sitl``)
NEEDS_HARDWARE: set[str] = {"bench sitl"}


def _blocks(path: Path) -> list[str]:
    return re.findall(r"```[a-z]*\n(.*?)```", path.read_text(), flags=re.S)


def documented() -> list[tuple[str, str, list[str]]]:
    """(doc, command name, its arguments) for every scmbridge command line in a fenced block (optional parts
    written ``[--flag VALUE]`` left out; output lines, ``scmbridge NAME: ...``, skipped)."""
    out = []
    for doc in DOCS:
        for block in _blocks(doc):
            for raw in block.replace("\\\n", " ").splitlines():
                line = re.sub(r"\[[^\]]*\]", "", raw.split(" #", 1)[0])  # optional parts (they may hold a "|")
                line = line.split(" | ", 1)[0].split(" > ", 1)[0].strip()
                if "scmbridge" not in line:
                    continue  # code and output of other kinds (a python block's comment may hold a lone quote)
                words = shlex.split(line)
                at = next((i for i, w in enumerate(words) if (w == "scmbridge" or w.endswith("/bin/scmbridge"))
                           and (i == 0 or words[i - 1] != "-u")), None)
                if at is None or at + 1 >= len(words) or words[at + 1].endswith(":"):
                    continue
                words = words[at + 1:]
                name = " ".join(words[:2]) if " ".join(words[:2]) in cli.BY_NAME else words[0]
                out.append((str(doc.relative_to(ROOT)), name, words[len(name.split()):]))
    return out


def test_the_docs_show_commands() -> None:
    found = documented()
    assert len(found) >= 10, found
    assert {n for _, n, _ in found} <= RUN_HERE | NEEDS_LAB | NEEDS_HARDWARE, \
        {n for _, n, _ in found} - RUN_HERE - NEEDS_LAB - NEEDS_HARDWARE


@pytest.mark.parametrize(("doc", "name", "args"), documented(), ids=lambda x: x if isinstance(x, str) else None)
def test_every_documented_command_exists_and_parses(doc: str, name: str, args: list[str]) -> None:
    assert name in cli.BY_NAME, f"{doc}: `scmbridge {name}` is no command"
    parser = cli.parser_for(cli.BY_NAME[name])
    try:
        parser.parse_args([a if not a.startswith(("DIR", "FILE")) else "x" for a in args])
    except SystemExit as exc:
        if exc.code == 0 and "--help" in args:
            return
        pytest.fail(f"{doc}: `scmbridge {name} {' '.join(args)}` does not parse (exit {exc.code})")


def offline(name: str, args: list[str]) -> bool:
    """Whether a documented command runs here as written: every ``--help``, the offline commands (the driver host
    only for its help: it opens a vehicle), and the ones that read a file instead of the network (``pairs show
    --store``, ``report`` and ``replay`` of a recording: a replay in the default Zenoh mode publishes to nobody)."""
    if "--help" in args:
        return True
    if name == "driver" or (name == "keys mavlink" and "--install" in args):  # a vehicle: test_sitl_first_day.py
        return False
    return name in RUN_HERE or (name == "pairs show" and "--store" in args) or name in ("report", "replay")


def _files_the_docs_read(where: Path) -> None:
    """The files the offline documented commands read, in their working directory: a pair store
    (``demo_out/pairs.bin``) and a recording of a short run (``run.mcap``: poses, echoes, commands and both nodes'
    statuses, written by the recorder's own sink)."""
    from bridge.core import wire as M
    from bridge.core.config import StationConfig
    from bridge.tools.mcap_format import classify
    from bridge.tools.mcap_sink import McapSink
    from transfer.store import PairStore

    cfg = StationConfig()
    store = PairStore(cfg.learner_bounds.bounds(), cfg.teacher_bounds.bounds(), k_min=1)
    for v in (0.1, 0.2, 0.3):
        store.add([v * 1.2, 0.1], [v, 0.1])
    (where / "demo_out").mkdir(parents=True, exist_ok=True)
    (where / "demo_out" / "pairs.bin").write_bytes(store.to_bytes())
    sink = McapSink(where / "run.mcap")
    t, k = 100.0, M.Keys("rover1")
    for seq in range(60):  # 3 s at 20 Hz along the S-path's start
        t += 0.05
        msgs = [(k.state, M.LearnerState(stamp=t, seq=seq, x=-4.5 + 0.01 * seq, y=-1.0, theta=0.0)),
                (k.cmd, M.Command(stamp=t, seq=seq, v=0.2, omega=0.0, method="scm")),
                (k.applied, M.Applied(stamp=t + 0.002, seq=seq, v=0.2, omega=0.0, reason="cmd", cmd_seq=seq))]
        if seq % 20 == 0:
            msgs += [(M.status_key("rover1", n), M.Status(stamp=t, seq=seq, node=n, host="lab/1")) for n in
                     ("station", "driver")]
        for key, msg in msgs:
            for spec, data, _ in classify(key, M.encode(msg)):
                sink.write(spec, data, log_time_ns=int(t * 1e9))
    sink.close("done")


@pytest.mark.timeout(600)  # a hang guard: a few dozen tools one after another, each bounded by 120 s itself
def test_the_documented_offline_commands_run(tmp_path: Path) -> None:
    """Run what needs no robot and no lab, with /etc/scmbridge, /var/lib/scmbridge and DIR moved under tmp."""
    ran, names = 0, set()
    _files_the_docs_read(tmp_path)
    for doc, name, args in documented():
        if not offline(name, args):
            continue
        moved = [a.replace("/etc/scmbridge", str(tmp_path / "etc")).replace("/var/lib/scmbridge", str(tmp_path / "var"))
                 for a in args]
        moved = [str(tmp_path / a) if a in ("DIR", "certs/", "lab/") else a for a in moved]
        if name == "config check":
            cfg = tmp_path / "etc" / "driver-rover1.toml"
            cfg.parent.mkdir(parents=True, exist_ok=True)
            subprocess.run([sys.executable, "-m", "bridge", "config", "show", "--kind", "driver"], check=True,
                           stdout=cfg.open("w"), timeout=60)
            # OPERATING's "First day with your rover" copies the MAVLink example first (its cp line) and writes the
            # key its signing_key_file names before the check (its keys line, run here without --install)
            key = tmp_path / "rover1-mavlink.key"
            if not key.exists():
                subprocess.run([sys.executable, "-m", "bridge", "keys", "mavlink", "--robot", "rover1", "--out",
                                str(key), "--passphrase", "first-day"], check=True, capture_output=True, timeout=60)
            example = (ROOT / "deploy" / "driver.mavlink.example.toml").read_text()
            (tmp_path / "driver-rover1.toml").write_text(
                example.replace("/var/lib/scmbridge/keys/rover1-mavlink.key", str(key)))
        res = subprocess.run([sys.executable, "-m", "bridge", *name.split(), *moved], capture_output=True, text=True,
                             timeout=120, env={**os.environ, "SCMBRIDGE_STATE_DIR": str(tmp_path / "var")},
                             cwd=tmp_path)
        assert res.returncode == 0, f"{doc}: scmbridge {name} {' '.join(moved)}: {res.stderr[-500:]}"
        ran += 1
        names.add(name)
    assert ran >= 5
    assert {"pairs show", "report", "replay", "config show", "config check", "keys udp", "deploy certs"} <= names
