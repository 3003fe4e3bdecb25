"""Links as plugins: the ``scmbridge.links`` entry-point group registers a link from a package of its own.

A package installed beside scmbridge (a ``*.dist-info`` with its ``entry_points.txt`` on the path, as pip leaves one)
adds its link to :data:`drivers.LINKS` with no edit of scmbridge; the built-in links are the project's own entries
and are found without them in a source checkout; an entry that names an attribute, a bad name or a built-in link's
name with another module is refused, said in :data:`drivers.REFUSED`."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

import drivers
from tests.plugins import EXAMPLE, ROOT, install_dist, install_example


def test_the_projects_entry_points_are_the_builtin_links() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["entry-points"][drivers.ENTRY_POINT_GROUP] == drivers.BUILTIN_LINKS


def test_a_source_checkout_without_entry_points_still_has_the_builtin_links(tmp_path: Path) -> None:
    assert drivers.discover("scmbridge.no_such_group") == drivers.BUILTIN_LINKS
    assert set(drivers.BUILTIN_LINKS) <= set(drivers.LINKS)


def test_an_installed_package_registers_its_link(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    site = install_example(tmp_path / "site")
    monkeypatch.syspath_prepend(str(site))
    links = drivers.discover()
    assert links["loopback"] == "scmbridge_loopback_link"
    assert {k: links[k] for k in drivers.BUILTIN_LINKS} == drivers.BUILTIN_LINKS
    monkeypatch.setitem(drivers.LINKS, "loopback", links["loopback"])  # as LINKS is built when drivers is imported
    try:
        driver = drivers.open_driver("loopback", drivers.link_config("loopback")(gain=2.0))
        driver.open(10.0)
        driver.engage(10.0)
        assert driver.health(10.0).ok and driver.health(10.0).reason == "ok"
        driver.send(0.5, 0.0, 10.0)
        (pose,) = driver.poll(11.0)
        assert (pose.x, pose.v) == (pytest.approx(1.0), pytest.approx(1.0))  # gain 2 x 0.5 m/s for 1 s
    finally:
        sys.modules.pop("scmbridge_loopback_link", None)


def test_drivers_imported_in_a_fresh_interpreter_offers_the_installed_link(tmp_path: Path) -> None:
    site = install_example(tmp_path / "site")
    code = ("import drivers\nfrom bridge.nodes.driver_config import load_driver\n"
            "print(drivers.link_names())\nprint(type(load_driver(None).link.loopback).__name__)\n")
    env = {"PYTHONPATH": f"{ROOT}:{site}", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    names, config = out.stdout.split("\n")[:2]
    assert "loopback" in names and "can" in names and config == "LoopbackLinkConfig"


@pytest.mark.parametrize(("name", "value", "why"), [
    ("serial", "pkg.mod:DRIVER", "must be a module"),
    ("Serial-Bot", "pkg.mod", "lowercase letters"),
    ("can", "evil_can", "the can link is drivers.can"),
])
def test_a_bad_entry_is_refused_and_said(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, value: str,
                                         why: str) -> None:
    site = install_dist(tmp_path / "site", "bad-link", "1.0", {drivers.ENTRY_POINT_GROUP: {name: value}})
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr(drivers, "REFUSED", [])
    links = drivers.discover()
    assert links == drivers.BUILTIN_LINKS
    assert [n for n, _ in drivers.REFUSED] == [name] and why in drivers.REFUSED[0][1]


def test_the_example_is_a_complete_package() -> None:
    project = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())
    assert project["project"]["entry-points"][drivers.ENTRY_POINT_GROUP] == {"loopback": "scmbridge_loopback_link"}
    assert "scmbridge" in project["project"]["dependencies"]
