"""The bounds of a run, in a module of their own: ``hil.runtime.argtypes`` (every command line,
every service process) checks them without importing the scenario loader and numpy with it."""

from __future__ import annotations

#: The longest run a scenario (or ``--duration``) may ask for: ~11.6 days of rig time. Longer is a
#: typo: ``1e12`` once asked ``hil sim`` for a 14.6 TiB allocation.
MAX_DURATION_S = 1e6
#: The rig clock's speed (rig seconds per wall second): faster, no host keeps up (``hil up``
#: holds ~4x on 2 cores); slower, one rig second takes over 16 minutes.
MIN_SPEED, MAX_SPEED = 1e-3, 1000.0
#: The largest σ a GNSS fix may claim (m, m/s); σ must be > 0 too: the fusion refuses a fix
#: outside (0, MAX_GNSS_SIGMA) as implausible (``hil.fusion.core.implausible``), and the scenario
#: loader a receiver model or spoofer that would send one.
MAX_GNSS_SIGMA = 1e6
