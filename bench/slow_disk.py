"""A station on a slow disk, before and after its saves moved off the tick (a figure and one JSON object).

``python -m bench.slow_disk --base DIR``: for each source tree (``DIR``, a checkout of the base commit, and this
one) a real ``scmbridge station`` process runs under ``strace``, which delays every ``fsync`` it makes by
``--stall-ms`` (a disk that takes that long to make a write durable), with the pair store saved every tick
(``persist_every_s = 0.1``). This process is the Zenoh router: it takes every ``cmd`` the station publishes (one a
tick, a stop: nobody started the mission) and asks the station ``mission status`` every 0.25 s. The figure shows the
gaps between successive commands (by their stamps: the tick's own start) and the answers' round trips, for both
trees. Each station's robot gets a name of its own; everything on 127.0.0.1, every process stopped.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bridge.core import wire as M
from bridge.core.logsink import print_line
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from bridge.tools.mission import ask

ROOT = Path(__file__).resolve().parent.parent
ASK_TIMEOUT_S = 3.0  # how long each ``mission status`` waits for the station (asking again each second)


def one(tree: Path, label: str, seconds: float, stall_us: int, tmp: Path) -> dict:
    """One station of ``tree`` on the slow disk: its commands' stamps and receipt times, and the answers' times."""
    robot = f"disk{os.getpid()}{label}"
    work = tmp / label
    work.mkdir()
    (work / "station.toml").write_text("[station]\npersist_every_s = 0.1\n")
    env = dict(os.environ, PYTHONPATH=str(tree), SCMBRIDGE_STATE_DIR=str(work / "state"))
    port = free_port()
    cmds: list[tuple[float, float]] = []
    lock = threading.Lock()

    def on_cmd(sample) -> None:
        c = M.decode(sample.payload.to_bytes(), M.Command)
        with lock:
            cmds.append((c.stamp, time.monotonic()))

    with open_session(make_config(mode="router", listen=[tcp(port)])) as session, \
            open(work / "station.log", "w") as log:
        session.declare_subscriber(M.key(robot, "cmd"), on_cmd)
        proc = subprocess.Popen(
            ["/usr/bin/strace", "-f", "--seccomp-bpf", "-qq", "-o", "/dev/null", "-e", "trace=fsync",
             "-e", f"inject=fsync:delay_enter={stall_us}", sys.executable, "-m", "bridge", "station", "--robot", robot,
             "--mode", "client", "--connect", tcp(port), "--config", str(work / "station.toml"),
             "--store", str(work / "pairs.bin"), "--duration", str(seconds + 120)],
            stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tree, start_new_session=True)
        try:
            t_end = time.monotonic() + 90
            while time.monotonic() < t_end:  # the station's start: imports, SC kernels
                with lock:
                    if len(cmds) >= 5:
                        break
                time.sleep(0.05)
            else:
                raise RuntimeError(f"{label}: no command from the station ({work / 'station.log'})")
            t0 = time.monotonic()
            answers: list[tuple[float, float | None]] = []
            while time.monotonic() < t0 + seconds:
                t = time.monotonic()
                ans = ask(session, robot, M.MissionRequest(stamp=t, action="status", source="bench"),
                      timeout=ASK_TIMEOUT_S)
                answers.append((t - t0, time.monotonic() - t if ans is not None else None))
                time.sleep(max(0.0, t + 0.25 - time.monotonic()))
            t1 = time.monotonic()
        finally:
            os.killpg(proc.pid, signal.SIGKILL)  # its exit's saves would take seconds on this disk
            proc.wait(timeout=30)
    with lock:
        window = [(s, r) for s, r in cmds if t0 <= r <= t1]
    stamps = np.array([s for s, _ in window])
    gaps = np.diff(stamps)
    rt = np.array([a for _, a in answers if a is not None])
    return {"label": label, "commands": len(window), "window_s": round(t1 - t0, 2),
            "gap_ms": {"median": round(float(np.median(gaps)) * 1e3, 1), "p99": round(float(np.percentile(gaps, 99))
                                                                                     * 1e3, 1),
                       "max": round(float(gaps.max()) * 1e3, 1)},
            "answer_ms": {"median": round(float(np.median(rt)) * 1e3, 1), "max": round(float(rt.max()) * 1e3, 1),
                          "unanswered": sum(1 for _, a in answers if a is None)},
            "_t": (stamps[1:] - stamps[0]).tolist(), "_gaps": gaps.tolist(), "_answers": answers}


def figure(runs: list[dict], out: Path, stall_ms: float, load: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.2))
    colours = {"base": "tab:red", "after": "tab:blue"}
    for r in runs:
        c = colours.get(r["label"])
        a.plot(r["_t"], np.array(r["_gaps"]) * 1e3, ".-", color=c, ms=3, lw=0.8,
               label=f"{r['label']}: {r['commands']} cmds in {r['window_s']} s, gap median {r['gap_ms']['median']} ms,"
                     f" max {r['gap_ms']['max']} ms")
        t = [x for x, y in r["_answers"] if y is not None]
        y = [y * 1e3 for x, y in r["_answers"] if y is not None]
        b.plot(t, y, "o", color=c, ms=4,
               label=f"{r['label']}: median {r['answer_ms']['median']} ms, max {r['answer_ms']['max']} ms")
        lost = [x for x, y in r["_answers"] if y is None]
        if lost:
            b.plot(lost, [ASK_TIMEOUT_S * 1e3] * len(lost), "x", color=c, ms=7,
                   label=f"{r['label']}: {len(lost)} not answered within {ASK_TIMEOUT_S:g} s")
    a.axhline(100, color="grey", lw=0.6, ls="--")
    a.set(xlabel="s", ylabel="gap between commands (stamps), ms", yscale="log",
          title=f"station tick gaps, every fsync +{stall_ms:g} ms, store saved every tick")
    b.set(xlabel="s", ylabel="round trip, ms", yscale="log", ylim=(0.5, 3e5), title="mission status query answered in")
    a.legend(fontsize=7, loc="center right")
    b.legend(fontsize=7, loc="upper right")
    fig.suptitle(f"a slow disk: saves in the tick under the lock (base) vs. on a writer thread (after); {load}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="a checkout of the base commit")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--stall-ms", type=float, default=500.0)
    ap.add_argument("--out", default=str(ROOT / "docs" / "figures" / "station_slow_disk.png"))
    args = ap.parse_args()
    load = "load {:.2f} {:.2f} {:.2f} on {} cores (other work running)".format(*os.getloadavg(), os.cpu_count())
    with tempfile.TemporaryDirectory(prefix="scm-disk-") as tmp:
        runs = [one(Path(args.base), "base", args.seconds, int(args.stall_ms * 1e3), Path(tmp)),
                one(ROOT, "after", args.seconds, int(args.stall_ms * 1e3), Path(tmp))]
    figure(runs, Path(args.out), args.stall_ms, load)
    print_line(json.dumps({"stall_ms": args.stall_ms, "load_start": load, "runs": [
        {k: v for k, v in r.items() if not k.startswith("_")} for r in runs]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
