"""The simulated drive's data recorder (issue 16 section 1) against seed 004's tables.

The first tests drive it the way an external master would: a stock canopen `RemoteNode` (not the
product's recorder code) on a python-can virtual bus against `bus.sim.node.SimulatedCell`, in real time,
over SDO (expedited writes, segmented and block upload of 0x201B). The rest run the `EposDrive` in
virtual time, where every timing branch is reachable: sub-stepping, the triggers, both drive clocks. The
recorder is maxon's: its objects are the EPOS family's only, and a drive without one (`recorder` None)
runs, faults and halts as before.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass

import canopen
import pytest
from bus_testkit import VDrive, make_axis, make_cell, ramp_records, remote_network, unique_channel, wait_until

from bus import codec
from bus.sim import od as odm
from bus.sim.data_recorder import (
    STATUS_RUNNING,
    STATUS_TRIGGERED,
    TRIGGER_END,
    TRIGGER_ERROR,
    TRIGGER_INPUT,
    TRIGGER_MOVEMENT,
    max_samples,
    ring_starts,
    substep_units,
)
from bus.sim.eds import EDS_PATH
from bus.sim.node import SdoBlockUploadServer, SimulatedCell
from bus.sim.od import SdoAbort
from planner.encoding import record
from planner.readings import SimDriveOptions

SEG_MS = 50
# the stock client's 0.3 s SDO timeout against a drive thread on a loaded 2-core machine: a segmented upload
# of 0x201B is ~150 request/response turns, any of which may wait that long when the machine is busy
SDO_TIMEOUT_S = 2.0


@dataclass
class Rig:
    sim: SimulatedCell
    net: canopen.Network
    node: canopen.RemoteNode

    def configure(self, variables: list[tuple[int, int]], *, period: int = 10, preceding: int = 0,
                  triggers: int = 0) -> None:
        sdo = self.node.sdo
        sdo[0x2010].raw = 0
        sdo[0x2011].raw = triggers
        sdo[0x2012].raw = period
        sdo[0x2013].raw = preceding
        sdo[0x2014].raw = len(variables)
        for k, (index, sub) in enumerate(variables, start=1):
            sdo[0x2015][k].raw = index
            sdo[0x2016][k].raw = sub

    def status(self) -> int:
        return int(self.node.sdo[0x2017].raw)

    def words(self, block: bool = False) -> list[int]:
        if block:
            with self.node.sdo.open(0x201B, 0, "rb", block_transfer=True) as f:
                data = f.read()
        else:
            data = self.node.sdo.upload(0x201B, 0)
        return [w for (w,) in struct.iter_unpack("<H", data)]

    def start_movement(self, prime: int = 4) -> list[tuple[int, int, int]]:
        """Seed 000 table 4-39 over SDO up to controlword 0x001F (ip mode active); the records left."""
        sdo = self.node.sdo
        records = ramp_records(20_000, cruise_rpm=600, seg_ms=SEG_MS)
        sdo[0x6060].raw = 7
        sdo[0x6040].raw = 0x0006
        sdo[0x6040].raw = 0x000F
        sdo[0x60C4][6].raw = 0
        sdo[0x60C4][6].raw = 1
        for r in records[:prime]:
            sdo[0x20C1].raw = int.from_bytes(record.pack(r), "little")
        sdo[0x6040].raw = 0x001F
        return records[prime:]


@pytest.fixture
def rig() -> Iterator[Rig]:
    channel = unique_channel("recorder")
    cell = make_cell(1, sync_period_ms=10, channel=channel)
    sim = SimulatedCell(cell, sync_gap_factor=5.0)
    sim.start()
    try:
        with remote_network(channel) as net:
            node = net.add_node(1, str(EDS_PATH))
            node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
            net.sync.start(0.010)
            yield Rig(sim, net, node)
    finally:
        sim.stop()


# ---- seed 004 through a stock canopen SDO client -------------------------------------------------------------
@pytest.mark.parametrize(("variables", "words", "samples"), [
    ([(0x6041, 0)], 1, 512),  # 1 x 16-bit
    ([(0x6061, 0)], 1, 512),  # 1 x 8-bit: takes a word
    ([(0x6064, 0)], 2, 256),  # 1 x 32-bit
    ([(0x6041, 0), (0x6064, 0)], 3, 170),  # 1 x 16-bit + 1 x 32-bit
    ([(0x6062, 0), (0x6064, 0), (0x606C, 0), (0x60F4, 0)], 8, 64),  # 4 x 32-bit
])
def test_max_samples_per_seed_004_table_4(rig: Rig, variables: list[tuple[int, int]], words: int,
                                          samples: int) -> None:
    rig.configure(variables)
    assert rig.node.sdo[0x2018].raw == samples == max_samples(words)


def test_max_samples_is_zero_for_a_variable_the_recorder_cannot_take(rig: Rig) -> None:
    rig.configure([(0x20C1, 0)])  # the 64-bit, write-only PVT record
    assert rig.node.sdo[0x2018].raw == 0
    with pytest.raises(canopen.SdoAbortedError) as e:
        rig.node.sdo[0x2010].raw = 1
    assert e.value.code == odm.ABORT_INVALID_VALUE
    assert rig.status() == 0


def test_ring_buffers_of_two_16_bit_and_one_32_bit_variable(rig: Rig) -> None:
    """Seed 004 "Data Buffer Segmentation" (2 x 16-bit, 1 x 32-bit): StartRingBuffer1 = 0,
    StartRingBuffer2 = MaxNbOfSamples * 1, StartRingBuffer3 = MaxNbOfSamples * (1 + 1); a 32-bit sample
    takes two words, low word first. Three objects with known constant values make every ring visible."""
    sdo = rig.node.sdo
    sdo[0x20C4][3].raw = 61  # overflow watermark, U16
    sdo[0x6065].raw = 0x12345678  # following error window, U32
    rig.configure([(0x2013, 0), (0x20C4, 3), (0x6065, 0)], period=1, preceding=0x0102)  # 0x2013 records itself
    assert sdo[0x2018].raw == 128
    assert ring_starts([1, 1, 2], 128) == (0, 128, 256)
    sdo[0x2010].raw = 1
    assert wait_until(lambda: rig.sim.model(1).recorder.samples_taken >= 128, 3.0)
    sdo[0x2010].raw = 0
    words = rig.words()
    assert len(words) == 512
    assert words[0:128] == [0x0102] * 128  # ring 1 from word 0
    assert words[128:256] == [61] * 128  # ring 2 from MaxNbOfSamples * 1
    assert words[256:512] == [0x5678, 0x1234] * 128  # ring 3 from MaxNbOfSamples * 2, two words a sample
    assert rig.words(block=True) == words  # block upload gives the same bytes


def test_status_bits_through_one_single_trigger_cycle(rig: Rig) -> None:
    """Seed 004 table 3 and "Data Recorder Overview": stopped -> waiting (running) -> triggered
    (running, triggered) -> stopped by itself when full (triggered kept until the next start)."""
    rig.configure([(0x6062, 0)], period=50, preceding=10, triggers=TRIGGER_MOVEMENT)
    assert rig.status() == 0
    rig.node.sdo[0x2010].raw = 1
    assert rig.status() == STATUS_RUNNING
    rig.sim.check()
    assert wait_until(lambda: rig.sim.model(1).recorder.samples_taken >= 15, 2.0)
    assert rig.status() == STATUS_RUNNING  # samples go round the ring: no trigger yet
    rig.start_movement()
    assert rig.status() == STATUS_RUNNING | STATUS_TRIGGERED  # full only 246 samples (1.23 s) later
    assert wait_until(lambda: rig.status() == STATUS_TRIGGERED, 5.0)  # stopped by itself, triggered kept
    assert rig.node.sdo[0x2010].raw == 1  # reads back as written
    rig.node.sdo[0x2010].raw = 1  # start again: waiting, not triggered
    assert rig.status() == STATUS_RUNNING
    rig.node.sdo[0x2010].raw = 0
    assert rig.status() == 0


def test_preceding_samples_put_the_trigger_at_the_right_sample(rig: Rig) -> None:
    """0x2013 = P: the vector (unwrapped from 0x2019) holds P samples before the trigger's; the statusword's
    ip-active bit (12) rises in the first sample after it (the trigger's sample is taken at the trigger
    instant, before the movement starts)."""
    preceding = 30
    rig.configure([(0x6041, 0)], period=10, preceding=preceding, triggers=TRIGGER_MOVEMENT)
    rig.node.sdo[0x2010].raw = 1
    assert wait_until(lambda: rig.sim.model(1).recorder.samples_taken >= 3 * preceding, 2.0)
    rig.start_movement()
    assert wait_until(lambda: rig.status() == STATUS_TRIGGERED, 2.0)
    samples, offset = rig.node.sdo[0x2018].raw, rig.node.sdo[0x2019].raw
    ring = rig.words(block=True)
    vector = [ring[(offset + k) % samples] for k in range(samples)]
    active = [bool(w & codec.SW_IP_ACTIVE) for w in vector]
    assert active.index(True) == preceding + 1
    assert not any(active[:preceding + 1]) and all(active[preceding + 1:preceding + 20])
    rec = rig.sim.model(1).recorder
    assert rec.trigger_kind == "movement start"
    assert (offset + preceding) % samples == (rec.trigger_sample or 0) % samples


def test_segmented_upload_where_the_drive_has_no_block_upload() -> None:
    """A drive without block upload (canopen's own SdoServer answers a block request as a normal upload):
    the product's `Recorder` falls back to segmented upload, with the same bytes."""
    from streamer.recording.drive import RecordRequest, parse_variable
    from streamer.recording.recorder_client import Recorder

    channel = unique_channel("recorder-noblock")
    cell = make_cell(1, sync_period_ms=10, channel=channel)
    with SimulatedCell(cell, block_upload=False, sync_gap_factor=5.0) as sim, remote_network(channel) as net:
        net.sync.start(0.010)
        rec = Recorder.over(net, 1)
        net[1].sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        rec.configure(RecordRequest((parse_variable("position_actual"),), trigger="continuous", period_ms=1.0))
        rec.arm()
        assert wait_until(lambda: sim.model(1).recorder.samples_taken >= 10, 2.0)
        rec.stop()
        first = rec.read()
        assert rec.last_upload == "segmented" and rec.block is False
        assert first.samples == 256
        assert rec.upload() == sim.model(1).recorder.buffer()


# ---- virtual time ------------------------------------------------------------------------------------------
def drive(**options: object) -> VDrive:
    d = VDrive(options=SimDriveOptions(**options)) if options else VDrive()  # type: ignore[arg-type]
    d.enable()
    return d


def configure(d: VDrive, variables: list[tuple[int, int]], *, period: int = 10, preceding: int = 0,
              triggers: int = 0, start: bool = True) -> None:
    d.sdo(0x2011, 0, triggers)
    d.sdo(0x2012, 0, period)
    d.sdo(0x2013, 0, preceding)
    d.sdo(0x2014, 0, len(variables))
    for k, (index, sub) in enumerate(variables, start=1):
        d.sdo(0x2015, k, index)
        d.sdo(0x2016, k, sub)
    if start:
        d.sdo(0x2010, 0, 1)


def vector(d: VDrive, var: int = 0) -> list[int]:
    """Variable `var` (32-bit variables only before it... here: every variable 32-bit) unwrapped from 0x2019."""
    m = d.model
    samples, offset = m.sdo_read(0x2018, 0), m.sdo_read(0x2019, 0)
    data = m.read_domain(0x201B, 0)
    ring = [v for (v,) in struct.iter_unpack("<i", data[var * 4 * samples:(var + 1) * 4 * samples])]
    return [ring[(offset + k) % samples] for k in range(samples)]


def test_trigger_between_two_samples_takes_the_next_sample() -> None:
    """Period 3 ms, movement 10 ms after the start: the trigger's sample is the one at 12 ms (the first at
    or after the trigger), and it already shows ip mode active."""
    d = drive()
    configure(d, [(0x6041, 0)], period=30, preceding=2, triggers=TRIGGER_MOVEMENT)
    d.start(ramp_records(5_000), prime=4)  # one SYNC (10 ms) later the controlword applies
    d.sync(40)
    rec = d.model.recorder
    assert rec.trigger_sample == 4  # samples at 0, 3, 6, 9 ms were before the trigger; 12 ms is its sample
    m = d.model
    samples, offset = m.sdo_read(0x2018, 0), m.sdo_read(0x2019, 0)
    words = [w for (w,) in struct.iter_unpack("<H", m.read_domain(0x201B, 0))]
    vec = [words[(offset + k) % samples] for k in range(samples)]
    assert [bool(w & codec.SW_IP_ACTIVE) for w in vec[:4]] == [False, False, True, True]


def run_move(d: VDrive) -> None:
    pending = d.start(ramp_records(30_000, cruise_rpm=900, seg_ms=10), prime=6)
    d.run(pending)
    d.sync(5)


def test_a_recording_at_whole_ticks_leaves_the_simulation_bit_identical() -> None:
    plain, recorded = drive(), drive()
    configure(recorded, [(0x6064, 0)], period=20, triggers=0)
    run_move(plain)
    run_move(recorded)
    assert recorded.model.recorder.active and recorded.model.recorder.samples_taken > 100
    assert recorded.model.position_actual_exact == plain.model.position_actual_exact
    assert recorded.model.counters.ticks == plain.model.counters.ticks


def feed(d: VDrive, pending: list[tuple[int, int, int]], syncs: int) -> None:
    for _ in range(syncs):
        while pending and d.model.fifo_fill < 8:
            d.record(*pending.pop(0))
        d.sync()


def test_sub_ms_periods_sub_step_the_plant() -> None:
    """At 0.1 ms the position actual moves between the samples of one 1 ms tick while the demand (the
    interpolator's, 1 ms) holds; at the ticks the sub-stepped plant agrees with the 1 ms plant."""
    assert substep_units(1) == 1 and substep_units(5) == 5 and substep_units(3) == 1 and substep_units(15) == 5
    plain, fine = drive(), drive()
    records = ramp_records(60_000, cruise_rpm=900, seg_ms=10)
    pendings = {}
    for d in (plain, fine):
        pendings[id(d)] = d.start(records, prime=6)
        feed(d, pendings[id(d)], 30)  # 300 ms: at speed
    configure(fine, [(0x6062, 0), (0x6064, 0)], period=1, triggers=0)
    for d in (plain, fine):
        feed(d, pendings[id(d)], 2)  # 20 ms = 200 samples at 0.1 ms
    fine.sdo(0x2010, 0, 0)
    taken = fine.model.recorder.samples_taken
    assert taken == 201
    demand, actual = vector(fine, 0), vector(fine, 1)
    assert len(demand) == 128
    first = taken - 128  # the sample number of vector[0] (sample 0 at the start, on a tick boundary)
    steps = [k for k in range(1, 128) if actual[k] != actual[k - 1]]
    assert len(steps) > 100  # ~12 counts per 0.1 ms at 900 rpm
    changes = [first + k for k in range(1, 128) if demand[k] != demand[k - 1]]
    assert len(changes) == 12 and all(n % 10 == 1 for n in changes)  # the demand steps once per 1 ms tick
    assert plain.model.counters.ticks == fine.model.counters.ticks
    assert abs(plain.model.position_actual_exact - fine.model.position_actual_exact) < 1.0


@pytest.mark.parametrize("options", [{}, {"clock": "own", "clock_drift_ppm": 400.0}],
                         ids=["sync-locked", "own-clock"])
def test_samples_follow_the_drive_ticks_in_both_clock_modes(options: dict[str, object]) -> None:
    """The recorder samples by the drive's own ticks: with SYNC as the clock and with the drive's own
    (drifting) clock the recorded demand after the movement trigger is the interpolator's tick by tick."""
    d = drive(**options)
    configure(d, [(0x6062, 0)], period=10, preceding=5, triggers=TRIGGER_MOVEMENT)
    records = ramp_records(10_000, cruise_rpm=600, seg_ms=10)
    pending = d.start(records, prime=6)
    d.run(pending, until=lambda m: m.recorder.status == STATUS_TRIGGERED)
    rec = vector(d)
    from planner.encoding import hermite

    expected = [0]
    prev = (0, 0.0)
    for p, v, dt in records:
        if dt == 0:
            break
        v_end = v * 8192 / hermite.MS_PER_MINUTE
        expected += hermite.demand_from_coefficients(hermite.coefficients(prev[0], prev[1], p, v_end, dt), dt,
                                                     False)
        prev = (p, v_end)
    expected += [expected[-1]] * len(rec)  # standing at the end
    assert rec[:5] == [0] * 5
    assert rec[5:] == expected[:len(rec) - 5]


def test_continuous_mode_keeps_the_newest_samples_oldest_first() -> None:
    d = drive()
    configure(d, [(0x6062, 0)], period=10, triggers=0)
    pending = d.start(ramp_records(30_000, cruise_rpm=900, seg_ms=10), prime=6)
    d.run(pending, until=lambda m: m.recorder.samples_taken > 400)
    d.sdo(0x2010, 0, 0)
    rec = d.model.recorder
    assert rec.status == 0  # stopped, never triggered
    assert d.model.sdo_read(0x2019, 0) == rec.samples_taken % 256
    v = vector(d)
    assert v == sorted(v) and v[-1] == d.model.position_demand  # chronological, the newest last


def test_error_end_input_and_forced_triggers() -> None:
    # error: an underflow (nothing fed after priming)
    d = drive()
    configure(d, [(0x6041, 0)], triggers=TRIGGER_ERROR)
    d.start(ramp_records(10_000), prime=2)
    d.sync(30)
    assert d.model.recorder.trigger_kind == "error 0x8782"
    # end of profile: the time-0 record
    d = drive()
    configure(d, [(0x6041, 0)], triggers=TRIGGER_END | TRIGGER_ERROR)
    pending = d.start(ramp_records(20_000, seg_ms=10), prime=4)
    d.run(pending)
    assert d.model.recorder.trigger_kind == "end of profile" and d.model.counters.faults == 0
    # a movement does not trigger a recorder waiting for the digital input; an input edge does
    d = drive()
    configure(d, [(0x6041, 0)], triggers=TRIGGER_INPUT)
    d.start(ramp_records(20_000, seg_ms=10), prime=4)
    assert d.model.recorder.status == STATUS_RUNNING
    d.model.set_digital_inputs(0b100, d.t)
    assert d.model.recorder.status == STATUS_RUNNING | STATUS_TRIGGERED
    assert d.model.recorder.trigger_kind == "digital input"
    # forced (0x2010 = 3), in continuous mode too
    d = drive()
    configure(d, [(0x6041, 0)], triggers=0)
    d.sync(2)
    d.sdo(0x2010, 0, 3)
    assert d.model.recorder.trigger_kind == "force" and d.model.recorder.status & STATUS_TRIGGERED


def test_a_stop_before_the_triggers_sample_leaves_the_recording_untriggered() -> None:
    """A forced trigger between two samples takes effect at the next sample; a stop before it leaves no
    trigger sample in the rings, so the status says not triggered and 0x2019 is the continuous one (a
    host decoding it puts no t = 0 on a sample that is not the trigger's)."""
    d = drive()
    configure(d, [(0x6062, 0)], period=7, triggers=0)
    d.sync(6)  # 60 ms = 600 units: the last sample was at 595, the next is at 602
    d.sdo(0x2010, 0, 3)  # force: pending until the next sample
    rec = d.model.recorder
    assert rec.status == STATUS_RUNNING | STATUS_TRIGGERED and rec.trigger_sample is None
    d.sdo(0x2010, 0, 0)
    assert rec.status == 0 and rec.trigger_kind is None and rec.trigger_sample is None
    assert d.model.sdo_read(0x2019, 0) == 0  # 86 samples taken, the rings not yet wrapped: from row 0
    # the same force, then one more sample before the stop: triggered, the trigger at that sample
    configure(d, [(0x6062, 0)], period=7, triggers=0)
    d.sync(6)
    d.sdo(0x2010, 0, 3)
    d.sync(1)
    d.sdo(0x2010, 0, 0)
    assert rec.status == STATUS_TRIGGERED and rec.trigger_kind == "force" and rec.trigger_sample is not None


def test_bad_configurations_are_refused_at_start() -> None:
    d = drive()
    configure(d, [(0x6041, 0)], start=False)
    d.sdo(0x2014, 0, 0)
    for setup, code in (
        (lambda: None, odm.ABORT_INVALID_VALUE),  # no variable
        (lambda: (d.sdo(0x2014, 0, 1), d.sdo(0x2015, 1, 0x20C1)), odm.ABORT_INVALID_VALUE),  # 64-bit, write-only
        (lambda: (d.sdo(0x2015, 1, 0x6041), d.sdo(0x2012, 0, 0)), odm.ABORT_INVALID_VALUE),  # period 0
    ):
        setup()
        with pytest.raises(SdoAbort) as e:
            d.sdo(0x2010, 0, 1)
        assert e.value.code == code
        assert not d.model.recorder.active
    with pytest.raises(SdoAbort) as e:
        d.sdo(0x2011, 0, 0x10)  # reserved trigger bit
    assert e.value.code == odm.ABORT_VALUE_TOO_HIGH
    with pytest.raises(SdoAbort) as e:
        d.model.sdo_read(0x201B, 0)  # a domain: read_domain
    assert d.model.read_domain(0x201B, 0) == b""  # never started: nothing to upload


def test_reset_node_stops_the_recorder_and_store_keeps_its_configuration() -> None:
    d = drive()
    configure(d, [(0x6064, 0)], period=5, triggers=TRIGGER_MOVEMENT)
    d.sdo(0x1010, 1, 0x65766173)  # "save"
    d.frame(0, bytes((codec.NmtCommand.RESET_NODE, 1)))
    m = d.model
    assert not m.recorder.active and m.sdo_read(0x2017, 0) == 0
    assert m.sdo_read(0x2010, 0) == 0  # a command: not stored
    assert (m.sdo_read(0x2012, 0), m.sdo_read(0x2015, 1), m.sdo_read(0x2011, 0)) == (5, 0x6064, TRIGGER_MOVEMENT)
    assert m.sdo_read(0x2018, 0) == 256


def test_block_upload_server_resends_what_the_client_did_not_acknowledge() -> None:
    data = bytes(range(256)) * 4
    server = SdoBlockUploadServer(lambda index, sub: data)
    init = server.on_request(bytes([0xA4]) + struct.pack("<HBBB", 0x201B, 0, 10, 0) + bytes(2))
    assert init[0][0] == 0xC6 and struct.unpack_from("<L", init[0], 4)[0] == 1024
    block = server.on_request(bytes([0xA3]) + bytes(7))
    assert [f[0] for f in block] == list(range(1, 11))
    again = server.on_request(bytes([0xA2, 7, 10]) + bytes(5))  # segments 8-10 lost: resent from 8
    assert again[0][1:8] == data[49:56] and again[0][0] == 1
    got = b"".join(f[1:8] for f in block[:7])
    frames = again
    while True:
        last = frames[-1][0] & 0x80
        got += b"".join(f[1:8] for f in frames)
        frames = server.on_request(bytes([0xA2, len(frames), 10]) + bytes(5))
        if last:
            break
    (end,) = frames
    unused = (end[0] >> 2) & 7
    assert got[:len(got) - unused] == data
    import binascii

    assert end[0] & 0x03 == 1 and struct.unpack_from("<H", end, 1)[0] == binascii.crc_hqx(data, 0)
    assert server.on_request(bytes([0xA1]) + bytes(7)) == [] and not server.busy


# ---- the recorder in the drive families ------------------------------------------------------------------------
RECORDER_OBJECTS = (0x2010, 0x2011, 0x2012, 0x2013, 0x2014, 0x2015, 0x2016, 0x2017, 0x2018, 0x2019, 0x201B)


def test_the_recorder_objects_are_the_epos_familys_only() -> None:
    """Seed 004's objects are maxon's: in EPOS_TABLE (and its EDS) only; the XtrapulsPac's 0x2010 is its
    boot-up message object (seed 003), which a recorder start must never be written to."""
    assert all(index in odm.EPOS_TABLE.indices for index in RECORDER_OBJECTS)
    assert odm.EPOS_TABLE.spec(0x201B, 0).dtype == odm.DataType.DOMAIN
    assert "boot-up" in odm.XTRAPULS_TABLE.spec(0x2010, 0).name.lower()
    for table in (odm.XTRAPULS_TABLE, odm.CSP_TABLE):
        assert not any(index in table.indices for index in RECORDER_OBJECTS[1:]), table.name
    assert 0x2010 not in odm.CSP_TABLE.indices
    eds = EDS_PATH.read_text()
    assert "[201B]\nParameterName=Data recorder data buffer\nObjectType=0x7\nDataType=0x000F" in eds


def test_halt_to_standstill_is_the_end_of_profile_trigger() -> None:
    """End of profile (0x2011 bit 3) also when a halt (controlword bit 8) ramp reaches standstill: the
    shared drive's halt-end hook, not only the EPOS time-0 record."""
    d = drive()
    configure(d, [(0x6062, 0)], triggers=TRIGGER_END)
    pending = d.start(ramp_records(40_000, cruise_rpm=900, seg_ms=10), prime=8)
    feed(d, pending, 10)  # 100 ms: moving
    assert d.model.recorder.status == STATUS_RUNNING and d.model.demand_velocity_rpm > 100
    d.cw(0x011F)  # halt
    for _ in range(100):
        d.sync()
        if d.model.recorder.status & STATUS_TRIGGERED:
            break
    assert d.model.recorder.trigger_kind == "end of profile (halt)"
    assert d.model.counters.faults == 0 and d.model.demand_velocity_rpm == 0.0


def test_read_domain_refuses_an_integer_object() -> None:
    d = drive()
    with pytest.raises(SdoAbort) as e:
        d.model.read_domain(0x6041, 0)
    assert e.value.code == odm.ABORT_UNSUPPORTED_ACCESS
    with pytest.raises(SdoAbort) as e:
        d.model.read_domain(0x7777, 0)
    assert e.value.code == odm.ABORT_NO_OBJECT


def test_a_drive_without_a_recorder_runs_and_faults_as_before() -> None:
    """The shared drive with no recorder (`recorder` None: a family without one): the tick loop, the
    error trigger's place in `_fault` and the halt-end hook do nothing, and it has no domain to upload."""
    from bus.sim.device import DriveDevice

    class NoRecorder(DriveDevice):  # the shared drive as a family of its own, accepting the master's mode 7
        supported_modes = frozenset({0, 7})

    m = NoRecorder(1, make_axis())
    assert m.recorder is None
    m.configure(10, t=0.0)
    for cw in (0x0006, 0x000F):
        m.sdo_write(0x6040, 0, cw, 0.0)
    assert m.state == codec.Cia402State.OPERATION_ENABLED
    m.disturbance_current_a = 100.0  # a load the controller cannot hold: the following error trips
    t = 0.0
    for _ in range(300):
        t += 0.01
        m.advance(t)
        m.on_sync(t)
        if m.counters.faults:
            break
    assert [f.code for f in m.fault_log] == [codec.EMCY_FOLLOWING_ERROR]
    assert m.counters.ticks == round(t * 1000)
    with pytest.raises(SdoAbort) as e:
        m.read_domain(0x201B, 0)
    assert e.value.code == odm.ABORT_UNSUPPORTED_ACCESS
