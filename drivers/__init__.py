"""Vehicle links behind one small :class:`drivers.base.Driver` protocol, picked by name like python-can interfaces.

Each link is a plugin: one module that defines its configuration (``CONFIG``, a :class:`bridge.core.config.Cfg`
struct: the ``[link.<name>]`` section of a driver host's file), its driver (``DRIVER``, built from that
configuration, doing no I/O until ``open``) and ``EMULATED`` (whether ``scmbridge learner`` emulates the device),
registered by one line in :data:`LINKS`. The driver host's configuration, every ``--link`` option and
:func:`open_driver` read this table, so adding a link is that module plus that line (docs/ARCHITECTURE.md, "Adding a
link"). A link module imports its vehicle's library (python-can, pymavlink) only when a driver is built, so reading
the configuration loads none of them and a machine without one can still run the other links.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

from drivers.base import Driver, DriverError

#: link name -> the module that defines its ``CONFIG``, ``DRIVER`` and ``EMULATED``
LINKS: dict[str, str] = {
    "can": "drivers.can",
    "mavlink": "drivers.mavlink",
    "udp": "drivers.udp",
}


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


__all__ = ["LINKS", "Driver", "DriverError", "link_config", "link_module", "link_names", "open_driver"]
