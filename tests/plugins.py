"""A link package installed the way pip leaves one: its module and a ``*.dist-info`` directory with its
``entry_points.txt`` in a directory that goes on ``sys.path`` (or ``PYTHONPATH``). importlib.metadata reads exactly
that, so a link found through it is found as a ``pip install`` of the package would have it found."""

from __future__ import annotations

import shutil
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "deploy" / "examples" / "link-plugin"


def install_dist(site: Path, name: str, version: str, entry_points: dict[str, dict[str, str]],
                 modules: dict[str, str] | None = None) -> Path:
    """``name``'s dist-info in ``site`` with ``entry_points`` (group -> {entry name: value}) and ``modules``
    (file name -> source) beside it; returns ``site``."""
    site.mkdir(parents=True, exist_ok=True)
    dist = site / f"{name.replace('-', '_')}-{version}.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    lines = []
    for group, entries in entry_points.items():
        lines.append(f"[{group}]")
        lines += [f"{k} = {v}" for k, v in entries.items()]
        lines.append("")
    (dist / "entry_points.txt").write_text("\n".join(lines))
    for file, source in (modules or {}).items():
        (site / file).write_text(source)
    return site


def install_example(site: Path) -> Path:
    """deploy/examples/link-plugin as pip would install it: its modules and its pyproject.toml's entry points."""
    project = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]
    install_dist(site, project["name"], project["version"], project["entry-points"])
    for module in tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["tool"]["setuptools"]["py-modules"]:
        shutil.copy(EXAMPLE / f"{module}.py", site / f"{module}.py")
    return site
