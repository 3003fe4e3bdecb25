"""drivers/can/codec.py: CANSimple frames in and out (node in the id, refusals of what is not a CANSimple frame). The
byte layout against ODrive's 0.6 reference and random frames are tested in tests/unit/drivers/can/test_driver.py;
this file tests the codec's own contract around them."""

from __future__ import annotations

import can
import pytest

from drivers.can.codec import database, decode, encode


def test_the_database_is_loaded_once() -> None:
    assert database() is database()


@pytest.mark.parametrize("node", [-1, 64, 1000])
def test_a_node_outside_0_to_63_is_refused(node: int) -> None:
    with pytest.raises(ValueError, match="0..63"):
        encode(node, "Estop")


def test_the_node_goes_into_the_upper_six_bits_of_an_11_bit_id() -> None:
    for node in (0, 1, 31, 63):
        f = encode(node, "Clear_Errors", {"Identify": 0})
        assert f.arbitration_id == node << 5 | 0x18 and f.arbitration_id < 0x800 and not f.is_extended_id


def test_every_message_round_trips_through_decode() -> None:
    values = {
        "Heartbeat": {"Axis_Error": 0x02000040, "Axis_State": 8, "Procedure_Result": 1, "Trajectory_Done_Flag": 1},
        "Estop": {},
        "Set_Axis_State": {"Axis_Requested_State": 1},
        "Get_Encoder_Estimates": {"Pos_Estimate": -12.5, "Vel_Estimate": 0.25},
        "Set_Controller_Mode": {"Control_Mode": 2, "Input_Mode": 1},
        "Set_Input_Vel": {"Input_Vel": 3.0, "Input_Torque_FF": 0.0},
        "Clear_Errors": {"Identify": 1},
    }
    assert set(values) == {m.name for m in database().messages}
    for name, signals in values.items():
        node, got_name, got = decode(encode(5, name, signals))
        assert (node, got_name, got) == (5, name, signals)


def test_a_message_without_signals_is_an_empty_frame() -> None:
    f = encode(2, "Estop")
    assert bytes(f.data) == b"" and decode(f) == (2, "Estop", {})


def test_a_request_for_a_message_is_a_remote_frame_decoded_as_such() -> None:
    rtr = can.Message(arbitration_id=4 << 5 | 0x09, is_remote_frame=True, is_extended_id=False, dlc=8)
    assert decode(rtr) == (4, "Get_Encoder_Estimates", {"_rtr": True})


def test_what_is_not_a_cansimple_frame_is_refused_with_its_reason() -> None:
    with pytest.raises(ValueError, match="extended id"):
        decode(can.Message(arbitration_id=0x09, data=bytes(8), is_extended_id=True))
    with pytest.raises(ValueError, match="error frame"):
        decode(can.Message(arbitration_id=0x09, data=bytes(8), is_extended_id=False, is_error_frame=True))
    with pytest.raises(ValueError, match="unknown CANSimple command 0x1f"):
        decode(can.Message(arbitration_id=3 << 5 | 0x1F, data=bytes(8), is_extended_id=False))
    with pytest.raises(ValueError, match="Heartbeat: 9 data bytes, expected 8"):
        decode(can.Message(arbitration_id=0x01, data=bytes(9), is_extended_id=False, is_fd=True))


def test_an_infinite_float_is_refused_like_a_nan() -> None:
    inf = bytes.fromhex("0000807f")  # +inf, float32 little endian
    with pytest.raises(ValueError, match=r"Get_Encoder_Estimates\.Vel_Estimate is not finite"):
        decode(can.Message(arbitration_id=0x09, data=bytes(4) + inf, is_extended_id=False))
