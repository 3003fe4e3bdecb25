"""A station's callbacks (:mod:`bridge.nodes.station_inbox`): what arrives waits in the inbox for the loop, wakes
it when it must be handled now, and is answered at once while no loop runs (in the callback, or on the thread
``off`` gives)."""

from __future__ import annotations

import threading

from bridge.core import wire as M
from bridge.nodes.node import Inputs, OffThread
from bridge.nodes.station_inbox import Asked, Receiver
from tests.fakeclock import FakeClock


class _Rig:
    def __init__(self) -> None:
        self.clock = FakeClock(t=5.0)
        self.woken = threading.Event()
        self.answered: list[tuple[list[Asked], float]] = []
        self.inputs = Inputs(self.clock)
        self.rx = Receiver(41, self.inputs, self.clock, self.woken.set, lambda q, now: self.answered.append((q, now)))


def _status(seq: int) -> M.Status:
    return M.Status(stamp=0.0, seq=seq, node="driver", ok=True, text="link can: driving (cmd)")


def test_what_arrives_waits_in_the_inbox_until_the_loop_takes_it() -> None:
    rig = _Rig()
    rx = rig.rx
    rx.on_own_cmd(M.Command(stamp=1.0, seq=0, v=0.0, omega=0.0, method="stop", epoch=41), 1.0)  # its own: dropped
    rx.on_own_cmd(M.Command(stamp=1.0, seq=0, v=0.0, omega=0.0, method="stop", epoch=42), 1.1)
    rx.on_driver_status(_status(3), 1.2)
    rx.on_mission(M.MissionSpec(name="line", path=[[0.0, 0.0], [1.0, 0.0]]), 1.3)
    assert not rig.woken.is_set()  # nothing of it must be handled before the next deadline
    inbox = rx.take()
    assert [c.epoch for c, _ in inbox.foreign] == [42] and inbox.driver == (_status(3), 1.2)
    assert inbox.mission is not None and inbox.mission[0].name == "line"
    empty = rx.take()
    assert not empty.foreign and empty.driver is None and empty.mission is None


def test_an_external_teachers_command_wakes_the_loop() -> None:
    rig = _Rig()
    rig.rx.on_teacher(M.TeacherCommand(stamp=1.0, seq=1, v=0.2, omega=0.0), 1.0)
    assert rig.woken.is_set()
    queries, teacher, driver = rig.rx.take_queries()
    assert queries == [] and teacher and driver is None


def test_a_query_is_answered_at_once_without_a_loop_and_waits_for_it_while_it_runs() -> None:
    rig = _Rig()
    rx, asked = rig.rx, object()  # the receiver only carries the query to whoever answers it
    rx.on_pairs_query(asked)
    assert [q.query for q in rig.answered[0][0]] == [asked] and not rig.woken.is_set()
    rx.begin()
    rx.on_pairs_query(asked)
    assert len(rig.answered) == 1 and rig.woken.is_set()
    rx.on_driver_status(_status(4), 5.1)  # a query waits: the status is handed over with it
    queries, _, driver = rx.take_queries()
    assert [q.kind for q in queries] == ["pairs"] and driver == (_status(4), 5.1)
    rx.requeue(queries)  # waits for a driver host status
    rx.end(7.0)  # the loop ended: what waited is answered now
    assert not rx.looping and [q.kind for q in rig.answered[1][0]] == ["pairs"] and rig.answered[1][1] == 7.0


def test_with_an_off_thread_a_query_without_a_loop_is_answered_there_in_order_or_handed_to_a_loop_begun_since(
        caplog) -> None:
    """The station's callbacks run on Zenoh's thread: a query while no loop runs is answered on the process's
    OffThread, the jobs in the order they were handed; one that finds the loop begun meanwhile waits in the inbox."""
    rig, off = _Rig(), OffThread("test-off")
    rx, done = rig.rx, threading.Event()
    rx.off = off
    gate = threading.Event()
    off(gate.wait, 10)  # holds the thread: what follows waits behind it
    rx.on_pairs_query("first")
    rx.on_pairs_query("second")
    assert rig.answered == []  # not answered in the callback
    off(done.set)
    gate.set()
    assert done.wait(10)
    assert [q.query for qs, _ in rig.answered for q in qs] == ["first", "second"]
    assert off.thread is not None and off.thread.name == "test-off" and off.thread.daemon
    gate.clear()
    done.clear()
    off(gate.wait, 10)
    rx.on_pairs_query("third")
    rx.begin()  # the loop begins before the thread gets to it: the loop answers it
    off(lambda: 1 / 0)  # a job that raises is logged; the thread goes on
    off(done.set)
    gate.set()
    assert done.wait(10)
    assert len(rig.answered) == 2 and rig.woken.is_set()
    queries, _, _ = rx.take_queries()
    assert [q.query for q in queries] == ["third"]
    assert "test-off" in caplog.text and "ZeroDivisionError" in caplog.text
