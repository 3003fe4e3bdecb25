"""``scmbridge record`` / ``replay`` / ``report`` (bridge/tools/record.py, mcap_sink.py, report.py).

The fast tests drive a short, deterministic run (poses along a mission path, commands, echoes, both nodes' status,
a mission message, a malformed and a non-canonical sample) through a Zenoh router on a free 127.0.0.1 port, with
the demo's own :class:`bridge.tools.demo.Monitor` watching live next to a recorder process. The slow test records the
real HIL demo (``scmbridge demo``) end to end. Every process is started through ``bridge.tools.procs`` and stopped.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import msgspec
import pytest
import zenoh

from bridge.core import wire as M
from bridge.core.config import mission_from_spec
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.mcap_format import (
    MALFORMED,
    NONCANONICAL,
    TOPIC_KINDS,
    RawSample,
    classify,
    from_json,
    json_schema,
    read_recording,
)
from bridge.tools.mcap_sink import McapSink
from bridge.tools.procs import Children, stop_group
from tests.missions import first_bend_file
from tests.wait import Pace, until

ROBOT = "rec1"
MISSION = M.MissionSpec(name="test-bend", path=[[0.0, 0.0], [2.0, 0.0], [3.0, 1.0]], goal_tolerance=0.2)


# ------------------------------------------------------------------------------------------------- helpers
@contextmanager
def router() -> Iterator[tuple[zenoh.Session, int]]:
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])) as s:
        yield s, port


def client_args(port: int) -> list[str]:
    return ["--mode", "client", "--connect", tcp(port)]


def wait_line(proc: subprocess.Popen, pattern: str, timeout: float = 30.0) -> str:
    """The first line of the child's output matching ``pattern`` (fails on timeout or exit)."""
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    t_end = time.monotonic() + timeout
    seen = []
    while time.monotonic() < t_end:
        if sel.select(timeout=0.1):
            line = proc.stdout.readline().decode(errors="replace")
            if not line and proc.poll() is not None:
                break
            seen.append(line)
            if re.search(pattern, line):
                return line
    raise AssertionError(f"no line matching {pattern!r} in {timeout} s; output: {''.join(seen)[-2000:]}")


def start_recorder(kids: Children, port: int, out: Path, *extra: str) -> subprocess.Popen:
    proc = kids.spawn(["record", "--all", "--out", str(out), *client_args(port), *extra], subprocess.PIPE)
    wait_line(proc, r"^recording scm/")
    return proc


def wait_matching(pub: zenoh.Publisher, timeout: float = 20.0) -> None:
    assert until(lambda: pub.matching_status.matching, timeout, step=0.01), \
        "the recorder's subscriber never reached the publisher"


def recorded_seqs(paths: list[Path]) -> list:
    """The wire messages the recorder's files hold so far: the chunks it has closed (it closes one each second, so
    what it took is on disk within about a second); a file being written reads as truncated, not as an error."""
    try:
        entries, _ = read_recording(paths)
    except Exception:  # noqa: BLE001 (a file just created: not even its header yet)
        return []
    return [e for e in entries if e.topic != NONCANONICAL]


def settled(out: Path, timeout: float = 30.0) -> int:
    """Once nothing more can arrive (the publishers are gone), wait until the recording has taken what it
    received: the count on disk is unchanged over two of the sink's chunk closings. Returns the count."""
    seen = [-1, time.monotonic()]

    def still() -> bool:
        n = len(recorded_seqs([out]))
        if n != seen[0]:
            seen[:] = [n, time.monotonic()]
        return n > 0 and time.monotonic() - seen[1] > 2.5

    until(still, timeout, step=0.1)
    return seen[0]


def finish(proc: subprocess.Popen) -> str:
    """SIGTERM the child (a clean stop), return all its output."""
    stop_group(proc)
    return proc.stdout.read().decode(errors="replace")


class Run:
    """A short deterministic run of one robot, published the way the station and the driver host publish."""

    def __init__(self, session: zenoh.Session, robot: str = ROBOT) -> None:
        self.session = session
        self.keys = M.Keys(robot)
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.sent: list[tuple[str, bytes]] = []  # everything put, in order

    def put(self, key: str, data: bytes) -> None:
        pub = self.pubs.get(key)
        if pub is None:
            pub = self.pubs[key] = self.session.declare_publisher(key,
                                                                  congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(data)
        self.sent.append((key, data))

    def drive(self, ticks: int = 240, period: float = 0.005) -> None:
        k, mission, pace = self.keys, mission_from_spec(MISSION), Pace(period)
        self.put(k.mission, M.encode(MISSION))
        epoch_c, epoch_d = 11, 22
        methods = ["scm", "scm", "direct", "perturb", "scm", "stop"]
        counts: dict[str, int] = {}
        cmd_seq = None
        for i in range(ticks):
            now = time.monotonic()
            s = mission.path.length * i / (ticks - 1)
            x, y = _point_at(mission, s)
            off = 0.03 * math.sin(i / 7.0)
            self.put(k.state, M.encode(M.LearnerState(stamp=now, seq=i, x=x, y=y + off, theta=0.1 * off, v=0.2,
                                                      omega=0.0, source="test", epoch=epoch_d)))
            if i % 5 == 0:
                m = methods[(i // 5) % len(methods)]
                counts[m] = counts.get(m, 0) + 1
                cmd_seq = i // 5
                self.put(k.cmd, M.encode(M.Command(stamp=now, seq=cmd_seq, v=0.0 if m == "stop" else 0.2,
                                                   omega=0.0, method=m, sender="station", epoch=epoch_c)))
            if cmd_seq is not None:
                self.put(k.applied, M.encode(M.Applied(stamp=time.monotonic(), seq=i, v=0.2, omega=0.0,
                                                       reason="cmd", cmd_seq=cmd_seq)))
            if i % 40 == 0 or i == ticks - 1:
                last = i == ticks - 1
                self.put(M.status_key(k.robot, "station"), M.encode(M.Status(
                    stamp=now, seq=i, node="station", latencies_ms={"solve_median": 3.0 + i / 1000, "solve_max": 9.0},
                    counters={**{f"method_{a}": b for a, b in counts.items()}, "refined_pairs": i // 10,
                              "raw_pairs": i, "missed_deadlines": i // 100, "goal_reached": int(last)})))
                self.put(M.status_key(k.robot, "driver"), M.encode(M.Status(
                    stamp=now, seq=i, node="driver", latencies_ms={"jitter_p99": 0.5, "telemetry_age": 10.0},
                    counters={"missed_deadlines": 0})))
            if i == ticks // 2:
                self.put(k.state, b"\xc1 not msgpack")  # malformed: counted by the monitor, kept by the recorder
                self.put(f"scm/{k.robot}/bogus", b"\x80")  # outside the wire contract
                # a valid Limits with its fields in another order than wire.encode writes them
                self.put(k.limits, msgspec.msgpack.encode({"box": [0.0, 1.0, -1.0, 1.0], "version": 1,
                                                           "robot": k.robot, "stamp": now}))
            pace.wait()  # pacing: the run's ticks


def _point_at(mission, s: float) -> tuple[float, float]:
    pts = mission.path.points
    for a, b in zip(pts[:-1], pts[1:]):
        seg = math.dist(a, b)
        if s <= seg:
            f = s / seg
            return float(a[0] + f * (b[0] - a[0])), float(a[1] + f * (b[1] - a[1]))
        s -= seg
    return float(pts[-1][0]), float(pts[-1][1])


def canonical(sent: list[tuple[str, bytes]]) -> list[tuple[str, bytes]]:
    """What a replay should publish for what was sent: wire messages only, in wire.encode's form."""
    from bridge.tools.mcap_format import kind_of

    out = []
    for key, data in sent:
        try:
            kind = kind_of(key)
            out.append((key, M.encode(M.decode(data, kind))))
        except (ValueError, M.MessageError):
            continue
    return out


# ---------------------------------------------------------------------------------------------- the format
def test_every_topic_has_a_viewer_schema() -> None:
    assert set(TOPIC_KINDS) == set(M.TOPICS)
    for kind in {*TOPIC_KINDS.values()}:
        schema = json_schema(kind)
        assert schema["type"] == "object", kind  # Foxglove wants an object at the root
        refs = re.findall(r'"\$ref": "#/\$defs/([^"]+)"', json.dumps(schema))
        assert set(refs) <= set(schema.get("$defs", {})), kind  # internal references only, all resolvable


def test_classify_keeps_what_it_cannot_decode() -> None:
    good = M.encode(M.Applied(stamp=1.0, seq=2, v=0.1, omega=0.0, reason="cmd", cmd_seq=1))
    [(spec, data, outcome)] = classify("scm/r/applied", good)
    assert (spec.topic, spec.schema_name, outcome) == ("scm/r/applied", "scmbridge.Applied", "ok")
    assert M.encode(from_json(data, M.Applied)) == good
    for key, payload, why in [("scm/r/applied", b"\xc1", "bad Applied"), ("scm/r/nope", good, "unknown topic"),
                              ("scm/r/status", good, "status is"), ("scm/r/cmd/x", good, "chunks after"),
                              ("other/r/cmd", good, "not scm/")]:
        [(spec, data, outcome)] = classify(key, payload)
        raw = json.loads(data)
        assert (spec.topic, outcome) == (MALFORMED, "malformed")
        assert why in raw["error"] and raw["key"] == key and raw["size"] == len(payload)
    [(spec, _, outcome)] = classify("scm/r/cmd", b"", is_put=False)
    assert (spec.topic, outcome) == (MALFORMED, "malformed")
    odd = msgspec.msgpack.encode({"seq": 2, "stamp": 1.0, "v": 0.1, "omega": 0.0, "reason": "cmd"})
    (spec, data, outcome), (spec2, raw, outcome2) = classify("scm/r/applied", odd)
    assert (outcome, outcome2, spec2.topic) == ("ok", "noncanonical", NONCANONICAL)
    assert from_json(raw, RawSample).payload == odd


def test_size_limit_is_never_exceeded(tmp_path: Path) -> None:
    """The sink's estimate of a closed file's size is an upper bound, whatever mix of channels is written."""
    for limit in (2500, 9000, 40000):
        sink = McapSink(tmp_path / f"l{limit}.mcap", max_bytes=limit, chunk_bytes=2048)
        n = 0
        while True:
            key = f"scm/r{n % 7}/state"
            msg = M.LearnerState(stamp=float(n), seq=n, x=0.1 * n, y=1.0, theta=0.0, source="x" * (n % 50))
            if sink.write(*classify(key, M.encode(msg))[0][:2], log_time_ns=n) == "full":
                break
            n += 1
        sink.close("size limit")
        size = (tmp_path / f"l{limit}.mcap").stat().st_size
        entries, rec = read_recording([tmp_path / f"l{limit}.mcap"])
        assert size <= limit and len(entries) == n and not rec.truncated, (limit, size, n)
        assert size > 0.6 * limit or limit < 5000, (limit, size)  # and the bound is not wasteful
        print(limit, size, n)


# ------------------------------------------------------------------------------------ one recorded run
@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict:
    """A synthetic run watched live by the demo's Monitor and recorded by `scmbridge record --all`."""
    from bridge.tools.demo import Monitor

    out = tmp_path_factory.mktemp("rec") / "run.mcap"
    with router() as (session, port), Children() as kids:
        mon = Monitor(session, ROBOT)
        rec = start_recorder(kids, port, out)
        with open_session(make_config(mode="client", connect=[tcp(port)])) as pub_session:
            run = Run(pub_session)
            probe = pub_session.declare_publisher(M.key(ROBOT, "teacher"))  # only the recorder subscribes to it
            wait_matching(probe)
            run.drive()
            # the recorder has taken all of it: every message sent is in a chunk it closed
            assert until(lambda: len(recorded_seqs([out])) >= len(run.sent), 30, step=0.1), "the recorder fell behind"
        text = finish(rec)
        live = mon.summary(mission_from_spec(MISSION))
    live.pop("_traj")
    return {"out": out, "sent": run.sent, "live": live, "log": text}


def test_the_recording_holds_every_sample_in_order_with_schemas(recorded: dict) -> None:
    from mcap.reader import make_reader

    assert re.search(r"stopped: signal", recorded["log"]), recorded["log"]
    with open(recorded["out"], "rb") as f:  # a cleanly stopped recording has its summary: an indexed reader works
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == len(recorded["sent"]) + 1
    schemas = {s.name: s for s in summary.schemas.values()}
    assert {s.encoding for s in schemas.values()} == {"jsonschema"}
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}
    assert "scmbridge.Command" in schemas and json.loads(schemas["scmbridge.Command"].data)["type"] == "object"
    topics = {c.topic for c in summary.channels.values()}
    assert {M.key(ROBOT, "state"), M.key(ROBOT, "cmd"), M.status_key(ROBOT, "driver"), MALFORMED,
            NONCANONICAL} <= topics
    entries, rec = read_recording([recorded["out"]])
    assert not rec.truncated
    wire = [e for e in entries if e.topic != NONCANONICAL]
    assert len(wire) == len(recorded["sent"])
    for e, (key, data) in zip(wire, recorded["sent"]):
        if e.topic == MALFORMED:
            raw = e.message()
            assert (raw.key, raw.payload) == (key, data)
        else:
            assert e.topic == key
            msg = e.message()
            assert M.encode(msg) == data or msg == M.decode(data, type(msg))
    [odd] = [e.message() for e in entries if e.topic == NONCANONICAL]
    assert odd.key == M.key(ROBOT, "limits") and (odd.key, odd.payload) in recorded["sent"]
    assert all(a.log_time <= b.log_time for a, b in zip(entries, entries[1:]))


def test_report_gives_the_live_monitors_summary(recorded: dict, tmp_path: Path) -> None:
    from bridge.tools.cli import main as cli_main

    out = tmp_path / "report"
    proc = subprocess.run([sys.executable, "-m", "bridge", "report", str(recorded["out"]), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    line = next(x for x in proc.stdout.splitlines() if x.startswith("summary: "))
    assert json.loads(line[len("summary: "):]) == recorded["live"]
    mapped = recorded["live"]["methods"]  # by an SC region, or linearly along a learned limit or on a triangle
    assert recorded["live"]["reached_goal"] and mapped.get("scm", 0) + mapped.get("barycentric", 0) > 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["mission"]["name"] == MISSION.name and "recorded" in rep["mission"]["source"]
    lat = rep["cmd_to_applied"]
    assert lat["paired"] == lat["commands"] == 48 and lat["stamps_one_clock"]  # one machine: one clock
    assert 0 <= lat["by_stamps_ms"]["median"] < 50
    for name in ("trajectory.png", "deviation.png", "timeline.png"):
        assert (out / name).stat().st_size > 10_000, name
    assert cli_main(["report", str(recorded["out"]), "--out", str(tmp_path / "r2"), "--robot", "nobody"]) == 1


@pytest.mark.parametrize("with_commands", [True, False], ids=["with-commands", "default"])
def test_replay_publishes_every_message_in_order(recorded: dict, with_commands: bool) -> None:
    expected = canonical(recorded["sent"])
    if not with_commands:
        expected = [(k, d) for k, d in expected if k.split("/")[2] not in ("cmd", "estop")]
    got: list[tuple[str, bytes]] = []
    with router() as (session, port), Children() as kids:
        session.declare_subscriber("scm/**", lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
        args = ["replay", str(recorded["out"]), "--fast", *client_args(port)]
        proc = kids.spawn(args + (["--with-commands"] if with_commands else []), subprocess.PIPE)
        line = wait_line(proc, r"^replayed ", timeout=60)
        assert proc.wait(timeout=30) == 0
        until(lambda: len(got) >= len(expected), 20)  # the last ones are on their way
    assert f"replayed {len(expected)} messages" in line, line
    assert got == expected


def test_replay_keeps_the_recorded_pace_and_renames(recorded: dict) -> None:
    entries, _ = read_recording([recorded["out"]])
    span = (entries[-1].log_time - entries[0].log_time) / 1e9
    got: list[tuple[float, str]] = []
    with router() as (session, port), Children() as kids:
        session.declare_subscriber("scm/**", lambda s: got.append((time.monotonic(), str(s.key_expr))))
        proc = kids.spawn(["replay", str(recorded["out"]), "--speed", "2", "--robot-rename", f"{ROBOT}=copy",
                           *client_args(port)], subprocess.PIPE)
        wait_line(proc, r"^replayed ", timeout=60)
        proc.wait(timeout=30)
    took = got[-1][0] - got[0][0]
    assert span / 2 * 0.8 < took < span / 2 + 1.0, (span, took)
    assert {k.split("/")[1] for _, k in got} == {"copy"}


# ------------------------------------------------------------------------------- durability and disk bounds
def _steady(session: zenoh.Session, seconds: float, rate: float = 200.0, robot: str = ROBOT) -> int:
    """Publish poses at ``rate`` for ``seconds``; returns how many."""
    pub = session.declare_publisher(M.key(robot, "state"), congestion_control=zenoh.CongestionControl.BLOCK)
    wait_matching(pub)
    n, t_end, pace = 0, time.monotonic() + seconds, Pace(1.0 / rate)
    while time.monotonic() < t_end:
        pub.put(M.encode(M.LearnerState(stamp=time.monotonic(), seq=n, x=0.001 * n, y=0.0, theta=0.0,
                                        source="steady", epoch=7)))
        n += 1
        pace.wait()  # pacing: a robot's poses at ``rate``
    return n


def test_a_killed_recorder_leaves_a_readable_file(tmp_path: Path) -> None:
    from mcap.exceptions import EndOfFile
    from mcap.reader import NonSeekingReader

    out = tmp_path / "killed.mcap"
    with router() as (session, port), Children() as kids:
        rec = start_recorder(kids, port, out)
        t0 = time.monotonic()
        n = _steady(session, 2.7)
        os.killpg(rec.pid, signal.SIGKILL)
        rec.wait(timeout=10)
        assert rec.returncode == -signal.SIGKILL
        killed_after = time.monotonic() - t0
    # the mcap library's own scanning reader reads it, up to the torn tail (no summary, no footer)
    seqs = []
    with open(out, "rb") as f:
        try:
            for _schema, _channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                seqs.append(json.loads(message.data)["seq"])
        except EndOfFile:
            pass
    assert seqs == list(range(len(seqs)))
    # chunks are closed each second: at most ~1 s of a ~2.7 s recording is lost
    assert len(seqs) >= n * (killed_after - 1.3) / killed_after, (len(seqs), n, killed_after)
    entries, recording = read_recording([out])
    assert len(entries) == len(seqs) and len(recording.truncated) == 1


def test_max_bytes_stops_the_recording_within_the_limit(tmp_path: Path) -> None:
    out = tmp_path / "capped.mcap"
    with router() as (session, port), Children() as kids:
        rec = start_recorder(kids, port, out, "--max-bytes", "12k")
        pub = session.declare_publisher(M.key(ROBOT, "state"))
        wait_matching(pub)
        t_end = time.monotonic() + 20
        n = 0
        while rec.poll() is None and time.monotonic() < t_end:
            pub.put(M.encode(M.LearnerState(stamp=time.monotonic(), seq=n, x=0.0, y=0.0, theta=0.0)))
            n += 1
            time.sleep(0.002)  # pacing: poses until the recorder stops (the loop's deadline is the test)
        assert rec.poll() == 0, "the recorder did not stop at its size limit"
        text = rec.stdout.read().decode()
    assert "stopped: size limit" in text, text
    assert out.stat().st_size <= 12 * 1024
    entries, recording = read_recording([out])
    assert not recording.truncated and len(entries) > 50
    assert [e.message().seq for e in entries] == list(range(len(entries)))


def test_rotation_keeps_the_last_files_each_within_its_size(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    with router() as (session, port), Children() as kids:
        rec = start_recorder(kids, port, out, "--rotate-bytes", "6k", "--keep", "3")
        n = _steady(session, 2.0, rate=300)
        # the last pose is on disk (in the newest file, or the one before if it just rotated)
        assert until(lambda: any(e.message().seq == n - 1 for f in sorted(tmp_path.glob("run-*.mcap"), key=lambda f:
                                                                           int(f.stem.split("-")[1]))[-2:]
                                 for e in recorded_seqs([f])), 30, step=0.1), "the recorder fell behind"
        text = finish(rec)
    files = sorted(tmp_path.glob("run-*.mcap"))
    assert len(files) == 3, (files, text)
    indexes = [int(f.stem.split("-")[1]) for f in files]
    assert indexes == list(range(indexes[0], indexes[0] + 3)) and indexes[0] > 1
    seqs = []
    for f in files:
        assert f.stat().st_size <= 6 * 1024, f
        entries, recording = read_recording([f])
        assert not recording.truncated and entries
        seqs += [e.message().seq for e in entries]
    assert seqs == list(range(seqs[0], n)), "the kept files hold the newest messages, none missing"


# ------------------------------------------------------------------------------------------- the HIL demo
def _children_of(pid: int) -> list[int]:
    kids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(d.name))
    return kids


def _cmdline(pid: int) -> list[str]:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().decode().split("\0")
    except OSError:
        return []


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_a_recorded_demo_reports_the_live_demos_figures(tmp_path: Path) -> None:
    """`scmbridge demo` with `scmbridge record --all` attached: the report of the recording prints the summary the
    demo printed. The demo does not say its port, so this finds it on the command lines of the demo's children,
    and holds them (SIGSTOP) until the recorder is subscribed so it misses nothing of the run. The mission is the
    S-path's first bend (tests/missions.py): the recording's figures are the claim, not the whole path's."""
    demo_out, out = tmp_path / "demo", tmp_path / "demo.mcap"
    mission = first_bend_file(tmp_path)
    with Children() as kids:
        demo = kids.spawn(["demo", "--out", str(demo_out), "--mission", str(mission), "--duration", "150"],
                          subprocess.PIPE)
        held: dict[int, list[str]] = {}
        demo_done = False
        try:
            port = None
            t_end = time.monotonic() + 60
            while len(held) < 2 and time.monotonic() < t_end:  # the driver host and the station
                for pid in _children_of(demo.pid):
                    cmd = _cmdline(pid)
                    if pid not in held and "bridge" in cmd and cmd[cmd.index("bridge") + 1] in ("driver",
                                                                                                        "station"):
                        os.killpg(pid, signal.SIGSTOP)
                        held[pid] = cmd
                        port = int(cmd[cmd.index("--connect") + 1].rsplit(":", 1)[1])
                time.sleep(0.005)  # the poll step: catch them before they publish
            assert len(held) == 2 and port, held
            rec = start_recorder(kids, port, out)
            with open_session(make_config(mode="client", connect=[tcp(port)])) as probe_session:
                # the recorder's subscription has reached the demo's router: a probe on a key only it subscribes to
                wait_matching(probe_session.declare_publisher(M.key(f"probe{os.getpid()}", "teacher")))
            for pid in held:
                os.killpg(pid, signal.SIGCONT)
            line = wait_line(demo, r"^summary: ", timeout=300)
            assert demo.wait(timeout=60) == 0
            demo_done = True
            settled(out)  # the demo's router is gone: the recorder has written what it took
            text = finish(rec)
        finally:  # held children sit in sessions of their own: stopping the demo's group would miss them
            if not demo_done:
                for pid in held:
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(pid, signal.SIGKILL)
    live = json.loads(line[len("summary: "):])
    # the demo itself (make demo's job): the goal from no pairs, its figures, nothing left behind
    mapped = live["methods"].get("scm", 0) + live["methods"].get("barycentric", 0)  # by the learned pairs
    assert live["reached_goal"] and live["raw_pairs"] > 100 and mapped > 0
    assert live["max_dev_m"] < 1.0 and math.isfinite(live["mean_dev_m"])
    for fig in ("demo_trajectory.png", "demo_pairs.png"):
        assert (demo_out / fig).stat().st_size > 10_000, fig
    left = subprocess.run(["pgrep", "-f", f"--store {demo_out}"], capture_output=True, text=True)
    assert left.stdout.strip() == "", "the demo left a process behind"
    assert "stopped: signal" in text, text
    proc = subprocess.run([sys.executable, "-m", "bridge", "report", str(out), "--out", str(tmp_path / "rep"),
                           "--mission", str(mission)],  # the demo's station read it from its file: not recorded
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    got = json.loads(next(x for x in proc.stdout.splitlines() if x.startswith("summary: "))[len("summary: "):])
    print("live:    ", json.dumps(live))
    print("recorded:", json.dumps(got))
    print(next(x for x in text.splitlines() if x.startswith("recorded ")))
    print(next(x for x in proc.stdout.splitlines() if x.startswith("command to applied")))
    assert re.search(r"\(0 malformed, 0 noncanonical, 0 dropped", text), text
    for k in ("reached_goal", "methods", "refined_pairs", "raw_pairs", "missed_deadlines", "solve_ms_median"):
        assert got[k] == live[k], k
    assert abs(got["time_s"] - live["time_s"]) <= 0.1 + 1e-9
    for k in ("mean_dev_m", "max_dev_m"):
        assert abs(got[k] - live[k]) <= 2e-4, k
    entries, _ = read_recording([out])
    first_state = next(e for e in entries if e.topic == "scm/demo/state").message()
    assert first_state.seq == 0, "the recorder missed the start of the run"


def test_a_recording_of_nothing_is_not_a_success(tmp_path: Path) -> None:
    """Finding: with a certificate the access control denied, `record` recorded 0 messages and exited 0."""
    port = free_port()
    with open_session(make_config(mode="router", listen=[tcp(port)])):
        res = subprocess.run([sys.executable, "-m", "bridge", "record", "--all", "--out", str(tmp_path / "r.mcap"),
                              *client_args(port), "--duration", "1"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 1 and "nothing received" in res.stderr, res.stdout + res.stderr


def test_the_reports_figures_cover_the_driving_time_only() -> None:
    """Finding: on a real recording `time_s` ran from the first to the last recorded pose (68.2 s for a 34 s drive),
    the mean deviation included the time parked at the goal, and 401 stop commands after the goal counted as the
    run's commands. Parked before the start (2 s), drive 3 s to the goal, parked 5 s: the figures are the drive's."""
    from bridge.core.config import mission_from_spec
    from bridge.tools.demo import Monitor
    from bridge.tools.report import FeedSession

    mission = mission_from_spec(M.MissionSpec(name="line", path=[[0.0, 0.0], [0.6, 0.0]], goal_tolerance=0.05))
    feed = FeedSession()
    mon = Monitor(feed, "r1")
    k = M.Keys("r1")
    t, x = 100.0, 0.0
    for step in range(200):  # 10 s at 20 Hz: parked 2 s, 3 s at 0.2 m/s along the path, parked 5 s
        t += 0.05
        moving = 2.0 <= step * 0.05 < 5.0
        x = min(0.6, x + 0.01) if moving else x
        seq = step + 1
        feed.put(k.cmd, M.encode(M.Command(stamp=t, seq=seq, v=0.2 if moving else 0.0, omega=0.0,
                                           method="scm" if moving else "stop")))
        feed.put(k.applied, M.encode(M.Applied(stamp=t, seq=seq, v=0.2 if moving else 0.0, omega=0.0,
                                               reason="cmd" if moving else "stop", cmd_seq=seq)))
        feed.put(k.state, M.encode(M.LearnerState(stamp=t, seq=seq, x=x, y=0.3 if not moving and step > 100 else 0.0,
                                                  theta=0.0)))
    feed.put(M.status_key("r1", "station"), M.encode(M.Status(stamp=t, seq=1, node="station",
                                                              counters={"goal_reached": 1, "method_stop": 140})))
    s = mon.summary(mission)
    assert 2.6 <= s["time_s"] <= 3.1 and s["parked_before_s"] >= 1.9 and s["parked_after_s"] >= 4.9, s
    assert s["methods"] == {"scm": s["methods"]["scm"]} and 50 <= s["methods"]["scm"] <= 61, s["methods"]
    assert s["mean_dev_m"] < 0.01, s  # the pose parked 0.3 m off the path after the goal does not count
