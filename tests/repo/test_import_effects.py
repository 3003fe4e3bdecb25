"""Importing the project changes nothing: every module of bridge/, drivers/, transfer/ and sim_learner/ imported in
a fresh interpreter leaves the environment as it was (no ``MAVLINK20``; pymavlink is imported first, as its own
import sets ``MAVLINK_DIALECT``), pymavlink's process-wide dialect as pymavlink chose it, matplotlib's backend
unchosen, and reads no file under /proc from the project's own code. What a module needs of that kind happens when it
is used: :func:`sim_learner.mavlink_dialect.mavutil_v2` before a pymavlink connection,
:func:`sim_learner.plots.headless` before a figure, :func:`bridge.core.clock.machine` when a status is made. A
process that imports a helper for its constants keeps its own settings."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("bridge", "drivers", "transfer", "sim_learner")

PROBE = r'''
import importlib, json, os, sys, sysconfig
from pathlib import Path

root = Path(sys.argv[1]).resolve()
ours = tuple(str(root / p) + os.sep for p in sys.argv[2].split(","))
stdlib = tuple(sysconfig.get_paths()[k] + os.sep for k in ("stdlib", "platstdlib"))
proc_reads = []


def hook(event, args):
    if event != "open" or not args or not isinstance(args[0], (str, bytes)):
        return
    path = os.fsdecode(args[0])
    if not path.startswith("/proc/"):
        return
    f = sys._getframe(1)
    while f is not None and f.f_code.co_filename.startswith(stdlib):  # pathlib, io: whoever called them
        f = f.f_back
    if f is not None and f.f_code.co_filename.startswith(ours):
        proc_reads.append(f"{path} from {f.f_code.co_filename}:{f.f_lineno}")


import pymavlink.mavutil  # its own import sets MAVLINK_DIALECT if unset: pymavlink's doing, not the project's

before = dict(os.environ)
sys.addaudithook(hook)
modules = []
for pkg in sys.argv[2].split(","):
    for p in sorted((root / pkg).rglob("*.py")):
        rel = p.relative_to(root).with_suffix("")
        if rel.name == "__main__" or "fuzz" in rel.parts:
            continue
        name = ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)
        importlib.import_module(name)
        modules.append(name)
after = dict(os.environ)
out = {"modules": len(modules), "proc_reads": proc_reads,
       "env_changed": sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))}
if "matplotlib" in sys.modules:
    import matplotlib
    out["mpl_backend_chosen"] = matplotlib.rcParams._get_backend_or_none()
out["mavutil_wire"] = pymavlink.mavutil.mavlink.WIRE_PROTOCOL_VERSION
print(json.dumps(out))
'''


def test_importing_every_module_changes_nothing_and_reads_no_proc() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK20", "MAVLINK_DIALECT", "MPLBACKEND")}
    env["PYTHONPATH"] = str(ROOT)
    env["SCMBRIDGE_NO_COMPILE"] = "1"
    res = subprocess.run([sys.executable, "-c", PROBE, str(ROOT), ",".join(PACKAGES)], capture_output=True, text=True,
                         timeout=300, env=env, cwd=ROOT)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["modules"] > 100, out  # every module was imported, not a handful
    assert out["env_changed"] == [], out
    assert out["proc_reads"] == [], out
    assert out.get("mpl_backend_chosen") is None, out  # matplotlib.use() at import would have chosen one
    assert out["mavutil_wire"] == "1.0", out  # pymavlink's own default: nothing chose MAVLink 2 by being imported
