"""The planner's first stage: what every axis does, millisecond by millisecond (a `Reference`).

Each job kind's builder ends in `reference.Reference`, the one input of planner/encoding/: paths
(`geometry`, timed by `path`'s compiled TOPP-RA in `topp`, or by `jerkpath` under jerk limits, or the
moves from waypoint to waypoint of `stop_moves` where faster), moves
and stops (`jerk`, `travel`, `stop`), the user's timing (`timed`). Nothing here knows PVT records or
SYNC periods. Importing the package imports none of its modules (the bus layer stays cheap).
"""
