"""Cell configuration: the axes of one CAN bus, their scaling and limits, and the runtime settings.

A cell is loaded from TOML (see configs/demo.toml and docs/formats.md). Every section and key is
checked on load: unknown keys, wrong types, NaN and impossible limits raise `PlanningError(CONFIG or
LIMITS)` naming the field, so a typo in a config fails at start-up instead of mid-motion.

Units: user units (rad or mm) for positions, user units/s, /s^2, /s^3 for the limits; the drive's
own units (counts, rpm) only where the drive has them (`max_profile_velocity_rpm` = 0x607F).
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from planner.errors import CONFIG, LIMITS, PlanningError
from planner.readings import DriveReadings, SimDriveOptions, drive_readings, sim_options

# One rule for every name that becomes a Zenoh key chunk (cell names, job ids): 1-64 characters of
# letters, digits, '_', '-' and '.', not starting with '.'. docs/formats.md "Names" states it once; the
# planner (job files), the config loader, the job API's decoder, the client and the CLI all call
# `check_name`, so a name is accepted or refused the same way everywhere.
NAME_MAX = 64
NAME_RULE = "1-64 characters of letters, digits, '_', '-' and '.', not starting with '.'"
_NAME = re.compile(r"^[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,63}$")
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1  # the drive's position range in counts (0x607A, 0x6064)
DEFAULT_UNIT = "rad"  # an axis' user unit when [[axis]] has no `unit`
# An emergency stop brakes harder than a normal one: by default at this multiple of the axis' acceleration
# limit, never above the drive's own 0x60C5 (the encoder and the drive refuse more).
EMERGENCY_DECELERATION_FACTOR = 2.0
# The target window by default: this many counts around the target (a servo at rest dithers by a count
# or two; seed 002 gives no default), and the in-target timeout (ms) after the plan has ended.
DEFAULT_TARGET_WINDOW_COUNTS = 10
DEFAULT_IN_TARGET_TIMEOUT_MS = 1000
MAX_IN_TARGET_TIMEOUT_MS = 600_000


def valid_name(value: object) -> bool:
    """True when `value` follows NAME_RULE (safe as one Zenoh key chunk)."""
    return isinstance(value, str) and bool(_NAME.match(value))


def check_name(value: object, what: str, *, path: str, code: str = "SCHEMA") -> str:
    """`value` if it follows NAME_RULE, else PlanningError(code) saying what is wrong with it."""
    if not isinstance(value, str):
        raise PlanningError("TYPE" if code == "SCHEMA" else code, f"{what} must be a string, got {value!r}",
                            path=path)
    if not _NAME.match(value):
        bad = sorted({c for c in value if not (c.isascii() and (c.isalnum() or c in "_-."))})
        why = (
            "is empty" if not value
            else f"is {len(value)} characters long" if len(value) > NAME_MAX
            else "starts with '.'" if value.startswith(".")
            else f"contains {', '.join(repr(c) for c in bad)}, which is not allowed"
        )
        raise PlanningError(code, f"{what} {value!r} {why}; names are {NAME_RULE}", path=path)
    return value


def _unknown_keys(where: str, unknown: list[str], known: list[str]) -> str:
    """'unknown key 'count_per_unit' in [[axis]] 'x' (did you mean 'counts_per_unit'?)'."""
    parts = []
    for key in unknown:
        close = difflib.get_close_matches(key, known, n=1, cutoff=0.75)
        parts.append(f"{key!r} (did you mean {close[0]!r}?)" if close else repr(key))
    noun = "key" if len(unknown) == 1 else "keys"
    return f"unknown {noun} {', '.join(parts)} in {where}"


def _number(section: str, key: str, value: Any, *, positive: bool = False, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise PlanningError(CONFIG, f"{section}.{key} must be a number, got {value!r}",
                            path=f"{section}.{key}")
    if integer and not isinstance(value, int):
        raise PlanningError(CONFIG, f"{section}.{key} must be an integer, got {value!r}",
                            path=f"{section}.{key}")
    if not math.isfinite(value):
        raise PlanningError(LIMITS, f"{section}.{key} is {value}", path=f"{section}.{key}")
    if positive and value <= 0:
        raise PlanningError(LIMITS, f"{section}.{key} must be > 0, got {value}", path=f"{section}.{key}")
    return float(value)


@dataclass(frozen=True)
class AxisConfig:
    """One drive axis. Limits are in user units; the drive's own limits in its units."""

    name: str
    node_id: int
    counts_per_unit: float  # position counts (quadcounts) per user unit, gear included
    counts_per_rev: int  # motor quadcounts per revolution (velocity on the wire is rpm)
    velocity: float  # user units/s
    acceleration: float  # user units/s^2
    jerk: float  # user units/s^3 (move jobs and stops)
    position_min: float  # user units (0x607D:01)
    position_max: float  # user units (0x607D:02)
    max_profile_velocity_rpm: float  # 0x607F
    max_acceleration: float  # 0x60C5 in user units/s^2
    # how the drive settles the points the manuals leave open: what the master knows ([axis.probed]) and,
    # for a simulated drive, what it does ([axis.sim]); see planner/readings.py
    probed: DriveReadings = field(default_factory=DriveReadings)
    sim: SimDriveOptions = field(default_factory=SimDriveOptions)
    # the drive family (bus/profile.py): "epos-ipm" (PVT FIFO), "xtrapuls-ip" (one set point per SYNC in
    # interpolated position mode), "cia402-csp" (cyclic synchronous position); for xtrapuls-ip the
    # interpolation sub-mode ("linear", "pv", "p3") and the multiplexed RPDO group (up to 4 axes share one
    # frame of 16-bit set points; 0 = an RPDO of its own)
    profile: str = "epos-ipm"
    ip_submode: str = "pv"
    mux_group: int = 0
    unit: str = DEFAULT_UNIT  # the user unit's name ("rad", "mm", ...): labels of tables and plots
    # travel commands (seed 002, planner/motion/travel.py): a modulo axis' period (user units; 0 = not a modulo axis)
    # and its tolerance window (+- user units around a modulo target, 8020:0F); the emergency stop's
    # deceleration (user units/s^2; 0 = the default, `emergency_stop_deceleration`); the target window
    # (user units; 0 = the default, `target_window_user`) and the in-target timeout the streaming side
    # watches when a move's plan has ended (PRE_TARGET -> TARGET)
    modulo_period: float = 0.0
    modulo_tolerance: float = 0.0
    emergency_deceleration: float = 0.0
    target_window: float = 0.0
    in_target_timeout_ms: int = DEFAULT_IN_TARGET_TIMEOUT_MS

    def __post_init__(self) -> None:
        where = f"axis '{self.name}'"
        if not self.name or not isinstance(self.name, str):
            raise PlanningError(CONFIG, f"axis name must be a non-empty string, got {self.name!r}",
                                path="axis.name")
        if not (isinstance(self.unit, str) and 1 <= len(self.unit) <= 16 and self.unit.isprintable()
                and self.unit.strip() == self.unit):
            raise PlanningError(CONFIG, f"unit of {where} must be 1-16 printable characters (e.g. \"rad\", "
                                f"\"mm\"), got {self.unit!r}", path="axis.unit")
        if not (1 <= self.node_id <= 127):
            raise PlanningError(CONFIG, f"node_id of {where} must be 1..127, got {self.node_id}",
                                path="axis.node_id")
        for f in fields(self):
            if f.name in _AXIS_NOT_NUMBERS:
                continue
            v = getattr(self, f.name)
            if not math.isfinite(v):
                raise PlanningError(LIMITS, f"{f.name} of {where} is {v}", path=f"axis.{f.name}")
        for key in ("counts_per_unit", "counts_per_rev", "velocity", "acceleration", "jerk",
                    "max_profile_velocity_rpm", "max_acceleration"):
            if getattr(self, key) <= 0:
                raise PlanningError(LIMITS, f"{key} of {where} must be > 0, got {getattr(self, key)}",
                                    path=f"axis.{key}")
        if self.profile not in PROFILE_NAMES:
            raise PlanningError(CONFIG, f"profile of {where} must be one of {list(PROFILE_NAMES)}, got "
                                f"{self.profile!r}", path="axis.profile")
        if self.ip_submode not in IP_SUBMODES:
            raise PlanningError(CONFIG, f"ip_submode of {where} must be one of {list(IP_SUBMODES)}, got "
                                f"{self.ip_submode!r}", path="axis.ip_submode")
        if not 0 <= self.mux_group <= 127 or (self.mux_group and self.profile != "xtrapuls-ip"):
            raise PlanningError(CONFIG, f"mux_group of {where} must be 0..127 (an XtrapulsPac axis' multiplexed "
                                f"RPDO group, 0 = none), got {self.mux_group}", path="axis.mux_group")
        if self.position_min >= self.position_max:
            raise PlanningError(
                LIMITS,
                f"position_min {self.position_min} of {where} is not below position_max {self.position_max}",
                path="axis.position_min",
            )
        for key in ("position_min", "position_max"):
            counts = getattr(self, key) * self.counts_per_unit
            if not INT32_MIN <= round(counts) <= INT32_MAX:
                raise PlanningError(
                    LIMITS,
                    f"{key} {getattr(self, key):g} {self.unit} of {where} is {counts:.0f} counts at "
                    f"counts_per_unit {self.counts_per_unit:g}: beyond the drive's int32 position range "
                    f"[{INT32_MIN}, {INT32_MAX}]",
                    path=f"axis.{key}",
                )
        self._check_travel(where)
        if self.acceleration > self.max_acceleration:
            raise PlanningError(
                LIMITS,
                f"acceleration {self.acceleration} of {where} exceeds the drive's max_acceleration "
                f"{self.max_acceleration} (0x60C5)",
                path="axis.acceleration",
            )
        if self.velocity_rpm(self.velocity) > self.max_profile_velocity_rpm:
            raise PlanningError(
                LIMITS,
                f"velocity {self.velocity} of {where} is {self.velocity_rpm(self.velocity):.1f} rpm, "
                f"above the "
                f"drive's max_profile_velocity_rpm {self.max_profile_velocity_rpm} (0x607F)",
                path="axis.velocity",
            )

    def _check_travel(self, where: str) -> None:
        """The travel-command settings (seed 002): a modulo window narrower than half the period (else the
        nearest modulo position would be ambiguous), an emergency deceleration the drive can do."""
        for key in ("modulo_period", "modulo_tolerance", "emergency_deceleration", "target_window"):
            if getattr(self, key) < 0:
                raise PlanningError(LIMITS, f"{key} of {where} must be >= 0, got {getattr(self, key)}",
                                    path=f"axis.{key}")
        if self.modulo_tolerance > 0 and self.modulo_period == 0:
            raise PlanningError(CONFIG, f"modulo_tolerance of {where} is {self.modulo_tolerance:g} but the axis has "
                                "no modulo_period: the window belongs to a modulo axis", path="axis.modulo_tolerance")
        if self.modulo_period > 0 and not self.modulo_tolerance < self.modulo_period / 2:
            raise PlanningError(LIMITS, f"modulo_tolerance {self.modulo_tolerance:g} of {where} must be below half "
                                f"the modulo_period {self.modulo_period:g}", path="axis.modulo_tolerance")
        if self.emergency_deceleration > self.max_acceleration:
            raise PlanningError(LIMITS, f"emergency_deceleration {self.emergency_deceleration:g} of {where} exceeds "
                                f"the drive's max_acceleration {self.max_acceleration:g} (0x60C5)",
                                path="axis.emergency_deceleration")
        if not (isinstance(self.in_target_timeout_ms, int)
                and 1 <= self.in_target_timeout_ms <= MAX_IN_TARGET_TIMEOUT_MS):
            raise PlanningError(LIMITS, f"in_target_timeout_ms of {where} must be a whole number of ms in "
                                f"1..{MAX_IN_TARGET_TIMEOUT_MS}, got {self.in_target_timeout_ms!r}",
                                path="axis.in_target_timeout_ms")

    @property
    def is_modulo(self) -> bool:
        return self.modulo_period > 0

    @property
    def emergency_stop_deceleration(self) -> float:
        """User units/s^2: `emergency_deceleration`, or EMERGENCY_DECELERATION_FACTOR x the acceleration
        limit capped at the drive's 0x60C5."""
        if self.emergency_deceleration > 0:
            return self.emergency_deceleration
        return min(EMERGENCY_DECELERATION_FACTOR * self.acceleration, self.max_acceleration)

    @property
    def target_window_user(self) -> float:
        """User units: `target_window`, or DEFAULT_TARGET_WINDOW_COUNTS counts."""
        return self.target_window if self.target_window > 0 else DEFAULT_TARGET_WINDOW_COUNTS / self.counts_per_unit

    # unit conversions (user units <-> drive units)
    def to_counts(self, user: float) -> float:
        return user * self.counts_per_unit

    def velocity_rpm(self, user_per_s: float) -> float:
        """User units/s -> rpm of the motor shaft."""
        return user_per_s * self.counts_per_unit * 60.0 / self.counts_per_rev

    def rpm_to_user(self, rpm: float) -> float:
        return rpm * self.counts_per_rev / (60.0 * self.counts_per_unit)

    @property
    def max_profile_velocity(self) -> float:
        """The drive's 0x607F in user units/s."""
        return self.rpm_to_user(self.max_profile_velocity_rpm)


_AXIS_NOT_NUMBERS = ("name", "node_id", "probed", "sim", "unit", "profile", "ip_submode", "mux_group")
PROFILE_NAMES = ("epos-ipm", "xtrapuls-ip", "cia402-csp")
IP_SUBMODES = ("linear", "pv", "p3")

# ---- homing (docs/drive-model.md "Homing") -----------------------------------------------------------------
# The homing methods (0x6098) the simulated drive of each family performs, the master's single list: a home
# job asking another method of an axis is refused, and the simulated drive raises homing error (statusword bit
# 13) for a method it does not perform, as seed 003 says of "an unimplemented selected method". CiA 402's:
# 17/18 negative/positive limit switch, 19/20 positive home switch, 21/22 negative home switch, 23/27 the cam
# (a home switch of finite width) searched with a positive/negative initial move and left on the side it was
# met (seed 002's calibration against a cam with two velocities), 35 (and 37 in CiA 402's later edition) the
# current position. The XtrapulsPac lists "1..14, 17..30, 33..35" and -1..-4: no 37 (seed 003 0x6098).
HOMING_CURRENT_POSITION = (35, 37)
HOMING_METHODS: dict[str, frozenset[int]] = {
    "epos-ipm": frozenset({17, 18, 19, 20, 21, 22, 23, 27, 35, 37}),
    "xtrapuls-ip": frozenset({17, 18, 19, 20, 21, 22, 23, 27, 35}),
    "cia402-csp": frozenset({17, 18, 19, 20, 21, 22, 23, 27, 35, 37}),
}


@dataclass(frozen=True)
class BusConfig:
    interface: str = "virtual"
    channel: str = "pvt"
    bitrate: int = 1_000_000

    def __post_init__(self) -> None:
        if self.interface == "udp_multicast":
            raise PlanningError(CONFIG, "the udp_multicast interface is not allowed (it leaves this host)",
                                path="bus.interface")
        if self.bitrate <= 0:
            raise PlanningError(CONFIG, f"bus.bitrate must be > 0, got {self.bitrate}", path="bus.bitrate")

    def with_spec(self, spec: str | None, bitrate: int | None = None) -> BusConfig:
        """This bus with `--bus INTERFACE:CHANNEL` (e.g. socketcan:vcan0; the channel may contain ':')
        and `--bitrate` applied where given."""
        interface, channel = self.interface, self.channel
        if spec is not None:
            interface, sep, channel = spec.partition(":")
            if not sep or not interface or not channel:
                raise PlanningError(CONFIG, f"--bus must be INTERFACE:CHANNEL (e.g. socketcan:vcan0), got {spec!r}",
                                    path="bus")
        return BusConfig(interface=interface, channel=channel, bitrate=bitrate or self.bitrate)


@dataclass(frozen=True)
class DriveSettings:
    """Settings the master writes to every drive (seed 000 4.3.6 defaults)."""

    underflow_warning: int = 4  # 0x20C4:02
    overflow_warning: int = 60  # 0x20C4:03
    heartbeat_ms: int = 100  # 0x1017 producer time the master configures
    heartbeat_timeout_ms: int = 350  # consumer timeout on the master side
    following_error_counts: int = 20_000  # 0x6065
    profile_deceleration: float = 0.0  # 0x6084 in user units/s^2 for halt; 0 = use axis acceleration
    # master side: a drive whose TPDO1/TPDO2 miss this many SYNCs in a row has failed (TPDO_TIMEOUT); a
    # host that stalls longer than that (a busy laptop, drives simulated in the master's process) needs more
    tpdo_timeout_syncs: int = 3

    def __post_init__(self) -> None:
        if isinstance(self.tpdo_timeout_syncs, bool) or not isinstance(self.tpdo_timeout_syncs, int) or not (
            1 <= self.tpdo_timeout_syncs <= 100
        ):
            raise PlanningError(
                CONFIG,
                f"drive.tpdo_timeout_syncs is {self.tpdo_timeout_syncs!r}; it must be a whole number of SYNCs "
                "in 1..100",
                path="drive.tpdo_timeout_syncs",
            )
        if self.heartbeat_ms > 0 and self.heartbeat_timeout_ms < self.heartbeat_ms + 10 + 50:
            raise PlanningError(
                CONFIG,
                f"drive.heartbeat_timeout_ms {self.heartbeat_timeout_ms} must be at least heartbeat_ms "
                f"({self.heartbeat_ms}) + 60: the drives' producer times are spread up to 10 ms above it",
                path="drive.heartbeat_timeout_ms",
            )
        if not (0 <= self.underflow_warning < self.overflow_warning <= 64):
            raise PlanningError(
                CONFIG,
                f"watermarks must satisfy 0 <= underflow_warning ({self.underflow_warning}) < "
                f"overflow_warning ({self.overflow_warning}) <= 64",
                path="drive.underflow_warning",
            )


@dataclass(frozen=True)
class ZenohSettings:
    mode: str = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    telemetry_hz: float = 20.0

    def __post_init__(self) -> None:
        if self.mode not in ("peer", "client", "router"):
            raise PlanningError(CONFIG, f"zenoh.mode must be peer, client or router, got {self.mode!r}",
                                path="zenoh.mode")


_SUBJECT = re.compile(r"^(cn:[^+:]+|user:[^+:]+|cn:[^+:]+\+user:[^+:]+|user:[^+:]+\+cn:[^+:]+)$")


@dataclass(frozen=True)
class SecuritySettings:
    """[security]: TLS links, logins and the roles of the job API (docs/security.md); off by default.

    Role lists hold subjects: 'cn:NAME' (a certificate's common name), 'user:NAME' (a login) or
    'cn:NAME+user:NAME' (both). Files are relative to the cell config; streamer/api/security.py reads them.
    """

    enabled: bool = False
    ca: str = ""  # the CA certificate (PEM) that signs every certificate of the deployment
    certificate: str = ""  # the service's certificate (PEM)
    private_key: str = ""  # the service's private key (PEM)
    mtls: bool = True  # clients must present a certificate signed by `ca`
    users_file: str = ""  # "user:password" lines: clients must also log in
    user: str = ""  # the service's own login when it dials a router that asks for one
    password_file: str = ""  # the file holding that login's password
    operator: tuple[str, ...] = ()
    observer: tuple[str, ...] = ()
    service: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        def bad(key: str, message: str) -> PlanningError:
            return PlanningError(CONFIG, f"security.{key}: {message}", path=f"security.{key}")

        seen: dict[str, str] = {}
        for role in ("operator", "observer", "service"):
            for subject in getattr(self, role):
                text = subject.replace(" ", "")
                if not _SUBJECT.match(text):
                    raise bad(role, f"subject {subject!r} must be 'cn:NAME', 'user:NAME' or 'cn:NAME+user:NAME'")
                if text in seen:
                    raise bad(role, f"subject {subject!r} is in both {seen[text]} and {role}")
                seen[text] = role
                if "cn:" in text and not self.mtls:
                    raise bad(role, f"subject {subject!r} names a certificate but mtls = false")
                if "user:" in text and not self.users_file:
                    raise bad(role, f"subject {subject!r} names a login but there is no users_file")
        if bool(self.user) != bool(self.password_file):
            raise bad("user", "user and password_file go together")
        if not self.enabled:
            return
        for key in ("ca", "certificate", "private_key"):
            if not getattr(self, key):
                raise bad(key, "is required when security is enabled")
        if not self.mtls and not self.users_file:
            raise bad("mtls", "false needs a users_file: clients must be identified by certificate or login")
        if not (self.operator or self.observer or self.service):
            raise bad("operator", "no role has a subject: nobody could use the service")


@dataclass(frozen=True)
class CellConfig:
    name: str
    sync_period_ms: int
    axes: tuple[AxisConfig, ...]
    bus: BusConfig = field(default_factory=BusConfig)
    drive: DriveSettings = field(default_factory=DriveSettings)
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    security: SecuritySettings = field(default_factory=SecuritySettings)
    source: str = ""  # file the config was loaded from, for messages and default store location
    # the master sends the high-resolution time stamp 0x1013 after every SYNC (seed 001 3.6.2) so that
    # drives with their own clock correct it
    time_stamp: bool = False
    # TPDO2 (position feedback) every n-th SYNC, staggered over the axes; 0 = the smallest n that fits
    # the bus budget (1 on small cells)
    feedback_every_syncs: int = 0
    # homing: jobs that move an axis the master has not referenced (no home job since the drive's
    # last fault or power cycle) are refused NOT_HOMED
    require_homing: bool = False

    def __post_init__(self) -> None:
        if not (1 <= self.sync_period_ms <= 255):
            raise PlanningError(CONFIG, f"cell.sync_period_ms must be 1..255, got {self.sync_period_ms}",
                                path="cell.sync_period_ms")
        if not self.axes:
            raise PlanningError(CONFIG, "a cell needs at least one [[axis]]", path="axis")
        if not 0 <= self.feedback_every_syncs <= 16:
            raise PlanningError(CONFIG, f"cell.feedback_every_syncs must be \"auto\" or 1..16, got "
                                f"{self.feedback_every_syncs}", path="cell.feedback_every_syncs")
        names: list[str | int] = [a.name for a in self.axes]
        ids: list[str | int] = [a.node_id for a in self.axes]
        for label, values in (("name", names), ("node_id", ids)):
            dup = next((v for v in values if values.count(v) > 1), None)
            if dup is not None:
                at = [i for i, v in enumerate(values) if v == dup]
                which = " and ".join(f"axis[{i}] {self.axes[i].name!r}" for i in at)
                raise PlanningError(CONFIG, f"duplicate axis {label} {dup!r}: {which} both have it; each axis "
                                    f"needs its own {label}", path=f"axis[{at[1]}].{label}")
        self._check_families()

    def _check_families(self) -> None:
        """What the drive families ask of the cell (bus/families.py): the XtrapulsPac's node ids 1..63 and
        SYNC period of at most 150 ms (seed 003 1), and multiplexed groups that fit one frame."""
        groups: dict[int, list[AxisConfig]] = {}
        for a in self.axes:
            if a.profile == "xtrapuls-ip":
                if a.node_id > 63:
                    raise PlanningError(CONFIG, f"axis '{a.name}': an XtrapulsPac takes node ids 1..63 (64..127 "
                                        f"redirect its SDOs), got {a.node_id}", path="axis.node_id")
                if self.sync_period_ms > 150:
                    raise PlanningError(CONFIG, f"axis '{a.name}': an XtrapulsPac's SYNC period is at most 150 ms, "
                                        f"cell.sync_period_ms is {self.sync_period_ms}", path="cell.sync_period_ms")
            if a.mux_group:
                groups.setdefault(a.mux_group, []).append(a)
        for g, members in sorted(groups.items()):
            names = ", ".join(repr(a.name) for a in members)
            bits = sum(32 if a.ip_submode == "pv" else 16 for a in members)
            if len(members) > 4 or bits > 64:
                raise PlanningError(
                    CONFIG, f"mux_group {g} ({names}) needs {bits} bits in one frame: a multiplexed frame carries "
                    "64 (four 16-bit positions, or two positions with their 16-bit velocities in sub-mode pv)",
                    path="axis.mux_group")

    @property
    def sync_period_s(self) -> float:
        return self.sync_period_ms / 1000.0

    def axis(self, name: str) -> AxisConfig:
        for a in self.axes:
            if a.name == name:
                return a
        raise PlanningError("AXIS_ID", f"unknown axis {name!r} (cell has {[a.name for a in self.axes]})",
                            path="axes")

    def axis_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.axes)

    def with_axes(self, n: int) -> CellConfig:
        """The first n axes, or more axes made by repeating the configured ones with new names and ids."""
        if n < 1 or n > 127:
            raise PlanningError(CONFIG, f"axis count must be 1..127, got {n}", path="axes")
        out = []
        for i in range(n):
            base = self.axes[i % len(self.axes)]
            if i < len(self.axes):
                out.append(base)
            else:
                used = {a.node_id for a in out} | {a.node_id for a in self.axes}
                nid = next(k for k in range(1, 128) if k not in used)
                # a copy gets an RPDO of its own (its group's frame is full with the originals)
                out.append(_replace(base, name=f"{base.name}_{i // len(self.axes)}", node_id=nid, mux_group=0))
        cell: CellConfig = _replace(self, axes=tuple(out))
        return cell


def _replace(obj: Any, **changes: Any) -> Any:
    import dataclasses

    return dataclasses.replace(obj, **changes)


def _section(data: Mapping[str, Any], key: str, cls: type, path: str) -> Any:
    raw = data.get(key, {})
    if not isinstance(raw, Mapping):
        raise PlanningError(CONFIG, f"[{path}] must be a table, got {type(raw).__name__}", path=path)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise PlanningError(CONFIG, f"{_unknown_keys(f'[{path}]', unknown, sorted(known))} (known: "
                            f"{', '.join(sorted(known))})", path=f"{path}.{unknown[0]}")
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        if f.name not in raw:
            continue
        v = raw[f.name]
        if f.type in ("int",) or f.type is int:
            v = int(_number(path, f.name, v, integer=True))
        elif f.type in ("float",) or f.type is float:
            v = _number(path, f.name, v)
        elif f.type == "bool":
            if not isinstance(v, bool):
                raise PlanningError(CONFIG, f"{path}.{f.name} must be true or false, got {v!r}",
                                    path=f"{path}.{f.name}")
        elif "tuple" in str(f.type):
            if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
                raise PlanningError(CONFIG, f"{path}.{f.name} must be a list of strings",
                                    path=f"{path}.{f.name}")
            v = tuple(v)
        elif not isinstance(v, str):
            raise PlanningError(CONFIG, f"{path}.{f.name} must be a string, got {v!r}",
                                path=f"{path}.{f.name}")
        kwargs[f.name] = v
    return cls(**kwargs)


_AXIS_TRAVEL = ("modulo_period", "modulo_tolerance", "emergency_deceleration", "target_window", "in_target_timeout_ms")
_AXIS_OPTIONAL = ("probed", "sim", "unit", "profile", "ip_submode", "mux_group", *_AXIS_TRAVEL)
_AXIS_REQUIRED = [f.name for f in fields(AxisConfig) if f.name not in _AXIS_OPTIONAL]


def cell_from_dict(data: Mapping[str, Any], *, source: str = "") -> CellConfig:
    """Build a validated CellConfig from parsed TOML."""
    allowed = {"cell", "axis", "bus", "drive", "zenoh", "sim", "probed", "security"}
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise PlanningError(CONFIG, f"{_unknown_keys('the cell config', unknown, sorted(allowed))} (sections: "
                            f"{', '.join(sorted(allowed))})", path=unknown[0])
    cell = data.get("cell")
    if not isinstance(cell, Mapping):
        raise PlanningError(CONFIG, "missing [cell] table", path="cell")
    cell_keys = ["name", "sync_period_ms", "time_stamp", "feedback_every_syncs", "require_homing"]
    extra = sorted(set(cell) - set(cell_keys))
    if extra:
        raise PlanningError(CONFIG, _unknown_keys("[cell]", extra, cell_keys), path=f"cell.{extra[0]}")
    name = check_name(cell.get("name"), "cell.name", path="cell.name", code=CONFIG)
    period = int(_number("cell", "sync_period_ms", cell.get("sync_period_ms", 10), integer=True))
    time_stamp = cell.get("time_stamp", False)
    if not isinstance(time_stamp, bool):
        raise PlanningError(CONFIG, f"cell.time_stamp must be true or false, got {time_stamp!r}",
                            path="cell.time_stamp")
    require_homing = cell.get("require_homing", False)
    if not isinstance(require_homing, bool):
        raise PlanningError(CONFIG, f"cell.require_homing must be true or false, got {require_homing!r}",
                            path="cell.require_homing")
    every = cell.get("feedback_every_syncs", "auto")
    every = 0 if every == "auto" else int(_number("cell", "feedback_every_syncs", every, integer=True))
    raw_axes = data.get("axis")
    if not isinstance(raw_axes, list) or not raw_axes:
        raise PlanningError(CONFIG, "a cell needs at least one [[axis]] table", path="axis")
    axes = []
    for i, ax in enumerate(raw_axes):
        p = f"axis[{i}]"
        if not isinstance(ax, Mapping):
            raise PlanningError(CONFIG, f"{p} must be a table", path=p)
        missing = [k for k in _AXIS_REQUIRED if k not in ax]
        unknown_k = sorted(set(ax) - set(_AXIS_REQUIRED) - set(_AXIS_OPTIONAL))
        label = f"{p} ({ax.get('name', '?')!r})"
        # unknown keys first: a misspelt key is also a missing one, and the misspelling is the news
        if unknown_k:
            raise PlanningError(CONFIG, _unknown_keys(label, unknown_k, [*_AXIS_REQUIRED, *_AXIS_OPTIONAL]),
                                path=f"{p}.{unknown_k[0]}")
        if missing:
            raise PlanningError(CONFIG, f"{label} is missing {missing}", path=f"{p}.{missing[0]}")
        if not isinstance(ax["name"], str):
            raise PlanningError(CONFIG, f"{p}.name must be a string", path=f"{p}.name")
        kw: dict[str, Any] = {"name": ax["name"]}
        if "unit" in ax:
            if not isinstance(ax["unit"], str):
                raise PlanningError(CONFIG, f"{p}.unit must be a string such as \"mm\", got {ax['unit']!r}",
                                    path=f"{p}.unit")
            kw["unit"] = ax["unit"]
        for k in _AXIS_REQUIRED[1:]:
            integer = k in ("node_id", "counts_per_rev")
            val = _number(p, k, ax[k], integer=integer)
            kw[k] = int(val) if integer else val
        for key in ("profile", "ip_submode"):
            if key in ax:
                if not isinstance(ax[key], str):
                    raise PlanningError(CONFIG, f"{p}.{key} must be a string, got {ax[key]!r}", path=f"{p}.{key}")
                kw[key] = ax[key]
        if "mux_group" in ax:
            kw["mux_group"] = int(_number(p, "mux_group", ax["mux_group"], integer=True))
        for key in _AXIS_TRAVEL:
            if key in ax:  # given in the file: > 0 (0 is the dataclass' "not set"), but a window may be 0
                integer = key == "in_target_timeout_ms"
                val = _number(p, key, ax[key], positive=key != "modulo_tolerance", integer=integer)
                kw[key] = int(val) if integer else val
        kw["probed"] = drive_readings(data.get("probed"), ax.get("probed"), p)
        kw["sim"] = sim_options(data.get("sim"), ax.get("sim"), p)
        try:
            axes.append(AxisConfig(**kw))
        except PlanningError as e:
            raise PlanningError(e.code, e.message, path=e.path.replace("axis.", f"{p}.")) from None
    return CellConfig(
        name=name,
        sync_period_ms=period,
        axes=tuple(axes),
        bus=_section(data, "bus", BusConfig, "bus"),
        drive=_section(data, "drive", DriveSettings, "drive"),
        zenoh=_section(data, "zenoh", ZenohSettings, "zenoh"),
        security=_section(data, "security", SecuritySettings, "security"),
        source=source,
        time_stamp=time_stamp,
        feedback_every_syncs=every,
        require_homing=require_homing,
    )


def load_cell(path: str | Path) -> CellConfig:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise PlanningError(CONFIG, f"cell config {str(p)!r} not found", path="config") from None
    except tomllib.TOMLDecodeError as e:
        raise PlanningError(CONFIG, f"cell config {str(p)!r} is not valid TOML: {e}", path="config") from None
    return cell_from_dict(data, source=str(p))


DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "configs" / "demo.toml"


def default_config_path() -> Path:
    """configs/demo.toml of the source tree, or the copy installed as package data."""
    if DEFAULT_CONFIG.exists():
        return DEFAULT_CONFIG
    packaged = Path(__file__).resolve().parent / "data" / "demo.toml"
    return packaged
