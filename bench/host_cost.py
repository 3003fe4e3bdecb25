"""The driver host's CPU per tick, in-process: ``python -m bench.host_cost [--ticks N]``.

The CAN link on a python-can ``virtual`` bus with the emulated controllers in this process (as ``scmbridge driver
--emulate`` runs them), engaged, a station's command offered every fifth tick at 50 Hz; the thread CPU time of each
tick and of its status when one is due, on the machine's clock. It uses only what the driver host has had for
several rounds (``tick``, ``status``), so the same file measures an older checkout for an A/B comparison (a copy
of it outside ``bench/``, whose ``bridge.py`` would shadow the package: ``PYTHONPATH=<checkout> python
/tmp/host_cost.py``). Prints one JSON line: the ticks, their median and 90th
percentile in microseconds, and whether the link drove throughout."""

from __future__ import annotations

import argparse
import json
import time
import uuid

import msgspec

from bridge.core.logsink import print_line


class _Sink:
    """A publisher that drops what it is given (the Zenoh put is not the host's own cost)."""

    def put(self, payload: bytes) -> None:
        pass


def measure(ticks: int) -> dict:
    from bridge.core import wire as M
    from bridge.nodes.driver_config import DriverConfig
    from bridge.nodes.driver_host import DriverHost
    from drivers import open_driver
    from sim_learner.can_ecu import DiffDriveEcus
    from sim_learner.dynamics import model_by_name
    from sim_learner.vehicle import SimVehicle

    cfg = DriverConfig()
    link = msgspec.structs.replace(cfg.link.can, interface="virtual", channel=f"cost-{uuid.uuid4().hex[:6]}")
    host = DriverHost(cfg, "can", open_driver("can", link), "r1", 50.0)
    ecus = DiffDriveEcus({"interface": "virtual", "channel": link.channel},
                         SimVehicle(model_by_name("mpc"), (0.0, 0.0, 0.0), now=time.monotonic()),
                         left_node=link.left_node, right_node=link.right_node, left_sign=link.left_sign,
                         right_sign=link.right_sign, wheel_radius=link.wheel_radius,
                         track_width=link.track_width).start()
    host.pubs = {"applied": _Sink(), "state": _Sink(), "status": _Sink()}
    cpu: list[float] = []
    driving = True
    try:
        host.driver.open(time.monotonic())
        ans = host.handle_engage(M.EngageRequest(stamp=0.0, source="bench"), time.monotonic())
        if not ans.engaged:
            raise RuntimeError(f"not engaged: {ans.text}")
        seq = 0
        for k in range(ticks):
            now = time.monotonic()
            if k % 5 == 0:
                seq += 1
                host.on_cmd(M.Command(stamp=now, seq=seq, v=0.2, omega=0.1, method="scm", epoch=9, sender="bench"),
                            now)
            ecus.emit_due()
            c0 = time.thread_time()
            host.tick(now)
            assessed = host._status_due(now)
            if assessed is not None:
                host._put("status", host.status(now, assessed))
            cpu.append(time.thread_time() - c0)
            driving = driving and (k < 10 or host.health.ok)
            time.sleep(max(0.0, now + 0.02 - time.monotonic()))
    finally:
        host.close()
        ecus.stop()
    cpu.sort()
    return {"ticks": len(cpu), "median_us": round(cpu[len(cpu) // 2] * 1e6, 1),
            "p90_us": round(cpu[int(len(cpu) * 0.9)] * 1e6, 1), "driving": driving}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=1500, help="ticks at 50 Hz (default 1500: 30 s)")
    print_line(json.dumps(measure(ap.parse_args().ticks)))


if __name__ == "__main__":
    main()
