"""The drive families the product streams to, as `DriveProfile`s (bus/profile.py), one per family.

`epos-ipm`: maxon EPOS interpolated position mode (seed 000 ch. 4, seed 001), PVT records into a 64-entry
FIFO, bus/cob.py's layout. `xtrapuls-ip`: Infranor XtrapulsPac interpolated position (seed 003 3), one set
point per SYNC in 0x60C1, optionally 16-bit multiplexed, no FIFO. `cia402-csp`: cyclic synchronous
position, 0x607A every SYNC, followed while operation is enabled (so the master writes the drive's
position there first). Halt does not exist in the XtrapulsPac's IP mode, so a cyclic axis that cannot
follow a stop trajectory quick-stops.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

from bus import cob
from bus.profile import (
    MAX_GROUP_AXES,
    MAX_GROUP_BITS,
    DriveProfile,
    ObjectRef,
    PdoEntry,
    PdoLayout,
    SdoWrite,
    SetpointSlot,
    rpm_per_s,
    u32,
)
from planner.config import AxisConfig, DriveSettings

# objects every family has (CiA 301 + CiA 402), by the names the master uses
_COMMON: dict[str, ObjectRef] = {
    "device_type": ObjectRef(0x1000),
    "error_register": ObjectRef(0x1001),
    "sync_cob_id": ObjectRef(0x1005),
    "sync_period": ObjectRef(0x1006),
    "store_parameters": ObjectRef(0x1010, 1),
    "restore_defaults": ObjectRef(0x1011, 1),
    "identity_vendor": ObjectRef(0x1018, 1),
    "identity_product": ObjectRef(0x1018, 2),
    "identity_revision": ObjectRef(0x1018, 3),
    "identity_serial": ObjectRef(0x1018, 4),
    "heartbeat_consumer": ObjectRef(0x1016, 1),
    "heartbeat_producer": ObjectRef(0x1017),
    "error_code": ObjectRef(0x603F),
    "controlword": ObjectRef(0x6040),
    "statusword": ObjectRef(0x6041),
    "quick_stop_option": ObjectRef(0x605A),
    "mode": ObjectRef(0x6060),
    "mode_display": ObjectRef(0x6061),
    "position_demand": ObjectRef(0x6062),
    "position_actual": ObjectRef(0x6064),
    "following_error_window": ObjectRef(0x6065),
    "position_window": ObjectRef(0x6067),
    "velocity_actual": ObjectRef(0x606C),
    "current_actual": ObjectRef(0x6078),
    "position_limit_min": ObjectRef(0x607D, 1),
    "position_limit_max": ObjectRef(0x607D, 2),
    "max_profile_velocity": ObjectRef(0x607F),
    "profile_velocity": ObjectRef(0x6081),
    "profile_acceleration": ObjectRef(0x6083),
    "profile_deceleration": ObjectRef(0x6084),
    "quick_stop_deceleration": ObjectRef(0x6085),
    "following_error_actual": ObjectRef(0x60F4),
    "supported_modes": ObjectRef(0x6502),
}
_CIA301_LATER: dict[str, ObjectRef] = {  # CiA 301 v4.2 objects (not in the XtrapulsPac's v4.01)
    "time_stamp_cob_id": ObjectRef(0x1012),
    "high_resolution_time_stamp": ObjectRef(0x1013),
    "sync_counter_overflow": ObjectRef(0x1019),
}

_FEEDBACK_TPDO2 = PdoLayout("tx", 2, cob.TPDO2_BASE, 1, (PdoEntry(0x6064, 0, 32), PdoEntry(0x6062, 0, 32)))
_CONTROLWORD_RPDO1 = PdoLayout("rx", 1, cob.RPDO1_BASE, 1, (PdoEntry(0x6040, 0, 16),))


# ---- maxon EPOS, interpolated position mode (PVT FIFO) -------------------------------------------------
@dataclass(frozen=True)
class EposProfile(DriveProfile):
    def pdo_layouts(self, axis: AxisConfig, slot: SetpointSlot | None) -> tuple[PdoLayout, ...]:
        return (
            _CONTROLWORD_RPDO1,
            PdoLayout("rx", 2, cob.RPDO2_BASE, 255, (PdoEntry(0x20C1, 0, 64),)),
            PdoLayout("tx", 1, cob.TPDO1_BASE, 1, (PdoEntry(0x6041, 0, 16), PdoEntry(0x60C4, 2, 32))),
            _FEEDBACK_TPDO2,
        )

    def _mode_writes(self, axis: AxisConfig, settings: DriveSettings, sync_period_ms: int,
                     slot: SetpointSlot | None) -> list[SdoWrite]:
        w = self._w
        return [
            w("mode", self.ip_mode, "modes of operation = interpolated position", "selects the PVT mode"),
            w("ip_submode", -1, "interpolation sub mode", "cubic PVT interpolation"),
            w("underflow_warning", settings.underflow_warning, "buffer underflow warning level",
              "the FIFO's low watermark"),
            w("overflow_warning", settings.overflow_warning, "buffer overflow warning level",
              "the FIFO's high watermark"),
        ]

    def _limit_writes(self, axis: AxisConfig, settings: DriveSettings) -> list[SdoWrite]:
        w = self._w
        decel = settings.profile_deceleration if settings.profile_deceleration > 0 else axis.acceleration
        return [
            w("max_profile_velocity", u32(axis.max_profile_velocity_rpm),
              "max profile velocity (rpm)", "the drive's own velocity limit"),
            w("profile_velocity", u32(axis.velocity_rpm(axis.velocity)),
              "profile velocity (rpm)", essential=False),
            w("profile_acceleration", u32(rpm_per_s(axis, axis.acceleration)),
              "profile acceleration (rpm/s)", essential=False),
            w("max_acceleration", u32(rpm_per_s(axis, axis.max_acceleration)),
              "max acceleration (rpm/s)", "the drive's own acceleration limit"),
            w("profile_deceleration", u32(rpm_per_s(axis, decel)),
              "profile deceleration (rpm/s)", "halt decelerates with it"),
            w("quick_stop_deceleration", u32(rpm_per_s(axis, axis.max_acceleration)),
              "quick stop deceleration (rpm/s)", essential=False),
        ]


EPOS_IPM = EposProfile(
    name="epos-ipm",
    eds_name="epos-ipm.eds",
    kind="fifo",
    ip_mode=7,
    fifo_depth=64,
    objects=MappingProxyType({
        **_COMMON, **_CIA301_LATER,
        "record": ObjectRef(0x20C1),
        "buffer_status": ObjectRef(0x20C4, 1),
        "underflow_warning": ObjectRef(0x20C4, 2),
        "overflow_warning": ObjectRef(0x20C4, 3),
        "ip_submode": ObjectRef(0x60C0),
        "ip_time_value": ObjectRef(0x60C2, 1),
        "ip_time_index": ObjectRef(0x60C2, 2),
        "max_buffer_size": ObjectRef(0x60C4, 1),
        "free_size": ObjectRef(0x60C4, 2),
        "buffer_organization": ObjectRef(0x60C4, 3),
        "buffer_position": ObjectRef(0x60C4, 4),
        "record_size": ObjectRef(0x60C4, 5),
        "buffer_clear": ObjectRef(0x60C4, 6),
        "max_acceleration": ObjectRef(0x60C5),
    }),
    after_enable=(("buffer_clear", 0), ("buffer_clear", 1)),
)


# ---- cyclic families: one set point per SYNC ------------------------------------------------------------
def _setpoint_rpdo(slot: SetpointSlot, position: int, velocity: int | None) -> PdoLayout:
    """RPDO3 of a cyclic axis: its slot's entries (dummies around its own in a multiplexed frame), with
    the slot's COB-ID (the group's, in a multiplexed frame)."""
    pos = PdoEntry(position >> 8, position & 0xFF, slot.position_bits)
    vel = PdoEntry(velocity >> 8, velocity & 0xFF, slot.velocity_bits) if velocity is not None and \
        slot.velocity_bits else None
    return PdoLayout("rx", 3, cob.RPDO3_BASE, 1, slot.entries(pos, vel), shared_cob_id=slot.cob_id)


_STATUS_TPDO1 = PdoLayout("tx", 1, cob.TPDO1_BASE, 1, (PdoEntry(0x6041, 0, 16),))
XTRAPULS_SUBMODES: Mapping[str, int] = MappingProxyType({"linear": 0, "pv": -1, "p3": -2})
XTRAPULS_MOTOR_INCREMENTS = 4096  # 0x6093:01 "must be set at 4096" (seed 003 5)


def _counts_per_s(axis: AxisConfig, user_per_s: float) -> int:
    return u32(user_per_s * axis.counts_per_unit)


@dataclass(frozen=True)
class XtrapulsProfile(DriveProfile):
    def velocity_in_setpoint(self, axis: AxisConfig) -> bool:
        return axis.ip_submode == "pv"

    def pdo_layouts(self, axis: AxisConfig, slot: SetpointSlot | None) -> tuple[PdoLayout, ...]:
        assert slot is not None
        return (_CONTROLWORD_RPDO1, _setpoint_rpdo(slot, 0x60C101, 0x60C102), _STATUS_TPDO1, _FEEDBACK_TPDO2)

    def _mode_writes(self, axis: AxisConfig, settings: DriveSettings, sync_period_ms: int,
                     slot: SetpointSlot | None) -> list[SdoWrite]:
        assert slot is not None
        w = self._w
        return [
            w("bootup_message", 1, "send the boot-up message", essential=False),
            w("mode", self.ip_mode, "modes of operation = interpolated position", "selects the IP mode"),
            w("ip_submode", XTRAPULS_SUBMODES[axis.ip_submode], f"interpolation sub mode ({axis.ip_submode})",
              "the drive's interpolation between set points (the planner's deviation bound assumes it)"),
            w("position_factor_numerator", XTRAPULS_MOTOR_INCREMENTS, "position factor numerator",
              "user units = the axis' counts"),
            w("position_factor_denominator", int(axis.counts_per_rev), "position factor denominator",
              "user units = the axis' counts"),
            w("ip_16bit", 1 if slot.position_bits == 16 else 0, "16-bit set points (multiplexed RPDO)",
              "the multiplexed frame carries 16-bit positions", essential=slot.position_bits == 16),
            w("quick_stop_option", 2, "quick stop: quick-stop ramp, then switch on disabled", essential=False),
        ]

    def _limit_writes(self, axis: AxisConfig, settings: DriveSettings) -> list[SdoWrite]:
        w = self._w
        decel = settings.profile_deceleration if settings.profile_deceleration > 0 else axis.acceleration
        return [
            w("max_motor_speed", max(100, min(60000, u32(axis.max_profile_velocity_rpm))),
              "max motor speed (rpm)", "the drive's own velocity limit"),
            w("profile_velocity", _counts_per_s(axis, axis.velocity), "profile velocity (counts/s)",
              essential=False),
            w("profile_acceleration", _counts_per_s(axis, axis.acceleration), "profile acceleration (counts/s^2)",
              essential=False),
            w("profile_deceleration", _counts_per_s(axis, decel), "profile deceleration (counts/s^2)",
              essential=False),
            w("quick_stop_deceleration", _counts_per_s(axis, axis.max_acceleration),
              "quick-stop ramp (counts/s^2)", essential=False),
        ]


XTRAPULS_IP = XtrapulsProfile(
    name="xtrapuls-ip",
    eds_name="xtrapuls-ip.eds",
    kind="cyclic",
    ip_mode=7,
    objects=MappingProxyType({
        **_COMMON,
        "sync_error_limit": ObjectRef(0x2006, 4),
        "bootup_message": ObjectRef(0x2010),
        "interpolator_output": ObjectRef(0x30C1),
        "ip_16bit": ObjectRef(0x3350),
        "max_motor_speed": ObjectRef(0x6080),
        "position_factor_numerator": ObjectRef(0x6093, 1),
        "position_factor_denominator": ObjectRef(0x6093, 2),
        "ip_submode": ObjectRef(0x60C0),
        "ip_data_position": ObjectRef(0x60C1, 1),
        "ip_data_velocity": ObjectRef(0x60C1, 2),
    }),
    hold_objects=("ip_data_position", "ip_data_velocity"),
    halt_in_mode=False,
    # seed 003 3.1.1.4 "At least 180 ms are necessary for the servo-drive to start the synchronisation"
    sync_lock_ms=180,
)


@dataclass(frozen=True)
class CspProfile(DriveProfile):
    def pdo_layouts(self, axis: AxisConfig, slot: SetpointSlot | None) -> tuple[PdoLayout, ...]:
        assert slot is not None
        return (_CONTROLWORD_RPDO1, _setpoint_rpdo(slot, 0x607A00, None), _STATUS_TPDO1, _FEEDBACK_TPDO2)

    def _mode_writes(self, axis: AxisConfig, settings: DriveSettings, sync_period_ms: int,
                     slot: SetpointSlot | None) -> list[SdoWrite]:
        w = self._w
        return [
            w("mode", self.ip_mode, "modes of operation = cyclic synchronous position", "selects CSP"),
            w("ip_time_value", sync_period_ms, "interpolation time period (the set point cycle)", essential=False),
            w("ip_time_index", -3, "interpolation time index (ms)", essential=False),
        ]

    def _limit_writes(self, axis: AxisConfig, settings: DriveSettings) -> list[SdoWrite]:
        w = self._w
        decel = settings.profile_deceleration if settings.profile_deceleration > 0 else axis.acceleration
        return [
            w("max_profile_velocity", _counts_per_s(axis, axis.max_profile_velocity),
              "max profile velocity (counts/s)", "the drive's own velocity limit"),
            w("profile_deceleration", _counts_per_s(axis, decel), "profile deceleration (counts/s^2)",
              essential=False),
            w("quick_stop_deceleration", _counts_per_s(axis, axis.max_acceleration),
              "quick stop deceleration (counts/s^2)", essential=False),
        ]


CIA402_CSP = CspProfile(
    name="cia402-csp",
    eds_name="cia402-csp.eds",
    kind="cyclic",
    ip_mode=8,
    objects=MappingProxyType({
        **_COMMON, **_CIA301_LATER,
        "target_position": ObjectRef(0x607A),
        "ip_time_value": ObjectRef(0x60C2, 1),
        "ip_time_index": ObjectRef(0x60C2, 2),
    }),
    hold_objects=("target_position",),
    starts_with_bit4=False,
    halt_in_mode=False,
)

PROFILES: Mapping[str, DriveProfile] = MappingProxyType(
    {p.name: p for p in (EPOS_IPM, XTRAPULS_IP, CIA402_CSP)})


def profile_of(axis: AxisConfig) -> DriveProfile:
    return PROFILES[axis.profile]


def setpoint_slots(axes: Sequence[AxisConfig]) -> dict[int, SetpointSlot]:
    """The set point slot of every cyclic axis of a cell (node id -> slot); FIFO axes have none.

    An axis with `mux_group` 0 has RPDO3 0x400 + node to itself: 32-bit position (+ 32-bit velocity in
    PV). The axes of one group share one frame, in node id order, 16 bits each (+ 16-bit velocity in PV),
    with the RPDO3 COB-ID of the group's lowest node. Raises ValueError for a group that does not fit one
    frame (more than 4 axes or 64 bits), or mixes families."""
    slots: dict[int, SetpointSlot] = {}
    groups: dict[int, list[AxisConfig]] = {}
    for a in axes:
        profile = PROFILES[a.profile]
        if profile.kind != "cyclic":
            continue
        pv = profile.velocity_in_setpoint(a)
        if a.mux_group:
            groups.setdefault(a.mux_group, []).append(a)
            continue
        size = 8 if pv else 4
        slots[a.node_id] = SetpointSlot(a.node_id, cob.rpdo3_id(a.node_id), 0, 32, 32 if pv else 0, size,
                                        (a.node_id,))
    for g, members in sorted(groups.items()):
        members.sort(key=lambda a: a.node_id)
        names = ", ".join(repr(a.name) for a in members)
        if len({a.profile for a in members}) > 1:
            raise ValueError(f"mux_group {g} ({names}) mixes drive families")
        widths = [32 if PROFILES[a.profile].velocity_in_setpoint(a) else 16 for a in members]
        if len(members) > MAX_GROUP_AXES or sum(widths) > MAX_GROUP_BITS:
            raise ValueError(
                f"mux_group {g} ({names}) needs {sum(widths)} bits in one frame; a frame carries 64 (four "
                "16-bit positions, or two positions with their 16-bit velocities in sub-mode pv)")
        cob_id = cob.rpdo3_id(members[0].node_id)
        nodes = tuple(a.node_id for a in members)
        offset = 0
        for a, w in zip(members, widths, strict=True):
            slots[a.node_id] = SetpointSlot(a.node_id, cob_id, offset // 8, 16, w - 16, sum(widths) // 8, nodes)
            offset += w
    return slots
