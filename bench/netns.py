"""Station hosts of their own on one machine: Linux network namespaces joined to this one by a veth pair each.

A lab that outgrows one base station runs several station hosts behind one Zenoh router (docs/FLEET.md, "several
base stations"; deploy/README.md). To exercise that layout on one machine without sharing a network stack,
:func:`hosts` makes ``n`` network namespaces, each with its loopback and one end of a veth pair addressed
``10.231.S.2/30`` (the other end in this namespace, ``10.231.S.1``): a process started in one
(:attr:`Host.prefix`, ``ip netns exec NAME``) reaches this namespace only at ``Host.router_addr`` over that link,
never another host's addresses or this namespace's 127.0.0.1. The links are private to the machine (no route
leaves it). Everything is removed when the block ends (deleting a namespace deletes its veth pair).

Making namespaces needs root (CAP_SYS_ADMIN and CAP_NET_ADMIN) and iproute2's ``ip``: :func:`unavailable` says why
they cannot be made here, so a test can skip with that reason.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass


@dataclass(frozen=True)
class Host:
    """One station host: its namespace's name, the command prefix that runs a program in it, its own address and
    the address of this namespace (where the router listens for it)."""

    name: str
    addr: str
    router_addr: str

    @property
    def prefix(self) -> tuple[str, ...]:
        return ("ip", "netns", "exec", self.name)


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=10)


def unavailable() -> str:
    """Why network namespaces cannot be made here ("" when they can): not root, no ``ip``, or the kernel refused."""
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2) on this machine"
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_SYS_ADMIN, CAP_NET_ADMIN); this process is not root"
    name = f"scmprobe{os.getpid()}"
    try:
        _ip("netns", "add", name)
    except (subprocess.SubprocessError, OSError) as exc:
        err = getattr(exc, "stderr", "") or str(exc)
        return f"`ip netns add` refused: {err.strip()[:200]}"
    try:
        _ip("netns", "del", name)
    except (subprocess.SubprocessError, OSError):
        pass
    return ""


@contextmanager
def hosts(n: int, tag: str | None = None) -> Iterator[list[Host]]:
    """``n`` namespaces joined to this one (module docstring), removed at the end; ``tag``: a short unique part of
    their names (default: this process's id)."""
    tag = tag or str(os.getpid())
    base = (os.getpid() % 60) * 4  # a /30 per host; two runs at once on one machine rarely share a pid mod 60
    made: list[str] = []
    out: list[Host] = []
    try:
        for k in range(n):
            name, outer, inner = f"scm{tag}h{k}", f"vs{tag}r{k}"[:15], f"vs{tag}n{k}"[:15]
            sub = base + k
            router_addr, addr = f"10.231.{sub}.1", f"10.231.{sub}.2"
            _ip("netns", "add", name)
            made.append(name)
            _ip("link", "add", outer, "type", "veth", "peer", "name", inner)
            _ip("link", "set", inner, "netns", name)
            _ip("addr", "add", f"{router_addr}/30", "dev", outer)
            _ip("link", "set", outer, "up")
            for cmd in (("addr", "add", f"{addr}/30", "dev", inner), ("link", "set", inner, "up"),
                        ("link", "set", "lo", "up")):
                _ip("netns", "exec", name, "ip", *cmd)
            out.append(Host(name, addr, router_addr))
        yield out
    finally:
        for name in made:
            try:
                _ip("netns", "del", name)  # its veth pair goes with it
            except (subprocess.SubprocessError, OSError):
                pass


def same_namespace(pid: int) -> bool:
    """Whether process ``pid`` shares this process's network namespace."""
    return os.readlink(f"/proc/{pid}/ns/net") == os.readlink("/proc/self/ns/net")


__all__ = ["Host", "hosts", "same_namespace", "unavailable"]
