"""The runtimes: the streamer core on a bus.

- `virtual`: virtual time, a discrete-event model of one CAN bus between the core and the simulated
  drives (tests, `pvt demo --fast`);
- `realtime`: the core on a python-can bus through `bus.network.MasterAdapter` (`pvt demo`, `pvt serve`);
- `backend`: the motion backend of `pvt serve` (planner + real-time runtime);
- `trace`: what a job looked like on the bus, shared by both runtimes (report, plots).
"""
