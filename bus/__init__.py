"""Everything on the wire: CANopen codecs, drive profiles, the master-side adapter, simulated drives.

Importing `bus` imports no I/O library; the adapters that do (`bus.network`, `bus.sim.node`) are
imported explicitly by whoever runs them.
"""
