"""Which files of each pin of the robot lock install on a robot computer's platform (run by ``make lock``).

The robot lock (``requirements/robot.txt``) is resolved on Linux x86_64, but pip-compile lists the hash of every
file the index has for each pinned version, so the same lock installs on a Linux aarch64 robot (Raspberry Pi,
Jetson) when each pin has a file for it: a pure-Python wheel, a CPython 3.11 (or abi3) manylinux aarch64 wheel, or
an sdist. This script asks the index (PEP 691 JSON) once, when the lock is made, and writes
``requirements/robot-files.json``: for each pin, its files with their sha256; ``tests/repo/test_install.py`` then
checks, with no network, that every pin has an aarch64-installable file whose hash the lock carries.

    python requirements/platforms.py [requirements/robot.txt] [--index https://pypi.org/simple]
"""

from __future__ import annotations

import json
import re
import sys
import urllib.request
from pathlib import Path

HERE = Path(__file__).resolve().parent


def pins(lock: Path) -> dict[str, str]:
    """``{name: version}`` of every ``name==version`` line of a pip-compile lock."""
    out = {}
    for line in lock.read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9_.\-]+)==([^\s;\\]+)", line)
        if m:
            out[m.group(1).lower()] = m.group(2)
    return out


def files(index: str, name: str, version: str) -> dict[str, str]:
    """``{filename: sha256}`` of the index's files of ``name`` ``version``."""
    req = urllib.request.Request(f"{index.rstrip('/')}/{name}/",
                                 headers={"Accept": "application/vnd.pypi.simple.v1+json"})
    with urllib.request.urlopen(req, timeout=60) as r:
        data = json.load(r)
    norm = re.sub(r"[-_.]+", "_", name).lower()
    out = {}
    for f in data["files"]:
        fn = f["filename"]
        stem = re.sub(r"[-_.]+", "_", fn.lower())
        if stem.startswith(f"{norm}_{re.sub(r'[-_.]+', '_', version.lower())}_") or \
                stem.startswith(f"{norm}_{re.sub(r'[-_.]+', '_', version.lower())}_tar") or \
                fn.lower().startswith(f"{name.lower()}-{version.lower()}."):
            out[fn] = f["hashes"].get("sha256", "")
    return out


def main(argv: list[str]) -> int:
    lock = Path(argv[1]) if len(argv) > 1 and not argv[1].startswith("--") else HERE / "robot.txt"
    index = argv[argv.index("--index") + 1] if "--index" in argv else "https://pypi.org/simple"
    result = {f"{n}=={v}": files(index, n, v) for n, v in sorted(pins(lock).items())}
    (HERE / "robot-files.json").write_text(json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"wrote {HERE / 'robot-files.json'}: {len(result)} pins")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv))
