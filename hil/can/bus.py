"""The one factory for CAN transports: SocketCAN where the kernel has the channel, else the rig's
local sockets (``hillocal``, under ``hil up``), else Zenoh.

Emulator, bridge and replayer all call :func:`open_can_bus` and then only use python-can's
``BusABC`` API, so the same code runs on a bench with a real or virtual SocketCAN interface, in
user-mode-linux, in containers, or on a kernel without CAN at all.
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import can

from hil.can.local_bus import DIR_ENV as LOCAL_DIR_ENV  # the rig's local CAN directory (hil up's)
from hil.can.local_bus import LocalCanBus, running_rig_dir

INTERFACES = ("auto", "socketcan", "hillocal", "hilzenoh", "virtual", "udp_multicast")
#: A SocketCAN reader's kernel queue (candump -r): at 1 Mbit/s a bus carries ~7,400 classic
#: frames a second, and the default queue (~200 kB, a few hundred frames with their buffers)
#: overflows -- silently, frames lost in the kernel -- when the reading process stalls for a
#: fraction of a second (a loaded host, user-mode-linux's one slow vCPU).
SOCKETCAN_RCVBUF_BYTES = 8 << 20


class CanTransportError(RuntimeError):
    """The requested CAN transport cannot be opened; says which one, on which channel, why."""


def channel_exists(channel: str) -> bool:
    """True if this kernel has a network interface of that name (``vcan0``, ``can0``)."""
    return Path("/sys/class/net", channel).exists()


def interface_problem(channel: str, interface: str | None) -> str:
    """Why ``--can-interface``/``--channel`` cannot be opened, found before anything starts
    ("" when nothing is known against them): an interface python-can does not have, or SocketCAN
    on a channel this kernel lacks. Otherwise the bridge would die mid-run with a traceback."""
    iface = (interface or "auto").strip().lower()
    if iface == "auto":
        return ""
    known = {"hillocal", "hilzenoh", *can.interfaces.VALID_INTERFACES}
    if iface not in known:
        return (
            f"--can-interface {interface}: python-can has no such interface; use one of "
            f"{', '.join(sorted(known))}, or leave it out (socketcan if the channel exists, else hillocal)"
        )
    if iface == "socketcan" and not channel_exists(channel):
        return (
            f"--can-interface socketcan: this kernel has no CAN interface {channel} "
            f"(/sys/class/net/{channel}); create it (modprobe vcan; ip link add dev {channel} type vcan; "
            f"ip link set up {channel}) or give another --channel"
        )
    return ""


def resolve_interface(
    channel: str, interface: str | None, env: Mapping[str, str] | None = None, rig: str | None = None
) -> str:
    """``None``/``"auto"`` -> ``socketcan`` when the channel exists here, else ``hillocal`` when the
    process belongs to a rig that made a local CAN directory (``HIL_CAN_DIR``: ``hil up`` on one
    machine) or ``rig`` names one running here, else ``hilzenoh`` (containers, hosts joined
    through a router)."""
    iface = (interface or "auto").strip().lower()
    if iface == "auto":
        if channel_exists(channel):
            return "socketcan"
        if (os.environ if env is None else env).get(LOCAL_DIR_ENV):
            return "hillocal"
        if rig is not None and running_rig_dir(rig, env) is not None:
            return "hillocal"
        return "hilzenoh"
    return iface


def open_can_bus(
    channel: str = "vcan0",
    interface: str | None = None,
    *,
    fd: bool = False,
    rig: str = "default",
    session: Any = None,
    receive: bool = True,
    **kwargs: Any,
) -> tuple[can.BusABC, str]:
    """Open the bus; return it and a one-line description of the transport chosen.

    ``session``: a service's open Zenoh session, reused by ``hilzenoh`` (ignored otherwise).
    ``receive=False``: the caller only sends (``hilzenoh`` then subscribes to nothing).
    Extra keyword arguments go to ``can.Bus``.
    """
    iface = resolve_interface(channel, interface, rig=rig)
    kw: dict[str, Any] = dict(kwargs)
    if iface in ("hillocal", "hilzenoh"):  # ours: the rig names the bus (hillocal: if no directory does)
        kw.setdefault("rig", rig)
    if iface == "hilzenoh":
        kw.setdefault("no_traffic_warn_s", 0.0)  # the rig's own processes know their rig
        if session is not None:
            kw["session"] = session
        if not receive:
            kw["receive"] = False
            kw.setdefault("no_traffic_warn_s", 0)  # opened before time zero: silence is expected
    try:
        if iface == "hillocal":  # ours: no need of python-can's registry (the entry point)
            bus: can.BusABC = LocalCanBus(channel=channel, fd=fd, receive=receive, **kw)
        else:
            bus = can.Bus(interface=iface, channel=channel, fd=fd, **kw)
    except (can.CanError, OSError, ValueError, ImportError) as err:
        why = (
            "the kernel has no such interface (try interface='hilzenoh')"
            if iface == "socketcan" and not channel_exists(channel)
            else str(err)
        )
        raise CanTransportError(f"cannot open CAN {iface}:{channel} (fd={fd}): {why}") from err
    if iface == "socketcan" and receive:
        enlarge_receive_queue(bus, SOCKETCAN_RCVBUF_BYTES)
    auto = " (auto)" if (interface or "auto").lower() == "auto" else ""
    where = f"channel {channel}"
    if iface == "hilzenoh":
        where = f"key hilcan/{rig}/{channel}"
    elif isinstance(bus, LocalCanBus):
        where += f" in {bus.dir}"
    desc = f"{iface}{auto} {where}, {'CAN FD' if fd else 'CAN 2.0'}"
    return bus, desc


def enlarge_receive_queue(bus: can.BusABC, size: int) -> int:
    """Ask for a ``size``-byte kernel receive queue on a SocketCAN bus (beyond ``rmem_max`` when
    privileged, as candump -r does); returns what the kernel granted (0: not a socket bus)."""
    sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket):
        return 0
    # SO_RCVBUFFORCE (Linux 33; Python does not name it): past rmem_max, with CAP_NET_ADMIN
    for opt in (getattr(socket, "SO_RCVBUFFORCE", 33), socket.SO_RCVBUF):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, opt, size)
            break
    return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))
