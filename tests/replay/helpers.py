"""Shared by the replay tests: a loopback Zenoh hub that children connect to, and a collector."""

from __future__ import annotations

import os
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from hil.bus.session import BusConfig, open_session
from hil.messages import ServiceStatus, decode
from tests.conftest import REPO, free_port, hil_cmd

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
GOLDEN = GOLDEN_DIR / "straight_level_4s.mcap"
#: the golden recording as the recorder wrote it before the Foxglove-first change (NavSolution's
#: null sigmas, ServiceStatus maps, rig-time log times): old recordings must stay readable
LEGACY_GOLDEN = GOLDEN_DIR / "legacy_straight_level_4s.mcap"


class Hub:
    """A real Zenoh peer on a free loopback port; records statuses and any key it is asked to."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session: zenoh.Session = open_session(
            BusConfig(mode="router", listen=(self.endpoint,), connect=())
        )
        self.status: dict[str, ServiceStatus] = {}
        self.samples: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self._subs = [self.session.declare_subscriber("hil/*/status/*", self._on_status)]

    def _on_status(self, s: zenoh.Sample) -> None:
        st = decode(ServiceStatus, s.payload.to_bytes())
        self.status[st.service] = st

    def collect(self, key: str) -> None:
        def on(s: zenoh.Sample) -> None:
            with self._lock:
                self.samples.append((str(s.key_expr), s.payload.to_bytes()))

        self._subs.append(self.session.declare_subscriber(key, on))

    def env(self) -> dict[str, str]:
        return dict(
            os.environ,
            HIL_ZENOH_MODE="client",
            HIL_ZENOH_CONNECT=self.endpoint,
            HIL_ZENOH_LISTEN="",
        )

    def wait_status(
        self, service: str, pred: Callable[[ServiceStatus], bool], timeout: float = 30.0
    ) -> ServiceStatus:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            st = self.status.get(service)
            if st is not None and pred(st):
                return st
            time.sleep(0.05)
        raise AssertionError(f"{service} status never matched; last: {self.status.get(service)}")

    def spawn(self, *args: str) -> subprocess.Popen[str]:
        return subprocess.Popen(
            hil_cmd(*args),
            cwd=REPO,
            env=self.env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )

    def run(self, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            hil_cmd(*args), cwd=REPO, env=self.env(), capture_output=True, text=True, timeout=timeout
        )

    def close(self) -> None:
        self.session.close()
