"""The driver host's loop records and options, pieces of one job each beside
:class:`bridge.nodes.driver_host.DriverHost` (docs/ARCHITECTURE.md section 4, "Threads and clocks"):
:class:`HostTiming` (the host's clock and waits, its scheduler and what the loop's timing was),
:class:`HostOptions` (what a person chose for this run) and :class:`Echo` (what the vehicle got last and the
``applied`` sequence). No Zenoh, no link: the host wires them."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.core.clock import SYSTEM, Clock
from bridge.core.gate import Decision
from bridge.core.stalls import StallWatch
from bridge.nodes.node import FixedRate

#: s between two loop iterations beyond which the log says why the loop was late (bridge.core.stalls.StallWatch)
STALL_REPORT_S = 0.25
#: periodic ticks whose start and lateness are kept (the status's jitter figures)
KEPT_TICKS = 500


class HostTiming:
    """The host's time: its ``clock`` (read once a tick) and ``wait`` (every wait of the loop and of its link's open
    retries), the loop's period and send budget, its scheduler once running (:class:`FixedRate`), the stall watch,
    and the start and lateness of the recent periodic ticks."""

    def __init__(self, rate_hz: float, max_send_hz: float, clock: Clock = SYSTEM) -> None:
        self.clock, self.wait = clock, clock.wait
        self.period = 1.0 / rate_hz
        self.max_send_hz = max_send_hz
        self.ticker: FixedRate | None = None  # the loop's scheduler (deadlines, wake-ups, the send budget)
        #: a loop iteration later than this says why in the log (the controllers' watchdog is 0.5 s on ODrive's
        #: example; the deadman a few periods), and where it is blocked while it is (two periods at a slow rate)
        self.stall_report_s = max(STALL_REPORT_S, 2.0 * self.period)
        self.stall_watch = StallWatch(self.stall_report_s)
        self.ticks: deque[float] = deque(maxlen=KEPT_TICKS)  # start times of the periodic ticks
        self.late: deque[float] = deque(maxlen=KEPT_TICKS)  # s each periodic tick came after its deadline (jitter)

    @property
    def missed(self) -> int:
        """Deadlines the scheduler missed so far."""
        return self.ticker.missed if self.ticker is not None else 0


@dataclass
class HostOptions:
    """What a person chose for this run of the host: ``dry_run`` (the whole loop, nothing sent to the vehicle),
    ``engage_on_start``, ``fence`` (a polygon, ENU in the link's frame, uploaded as the vehicle's own after the link
    opens: ``--fence``), ``co_located`` (emulated devices hosted in this process, ``--emulate``: each
    ``emit_due()`` runs before the link is read) and ``latch_path`` (where the estop latch is kept; None: memory)."""

    dry_run: bool = False
    engage_on_start: bool = False
    fence: list[tuple[float, float]] = field(default_factory=list)
    co_located: list[Any] = field(default_factory=list)
    latch_path: Path | None = None


@dataclass
class Echo:
    """What the vehicle got at the last tick (``last``) and the ``applied`` message's next sequence number."""

    last: Decision = field(default_factory=lambda: Decision(0.0, 0.0, "start"))
    seq: int = 0
