"""Open Zenoh sessions from config: the one place that knows how the rig reaches its peers.

Embedded default (no router, no docker): peer mode, multicast scouting off, listening on
loopback only, connecting to the rig's local hub endpoint (``hil up`` opens that hub and hands
its endpoint to every child in ``HIL_ZENOH_CONNECT``). A bench or compose deployment sets
``HIL_ZENOH_MODE=client`` and ``HIL_ZENOH_CONNECT=tcp/router:7447`` (or a json5 file in
``HIL_ZENOH_CONFIG``) instead.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field

import zenoh

DEFAULT_HUB = "tcp/127.0.0.1:7447"


class BusConfigError(ValueError):
    """The Zenoh configuration is unusable; the message says which setting and why."""


@dataclass(frozen=True)
class BusConfig:
    mode: str = "peer"  # "peer" | "client" | "router"
    connect: tuple[str, ...] = (DEFAULT_HUB,)
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    config_file: str | None = None  # a zenoh json5 file; the fields above then only override it
    extra: Mapping[str, object] = field(default_factory=dict)  # json5 path -> value

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> BusConfig:
        """Read ``HIL_ZENOH_MODE``, ``HIL_ZENOH_CONNECT``, ``HIL_ZENOH_LISTEN``, ``HIL_ZENOH_CONFIG``."""
        env = os.environ if env is None else env
        mode = env.get("HIL_ZENOH_MODE", "peer").strip() or "peer"
        if mode not in ("peer", "client", "router"):
            raise BusConfigError(f"HIL_ZENOH_MODE={mode!r}: use peer, client or router")
        connect = _split(env.get("HIL_ZENOH_CONNECT")) or (DEFAULT_HUB,)
        default_listen: tuple[str, ...] = () if mode == "client" else ("tcp/127.0.0.1:0",)
        listen = _split(env.get("HIL_ZENOH_LISTEN")) or default_listen
        cfg_file = env.get("HIL_ZENOH_CONFIG") or None
        if cfg_file and not os.path.isfile(cfg_file):
            raise BusConfigError(f"HIL_ZENOH_CONFIG={cfg_file!r}: no such file")
        return cls(mode=mode, connect=connect, listen=listen, config_file=cfg_file)

    def to_env(self) -> dict[str, str]:
        """The environment that makes a child process open the same kind of session."""
        env = {
            "HIL_ZENOH_MODE": self.mode,
            "HIL_ZENOH_CONNECT": ",".join(self.connect),
            "HIL_ZENOH_LISTEN": ",".join(self.listen),
        }
        if self.config_file:
            env["HIL_ZENOH_CONFIG"] = self.config_file
        return env


def _split(value: str | None) -> tuple[str, ...]:
    return tuple(v.strip() for v in (value or "").split(",") if v.strip())


def zenoh_config(cfg: BusConfig) -> zenoh.Config:
    """Build the ``zenoh.Config`` for ``cfg``."""
    try:
        conf = zenoh.Config.from_file(cfg.config_file) if cfg.config_file else zenoh.Config()
    except Exception as err:  # zenoh raises its own ZError with the parse message
        raise BusConfigError(f"cannot read Zenoh config {cfg.config_file!r}: {err}") from err
    settings: dict[str, object] = {"mode": cfg.mode}
    if not cfg.config_file:
        settings["scouting/multicast/enabled"] = False
    if cfg.connect:
        settings["connect/endpoints"] = list(cfg.connect)
    if cfg.listen or cfg.mode != "client":
        settings["listen/endpoints"] = list(cfg.listen)
    settings.update(cfg.extra)
    for path, value in settings.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except Exception as err:
            raise BusConfigError(f"Zenoh setting {path}={value!r} rejected: {err}") from err
    return conf


# Zenoh's async runtimes (rx, tx, app, acc, net) each start worker threads; a rig process moves a
# few thousand small messages a second, and on a machine the rig shares, the threads' wake-ups
# cost more CPU than they parallelise. So: one async worker (rx, accept and net handed over to
# it) and one for tx. `hil up` at 400 Hz, 20-30 s runs alternating with Zenoh's defaults on the
# same machine (load 4-6): the rig's CPU 115-122 % of a core in 5 runs against 129-149 % in 6, the
# hub's own ~23 -> ~19 %, no sample lost, the median IMU-to-fused-output latency ~1 ms longer.
# Giving rx a thread of its own saved less (119-149 %). ``ZENOH_RUNTIME`` set by the user wins.
# Not the hub's (hil up's own process, as hil router and zenohd): it routes every message of the
# rig, and on one worker it fell behind at 2 kHz with CAN FD (~10000 messages/s in, more out):
# in 30 s the recorder missed 56000-98000 messages (12-43 % of the IMU topics, a quarter of the
# truth) and the IMU reached the bridge at 1000-1400 Hz. On Zenoh's defaults it lost none, for
# 0-5 % more of a core at 400 Hz (2026-12-03, 30 s runs of hil up on a quiet machine).
RIG_ZENOH_RUNTIME = (
    "(rx: (handover: app), acc: (handover: app), net: (handover: app), "
    "app: (worker_threads: 1), tx: (worker_threads: 1))"
)
ZENOH_RUNTIME_ENV = "ZENOH_RUNTIME"  # read by Zenoh once, when the process's first session opens


def use_rig_runtime(env: dict[str, str] | None = None) -> None:
    """The rig's Zenoh runtime sizing in ``env`` (default: this process's environment, before its
    first session), unless ``ZENOH_RUNTIME`` already says otherwise."""
    if env is None:
        os.environ.setdefault(ZENOH_RUNTIME_ENV, RIG_ZENOH_RUNTIME)
    else:
        env.setdefault(ZENOH_RUNTIME_ENV, RIG_ZENOH_RUNTIME)


def open_session(cfg: BusConfig | None = None) -> zenoh.Session:
    """Open a session; raises ``BusConfigError`` with the reason when Zenoh refuses."""
    cfg = cfg or BusConfig.from_env()
    try:
        return zenoh.open(zenoh_config(cfg))
    except BusConfigError:
        raise
    except Exception as err:
        raise BusConfigError(
            f"cannot open a Zenoh {cfg.mode} session (connect={list(cfg.connect)}, "
            f"listen={list(cfg.listen)}): {err}"
        ) from err
