"""The CAN link's wire, without a driver: CANSimple frames and the DBC against ODrive's published 0.6 definitions,
random frames, and the emulated ODrive 0.6 controllers on a real python-can bus (``virtual`` interface, in-process)
as a 0.6 device behaves (the emulator's own contract). Split from tests/integration/test_can_link.py, which drives
the link through its driver.

The expected values here are transcribed from ODrive's published 0.6 definitions, not from the driver:
``src/ODriveEnums.h`` of odriverobotics/ODriveArduino and ``odrive_base/include/can_simple_messages.hpp`` of
odriverobotics/ros_odrive (see drivers/odrive.py)."""

from __future__ import annotations

import struct
import time
import uuid

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridge.core.config import Rule
from drivers.can import CanLinkConfig, database, decode, encode
from drivers.odrive import AxisState, ControlMode, InputMode, ODriveError, ProcedureResult, error_names
from sim_learner import can_ecu
from sim_learner.can_ecu import DiffDriveEcus
from sim_learner.dynamics import mpc_learner
from sim_learner.vehicle import SimVehicle
from tests.wait import until

# (cmd_id, length, {signal: (start bit, bit length, signed, float)}) per ODrive 0.6's generated CANSimple messages
REFERENCE_0_6 = {
    "Heartbeat": (0x01, 8, {"Axis_Error": (0, 32, False, False), "Axis_State": (32, 8, False, False),
                            "Procedure_Result": (40, 8, False, False), "Trajectory_Done_Flag": (48, 1, False, False)}),
    "Estop": (0x02, 0, {}),
    "Set_Axis_State": (0x07, 8, {"Axis_Requested_State": (0, 32, False, False)}),
    "Get_Encoder_Estimates": (0x09, 8, {"Pos_Estimate": (0, 32, True, True), "Vel_Estimate": (32, 32, True, True)}),
    "Set_Controller_Mode": (0x0B, 8, {"Control_Mode": (0, 32, False, False), "Input_Mode": (32, 32, False, False)}),
    "Set_Input_Vel": (0x0D, 8, {"Input_Vel": (0, 32, True, True), "Input_Torque_FF": (32, 32, True, True)}),
    "Clear_Errors": (0x18, 1, {"Identify": (0, 8, False, False)}),
}
# ODrive.Error (0.6), every bit
ODRIVE_ERROR_0_6 = {
    0x1: "INITIALIZING", 0x2: "SYSTEM_LEVEL", 0x4: "TIMING_ERROR", 0x8: "MISSING_ESTIMATE", 0x10: "BAD_CONFIG",
    0x20: "DRV_FAULT", 0x40: "MISSING_INPUT", 0x100: "DC_BUS_OVER_VOLTAGE", 0x200: "DC_BUS_UNDER_VOLTAGE",
    0x400: "DC_BUS_OVER_CURRENT", 0x800: "DC_BUS_OVER_REGEN_CURRENT", 0x1000: "CURRENT_LIMIT_VIOLATION",
    0x2000: "MOTOR_OVER_TEMP", 0x4000: "INVERTER_OVER_TEMP", 0x8000: "VELOCITY_LIMIT_VIOLATION",
    0x10000: "POSITION_LIMIT_VIOLATION", 0x1000000: "WATCHDOG_TIMER_EXPIRED", 0x2000000: "ESTOP_REQUESTED",
    0x4000000: "SPINOUT_DETECTED", 0x8000000: "BRAKE_RESISTOR_DISARMED", 0x10000000: "THERMISTOR_DISCONNECTED",
    0x40000000: "CALIBRATION_ERROR",
}


# ------------------------------------------------------------------------------------------ frames and tables
def test_dbc_matches_the_odrive_0_6_reference_signal_by_signal() -> None:
    db = database()
    assert {m.name for m in db.messages} == set(REFERENCE_0_6)
    for name, (cmd, length, signals) in REFERENCE_0_6.items():
        m = db.get_message_by_name(name)
        assert (m.frame_id, m.length) == (cmd, length), name
        got = {s.name: (s.start, s.length, s.is_signed, s.is_float) for s in m.signals}
        assert got == signals, name
        assert all(s.byte_order == "little_endian" for s in m.signals), name


def test_error_table_and_enumerations_are_odrive_0_6() -> None:
    assert {int(e): e.name for e in ODriveError if e.value} == ODRIVE_ERROR_0_6
    assert error_names(0x01000000) == ["WATCHDOG_TIMER_EXPIRED"]  # 0.5's 0x800 is DC_BUS_OVER_REGEN_CURRENT in 0.6
    assert error_names(0x02000040) == ["MISSING_INPUT", "ESTOP_REQUESTED"]
    assert error_names(0x80 | 0x800) == ["0x00000080", "DC_BUS_OVER_REGEN_CURRENT"]  # an undefined bit is shown
    assert (AxisState.IDLE, AxisState.CLOSED_LOOP_CONTROL) == (1, 8)
    assert (ControlMode.VELOCITY_CONTROL, ControlMode.POSITION_CONTROL) == (2, 3)
    assert (InputMode.INACTIVE, InputMode.PASSTHROUGH, InputMode.VEL_RAMP) == (0, 1, 2)
    assert (ProcedureResult.BUSY, ProcedureResult.DISARMED, ProcedureResult.INVALID_STATE) == (1, 3, 13)
    # the emulator's own transcription agrees with the driver's (both from the reference, neither from the other)
    assert can_ecu.WATCHDOG_TIMER_EXPIRED == ODriveError.WATCHDOG_TIMER_EXPIRED
    assert can_ecu.ESTOP_REQUESTED == ODriveError.ESTOP_REQUESTED


def test_cansimple_ids_and_layout_are_odrive_0_6() -> None:
    f = encode(3, "Set_Input_Vel", {"Input_Vel": 1.5, "Input_Torque_FF": -0.25})
    assert f.arbitration_id == (3 << 5) | 0x0D and not f.is_extended_id
    assert bytes(f.data) == bytes.fromhex("0000c03f000080be")  # two little-endian float32
    hb = encode(1, "Heartbeat", {"Axis_Error": 0x01000000, "Axis_State": 8, "Procedure_Result": 1,
                                 "Trajectory_Done_Flag": 1})
    assert hb.arbitration_id == 0x21 and bytes(hb.data) == struct.pack("<IBBBx", 0x01000000, 8, 1, 1)
    mode = encode(0, "Set_Controller_Mode", {"Control_Mode": 2, "Input_Mode": 1})
    assert mode.arbitration_id == 0x0B and bytes(mode.data) == struct.pack("<II", 2, 1)
    assert bytes(encode(0, "Set_Axis_State", {"Axis_Requested_State": 8}).data) == struct.pack("<Ixxxx", 8)
    assert decode(encode(2, "Get_Encoder_Estimates", {"Pos_Estimate": 2.5, "Vel_Estimate": -1.0})) == (
        2, "Get_Encoder_Estimates", {"Pos_Estimate": 2.5, "Vel_Estimate": -1.0})
    with pytest.raises(ValueError, match="data bytes"):
        decode(can.Message(arbitration_id=0x0D, data=b"\x00\x00", is_extended_id=False))
    with pytest.raises(ValueError, match="not finite"):
        decode(can.Message(arbitration_id=0x09, data=bytes.fromhex("0000c07f00000000"), is_extended_id=False))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_random_frames_never_crash_and_garbage_is_counted(arb: int, data: bytes) -> None:
    frame = can.Message(arbitration_id=arb, data=data, is_extended_id=False)
    try:
        node, name, sig = decode(frame)
    except ValueError:
        return
    assert 0 <= node < 64 and isinstance(sig, dict)


def test_config_refuses_a_backoff_bound_below_its_start() -> None:
    with pytest.raises(Rule, match="reopen_backoff_max"):
        CanLinkConfig(reopen_backoff=1.0, reopen_backoff_max=0.5)
    cfg = CanLinkConfig()
    assert 0.3 <= cfg.heartbeat_timeout <= 0.5  # 3-5 of ODrive's default 0.1 s heartbeat periods


# ------------------------------------------------------------------------------------------ the emulator
def test_emulated_controller_behaves_as_odrive_0_6() -> None:
    """Raw frames from a master bus, no driver: what a 0.6 device does with each (the emulator's own contract)."""
    channel = f"test-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    master = can.Bus(interface="virtual", channel=channel)

    def tx(node: int, cmd: int, data: bytes = b"") -> None:
        master.send(can.Message(arbitration_id=(node << 5) | cmd, data=data, is_extended_id=False))

    def heartbeat(node: int) -> tuple[int, int, int, int]:
        """The next Heartbeat of ``node`` sent from now on (older ones are drained)."""
        while master.recv(timeout=0) is not None:
            pass
        t_end = time.monotonic() + 10.0
        while time.monotonic() < t_end:
            f = master.recv(timeout=0.05)
            if f is not None and f.arbitration_id == (node << 5) | 0x01:
                assert len(f.data) == 8
                return struct.unpack("<IBBBx", bytes(f.data))
        raise AssertionError("no heartbeat")

    def settle(pred, timeout: float = 10.0) -> bool:
        return bool(until(pred, timeout, 0.01))

    with DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle, watchdog=0.3,
                       heartbeat_period=0.05) as ecus:
        try:
            assert heartbeat(0)[:2] == (0, 1)  # no error, IDLE
            tx(0, 0x07, struct.pack("<I", 8))  # a 4-byte Set_Axis_State, as ODrive's own example sends it
            tx(1, 0x07, struct.pack("<I", 8))
            assert settle(lambda: ecus.axis(0).state == 8 and ecus.axis(1).state == 8)
            # factory control mode is position control: Set_Input_Vel alone does not turn the wheels
            for _ in range(15):
                tx(0, 0x0D, struct.pack("<ff", 2.0, 0.0))
                tx(1, 0x0D, struct.pack("<ff", -2.0, 0.0))
                time.sleep(0.02)  # pacing: a host's 50 Hz feed (that also keeps the watchdog fed)
            assert ecus.axis(0).control_mode == 3 and vehicle.advance(time.monotonic()).v == 0.0
            tx(0, 0x0B, struct.pack("<II", 2, 1))  # velocity control, passthrough
            tx(1, 0x0B, struct.pack("<II", 2, 1))
            tx(0, 0x0D, struct.pack("<ff", 2.0, 0.0))
            tx(1, 0x0D, struct.pack("<ff", -2.0, 0.0))
            assert settle(lambda: vehicle.advance(time.monotonic()).v > 0.0)
            # Estop: idle, ESTOP_REQUESTED, and the other wheel alone pivots the body
            tx(1, 0x02)
            assert settle(lambda: ecus.axis(1).state == 1)
            assert ecus.axis(1).error == 0x02000000 and ecus.axis(1).procedure_result == 3
            assert abs(vehicle.advance(time.monotonic()).omega) > 0.0
            # closed loop is refused while the error is set; Clear_Errors clears it and does not re-arm
            tx(1, 0x07, struct.pack("<I", 8))
            assert settle(lambda: ecus.axis(1).procedure_result == 13)  # the refusal's own mark
            assert ecus.axis(1).state == 1 and ecus.axis(1).procedure_result == 13
            tx(1, 0x18, b"\x00")
            assert settle(lambda: ecus.axis(1).error == 0)
            assert heartbeat(1)[1] == 1  # its next Heartbeat, sent after the clear was handled: still IDLE
            assert ecus.axis(1).state == 1
            # the watchdog: no feed for 0.3 s -> idle with WATCHDOG_TIMER_EXPIRED, wheels held
            assert settle(lambda: ecus.axis(0).state == 1)
            assert ecus.axis(0).error == 0x01000000 and vehicle.advance(time.monotonic()).v == 0.0
            err, state, result, _ = heartbeat(0)
            assert (err, state, result) == (0x01000000, 1, 3)
            # injected error; an unplugged node falls silent
            ecus.inject_error(1, 0x20)
            assert heartbeat(1)[0] == 0x20
            ecus.unplug(1)  # under the emulator's lock: what node 1 sent before is on the bus already
            while master.recv(timeout=0) is not None:
                pass
            # absence (node 1 silent) is watched over a window, in which node 0 proves the emulator still sends
            heard, t_end = set(), time.monotonic() + 0.3
            while time.monotonic() < t_end or not heard:
                f = master.recv(timeout=0.05)
                assert f is None or f.arbitration_id >> 5 != 1
                if f is not None:
                    heard.add(f.arbitration_id >> 5)
                assert time.monotonic() < t_end + 10.0, "the emulator fell silent"
            # a short Set_Input_Vel is malformed, ignored
            before = ecus.malformed
            tx(0, 0x0D, b"\x00\x00")
            assert settle(lambda: ecus.malformed == before + 1)
        finally:
            master.shutdown()


def test_emulated_frames_carry_the_time_the_controller_measured_not_when_its_thread_got_the_cpu_back() -> None:
    """Finding (series 12, run 3, beside two busy loops): the emulator's thread, preempted between measuring the
    wheels and writing the frame, sent a frame stamped ~0.35 s after the position it carried; the next frame, on
    time, looked like a jump no wheel can make, the driver rejected it and the fleet demo's mission paused. A real
    controller transmits as it measures and the host's kernel stamps the frame on arrival."""
    channel = f"test-{uuid.uuid4().hex[:8]}"
    vehicle = SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic())
    readings = iter([time.monotonic() - 0.3])  # the measurement; every later reading is 0.3 s on: the preemption
    ecus = DiffDriveEcus({"interface": "virtual", "channel": channel}, vehicle,
                         clock=lambda: next(readings, None) or time.monotonic())
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        ecus._open()
        ecus.emit_due()
        frames = [spy.recv(timeout=1.0) for _ in range(4)]  # both encoder estimates and both Heartbeats
        assert all(f is not None for f in frames)
        assert {f.arbitration_id & 0x1F for f in frames} == {0x01, 0x09}
        assert all(abs(f.timestamp - (time.time() - 0.3)) < 0.1 for f in frames), [f.timestamp for f in frames]
    finally:
        ecus._close()
        spy.shutdown()
