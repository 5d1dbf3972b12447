"""Fault injection on the wire: one seeded fault model, two transports (a python-can bus, a virtual link).

Theory of operation. `FaultModel` is a pure, seeded decision maker: shown every frame with its direction
and time, it says what arrives instead (drop, duplicate, delay, reorder, corrupt). Rules select frames by
COB-ID class (`bus.cob.classify`), node, direction and time window, firing per frame or in bursts; it
also holds the bus-off state. Every injection is counted and recorded, and the seed is in every failure
message: a failing run is replayed by seed. Transports: `FaultyBus` (a python-can `BusABC` wrapping any
bus; a timer thread releases delayed frames; bus-off raises `can.CanOperationError`) and `FaultLink`
(the virtual-time runtime's link). One frame at a time: same seed and frames, same injections.
"""

from __future__ import annotations

import heapq
import random
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import can

from bus.cob import classify
from bus.codec import Frame

Direction = Literal["to_drives", "to_master"]
TO_DRIVES: Direction = "to_drives"
TO_MASTER: Direction = "to_master"
ACTIONS = frozenset({"drop", "duplicate", "delay", "reorder", "corrupt"})
CORRUPTIONS = frozenset({"short", "long", "flip", "dlc"})
KINDS = frozenset(
    {"NMT", "SYNC", "TIME", "EMCY", "TPDO1", "RPDO1", "TPDO2", "RPDO2", "TPDO3", "RPDO3", "TPDO4", "RPDO4",
     "SDO_TX", "SDO_RX", "HEARTBEAT", "OTHER"}
)


@dataclass(frozen=True)
class FaultRule:
    """Which frames a fault hits and how.

    `kinds`/`nodes` empty = every class / every node; `direction` None = both. A rule fires on a matching
    frame with `probability`; with `burst` > 1 each firing starts a burst of that many consecutive matching
    frames; with `start_after` set the (single) burst starts deterministically after that many matching
    frames (probability is then ignored). `start_s`/`end_s` bound the active window (virtual or wall
    time, whatever clock the transport passes). `delay_s` for "delay"; `max_hold_s` for "reorder" (a held
    frame with no follower of the same COB-ID is released after it); `corruption` for "corrupt".
    """

    action: str
    kinds: frozenset[str] = frozenset()
    nodes: frozenset[int] = frozenset()
    direction: Direction | None = None
    probability: float = 0.0
    burst: int = 1
    start_after: int | None = None
    start_s: float | None = None
    end_s: float | None = None
    delay_s: float = 0.0
    max_hold_s: float = 0.005
    corruption: str = "flip"

    def __post_init__(self) -> None:
        def bad(name: str, value: object, why: str) -> ValueError:
            return ValueError(f"fault rule {self.action!r}: {name} = {value!r} {why}")

        if self.action not in ACTIONS:
            raise bad("action", self.action, f"is not one of {sorted(ACTIONS)}")
        object.__setattr__(self, "kinds", frozenset(self.kinds))
        object.__setattr__(self, "nodes", frozenset(self.nodes))
        unknown = self.kinds - KINDS
        if unknown:
            raise bad("kinds", sorted(unknown), f"are not COB-ID classes ({sorted(KINDS)})")
        if self.direction not in (None, TO_DRIVES, TO_MASTER):
            raise bad("direction", self.direction, "is not 'to_drives', 'to_master' or None")
        if not 0.0 <= self.probability <= 1.0:
            raise bad("probability", self.probability, "is not in [0, 1]")
        if isinstance(self.burst, bool) or not isinstance(self.burst, int) or self.burst < 1:
            raise bad("burst", self.burst, "is not an integer >= 1")
        if self.start_after is not None and (not isinstance(self.start_after, int) or self.start_after < 0):
            raise bad("start_after", self.start_after, "is not None or an integer >= 0")
        if self.delay_s < 0 or self.max_hold_s < 0:
            raise bad("delay_s/max_hold_s", (self.delay_s, self.max_hold_s), "must be >= 0")
        if self.corruption not in CORRUPTIONS:
            raise bad("corruption", self.corruption, f"is not one of {sorted(CORRUPTIONS)}")

    def matches(self, kind: str, node: int, direction: Direction, t: float) -> bool:
        if self.kinds and kind not in self.kinds:
            return False
        if self.nodes and node not in self.nodes:
            return False
        if self.direction is not None and direction != self.direction:
            return False
        if self.start_s is not None and t < self.start_s:
            return False
        return not (self.end_s is not None and t >= self.end_s)


# ---- convenience constructors ---------------------------------------------------------------------------
def _set(x: str | Iterable[str] | None) -> frozenset[str]:
    return frozenset() if x is None else frozenset([x]) if isinstance(x, str) else frozenset(x)


def _nodes(x: int | Iterable[int] | None) -> frozenset[int]:
    return frozenset() if x is None else frozenset([x]) if isinstance(x, int) else frozenset(x)


def drop(kinds: str | Iterable[str] | None = None, probability: float = 0.0, *,
         nodes: int | Iterable[int] | None = None, **kw: Any) -> FaultRule:
    return FaultRule("drop", _set(kinds), _nodes(nodes), probability=probability, **kw)


def duplicate(kinds: str | Iterable[str] | None = None, probability: float = 0.0, *,
              nodes: int | Iterable[int] | None = None, **kw: Any) -> FaultRule:
    return FaultRule("duplicate", _set(kinds), _nodes(nodes), probability=probability, **kw)


def delay(kinds: str | Iterable[str] | None = None, probability: float = 0.0, delay_s: float = 0.0, *,
          nodes: int | Iterable[int] | None = None, **kw: Any) -> FaultRule:
    return FaultRule("delay", _set(kinds), _nodes(nodes), probability=probability, delay_s=delay_s, **kw)


def reorder(kinds: str | Iterable[str] | None = None, probability: float = 0.0, *,
            nodes: int | Iterable[int] | None = None, **kw: Any) -> FaultRule:
    return FaultRule("reorder", _set(kinds), _nodes(nodes), probability=probability, **kw)


def corrupt(kinds: str | Iterable[str] | None = None, probability: float = 0.0, corruption: str = "flip", *,
            nodes: int | Iterable[int] | None = None, **kw: Any) -> FaultRule:
    return FaultRule("corrupt", _set(kinds), _nodes(nodes), probability=probability, corruption=corruption,
                     **kw)


# ---- the model ------------------------------------------------------------------------------------------
class Delivery(NamedTuple):
    """A frame that arrives `delay_s` after the moment the model was shown the original."""

    frame: Frame
    delay_s: float = 0.0


class Injection(NamedTuple):
    t: float
    action: str
    direction: Direction
    cob_id: int
    data: bytes


@dataclass
class _Held:
    frame: Frame
    deadline: float


@dataclass
class _RuleState:
    rng: random.Random
    seen: int = 0
    burst_left: int = 0
    fired: int = 0


@dataclass
class FaultModel:
    """Seeded fault decisions for a stream of frames (see the module docstring)."""

    rules: Sequence[FaultRule] = ()
    seed: int = 0
    bus_off_windows: Sequence[tuple[float, float]] = ()
    stats: Counter[tuple[str, str]] = field(default_factory=Counter)
    injections: list[Injection] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.rules = tuple(self.rules)
        self._states = [_RuleState(random.Random(self.seed * 7919 + i)) for i in range(len(self.rules))]
        self._held: dict[tuple[Direction, int], _Held] = {}
        self._bus_off = False
        self._bus_off_reason = ""
        self._stopped: set[int] = set()
        self.frames_seen = 0

    def __repr__(self) -> str:
        return f"FaultModel(seed={self.seed}, rules={len(self.rules)}, injected={dict(self.stats)})"

    def describe(self) -> str:
        """One line for failure messages: the seed to replay and what was injected."""
        counts = ", ".join(f"{a} {k}: {n}" for (a, k), n in sorted(self.stats.items())) or "nothing"
        return f"fault seed {self.seed} ({counts} injected over {self.frames_seen} frames)"

    def stop_rule(self, rule: FaultRule) -> None:
        """Stop applying `rule` from now on (e.g. a drive's heartbeat comes back)."""
        self._stopped.add(self.rules.index(rule))

    # ---- bus-off
    def set_bus_off(self, reason: str = "bus-off") -> None:
        self._bus_off = True
        self._bus_off_reason = reason

    def recover(self) -> None:
        self._bus_off = False

    def bus_off_at(self, t: float) -> bool:
        return self._bus_off or any(a <= t < b for a, b in self.bus_off_windows)

    def refuse(self, frame: Frame, t: float) -> str | None:
        """Why the master's controller refuses to send `frame` at `t` (bus-off), or None."""
        if self.bus_off_at(t):
            self.stats[("refused", classify(frame.cob_id).kind)] += 1
            self.injections.append(Injection(t, "refused", TO_DRIVES, frame.cob_id, bytes(frame.data)))
            return self._bus_off_reason or "bus-off"
        return None

    # ---- the decision
    def apply(self, frame: Frame, t: float, direction: Direction) -> list[Delivery]:
        """What arrives for one frame on the wire at `t`, in order (held frames it releases included)."""
        self.frames_seen += 1
        kind, node = classify(frame.cob_id)
        if direction == TO_MASTER and self.bus_off_at(t):
            self._record(t, "lost_bus_off", direction, frame, kind)
            return []
        out = self.release(t, direction)
        action: FaultRule | None = None
        for i, (rule, state) in enumerate(zip(self.rules, self._states, strict=True)):
            if i in self._stopped or not rule.matches(kind, node, direction, t):
                continue
            if self._fires(rule, state) and action is None:
                action = rule
        key = (direction, frame.cob_id)
        held = self._held.pop(key, None)
        if action is None:
            out.append(Delivery(frame))
        else:
            out += self._act(action, frame, t, direction, kind, key)
        if held is not None:
            out.append(Delivery(held.frame))  # the held frame goes after its follower: swapped
        return out

    def release(self, t: float, direction: Direction | None = None) -> list[Delivery]:
        """Held (reordered) frames whose follower did not come within `max_hold_s` of `t`."""
        out: list[Delivery] = []
        for key in [k for k, h in self._held.items() if h.deadline <= t and (direction in (None, k[0]))]:
            out.append(Delivery(self._held.pop(key).frame))
        return out

    def release_all(self, direction: Direction | None = None) -> list[tuple[Direction, Frame]]:
        keys = [k for k in self._held if direction in (None, k[0])]
        return [(k[0], self._held.pop(k).frame) for k in keys]

    def next_release(self) -> float | None:
        return min((h.deadline for h in self._held.values()), default=None)

    def _fires(self, rule: FaultRule, state: _RuleState) -> bool:
        state.seen += 1
        draw = state.rng.random()  # one draw per matching frame, fired or not: stable sequences per seed
        if state.burst_left > 0:
            state.burst_left -= 1
            return True
        if rule.start_after is not None:
            if state.fired == 0 and state.seen > rule.start_after:
                state.fired += 1
                state.burst_left = rule.burst - 1
                return True
            return False
        if rule.probability > 0.0 and draw < rule.probability:
            state.fired += 1
            state.burst_left = rule.burst - 1
            return True
        return False

    def _act(self, rule: FaultRule, frame: Frame, t: float, direction: Direction, kind: str,
             key: tuple[Direction, int]) -> list[Delivery]:
        self._record(t, rule.action, direction, frame, kind)
        if rule.action == "drop":
            return []
        if rule.action == "duplicate":
            return [Delivery(frame), Delivery(frame)]
        if rule.action == "delay":
            return [Delivery(frame, rule.delay_s)]
        if rule.action == "reorder":
            self._held[key] = _Held(frame, t + rule.max_hold_s)
            return []
        return [Delivery(self._corrupt(frame, rule.corruption, self._states[self.rules.index(rule)].rng))]

    @staticmethod
    def _corrupt(frame: Frame, how: str, rng: random.Random) -> Frame:
        data = bytes(frame.data)
        if how == "short":
            return Frame(frame.cob_id, data[:-1] if data else data)
        if how == "long":
            return Frame(frame.cob_id, data + bytes([rng.randrange(256)]) if len(data) < 8 else data)
        if how == "dlc":
            n = rng.randrange(9)
            while n == len(data):
                n = rng.randrange(9)
            return Frame(frame.cob_id, bytes(rng.randrange(256) for _ in range(n)))
        if not data:
            return Frame(frame.cob_id, bytes([rng.randrange(256)]))
        i = rng.randrange(len(data) * 8)
        b = bytearray(data)
        b[i // 8] ^= 1 << (i % 8)
        return Frame(frame.cob_id, bytes(b))

    def _record(self, t: float, action: str, direction: Direction, frame: Frame, kind: str) -> None:
        self.stats[(action, kind)] += 1
        self.injections.append(Injection(t, action, direction, frame.cob_id, bytes(frame.data)))

    def injected(self, action: str, kind: str | None = None, direction: Direction | None = None) -> list[Injection]:
        return [i for i in self.injections if i.action == action
                and (kind is None or classify(i.cob_id).kind == kind)
                and (direction is None or i.direction == direction)]


# ---- transport 1: the virtual-time runtime's Link ------------------------------------------------------
class FaultLink:
    """`streamer.runtime.virtual.Link` over a FaultModel: frames or (frame, arrival time) pairs."""

    def __init__(self, model: FaultModel):
        self.model = model

    def _out(self, deliveries: Sequence[Delivery], t: float) -> list[Frame | tuple[Frame, float]]:
        return [d.frame if d.delay_s <= 0 else (d.frame, t + d.delay_s) for d in deliveries]

    def accept(self, frame: Frame, t: float) -> str | None:
        return self.model.refuse(frame, t)

    def to_drives(self, frame: Frame, t: float) -> list[Frame | tuple[Frame, float]]:
        return self._out(self.model.apply(frame, t, TO_DRIVES), t)

    def to_master(self, frame: Frame, t: float) -> list[Frame | tuple[Frame, float]]:
        return self._out(self.model.apply(frame, t, TO_MASTER), t)

    def release(self, t: float) -> tuple[list[Frame], list[Frame]]:
        """Held frames due by `t`: (to the drives, to the master)."""
        return ([d.frame for d in self.model.release(t, TO_DRIVES)],
                [d.frame for d in self.model.release(t, TO_MASTER)])


# ---- transport 2: a python-can bus ----------------------------------------------------------------------
def _to_frame(msg: can.Message) -> Frame:
    return Frame(msg.arbitration_id, bytes(msg.data))


def _to_msg(frame: Frame, like: can.Message | None = None, timestamp: float | None = None) -> can.Message:
    """`frame` as a python-can message with the kind of `like` (the message it was made from: 11- or 29-bit
    identifier, data or remote frame), its channel and direction; an 11-bit data frame without one."""
    remote = like is not None and like.is_remote_frame
    return can.Message(
        arbitration_id=frame.cob_id,
        data=None if remote else frame.data,
        dlc=like.dlc if like is not None and remote else None,
        is_extended_id=like.is_extended_id if like is not None else False,
        is_remote_frame=remote,
        timestamp=timestamp if timestamp is not None else (like.timestamp if like is not None else 0.0),
        is_rx=like.is_rx if like is not None else True,
        channel=like.channel if like is not None else None,
    )


class FaultyBus(can.BusABC):
    """A python-can bus that injects the faults of a `FaultModel` into another bus's traffic.

    `send` -> the model (direction "to_drives" when `master_side`) -> the inner bus, at once or later;
    received frames -> the model ("to_master") -> `recv`. Own frames echoed by the inner bus
    (`receive_own_messages`) pass untouched. While the model says bus-off, `send` raises `can.CanOperationError`
    and received frames are lost. The wrapper owns the inner bus: `shutdown` closes both.
    """

    def __init__(self, inner: can.BusABC, model: FaultModel, *, master_side: bool = True,
                 clock: Callable[[], float] = time.time, **kwargs: Any):
        self.inner = inner
        self.model = model
        self.clock = clock
        self._tx_dir: Direction = TO_DRIVES if master_side else TO_MASTER
        self._rx_dir: Direction = TO_MASTER if master_side else TO_DRIVES
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._timers: list[tuple[float, int, str, Frame, can.Message | None]] = []
        self._seq = 0
        self._rx_ready: list[can.Message] = []
        self._closing = False
        self.errors: list[Exception] = []
        self._echoes: Counter[tuple[int, bytes]] = Counter()
        self.channel_info = f"faulty({getattr(inner, 'channel_info', inner)})"
        self._thread = threading.Thread(target=self._run_timers, name="faulty-bus-timers", daemon=True)
        super().__init__(channel=self.channel_info, **kwargs)
        self._thread.start()

    # ---- convenience
    def bus_off(self, reason: str = "bus-off") -> None:
        self.model.set_bus_off(reason)

    def recover(self) -> None:
        self.model.recover()

    # ---- BusABC
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        t = self.clock()
        frame = _to_frame(msg)
        with self._lock:
            reason = self.model.refuse(frame, t)
            if reason is not None:
                raise can.CanOperationError(f"{reason}: frame 0x{frame.cob_id:03X} not sent")
            deliveries = self.model.apply(frame, t, self._tx_dir)
            now = [d.frame for d in deliveries if d.delay_s <= 0]
            for d in deliveries:
                if d.delay_s > 0:
                    self._schedule(t + d.delay_s, "tx", d.frame, msg)
            self._wake_for_holds()
        for f in now:
            self._sent(f)
            self.inner.send(_to_msg(f, msg), timeout)

    def _sent(self, frame: Frame) -> None:
        with self._lock:
            self._echoes[(frame.cob_id, frame.data)] += 1

    def _is_own_echo(self, msg: can.Message) -> bool:
        """Our own frame, received back (python-can marks it is_rx False; on socketcan so is every frame
        from this host, so only a frame we sent and have not seen back yet counts as an echo)."""
        if msg.is_rx:
            return False
        key = (msg.arbitration_id, bytes(msg.data))
        with self._lock:
            if self._echoes[key] > 0:
                self._echoes[key] -= 1
                return True
        return False

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else self.clock() + timeout
        while True:
            with self._lock:
                if self._rx_ready:
                    return self._rx_ready.pop(0), False
            left = None if deadline is None else max(0.0, deadline - self.clock())
            msg = self.inner.recv(timeout=left if left is None else min(left, 0.05))
            if msg is not None:
                if msg.is_error_frame or msg.is_remote_frame or self._is_own_echo(msg):
                    return msg, False  # error frames and our own echo: untouched
                t = self.clock()
                with self._lock:
                    for d in self.model.apply(_to_frame(msg), t, self._rx_dir):
                        if d.delay_s <= 0:
                            self._rx_ready.append(_to_msg(d.frame, msg))
                        else:
                            self._schedule(t + d.delay_s, "rx", d.frame, msg)
                    self._wake_for_holds()
                continue
            if deadline is not None and self.clock() >= deadline:
                return None, False

    def shutdown(self) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)
        super().shutdown()
        self.inner.shutdown()

    @property
    def state(self) -> can.BusState:
        return can.BusState.ERROR if self.model.bus_off_at(self.clock()) else can.BusState.ACTIVE

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        self.inner.state = new_state

    # ---- timers (delayed frames, reorder holds without a follower)
    def _schedule(self, due: float, where: str, frame: Frame, like: can.Message | None) -> None:
        self._seq += 1
        heapq.heappush(self._timers, (due, self._seq, where, frame, like))
        self._cond.notify_all()

    def _wake_for_holds(self) -> None:
        if self.model.next_release() is not None:
            self._cond.notify_all()

    def _run_timers(self) -> None:
        while True:
            sends: list[can.Message] = []
            with self._cond:
                if self._closing:
                    return
                now = self.clock()
                while self._timers and self._timers[0][0] <= now:
                    _, _, where, frame, like = heapq.heappop(self._timers)
                    if where == "tx":
                        sends.append(_to_msg(frame, like, now))
                    else:
                        self._rx_ready.append(_to_msg(frame, like, now))
                for d in self.model.release(now, self._tx_dir):
                    sends.append(_to_msg(d.frame))
                for d in self.model.release(now, self._rx_dir):
                    self._rx_ready.append(_to_msg(d.frame, None, now))
                if not sends:
                    nexts = [x for x in (self._timers[0][0] if self._timers else None, self.model.next_release())
                             if x is not None]
                    wait = min(nexts) - now if nexts else 0.05
                    self._cond.wait(timeout=max(0.0005, min(wait, 0.05)))
                    continue
            for m in sends:
                try:
                    self._sent(_to_frame(m))
                    self.inner.send(m)
                except can.CanError as e:  # kept, not swallowed: a test can assert on `errors`
                    self.errors.append(e)


__all__ = [
    "TO_DRIVES",
    "TO_MASTER",
    "Delivery",
    "Direction",
    "FaultLink",
    "FaultModel",
    "FaultRule",
    "FaultyBus",
    "Injection",
    "corrupt",
    "delay",
    "drop",
    "duplicate",
    "reorder",
]
