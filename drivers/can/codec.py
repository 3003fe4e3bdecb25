"""CANSimple frames as ODrive firmware 0.6 defines them, from the shipped ``drivers/odrive_cansimple.dbc`` (node 0
layout; the node goes into the id at run time: arbitration id = node_id << 5 | cmd_id, 11-bit, little endian, IEEE
float32). Pure: a frame in, its values out, and back. cantools and python-can are imported at the first frame."""

from __future__ import annotations

import math
from importlib import resources
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import can
    import cantools

_DB: cantools.database.can.Database | None = None


def database() -> cantools.database.can.Database:
    """The shipped CANSimple DBC (loaded once)."""
    global _DB
    if _DB is None:
        import cantools

        text = resources.files("drivers").joinpath("odrive_cansimple.dbc").read_text()
        _DB = cantools.database.load_string(text, database_format="dbc")
    return _DB


def encode(node: int, name: str, signals: dict[str, float] | None = None) -> can.Message:
    """A CANSimple frame for ``node`` (0..63)."""
    import can

    if not 0 <= node < 64:
        raise ValueError(f"CANSimple node id must be 0..63, got {node}")
    msg = database().get_message_by_name(name)
    data = msg.encode(signals or {}) if msg.signals else b""
    return can.Message(arbitration_id=(node << 5) | msg.frame_id, data=data, is_extended_id=False)


def decode(frame: can.Message) -> tuple[int, str, dict[str, Any]]:
    """(node, message name, signals) of a CANSimple frame; ValueError for anything that is not one (wrong length,
    non-finite float, unknown command, extended id, error frame)."""
    if frame.is_extended_id or frame.is_error_frame:
        raise ValueError("not a CANSimple frame (extended id or error frame)")
    node, cmd = frame.arbitration_id >> 5, frame.arbitration_id & 0x1F
    try:
        msg = database().get_message_by_frame_id(cmd)
    except KeyError:
        raise ValueError(f"unknown CANSimple command 0x{cmd:02x}") from None
    if frame.is_remote_frame:
        return node, msg.name, {"_rtr": True}
    if len(frame.data) != msg.length:
        raise ValueError(f"{msg.name}: {len(frame.data)} data bytes, expected {msg.length}")
    sig = msg.decode(bytes(frame.data), decode_choices=False) if msg.signals else {}
    for k, v in sig.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{msg.name}.{k} is not finite")
    return node, msg.name, dict(sig)

