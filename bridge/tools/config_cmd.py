"""``scmbridge config check|show``: validate a configuration file, or print a commented default made from the
configuration's own types (every key with its default, unit and range)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_origin, get_type_hints

import msgspec
from msgspec import Meta, Struct

from bridge.core.config import (
    SHIPPED_MISSIONS,
    StationConfig,
    guess_kind,
    load,
    load_mission,
    load_mission_spec,
    read_table,
)
from bridge.core.wire import MissionSpec
from bridge.nodes.driver_config import driver_config_type

#: the kinds of configuration file, by the name ``--kind`` takes
KIND_NAMES = ("driver", "mission", "station")


def kind_type(kind: str) -> type[Struct]:
    """The struct a file of ``kind`` decodes into (the driver's holds a section for every link registered now)."""
    return {"station": StationConfig, "driver": driver_config_type(), "mission": MissionSpec}[kind]


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")  # TOML's own, never nan for inf
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):  # a basic string: JSON's escapes are TOML's (control characters escaped, not raw)
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(a) for a in v) + "]"
    if isinstance(v, dict):  # an inline table
        return "{" + ", ".join(f"{_toml_value(str(k))} = {_toml_value(a)}" for k, a in v.items()) + "}"
    raise TypeError(f"no TOML form for {v!r}")


def _describe(tp: Any) -> str:
    parts: list[str] = []
    while get_origin(tp) is Annotated:
        args = get_args(tp)
        for meta in args[1:]:
            if isinstance(meta, Meta):
                if meta.description:
                    parts.append(meta.description)
                rng = [f"{op} {getattr(meta, k)}" for k, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))
                       if getattr(meta, k) is not None and abs(getattr(meta, k)) != 1e9]
                if rng:
                    parts.append(", ".join(rng))
        tp = args[0]
    if get_origin(tp) is Literal:
        parts.append("one of " + ", ".join(repr(a) for a in get_args(tp)))
    return "; ".join(parts)


def _show(obj: Struct, prefix: str, out: list[str]) -> None:
    hints = get_type_hints(type(obj), include_extras=True)
    tables = []
    for name in obj.__struct_fields__:
        val = getattr(obj, name)
        if isinstance(val, Struct):
            tables.append((name, val, _describe(hints[name])))
            continue
        if val is None:
            out.append(f"# {name} =  # {_describe(hints[name])} (unset)")
            continue
        text = f"{name} = {_toml_value(val)}"
        desc = _describe(hints[name])
        out.append(f"{text:<40} # {desc}" if desc else text)
    for name, val, desc in tables:
        if any(not isinstance(getattr(val, f), Struct) for f in val.__struct_fields__):
            out.append("")
            out.append(f"[{prefix}{name}]")
            doc = (type(val).__doc__ or "").strip().splitlines()
            out.append(f"# {desc}" if desc else f"# {doc[0].replace('``', '')}" if doc else "#")
        _show(val, f"{prefix}{name}.", out)


def show(kind: str) -> str:
    """A commented TOML file holding every default of ``kind`` (station, driver or mission)."""
    if kind == "mission":
        text = resources.files("bridge").joinpath("missions", SHIPPED_MISSIONS["paper-s-path"]).read_text()
        return text
    obj = msgspec.convert({}, kind_type(kind))
    out = [f"# scmbridge {kind} configuration: every key with its default (scmbridge config show --kind {kind})"]
    _show(obj, "", out)
    return "\n".join(out) + "\n"


def check(path: str, kind: str | None = None) -> str:
    """Validate a file; returns a one-line description of what it is. Raises ConfigError."""
    p = Path(path)
    if kind is None:
        kind = guess_kind(read_table(p))
    if kind == "mission":
        m = load_mission(p)
        return f"{p}: a valid mission '{m.name}': {len(m.path.points)} waypoints, {m.path.length:.2f} m, " \
               f"{len(m.obstacles)} obstacles"
    cfg = load(p, kind_type(kind))
    also = own_checks(kind, cfg, read_table(p))
    return f"{p}: a valid {kind} configuration for robot '{cfg.robot}'" + (f" ({also})" if also else "")


def own_checks(kind: str, cfg: Any, table: dict[str, Any]) -> str:
    """What the commands themselves check when they start, beyond the file's types: each key file a driver's link
    names (it exists, is a key of random bytes and is its owner's alone: what the driver reads when that link
    opens; the file does not say which link the robot uses, so a link without a key is not refused here), a
    station's mission. Raises their own errors; returns what was checked."""
    done = []
    if kind == "driver":
        from bridge.core.auth import load_key
        from drivers.udp import link_key

        for name in (table.get("link") or {}):
            section = getattr(cfg.link, name, None)
            if name == "udp" and section is not None and section.key_file:
                link_key(section)
                done.append("udp key")
            elif name == "mavlink" and section is not None and section.signing_key_file:
                load_key(section.signing_key_file, "mavlink")
                done.append("mavlink signing key")
    elif kind == "station" and cfg.station.mission:
        load_mission_spec(cfg.station.mission)
        done.append(f"mission {cfg.station.mission!r}")
    return ", ".join(f"{d} checked" for d in done)


def arguments_check(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("file", help="the file to check")
    ap.add_argument("--kind", choices=KIND_NAMES, help="station, driver or mission (default: guessed from its keys)")


def run_check(args: argparse.Namespace) -> int:
    """Validate a station, driver or mission file: exit 0 and one line saying what it is, or exit 2 and one line
    naming the key and the problem."""
    print(check(args.file, args.kind))
    return 0


def arguments_show(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--kind", choices=KIND_NAMES, required=True, help="station, driver or mission")


def run_show(args: argparse.Namespace) -> int:
    """Print a commented file holding every key of a station, driver or mission configuration with its default,
    unit and range (it is itself a valid file of exactly the defaults)."""
    sys.stdout.write(show(args.kind))
    return 0
