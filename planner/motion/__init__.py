"""The planner's first stage: what every axis does, millisecond by millisecond (a `Reference`).

Each job kind has its builder here, all ending in `reference.Reference` (the planned motion of every axis at
every ms, in drive units), the one input of the encoding stage (planner/encoding/):

- paths: `geometry` (the waypoints' segments with blended corners, or a spline) timed by `path` with the
  compiled TOPP-RA of `topp` (velocity and acceleration limits), or by `jerkpath` when every axis' jerk limit
  must hold too;
- moves and stops: `jerk` (ruckig, jerk-limited), `travel` (what a move's target means: absolute, relative,
  additive, modulo, endless), `stop` (a stop of all axes from any state, for the streamer's splices);
- the user's own timing: `timed` (splined positions at times, raw PVT rows).

Nothing here knows PVT records or SYNC periods: that is planner/encoding/'s. Importing this package imports
none of its modules (the bus layer imports single modules of the planner and stays cheap).
"""
