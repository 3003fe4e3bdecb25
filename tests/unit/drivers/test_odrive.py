"""drivers/odrive.py: the ODrive 0.6 tables' helpers a person reads (:func:`error_names`, :func:`state_name`). The
tables themselves are checked value by value against ODrive's reference in
tests/unit/drivers/can/test_driver.py (test_error_table_and_enumerations_are_odrive_0_6)."""

from __future__ import annotations

from drivers.odrive import AxisState, ODriveError, error_names, state_name


def test_no_error_has_no_names() -> None:
    assert error_names(0) == [] and error_names(ODriveError.NONE) == []


def test_every_defined_bit_is_named_alone_and_all_of_them_in_bit_order() -> None:
    defined = [e for e in ODriveError if e.value]
    for flag in defined:
        assert error_names(int(flag)) == [flag.name]
    everything = 0
    for flag in defined:
        everything |= int(flag)
    assert error_names(everything) == [f.name for f in sorted(defined, key=int)]


def test_undefined_bits_are_shown_as_hex_never_dropped() -> None:
    word = 0xFFFFFFFF
    names = error_names(word)
    assert len(names) == 32  # one entry per bit
    assert "0x00000080" in names and "0x80000000" in names and "CALIBRATION_ERROR" in names
    assert error_names(0x20000000) == ["0x20000000"]


def test_only_the_32_bit_word_counts() -> None:
    assert error_names(1 << 32) == []
    assert error_names((1 << 32) | 0x40) == ["MISSING_INPUT"]
    assert error_names(-1) == error_names(0xFFFFFFFF)  # a signed reading of the same word


def test_state_names_and_a_state_0_6_does_not_define() -> None:
    assert state_name(8) == "CLOSED_LOOP_CONTROL" and state_name(AxisState.IDLE) == "IDLE"
    assert state_name(5) == "state 5"  # sensorless control: gone in 0.6
    assert state_name(200) == "state 200"
