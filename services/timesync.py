"""timesync: re-stamps every raw measurement to rig time of validity and publishes clock models.

The behaviour is ``hil.nodes.timesync.TimeSyncNode``, run live by ``hil.runners.live``.
"""

from __future__ import annotations

from hil.nodes.timesync import TimeSyncNode
from hil.runners.live import main_for, service_for

SERVICE = service_for(TimeSyncNode)
main = main_for(SERVICE)
