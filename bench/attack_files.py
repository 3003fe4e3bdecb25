"""``scmbridge bench attack`` rows on what the station and the hosts read from disk and from the lab's files
(docs/SECURITY.md's attack table): a mission file rewritten while the station was down, files that are FIFOs or
devices, a ``--zenoh-config`` that says little, crafted pair stores and the files ``config check`` passes, and
``estop --all`` on a router the robot is not on.

Real components as in bench/attack.py: the station's own restore and store load on a real state directory, the
real CLIs as child processes (each bounded in time and killed past it), real Zenoh sessions and routers on free
loopback ports. Each row returns ``{"reached_vehicle": ..., "learned": ..., "ok": bool, ...}``.
"""

from __future__ import annotations

import contextlib
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from bench.attack_rigs import Result, _Station, _ZenohHost, until

#: how long a child CLI may take before it counts as hung (a bounded read fails in well under a second)
HUNG_S = 15.0


@contextlib.contextmanager
def _env(**values: str) -> Iterator[None]:
    """``os.environ`` with ``values`` set for the block (this process's station and tags read them)."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def mission_file_rewritten(short: bool) -> Result:
    """The station saved its paused mission and stopped; its mission file is rewritten (the same format, a path
    leading behind the robot; without the station's key the tag, if any, is left as it was); the station starts
    again (bridge/nodes/station.py ``restore_control``, as ``scmbridge station`` does) and a person resumes. The
    rewritten path must never be the mission a resume drives, and the mission's reason must say the file was
    refused. before (the hostile test, CHANGELOG.md 2026-12-06): the rewritten path was driven after ``mission
    resume``, x 1.11 -> -0.49 m, and status never said the file had changed."""
    import msgspec

    from bridge.core import wire as M
    from bridge.core.config import StationConfig, load_mission_spec
    from bridge.nodes.mission_control import Fitness, MissionControl, Saved
    from bridge.nodes.station import Station, control_file, restore_control

    robot = "atkmission"
    with tempfile.TemporaryDirectory() as d, _env(SCMBRIDGE_STATE_DIR=d, SCMBRIDGE_RECORD_DIR=f"{d}/records"):
        spec = load_mission_spec()
        control = MissionControl(robot, spec, "paused", "paused by a person")
        station = Station(StationConfig(), robot, 10.0, Path(d) / "pairs.bin", control.mission, control,
                          control_file(robot))
        station.persist()
        station.save_control()
        path = control_file(robot)
        blob = path.read_bytes()
        try:  # an untagged file (an older version's): the payload is all of it
            saved, head = msgspec.msgpack.decode(blob, type=Saved), b""
        except msgspec.DecodeError:  # a tagged one: magic + 16-byte tag, then the payload
            saved, head = msgspec.msgpack.decode(blob[18:], type=Saved), blob[:18]
        behind = [[-float(x), float(y)] for x, y in reversed(saved.spec.path)]
        forged = msgspec.structs.replace(saved, spec=msgspec.structs.replace(saved.spec, name="rewritten",
                                                                             path=behind))
        path.write_bytes(head + msgspec.msgpack.encode(forged))
        restored = restore_control(robot, None, None)
        said = restored.reason
        ans = restored.request(M.MissionRequest(stamp=1.0, action="resume", source="operator"), Fitness(""), 0.0)
        drives_forged = ans.phase == "running" and restored.spec.name == "rewritten"
        kept_aside = any(p.name.startswith(path.name) and p != path for p in Path(d).iterdir())
    return {"reached_vehicle": {"resumed_phase": ans.phase, "drives_rewritten_path": drives_forged},
            "learned": None, "restored_mission": restored.spec.name, "said": said[:160], "kept_aside": kept_aside,
            "ok": not drives_forged and restored.spec.name != "rewritten" and "refused" in said}


def _limited() -> None:
    """A child's address space capped at 1 GiB: an unbounded read fails there, not in the shared machine."""
    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))


def _child(args: list[str], env: dict[str, str]) -> dict:
    """``python -m bridge ARGS`` (or ``python -c``) bounded by :data:`HUNG_S`: its exit, time and last line."""
    t0 = time.monotonic()
    full = {**os.environ, **env,
            "PYTHONPATH": os.pathsep.join(p for p in (os.environ.get("PYTHONPATH"), *sys.path) if p)}
    try:
        p = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=HUNG_S, env=full,
                           preexec_fn=_limited)
    except subprocess.TimeoutExpired:
        return {"exit": None, "hung": True, "seconds": HUNG_S, "said": ""}
    lines = (p.stdout + p.stderr).strip().splitlines()
    return {"exit": p.returncode, "hung": False, "seconds": round(time.monotonic() - t0, 2),
            "said": (lines[-1] if lines else "")[:160],
            "crashed": "Traceback" in p.stderr or "MemoryError" in p.stderr}


def fifo_and_device_reads(short: bool) -> Result:
    """Where a key, the install marker, a configuration, the pair store or a ``--zenoh-config`` is read, a FIFO
    (nobody writes it) or a key symlinked to ``/dev/zero``; each reader is the real command as a child process
    (``config check``, ``pairs show --store``, ``status --zenoh-config``, ``doctor``'s state check). Each must end
    within seconds, refusing the file in a line, without a traceback. before (the hostile test, CHANGELOG.md
    2026-12-06): each FIFO hung the host, ``doctor``, the station and the CLIs; ``/dev/zero`` was read until
    MemoryError."""
    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        fifo = root / "fifo"
        os.mkfifo(fifo)
        zero = root / "zero.key"
        zero.symlink_to("/dev/zero")
        for name, key in (("key_fifo", fifo), ("key_dev_zero", zero)):
            drv = root / f"{name}.toml"
            drv.write_text(f'robot = "r1"\n[link.udp]\nkey_file = "{key}"\n')
            out[name] = _child(["-m", "bridge", "config", "check", str(drv), "--kind", "driver"], {})
        out["config_fifo"] = _child(["-m", "bridge", "config", "check", str(fifo), "--kind", "driver"], {})
        out["store_fifo"] = _child(["-m", "bridge", "pairs", "show", "--store", str(fifo)], {})
        out["zenoh_config_fifo"] = _child(["-m", "bridge", "status", "--all", "--zenoh-config", str(fifo),
                                           "--timeout", "1"], {})
        state = root / "state"
        state.mkdir(mode=0o700)
        os.mkfifo(state / "estop-r1.installed")
        out["marker_fifo"] = _child(["-c", "from bridge.tools.doctor import check_state\n"
                                           "for c in check_state('r1'): print(c)"],
                                    {"SCMBRIDGE_STATE_DIR": str(state), "SCMBRIDGE_RECORD_DIR": str(root / "rec")})
    hung = [n for n, r in out.items() if r["hung"]]
    crashed = [n for n, r in out.items() if r.get("crashed")]
    # the marker is only looked at (doctor exits 0 and names it); every other reader refuses the file (exit != 0)
    taken = [n for n, r in out.items() if n != "marker_fifo" and r["exit"] == 0]
    return {"reached_vehicle": None, "learned": None, "readers": out, "hung": hung, "crashed": crashed,
            "ok": not hung and not crashed and not taken}


def zenoh_config_says_little(short: bool) -> Result:
    """A lab's ``--zenoh-config`` naming only where to connect (no mode, listen or scouting), as the driver host and
    the station load it (bridge/nodes/zsession.py ``make_config``, the mode the commands ask for): the session
    opened from it must be a client (or a peer listening on loopback only) with multicast scouting off. A value
    the configuration leaves unset reads None: Zenoh's own default then applies. before (the hostile test,
    CHANGELOG.md 2026-12-06; this row on the code before: mode, scouting and listen all unset): a peer listening on
    every interface, multicast scouting on."""
    import json

    from bridge.nodes.zsession import free_port, make_config, open_session, tcp

    out = {}
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "lab.json5"
        port = free_port()
        f.write_text(f'{{ connect: {{ endpoints: ["{tcp(port)}"] }} }}\n')
        with open_session(make_config(mode="router", listen=[tcp(port)])):
            for asked in ("peer", "client"):
                conf = make_config(mode=asked, config_file=f)
                mode = json.loads(conf.get_json("mode"))
                multicast = json.loads(conf.get_json("scouting/multicast/enabled"))
                listen = json.loads(conf.get_json("listen/endpoints"))
                if isinstance(listen, dict):  # zenoh's per-mode form
                    listen = listen.get(mode, [])
                with open_session(conf) as s:  # the session a host would run on (it opens and connects)
                    opened = s is not None
                out[asked] = {"mode": mode, "multicast_scouting": multicast, "listen": listen, "opened": opened}
    wide = [a for a, r in out.items() if r["mode"] != "client"
            and any(not ("127.0.0.1" in e or "[::1]" in e or "localhost" in e) for e in (r["listen"] or ["all"]))]
    return {"reached_vehicle": None, "learned": None, "sessions": out,
            "ok": not wide and not any(r["multicast_scouting"] for r in out.values())}


def _store_file(path: Path, store, tagged: bool) -> None:
    """``store`` saved at ``path`` as the station saves it (``tagged``) or as someone without its key does; either
    way the station has run there before (its key exists, made by an earlier start, not this process)."""
    from bridge.core.auth import make_key
    from bridge.core.paths import save_atomic
    from bridge.nodes.station_tags import FileTags, key_file

    make_key(key_file(path))
    data = store.to_bytes()
    save_atomic(path, FileTags().seal("store", path, data) if tagged else data)


def crafted_stores_and_checks(short: bool) -> Result:
    """Pair stores loaded as the station loads them (bridge/nodes/station_core.py ``load_store`` with the station's
    tags): one of mirrored yaw-rate pairs (each plausible, written by someone else), one of the station's own
    saved on another grid; and ``config check`` (bridge/tools/config_cmd.py ``check``) on a driver file naming a
    missing, a short, a world-readable and an all-zero key, and a station file naming a missing mission. Each
    store must be quarantined with its reason and each file refused. before (the hostile test, CHANGELOG.md
    2026-12-06): the mirrored store loaded (the obstacle clearance 0.29 -> 0.16 m), the other grid's silently;
    ``config check`` passed every file, and the all-zero UDP key was taken."""
    from bridge.core.config import ConfigError
    from bridge.core.errors import UsageError
    from bridge.nodes.station_core import load_store
    from bridge.nodes.station_tags import FileTags
    from bridge.tools.config_cmd import check
    from transfer.domain import Bounds
    from transfer.paper import MPC_LEARNER_V, MPC_LEARNER_W, MPC_TEACHER_V, MPC_TEACHER_W
    from transfer.store import PairStore

    lb, tb = Bounds(MPC_LEARNER_V, MPC_LEARNER_W), Bounds(MPC_TEACHER_V, MPC_TEACHER_W)
    stores, checks = {}, {}
    with tempfile.TemporaryDirectory() as d, _env(SCMBRIDGE_RECORD_DIR=f"{d}/records"):
        root = Path(d)
        mirrored = PairStore(lb, tb, (11, 11), k_min=1)
        for v, w in ((0.2, 0.4), (0.3, -0.6), (0.1, 0.8)):
            mirrored.add([v, w], [0.5 * v, -0.5 * w])
        other = PairStore(lb, tb, (5, 5), k_min=1)
        other.add([0.2, 0.1], [0.1, 0.05])
        for name, store, tagged in (("mirrored_untagged", mirrored, False), ("other_grid", other, True)):
            f = root / name / "pairs.bin"
            f.parent.mkdir()
            _store_file(f, store, tagged)
            got, how = load_store(f, lb, tb, (11, 11), 1, FileTags())
            stores[name] = {"served_pairs": len(got.refined()), "load": how,
                            "quarantined": not f.exists() and any(f.parent.iterdir())}
        files = {"missing_key": root / "nokey", "short_key": root / "short.key",
                 "world_readable_key": root / "open.key", "all_zero_key": root / "zero.key"}
        for name, text, mode in (("short_key", os.urandom(8).hex(), 0o600),
                                 ("world_readable_key", os.urandom(32).hex(), 0o644),
                                 ("all_zero_key", bytes(32).hex(), 0o600)):
            files[name].write_text(text + "\n")
            files[name].chmod(mode)
        for name, k in files.items():
            drv = root / f"{name}.toml"
            drv.write_text(f'robot = "r1"\n[link.udp]\nkey_file = "{k}"\n')
            checks[name] = _refused(check, str(drv), "driver", (ConfigError, UsageError, OSError, ValueError))
        st = root / "station.toml"
        st.write_text(f'robot = "r1"\n[station]\nmission = "{root / "nomission.toml"}"\n')
        checks["missing_mission"] = _refused(check, str(st), "station", (ConfigError, UsageError, OSError, ValueError))
    return {"reached_vehicle": None, "learned": stores, "config_check": checks,
            "ok": all(s["served_pairs"] == 0 and s["quarantined"] for s in stores.values())
            and all(c["refused"] for c in checks.values())}


def _refused(check: Callable[[str, str], str], path: str, kind: str, errors: tuple) -> dict:
    try:
        return {"refused": False, "said": check(path, kind)[:160]}
    except errors as exc:
        return {"refused": True, "said": str(exc)[:160]}


def estop_all_other_router(short: bool) -> Result:
    """Two routers not connected, a real robot's host on each; a station drives the first. The person's ``scmbridge
    estop --all --fleet`` (the lab's fleet list naming both) runs on the second router: it stops the robot there,
    but the first keeps driving (no stop can cross), so the CLI must name the first as never confirmed and exit
    non-zero. before (the hostile test, CHANGELOG.md 2026-12-06): exit 0 while the robot on the other router kept
    driving."""
    from bridge.nodes.zsession import tcp

    with _ZenohHost() as rig, _ZenohHost() as near, _Station(rig, 0.3), tempfile.TemporaryDirectory() as d:
        driving = _release_and_engage(rig)
        fleet = Path(d) / "fleet.toml"
        fleet.write_text(f'[fleet]\nrobots = ["{rig.robot}", "{near.robot}"]\n')
        cli = _child(["-m", "bridge", "estop", "--all", "--fleet", str(fleet), "--timeout", "2", "--mode", "client",
                      "--connect", tcp(near.port)], {})
        t1 = time.monotonic()
        still = until(lambda: any(a.v != 0.0 for a in rig.since(t1)), 2.0)
        near_stopped = near.host.gate.estopped
    return {"reached_vehicle": {"other_router_still_driving": still}, "learned": None, "driving_before": driving,
            "same_router_robot_latched": near_stopped, "cli": cli,
            "ok": driving and near_stopped and cli["exit"] not in (0, None) and rig.robot in cli["said"]
            and near.robot not in cli["said"]}


def _release_and_engage(rig: _ZenohHost) -> bool:
    """The person releases the rig's robot (a first start is latched) and engages it: whether it then drives."""
    from bridge.core import wire as M
    from bridge.core.acts import address_of, stamped
    from bridge.tools.estop import latch_states

    states = latch_states(rig.attacker, rig.keys.estop, 2.0)
    to = address_of(next(iter(states.values()))) if states else None
    if rig.host.gate.estopped:
        rig.attacker.put(rig.keys.estop, M.encode(stamped(M.Estop(stamp=1.0, engaged=False, source="operator"), to)))
        until(lambda: not rig.host.gate.estopped, 3.0)
    ans = rig.engage(M.encode(stamped(M.EngageRequest(stamp=1.0, source="operator"), to)))
    t0 = time.monotonic()
    return bool(ans and ans.engaged) and until(lambda: any(a.v != 0.0 for a in rig.since(t0)), 3.0)


FILE_ATTACKS: dict[str, Callable[[bool], Result]] = {
    f.__name__: f for f in (mission_file_rewritten, fifo_and_device_reads, zenoh_config_says_little,
                            crafted_stores_and_checks, estop_all_other_router)}

__all__ = ["FILE_ATTACKS"]
