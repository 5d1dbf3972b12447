"""python-can's `virtual` interface with one frame order for every receiver, as on a CAN bus.

Theory of operation. On a CAN bus arbitration puts frames in one sequence and every node receives that
sequence. python-can's `VirtualBus.send` copies a frame into each receiver's queue in turn, with no lock:
two threads of one process sending at once (the master's SYNC task and its record sender; the simulated
drives' answers) interleave those copies, so one receiver can get SYNC then a record while another gets
the record then SYNC. A drive simulated that way takes a record into its FIFO before a SYNC that the
master saw first, and the master, judging by its own order, finds a record too many (PROTOCOL "arrived
twice") or a TPDO before the SYNC it answers. No real bus does this, so it is the transport that is
wrong, not the master: `OrderedVirtualBus.send` holds one process-wide lock while it copies, which makes
each frame's delivery atomic and the order the same for every receiver.

`register()` makes `can.Bus(interface="virtual", ...)` build this class (python-can looks the class up in
`can.interfaces.BACKENDS` at every construction); `bus.network` calls it on import, so every virtual bus
the product and its tests open after that delivers in one order. Buses from other processes are not
concerned: python-can's virtual bus does not leave its process (bus/ipc.py is the one that does).
"""

from __future__ import annotations

import threading

import can
from can.interfaces.virtual import VirtualBus

INTERFACE = "virtual"
_SEND_LOCK = threading.Lock()


class OrderedVirtualBus(VirtualBus):
    """`VirtualBus` whose `send` delivers to all receivers before any other send starts."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with _SEND_LOCK:
            super().send(msg, timeout)


def register() -> None:
    """Make the `virtual` interface name build `OrderedVirtualBus` (idempotent)."""
    can.interfaces.BACKENDS[INTERFACE] = (__name__, OrderedVirtualBus.__name__)
