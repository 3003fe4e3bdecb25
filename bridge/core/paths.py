"""Where a node keeps what must survive a restart (state: the pair store, the estop latch, the mission) and what it
may rebuild (cache: compiled code), and how it writes a file so a crash or a full disk never leaves it torn.

State: ``$SCMBRIDGE_STATE_DIR``, else systemd's ``$STATE_DIRECTORY`` (``StateDirectory=``), else
``$XDG_STATE_HOME/scmbridge`` (``~/.local/state/scmbridge``). Cache: ``$SCMBRIDGE_CACHE_DIR``, else
``$CACHE_DIRECTORY`` (``CacheDirectory=``), else ``$XDG_CACHE_HOME/scmbridge`` (``~/.cache/scmbridge``). Never the
working directory: two services started in one directory must not share a file by accident.
"""

from __future__ import annotations

import os
from pathlib import Path


def _first(value: str) -> str:
    """systemd passes several directories colon-separated; the first is this unit's own."""
    return value.split(":")[0]


def state_dir() -> Path:
    """The directory for files that must survive a restart (see the module docstring)."""
    for var in ("SCMBRIDGE_STATE_DIR", "STATE_DIRECTORY"):
        if os.environ.get(var):
            return Path(_first(os.environ[var]))
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "scmbridge"


def cache_dir() -> Path:
    """The directory for files that can be rebuilt (see the module docstring)."""
    for var in ("SCMBRIDGE_CACHE_DIR", "CACHE_DIRECTORY"):
        if os.environ.get(var):
            return Path(_first(os.environ[var]))
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "scmbridge"


def save_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` so that ``path`` holds either the old or the new content, never a torn file (write, fsync,
    rename, fsync the directory); on failure (a full disk) the temporary file is removed and the error raised."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    dfd = os.open(path.parent, os.O_DIRECTORY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
