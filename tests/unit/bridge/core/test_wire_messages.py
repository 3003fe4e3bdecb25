"""Wire contracts: decoding validates types, ranges and finiteness; keys are well-formed."""

from __future__ import annotations

import math

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.core.wire import (
    Applied,
    Command,
    Estop,
    Keys,
    LearnerState,
    MessageError,
    PairRecord,
    Pairs,
    Status,
    TeacherCommand,
    decode,
    encode,
    key,
    status_key,
    validated,
)


def _raw_command(**overrides: object) -> bytes:
    """A Command as raw msgpack built from a dict, so NaN/inf/unknown fields survive encoding."""
    body: dict[str, object] = {"stamp": 1.0, "seq": 3, "v": 0.2, "omega": 0.1, "method": "scm", "valid_ms": 200}
    body.update(overrides)
    return msgspec.msgpack.encode(body)


def test_round_trip_of_every_message() -> None:
    msgs = [
        LearnerState(stamp=1.0, seq=1, x=1.0, y=2.0, theta=0.5, v=0.1, omega=-0.2, source="can"),
        Command(stamp=1.0, seq=2, v=0.2, omega=0.1, method="perturb", valid_ms=250, region=[1, 2, 3, 4]),
        TeacherCommand(stamp=1.0, seq=3, v=0.4, omega=0.0, solver="fatrop", predicted_x=[0.0, 0.1], predicted_y=[0, 0]),
        Applied(stamp=2.0, seq=4, v=0.0, omega=0.0, reason="deadman"),
        Pairs(stamp=3.0, robot="r1", pairs=[PairRecord(id=1, version=2, count=5, teacher_v=0.3, teacher_omega=0.1,
                                                      learner_v=0.2, learner_omega=0.05)],
              limits_box=[0.05, 0.6, -0.7, 0.7], limits_hull=[[0.05, -0.7], [0.6, -0.7], [0.6, 0.7]]),
        Status(stamp=4.0, seq=5, node="station", rates_hz={"loop": 10.0}, counters={"malformed": 2}),
        Estop(stamp=5.0, engaged=True, source="test", reason="button"),
    ]
    for m in msgs:
        assert decode(encode(m), type(m)) == m


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 101.0, -1e9])
def test_non_finite_or_out_of_range_speed_is_rejected(bad: float) -> None:
    with pytest.raises(MessageError, match=r"\$\.v"):
        decode(_raw_command(v=bad), Command)


def test_unknown_fields_wrong_types_and_methods_are_rejected() -> None:
    with pytest.raises(MessageError):
        decode(_raw_command(extra=1), Command)
    with pytest.raises(MessageError):
        decode(_raw_command(v="fast"), Command)
    with pytest.raises(MessageError):
        decode(_raw_command(method="teleport"), Command)
    with pytest.raises(MessageError):
        decode(_raw_command(valid_ms=0), Command)
    with pytest.raises(MessageError):
        decode(b"\xc1", Command)  # never-used msgpack byte


def test_validated_catches_a_locally_built_bad_message() -> None:
    # Construction does not validate; validated() does.
    bad = Command(stamp=1.0, seq=1, v=math.nan, omega=0.0, method="scm")
    with pytest.raises(MessageError):
        validated(bad)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64))
def test_random_bytes_either_decode_to_a_valid_command_or_raise_message_error(data: bytes) -> None:
    try:
        cmd = decode(data, Command)
    except MessageError:
        return
    assert math.isfinite(cmd.v) and math.isfinite(cmd.omega)


def test_keys() -> None:
    k = Keys("rover-1")
    assert k.cmd == "scm/rover-1/cmd" and k.state == "scm/rover-1/state" and k.estop == "scm/rover-1/estop"
    assert status_key("rover-1", "driver") == "scm/rover-1/status/driver"
    for bad in ["", "a/b", "a*", "r$", "x" * 65]:
        with pytest.raises(ValueError):
            Keys(bad)
    with pytest.raises(ValueError):
        key("r1", "nope")
