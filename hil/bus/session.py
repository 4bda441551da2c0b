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
