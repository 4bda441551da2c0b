"""The one factory for CAN transports: SocketCAN where the kernel has the channel, else Zenoh.

Emulator, bridge and replayer all call :func:`open_can_bus` and then only use python-can's
``BusABC`` API, so the same code runs on a bench with a real or virtual SocketCAN interface, in
user-mode-linux, in containers, or on a kernel without CAN at all.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can

INTERFACES = ("auto", "socketcan", "hilzenoh", "virtual", "udp_multicast")


class CanTransportError(RuntimeError):
    """The requested CAN transport cannot be opened; says which one, on which channel, why."""


def channel_exists(channel: str) -> bool:
    """True if this kernel has a network interface of that name (``vcan0``, ``can0``)."""
    return Path("/sys/class/net", channel).exists()


def resolve_interface(channel: str, interface: str | None) -> str:
    """``None``/``"auto"`` -> ``socketcan`` when the channel exists here, else ``hilzenoh``."""
    iface = (interface or "auto").strip().lower()
    if iface == "auto":
        return "socketcan" if channel_exists(channel) else "hilzenoh"
    return iface


def open_can_bus(
    channel: str = "vcan0",
    interface: str | None = None,
    *,
    fd: bool = False,
    rig: str = "default",
    session: Any = None,
    **kwargs: Any,
) -> tuple[can.BusABC, str]:
    """Open the bus; return it and a one-line description of the transport chosen.

    ``session``: a service's open Zenoh session, reused by ``hilzenoh`` (ignored otherwise).
    Extra keyword arguments go to ``can.Bus``.
    """
    iface = resolve_interface(channel, interface)
    kw: dict[str, Any] = dict(kwargs)
    if iface == "hilzenoh":
        kw.setdefault("rig", rig)
        kw.setdefault("no_traffic_warn_s", 0.0)  # the rig's own processes know their rig
        if session is not None:
            kw["session"] = session
    try:
        bus = can.Bus(interface=iface, channel=channel, fd=fd, **kw)
    except (can.CanError, OSError, ValueError, ImportError) as err:
        why = (
            "the kernel has no such interface (try interface='hilzenoh')"
            if iface == "socketcan" and not channel_exists(channel)
            else str(err)
        )
        raise CanTransportError(f"cannot open CAN {iface}:{channel} (fd={fd}): {why}") from err
    auto = " (auto)" if (interface or "auto").lower() == "auto" else ""
    where = f"key hilcan/{rig}/{channel}" if iface == "hilzenoh" else f"channel {channel}"
    desc = f"{iface}{auto} {where}, {'CAN FD' if fd else 'CAN 2.0'}"
    return bus, desc
