"""Vehicle links behind one small :class:`drivers.base.Driver` protocol, picked by name like python-can interfaces.

Each link is a plugin: one module that defines its configuration (``CONFIG``, a :class:`bridge.core.config.Cfg`
struct: the ``[link.<name>]`` section of a driver host's file), its driver (``DRIVER``, built from that
configuration, doing no I/O until ``open``) and ``EMULATED`` (whether ``scmbridge learner`` emulates the device).
Links are registered in the ``scmbridge.links`` entry-point group (:data:`ENTRY_POINT_GROUP`), as python-can
registers its interfaces in ``can.interface``: an entry's name is the link's name and its value the module's
(``serialbot = "scmbridge_serialbot"``), so a lab's own link installs as a package of its own and needs no edit
here (docs/ARCHITECTURE.md, "Adding a link"; deploy/examples/link-plugin/ is one). The three built-in links are
registered in the same group by this project's pyproject.toml, and :data:`BUILTIN_LINKS` finds them in a source
checkout that was never installed. The driver host's configuration, every ``--link`` option and
:func:`open_driver` read :data:`LINKS`, built from both when this package is first imported (an entry point is read,
its module is not imported). A link module imports its vehicle's library (python-can, pymavlink) only when a driver
is built, so reading the configuration loads none of them and a machine without one can still run the other links.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import re
from types import ModuleType
from typing import Any

from drivers.base import Driver, DriverError

#: the entry-point group a link registers in: name = the link's name, value = its module (no attribute)
ENTRY_POINT_GROUP = "scmbridge.links"

#: the links this project ships (also its entry points in pyproject.toml): a source checkout that was never installed
#: has no entry points of its own, and an installed one must not lose a built-in link to a stale or missing one
BUILTIN_LINKS: dict[str, str] = {
    "can": "drivers.can",
    "mavlink": "drivers.mavlink",
    "udp": "drivers.udp",
}

#: why an entry point of the group was not registered (its name, what was wrong), for the log and ``doctor``
REFUSED: list[tuple[str, str]] = []


def discover(group: str = ENTRY_POINT_GROUP) -> dict[str, str]:
    """Link name -> module name: the built-in links, then every entry point of ``group`` whose value names a module.
    An entry that names an attribute (``pkg.mod:obj``), a name that is not a link name, or one that would replace a
    built-in link with another module is refused (kept in :data:`REFUSED`): a package must not take ``can`` over."""
    links = dict(BUILTIN_LINKS)
    for ep in importlib.metadata.entry_points(group=group):
        name, module = ep.name, ep.value.strip()
        problem = ""
        if ":" in module or not module:
            problem = f"its value {module!r} must be a module (pkg.module), not an attribute"
        elif not _LINK_NAME.fullmatch(name):
            problem = "a link's name is lowercase letters, digits and _ (it is a TOML table's name)"
        elif links.get(name, module) != module:
            problem = f"the {name} link is {links[name]}; {module} may not replace it"
        if problem:
            REFUSED.append((name, problem))
            continue
        links[name] = module
    return links


_LINK_NAME = re.compile(r"[a-z][a-z0-9_]*")

#: link name -> the module that defines its ``CONFIG``, ``DRIVER`` and ``EMULATED``
LINKS: dict[str, str] = discover()


def link_names() -> list[str]:
    """The registered links, sorted: what every ``--link`` option offers."""
    return sorted(LINKS)


def link_module(name: str) -> ModuleType:
    """The module of the link registered under ``name``; ValueError for a name not registered, DriverError for a
    registered module this build does not have."""
    try:
        module_name = LINKS[name]
    except KeyError:
        raise ValueError(f"unknown link {name!r}; known links: {', '.join(link_names())}") from None
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name != module_name:
            raise
        raise DriverError(f"the {name} link is not in this build yet (no module {module_name})") from None


def link_config(name: str) -> type:
    """The configuration struct of the link ``name`` (its ``[link.<name>]`` section)."""
    return link_module(name).CONFIG


def open_driver(name: str, config: Any = None) -> Driver:
    """Build (not yet open) the driver registered under ``name`` with its link configuration (``None``: defaults)."""
    module = link_module(name)
    return module.DRIVER(module.CONFIG() if config is None else config)


__all__ = ["BUILTIN_LINKS", "ENTRY_POINT_GROUP", "LINKS", "REFUSED", "Driver", "DriverError", "discover", "link_config",
           "link_module", "link_names", "open_driver"]
