"""bus.codec: round trips, total decoders (a value or ProtocolError, nothing else), the CiA 402 table."""

from __future__ import annotations

import contextlib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bus import cob, codec
from bus.codec import Cia402State as S
from bus.codec import Command, Internal
from bus.errors import BusError, ProtocolError
from bus.events import Bootup, BufferStatus, Emcy, PositionFeedback
from bus.families import EPOS_IPM

u16 = st.integers(0, 0xFFFF)
payload = st.binary(min_size=0, max_size=8)


# ---- buffer status ------------------------------------------------------------------------------------
@given(st.builds(codec.BufferStatusWord, *[st.booleans()] * 10))
def test_buffer_status_round_trip(status: codec.BufferStatusWord) -> None:
    assert codec.decode_buffer_status(status.encode()) == status


@given(u16)
def test_buffer_status_decode_is_total(word: int) -> None:
    try:
        status = codec.decode_buffer_status(word)
    except ProtocolError:
        assert word & codec.BS_RESERVED
    else:
        assert status.encode() == word


def test_buffer_status_bits_of_seed_table_4_35() -> None:
    s = codec.decode_buffer_status(0xC101)
    assert s.ip_active and s.buffer_enabled and s.underflow_error and s.underflow_warning
    assert s.any_error and s.any_warning and not s.overflow_error
    with pytest.raises(ProtocolError):
        codec.decode_buffer_status(0x0010)
    with pytest.raises(ProtocolError):
        codec.decode_buffer_status(0x10000)


# ---- CiA 402 ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("sw", "state"), [
    (0x0000, S.NOT_READY_TO_SWITCH_ON), (0x0240, S.SWITCH_ON_DISABLED), (0x0221, S.READY_TO_SWITCH_ON),
    (0x0223, S.SWITCHED_ON), (0x0227, S.OPERATION_ENABLED), (0x1637, S.OPERATION_ENABLED),
    (0x0207, S.QUICK_STOP_ACTIVE), (0x021F, S.FAULT_REACTION_ACTIVE), (0x0208, S.FAULT), (0x0228, S.FAULT),
])
def test_statusword_to_state(sw: int, state: S) -> None:
    assert codec.state_from_statusword(sw) == state


@given(u16)
def test_statusword_decode_is_total(sw: int) -> None:
    try:
        state = codec.state_from_statusword(sw)
    except ProtocolError:
        return
    assert codec.state_from_statusword(state.statusword_bits | (sw & ~0x6F)) == state


def test_unknown_statusword_pattern_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError):
        codec.state_from_statusword(0x0001)
    with pytest.raises(BusError):  # ProtocolError is a BusError with code PROTOCOL ...
        codec.state_from_statusword(0x0003)
    with pytest.raises(ValueError):  # ... and a ValueError
        codec.state_from_statusword(0x0005)


@given(u16)
def test_every_controlword_is_one_command(cw: int) -> None:
    command = codec.decode_command(cw)
    assert isinstance(command, Command)
    if cw & 0x80:
        assert command == Command.FAULT_RESET


@pytest.mark.parametrize("command", list(Command))
@pytest.mark.parametrize("enable_ip", [False, True])
@pytest.mark.parametrize("halt", [False, True])
def test_controlword_round_trip(command: Command, enable_ip: bool, halt: bool) -> None:
    cw = codec.controlword(command, enable_ip=enable_ip, halt=halt)
    assert codec.decode_command(cw) == command
    assert bool(cw & codec.CW_ENABLE_IP) == enable_ip and bool(cw & codec.CW_HALT) == halt


def test_seed_controlwords() -> None:
    assert codec.decode_command(0x0006) == Command.SHUTDOWN
    assert codec.decode_command(0x000F) == Command.ENABLE_OPERATION
    assert codec.decode_command(0x001F) == Command.ENABLE_OPERATION
    assert codec.decode_command(0x000B) == Command.QUICK_STOP
    assert codec.decode_command(0x0080) == Command.FAULT_RESET
    assert codec.decode_command(0x0000) == Command.DISABLE_VOLTAGE
    assert Command.disable_operation() == Command.SWITCH_ON


@given(st.sampled_from(list(S)), st.sampled_from([*Command, *Internal]))
def test_transition_table_answers_or_raises(state: S, trigger: codec.Trigger) -> None:
    try:
        new = codec.next_state(state, trigger)
    except codec.InvalidTransition as e:
        assert (state, trigger) not in codec.TRANSITIONS
        assert e.state == state and e.trigger == trigger
    else:
        assert isinstance(new, S)


def test_transition_table_cia402() -> None:
    path = [(S.SWITCH_ON_DISABLED, Command.SHUTDOWN, S.READY_TO_SWITCH_ON),
            (S.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION, S.OPERATION_ENABLED),
            (S.OPERATION_ENABLED, Command.QUICK_STOP, S.QUICK_STOP_ACTIVE),
            (S.QUICK_STOP_ACTIVE, Internal.QUICK_STOP_DONE, S.SWITCH_ON_DISABLED),
            (S.OPERATION_ENABLED, Internal.FAULT_DETECTED, S.FAULT_REACTION_ACTIVE),
            (S.FAULT_REACTION_ACTIVE, Internal.FAULT_REACTION_DONE, S.FAULT),
            (S.FAULT, Command.FAULT_RESET, S.SWITCH_ON_DISABLED)]
    for state, trigger, new in path:
        assert codec.next_state(state, trigger) == new
    with pytest.raises(codec.InvalidTransition):
        codec.next_state(S.SWITCH_ON_DISABLED, Command.ENABLE_OPERATION)
    with pytest.raises(codec.InvalidTransition):
        codec.next_state(S.FAULT, Internal.FAULT_DETECTED)
    with pytest.raises(TypeError):
        codec.TRANSITIONS[(S.FAULT, Command.SHUTDOWN)] = S.FAULT  # type: ignore[index]


# ---- EMCY, NMT, SYNC, heartbeat ----------------------------------------------------------------------------
@given(u16, st.integers(0, 255), st.binary(min_size=0, max_size=5))
def test_emcy_round_trip(code: int, register: int, manufacturer: bytes) -> None:
    msg = codec.decode_emcy(codec.encode_emcy(code, register, manufacturer))
    assert msg == codec.EmcyMessage(code, register, manufacturer.ljust(5, b"\x00"))


@given(payload)
def test_emcy_decode_is_total(data: bytes) -> None:
    try:
        msg = codec.decode_emcy(data)
    except ProtocolError:
        assert len(data) != 8
    else:
        assert codec.encode_emcy(*msg) == data


def test_emcy_manufacturer_bytes_carry_the_buffer_status() -> None:
    data = codec.encode_emcy(0x8782, 0x21, codec.emcy_manufacturer_bytes(0xC101))
    assert data[3:5] == b"\x01\xc1"
    msg = codec.decode_emcy(data)
    assert msg.buffer_status == 0xC101 and msg.name == "ip buffer underflow/overflow"
    assert codec.decode_emcy(codec.encode_emcy(0, 0)).is_error_reset
    with pytest.raises(ValueError):
        codec.encode_emcy(0x10000, 0)


@given(st.sampled_from(list(codec.NmtCommand)), st.integers(0, 127))
def test_nmt_round_trip(command: codec.NmtCommand, node: int) -> None:
    frame = codec.nmt_frame(command, node)
    assert frame.cob_id == 0 and codec.decode_nmt(frame.data) == (command, node)


@given(payload)
def test_nmt_decode_is_total(data: bytes) -> None:
    try:
        command, node = codec.decode_nmt(data)
    except ProtocolError:
        return
    assert codec.nmt_frame(command, node).data == data


@given(st.sampled_from(list(codec.NmtState)), st.integers(1, 127))
def test_heartbeat_round_trip(state: codec.NmtState, node: int) -> None:
    frame = codec.heartbeat_frame(node, state)
    assert frame.cob_id == 0x700 + node and codec.decode_heartbeat(frame.data) == state


@given(payload)
def test_heartbeat_and_sync_decode_are_total(data: bytes) -> None:
    for decode in (codec.decode_heartbeat, codec.decode_sync):
        with contextlib.suppress(ProtocolError):
            decode(data)


def test_sync_frames() -> None:
    assert codec.sync_frame() == codec.Frame(0x80, b"")
    assert codec.decode_sync(codec.sync_frame(7).data) == 7
    assert codec.decode_sync(b"") is None
    with pytest.raises(ValueError):
        codec.sync_frame(0)


# ---- frame bits, TPDOs, frame -> event -------------------------------------------------------------------
def test_frame_bits_worst_case_stuffing() -> None:
    assert codec.frame_bits(0) == 55
    assert codec.frame_bits(8) == 135
    assert [codec.frame_bits(n) for n in range(9)] == [47 + 8 * n + (34 + 8 * n - 1) // 4 for n in range(9)]
    assert codec.bus_load({8: 1000.0}, 1_000_000) == pytest.approx(0.135)
    for bad in (-1, 9, 2.0, True):
        with pytest.raises(ValueError):
            codec.frame_bits(bad)  # type: ignore[arg-type]


@given(st.integers(0, 0xFFFF), st.integers(0, 64),
       st.integers(-(2**31), 2**31 - 1), st.integers(-(2**31), 2**31 - 1))
def test_tpdo_round_trip(sw: int, free: int, actual: int, demand: int) -> None:
    t1 = codec.decode_tpdo1(cob.pack_tpdo1(sw, free))
    assert t1 == (sw, free)
    assert t1.buffer_status == (codec.BS_IP_ACTIVE if sw & codec.SW_IP_ACTIVE else 0)
    assert codec.decode_tpdo2(cob.pack_tpdo2(actual, demand)) == (actual, demand)


@given(st.integers(0, 0x7FF), payload, st.integers(0, 1000))
def test_frame_to_event_parses_or_raises_protocol_error(cob_id: int, data: bytes, sync: int) -> None:
    nodes = frozenset(range(1, 128))
    try:
        event = EPOS_IPM.frame_to_event(cob_id, data, 1.5, nodes, sync)
    except ProtocolError:
        return
    kind, node = cob.classify(cob_id)
    if event is None:
        assert kind not in ("TPDO1", "TPDO2", "EMCY") or node not in nodes
        return
    assert isinstance(event, BufferStatus | PositionFeedback | Emcy | Bootup)
    assert event.node == node and event.t == 1.5
    if isinstance(event, BufferStatus | PositionFeedback):
        assert event.sync_count == sync


def test_frame_to_event_ignores_other_nodes_and_maps_each_kind() -> None:
    nodes = frozenset({3})
    assert EPOS_IPM.frame_to_event(0x184, b"\x00" * 8, 0.0, nodes) is None
    ev = EPOS_IPM.frame_to_event(0x183, cob.pack_tpdo1(0x1637, 40), 2.0, nodes, 9)
    assert ev == BufferStatus(3, 0x1637, 0x8000, 40, 2.0, 9)  # ip mode active mirrored from the statusword
    ev = EPOS_IPM.frame_to_event(0x283, cob.pack_tpdo2(-5, 7), 2.0, nodes)
    assert ev == PositionFeedback(3, -5, 7, 2.0)
    ev = EPOS_IPM.frame_to_event(0x83, codec.encode_emcy(0x8611, 0x21), 2.0, nodes)
    assert isinstance(ev, Emcy) and ev.code == 0x8611 and ev.register == 0x21
    assert EPOS_IPM.frame_to_event(0x703, b"\x00", 2.0, nodes) == Bootup(3, 2.0)
    assert EPOS_IPM.frame_to_event(0x703, b"\x05", 2.0, nodes) is None
    with pytest.raises(ProtocolError):
        EPOS_IPM.frame_to_event(0x183, b"\x00" * 7, 2.0, nodes)
