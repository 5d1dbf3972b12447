"""Simulated CiA 402 servo drives, one model per drive family on a shared CiA 402 part.

`device.py` (what every family shares, in layers), `epos.py` (maxon's PVT FIFO), `xtrapuls.py` (Infranor,
one set point per SYNC), `csp.py` (CiA 402 cyclic synchronous position), `cyclic_drive.py` (what the
cyclic two share), `od.py` / `eds.py` (object dictionaries and EDS files), `motor.py`, `clock.py`, and
`virtual.py` / `node.py` (a cell's drives in virtual time, or in real time through canopen `LocalNode`s).
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
