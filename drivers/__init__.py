"""Vehicle links behind one small :class:`drivers.base.Driver` protocol, picked by name like python-can interfaces.

``open_driver("can", config)`` imports only the module of the link asked for, so a station machine without
pymavlink on its path (say) can still run the CAN link.
"""

from __future__ import annotations

import importlib
from typing import Any

from drivers.base import Driver, DriverError

#: link name -> "module:Class"; each class takes its link's typed configuration (``bridge.core.config``) as its only
#: argument.
LINKS: dict[str, str] = {
    "can": "drivers.can:CanDriver",
    "mavlink": "drivers.mavlink:MavlinkDriver",
    "udp": "drivers.udp:UdpDriver",
}


def open_driver(name: str, config: Any = None) -> Driver:
    """Build (not yet open) the driver registered under ``name`` with its link configuration (``None``: defaults)."""
    try:
        target = LINKS[name]
    except KeyError:
        raise ValueError(f"unknown link {name!r}; known links: {', '.join(sorted(LINKS))}") from None
    module_name, cls_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name != module_name:
            raise
        raise DriverError(f"the {name} link is not in this build yet (no module {module_name})") from None
    cls = getattr(module, cls_name)
    if config is None:
        from bridge.core.config import LINK_CONFIGS

        config = LINK_CONFIGS[name]()
    return cls(config)


__all__ = ["Driver", "DriverError", "LINKS", "open_driver"]
