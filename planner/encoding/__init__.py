"""The planner's second stage: a `Reference` (planner/motion/) -> what each drive is sent, and proof of what it
makes of it.

- FIFO drives (maxon EPOS, PVT records): `encoder` places knots on one shared integer-ms grid and chooses
  their values (`quantise`, compiled), `chain` and `continuity` keep the drive's cubic on the plan (and its
  acceleration continuous for jerk-limited plans); `record` is the 8-byte PVT record on the wire;
- cyclic drives (one set point per SYNC): `cyclic`;
- the drive's side: `hermite` is the single definition of the drive's cubic interpolation, `reconstruction`
  what the drive rebuilds from the knots (what the plan is measured on);
- `uniform`: the baseline an encoding is measured against (the coarsest uniform grid within the same bound).

Importing this package imports none of its modules (`planner.encoding.record` and `hermite` stay cheap for
the bus layer).
"""
