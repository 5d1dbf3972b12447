"""Pure math, no I/O: cell configs and jobs -> time-optimal trajectories -> PVT points."""
