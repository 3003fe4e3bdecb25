"""The driver host's estop latch fails safe: a latch the disk cannot take, a release that cannot be saved, a latch file
deleted, replaced by a "released" one written by someone else, or a host in another state directory all count as
latched, and say so. Each case runs the real DriverHost in this process with a real state directory (a "restart" is
a new DriverHost on the same directory) and the UDP link to the emulated robot on loopback. Split from
tests/integration/test_driver_host.py, which runs the host as a process over Zenoh."""

from __future__ import annotations

import os
import time

import pytest

from bridge.core import wire as M
from bridge.core.wire import Keys
from bridge.nodes.zsession import free_port, make_config, open_session, tcp
from tests.latch import FullDisk, wait_saved
from transfer.domain import Bounds

LIMITS = Bounds((-0.5, 0.5), (-1.0, 1.0))


# ------------------------------------------------------------------------------------------------------------------
# The estop latch fails safe. Found by a hostile test: with the robot's disk full, ``estop`` and
# ``status`` said LATCHED while the latch file was never written; after a restart the robot was unlatched and
# ``engage`` + ``mission resume`` drove it. The same when the file was deleted, replaced by a "released" one, or the
# host restarted with another state directory. Each case below runs the real DriverHost in this process with a real
# state directory (a "restart" is a new DriverHost on the same directory) and the UDP link to the emulated robot on
# loopback. A full disk is an injected saver raising ENOSPC (tests.latch.FullDisk: the suite runs as root, which a
# read-only chmod does not stop, and a tmpfs of its own needs privileges the suite does not assume).


class _Robot:
    """The emulated UDP robot on loopback and the link's configuration to it (insecure: no key file)."""

    def __enter__(self):
        from bridge.tools.procs import free_udp_port
        from drivers.udp import UdpLinkConfig
        from sim_learner.dynamics import mpc_learner
        from sim_learner.udp_robot import UdpRobot
        from sim_learner.vehicle import SimVehicle

        bind = free_udp_port()
        self.device = UdpRobot(SimVehicle(mpc_learner(), (0.0, 0.0, 0.0), now=time.monotonic()),
                               peer=("127.0.0.1", bind)).start()
        self.link_cfg = UdpLinkConfig(insecure=True, robot_port=self.device.port, bind_port=bind)
        self.hosts: list = []
        return self

    def host(self, latch, saver=None):
        """A driver host for this robot keeping its latch at ``latch`` (a start; its link opened)."""
        from bridge.core.paths import save_atomic
        from bridge.nodes.driver_config import load_driver
        from bridge.nodes.driver_host import DriverHost
        from drivers import open_driver

        cfg = load_driver(None)
        host = DriverHost(cfg, "udp", open_driver("udp", self.link_cfg), "r1", cfg.driver.rate_hz, latch_path=latch,
                          latch_saver=saver or save_atomic)
        host.driver.open(time.monotonic())
        self.hosts.append(host)
        return host

    def stop(self, host) -> None:
        """The host stops (its link closed, its latch writer finished)."""
        host.driver.close(disarm=False, stop_timeout=0.0)
        assert host.latch.close(5.0)
        self.hosts.remove(host)

    def __exit__(self, *exc) -> None:
        for host in list(self.hosts):
            self.stop(host)
        self.device.stop()


def _estop(host, engaged: bool = True, source: str = "operator") -> None:
    """An estop as the person's tool sends it (a release fresh and with its nonce: bridge/core/acts.py)."""
    from bridge.core.acts import stamped

    host.on_estop(stamped(M.Estop(stamp=time.monotonic(), engaged=engaged, source=source, reason="test"),
                          host.acts.address(time.monotonic())), time.monotonic())
    wait_saved(host.latch)


def _engage(host) -> M.EngageState:
    return host.handle_engage(M.EngageRequest(stamp=time.monotonic(), source="test"), time.monotonic())


def test_an_estop_the_disk_cannot_take_stops_refuses_engage_and_is_still_latched_after_a_restart(tmp_path) -> None:
    """(a) Disk full at estop time: the estop still stops, status says it is not saved (typed reason
    ``latch_unsaved``, and the path and error in words), engage is refused, the old latch file (released) is
    removed so a restart starts latched; a release on the still-full disk latches again; once the disk takes a
    release, the host engages."""
    from bridge.nodes.latch_store import latch_marker, read_latch
    from bridge.nodes.station_fitness import driver_estop

    latch = tmp_path / "state" / "estop-r1.bin"
    saver = FullDisk()
    full = saver.full

    with _Robot() as robot:
        host = robot.host(latch, saver)
        assert latch_marker(latch).exists() and not read_latch(latch).latched  # the first start: marker, released
        full.set()
        _estop(host)
        assert host.decide(time.monotonic()).reason == "estop"
        st = host.status(time.monotonic())
        assert not st.ok and st.state == "estop" and st.reason == "latch_unsaved", st
        assert f"estop latched but NOT saved to {latch}: No space left on device; engage refused until it is saved" \
            in st.text, st.text
        assert st.counters["latch_save_failures"] == 1 and driver_estop(st)  # a station takes it as an estop
        ans = _engage(host)
        assert not ans.engaged and not ans.accepted and "NOT saved" in ans.text, ans
        assert not latch.exists()  # the released file is gone: a restart must not read it
        # scmbridge estop's query (a real Zenoh session in this process) hears it latched, and not saved
        from bridge.tools.estop import latch_states

        with open_session(make_config(listen=[tcp(free_port())])) as session:
            session.declare_queryable(Keys("r1").estop, host.on_estop_query)
            answers = list(latch_states(session, Keys("r1").estop, 2.0).values())
        assert len(answers) == 1 and answers[0].latched and "NOT saved" in answers[0].reason, answers
        # the robot restarts (still on the full disk): latched, by the missing file
        robot.stop(host)
        again = robot.host(latch, saver)
        assert again.gate.estopped and again.gate.estop_source == "missing latch file"
        assert not _engage(again).engaged
        # a person releases, but the disk still takes nothing: latched again, said, engage refused
        _estop(again, engaged=False)
        assert again.gate.estopped and again.gate.estop_source == "unsaved release"
        st = again.status(time.monotonic())
        assert st.reason == "latch_unsaved" and "estop release NOT saved to" in st.text, st.text
        assert not _engage(again).engaged
        # space freed: a release that is saved clears it, and the host engages
        full.clear()
        _estop(again, engaged=False)
        assert not again.gate.estopped and not again.latch_unsaved
        assert not read_latch(latch).latched
        ans = _engage(again)
        assert ans.engaged, ans


def test_a_release_that_cannot_be_saved_after_a_saved_estop_latches_again(tmp_path) -> None:
    """The other order: the estop was saved, the release is not (the disk filled meanwhile): the gate latches again
    at once and says why, so memory never drives while the disk says latched."""
    import errno

    from bridge.nodes.latch_store import read_latch

    latch = tmp_path / "estop-r1.bin"
    saver = FullDisk(errno.EROFS)
    full = saver.full

    with _Robot() as robot:
        host = robot.host(latch, saver)
        _estop(host)
        assert read_latch(latch).latched and not host.latch_unsaved
        full.set()
        _estop(host, engaged=False)
        st = host.status(time.monotonic())
        assert host.gate.estopped and st.reason == "latch_unsaved" and "Read-only file system" in st.text, st.text
        assert read_latch(latch).latched  # the disk still says latched, and so does the host
        assert not _engage(host).engaged


def test_a_latch_file_deleted_while_the_host_was_stopped_counts_as_latched(tmp_path) -> None:
    """(b) The install marker says this state directory has an estop history: a latch file missing beside it
    (deleted, released or latched, while the host was stopped) is latched until a person releases it."""
    from bridge.nodes.latch_store import read_latch

    latch = tmp_path / "estop-r1.bin"
    with _Robot() as robot:
        for latched in (True, False):
            host = robot.host(latch)
            if latched:
                _estop(host)
            robot.stop(host)
            latch.unlink()
            host = robot.host(latch)
            assert host.gate.estopped and host.gate.estop_source == "missing latch file"
            assert "estop latched by missing latch file" in host.status(time.monotonic()).text
            assert not _engage(host).engaged
            _estop(host, engaged=False)  # a person looked at the robot and releases it: saved, signed
            assert not read_latch(latch).latched
            robot.stop(host)


def test_a_released_latch_file_written_by_someone_else_counts_as_latched(tmp_path) -> None:
    """(c) A "released" latch is believed only if it carries this host's keyed tag (the key is in the install
    marker, 0600): an unsigned one (what someone crafts, or an older version wrote), one with a made-up tag, one
    signed by another robot's host, or one beside a marker others may read, all start latched."""
    import shutil

    from bench.attack_latch import forged_releases
    from bridge.nodes.latch_store import latch_marker

    latch = tmp_path / "a" / "estop-r1.bin"
    other = tmp_path / "b" / "estop-r1.bin"
    with _Robot() as robot:
        robot.stop(robot.host(other))  # another state directory's host: its own key, a released file it signed
        host = robot.host(latch)
        _estop(host)
        robot.stop(host)
        for data in forged_releases(other):
            latch.write_bytes(data)
            host = robot.host(latch)
            assert host.gate.estopped and host.gate.estop_source == "unverified latch file", data
            assert not _engage(host).engaged
            robot.stop(host)
        # a release this host saves itself is believed
        shutil.copy(other, latch)
        host = robot.host(latch)
        _estop(host, engaged=False)
        robot.stop(host)
        host = robot.host(latch)
        assert not host.gate.estopped
        robot.stop(host)
        # a marker others may read: its key is no secret, so what it signed is not believed
        latch_marker(latch).chmod(0o644)
        host = robot.host(latch)
        assert host.gate.estopped and host.gate.estop_source == "unverified latch file"
        assert oct(latch_marker(latch).stat().st_mode & 0o777) == "0o600"  # a new key, private again
        robot.stop(host)


def test_a_host_in_another_state_directory_says_it_has_no_estop_history(tmp_path, caplog) -> None:
    """(d) A host started with an empty state directory cannot know of an estop latched in another one (the state
    directory must stay the same): it says so in its log at start, once; the next start there does not."""
    import logging

    with _Robot() as robot:
        for first in (True, False):
            caplog.clear()
            with caplog.at_level(logging.INFO, logger="scmbridge.driver"):
                host = robot.host(tmp_path / "fresh" / "estop-r1.bin")
            said = "first start in this state directory: no estop history" in caplog.text
            assert host.latch.fresh_state == first and said == first, caplog.text
            assert f"state directory {tmp_path / 'fresh'}" in caplog.text
            assert not host.gate.estopped
            robot.stop(host)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only directory (the ENOSPC saver above "
                                               "stands for it)")
def test_an_estop_in_a_read_only_state_directory_is_not_saved_and_says_so(tmp_path) -> None:
    """(a) with the real save: the state directory made read-only after the first start (a user other than root)."""
    latch = tmp_path / "state" / "estop-r1.bin"
    with _Robot() as robot:
        host = robot.host(latch)
        latch.parent.chmod(0o500)
        try:
            _estop(host)
            st = host.status(time.monotonic())
            assert st.reason == "latch_unsaved" and "NOT saved" in st.text, st.text
            assert not _engage(host).engaged
        finally:
            latch.parent.chmod(0o700)
