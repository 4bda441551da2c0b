"""Three "hosts" on one machine: network namespaces joined to a router namespace by veth pairs.

Only addresses inside the namespaces made here are used (10.231.x.y, never on the host side);
everything is removed afterwards. Needs root and ``ip netns``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from tests.docker import _engine


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if check and r.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip()}")
    return r


def netns_reason() -> str | None:
    """None when this process can create network namespaces; else why not, in one line."""
    if shutil.which("ip") is None:
        return "no `ip` command (apt-get install iproute2)"
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add)"
    probe = f"hilprobe{os.getpid()}"
    r = _ip("netns", "add", probe, check=False)
    if r.returncode != 0:
        return f"ip netns add failed: {r.stderr.strip()[:160]}"
    _ip("netns", "del", probe, check=False)
    return None


def require_netns() -> None:
    reason = netns_reason()
    if reason:
        _engine.unavailable(reason)


@dataclass(frozen=True)
class Hosts:
    router: str  # namespace names
    emulators: str
    fusion: str
    router_ip_for_emulators: str
    router_ip_for_fusion: str

    def exec_prefix(self, ns: str) -> list[str]:
        return ["ip", "netns", "exec", ns]


@contextmanager
def three_hosts() -> Iterator[Hosts]:
    tag = f"{os.getpid() % 100000}"
    r, e, f = f"hilr{tag}", f"hile{tag}", f"hilf{tag}"
    made: list[str] = []
    try:
        for ns in (r, e, f):
            _ip("netns", "add", ns)
            made.append(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
        for peer, net in ((e, "1"), (f, "2")):
            a, b = f"v{tag}r{net}", f"v{tag}h{net}"
            _ip("link", "add", a, "type", "veth", "peer", "name", b)
            _ip("link", "set", a, "netns", r)
            _ip("link", "set", b, "netns", peer)
            _ip("-n", r, "addr", "add", f"10.231.{net}.1/24", "dev", a)
            _ip("-n", peer, "addr", "add", f"10.231.{net}.2/24", "dev", b)
            _ip("-n", r, "link", "set", a, "up")
            _ip("-n", peer, "link", "set", b, "up")
        yield Hosts(r, e, f, "10.231.1.1", "10.231.2.1")
    finally:
        for ns in made:  # deleting a namespace removes its veth ends (and their peers)
            _ip("netns", "del", ns, check=False)
