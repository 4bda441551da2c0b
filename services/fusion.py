"""fusion: every estimator on the same synchronised inputs, each on ``nav/<estimator>``.

The behaviour is ``hil.nodes.fusion.FusionNode``, run live by ``hil.runners.live``; this module
adds the lockstep acknowledgement ``hil replay --lockstep`` waits for: after each input (and each
journal) the count of inputs pushed into the core, on ``hilack/<rig>`` (``hil.record.lockstep``).
"""

from __future__ import annotations

from typing import Any

from hil.nodes.fusion import FusionNode
from hil.record.lockstep import ack_key, encode_ack
from hil.runners.live import NodeService, main_for, service_for
from hil.runtime import jit


class _FusionService(NodeService):
    def setup(self) -> None:
        jit.enable_in_background()  # before ready; the core uses them once they are in place
        super().setup()
        self._ack: Any = self.ctx.session.declare_publisher(ack_key(self.ctx.rig))

    def after_outputs(self, why: str) -> None:
        node = self.node
        if node is not None and why in ("input", "tick"):
            self._ack.put(encode_ack(node.pushed))  # type: ignore[attr-defined]


SERVICE = service_for(FusionNode, _FusionService)
main = main_for(SERVICE, aliases={"--lag": "lag_s"})
