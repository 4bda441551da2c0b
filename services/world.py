"""world: decides the run (time zero, scenario, speed) and publishes the truth trajectory.

The behaviour is ``hil.nodes.world.WorldNode``; deciding the run live (waiting for the services
it was told to wait for, picking time zero on the wall clock, or the same run again after a
restart) is ``hil.runners.live.WorldService``.
"""

from __future__ import annotations

from hil.nodes.world import WorldNode
from hil.runners.live import WorldService, main_for, service_for

SERVICE = service_for(WorldNode, WorldService)
main = main_for(SERVICE, aliases={"--duration": "duration_s"})
