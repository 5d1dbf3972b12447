"""Simulated CiA 402 servo drives, one model per drive family on a shared CiA 402 part.

- `device.py`: `DriveDevice`, what every family shares (NMT, heartbeat, SDO, PDOs, EMCY, the CiA 402
  power state machine, the position loop and motor, the drive's clock, the manuals' open points);
- `epos.py`: maxon EPOS interpolated position mode, PVT records into a 64-entry FIFO;
- `xtrapuls.py`: Infranor XtrapulsPac interpolated position mode, one set point per SYNC;
- `csp.py`: CiA 402 cyclic synchronous position (0x607A every SYNC);
- `cyclic_drive.py`: what the two families fed one set point per SYNC share (the period's polynomial played
  over its 1 ms ticks, user units);
- `od.py` / `eds.py`: each family's object dictionary and its EDS; `motor.py`, `clock.py`: the plant
  and the drive's own clock; `virtual.py` / `node.py`: the drives of a cell in virtual time, or in real
  time on a python-can bus through canopen `LocalNode`s.
"""

from __future__ import annotations

from typing import Any

from bus.families import PROFILES
from bus.profile import DriveProfile
from bus.sim.device import DriveDevice
from planner.config import AxisConfig, DriveSettings


def drive_class(profile: DriveProfile) -> type[DriveDevice]:
    """The simulated drive of a profile's family."""
    from bus.sim.csp import CspDrive
    from bus.sim.epos import EposDrive
    from bus.sim.xtrapuls import XtrapulsDrive

    classes: dict[str, type[DriveDevice]] = {"epos-ipm": EposDrive, "xtrapuls-ip": XtrapulsDrive,
                                             "cia402-csp": CspDrive}
    if profile.name not in classes:
        raise ValueError(f"profile: no simulated drive of family {profile.name!r} (have {sorted(classes)})")
    return classes[profile.name]


def make_drive(axis: AxisConfig, settings: DriveSettings | None = None, *, profile: DriveProfile | None = None,
               **kwargs: Any) -> DriveDevice:
    """The simulated drive of `axis`, of its family (`axis.profile`, or `profile` to override)."""
    p = profile if profile is not None else PROFILES[axis.profile]
    return drive_class(p)(axis.node_id, axis, settings, profile=p, **kwargs)
