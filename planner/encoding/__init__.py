"""The planner's second stage: a `Reference` -> what each drive is sent, and proof of what it makes of it.

FIFO drives (PVT records): `encoder` places and values the knots (`quantise`, compiled), `chain` and
`continuity` keep the drive's cubic on the plan, `record` is the 8-byte wire record. Cyclic drives:
`cyclic`. The drive's side: `hermite` (its interpolation), `reconstruction` (what it rebuilds). The
baseline: `uniform`. Importing the package imports none of its modules (the bus layer stays cheap).
"""
