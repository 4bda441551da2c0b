"""Open a page in headless Chromium and collect what its console says (DevTools protocol).

Used by the report's test: a self-contained page must load with no console error, no uncaught
exception and no network request. Stdlib only: the DevTools websocket (RFC 6455, client side:
masked text frames out, unmasked frames in) is small enough to speak directly.

    chromium --headless --remote-debugging-port=0 ...   # prints "DevTools listening on ws://..."
    PUT /json/new?about:blank                           # a page target with its own websocket
    Runtime/Log/Network/Page.enable, Page.navigate, wait for Page.loadEventFired,
    Page.captureScreenshot
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import tempfile
import threading
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--no-default-browser-check",
    "--remote-debugging-port=0",
    "--remote-allow-origins=*",
)


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        p = shutil.which(name)
        if p:
            return p
    return None


class BrowserError(RuntimeError):
    """Chromium could not be started or driven; the message says what it printed."""


@dataclass
class PageReport:
    console: list[tuple[str, str]] = field(default_factory=list)  # (level, text), every level
    exceptions: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)  # every URL the page requested
    failed: list[str] = field(default_factory=list)  # network failures
    screenshot: bytes = b""
    height_px: int = 0

    @property
    def errors(self) -> list[str]:
        """Console errors and warnings, exceptions, failed loads, and any request off the page."""
        out = [f"console.{lvl}: {txt}" for lvl, txt in self.console if lvl in ("error", "warning", "assert")]
        out += [f"exception: {e}" for e in self.exceptions]
        out += [f"failed load: {u}" for u in self.failed]
        out += [f"network request: {u}" for u in self.requests if not u.startswith(("data:", "file:"))]
        return out


class _Ws:
    """A minimal websocket client: enough for the DevTools protocol on loopback."""

    def __init__(self, url: str, timeout_s: float) -> None:
        m = re.match(r"ws://([^/:]+):(\d+)(/.*)", url)
        if not m:
            raise BrowserError(f"unexpected DevTools url {url!r}")
        host, port, path = m.group(1), int(m.group(2)), m.group(3)
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
            ).encode()
        )
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise BrowserError("DevTools closed the websocket during the handshake")
            head += chunk
        status, _, rest = head.partition(b"\r\n\r\n")
        if b" 101 " not in status.split(b"\r\n", 1)[0]:
            raise BrowserError(f"DevTools refused the websocket: {status[:200]!r}")
        self.buf = rest

    def send(self, text: str) -> None:
        data = text.encode()
        mask = os.urandom(4)
        n = len(data)
        if n < 126:
            head = struct.pack("!BB", 0x81, 0x80 | n)
        elif n < 65536:
            head = struct.pack("!BBH", 0x81, 0x80 | 126, n)
        else:
            head = struct.pack("!BBQ", 0x81, 0x80 | 127, n)
        body = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
        self.sock.sendall(head + mask + body)

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(1 << 16)
            if not chunk:
                raise BrowserError("DevTools closed the websocket")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv(self) -> str:
        parts: list[bytes] = []
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                (n,) = struct.unpack("!H", self._read(2))
            elif n == 127:
                (n,) = struct.unpack("!Q", self._read(8))
            mask = self._read(4) if b1 & 0x80 else b""
            data = self._read(n)
            if mask:
                data = bytes(b ^ mask[i % 4] for i, b in enumerate(data))
            op = b0 & 0x0F
            if op == 0x8:
                raise BrowserError("DevTools closed the websocket")
            if op == 0x9:  # ping: answer is optional for a short session
                continue
            if op in (0x1, 0x2, 0x0):
                parts.append(data)
                if b0 & 0x80:
                    return b"".join(parts).decode()

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()


class _Cdp:
    def __init__(self, ws: _Ws, report: PageReport, timeout_s: float = 30.0) -> None:
        self.ws = ws
        self.report = report
        self.timeout_s = timeout_s  # per call: a loaded machine's Chromium answers late, not never
        self.next_id = 0
        self.events: list[dict[str, Any]] = []

    def call(
        self, method: str, params: dict[str, Any] | None = None, timeout_s: float | None = None
    ) -> dict[str, Any]:
        timeout_s = self.timeout_s if timeout_s is None else timeout_s
        self.next_id += 1
        mid = self.next_id
        self.ws.send(json.dumps({"id": mid, "method": method, "params": params or {}}))
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            # the whole time left, not what drain() last set (a screenshot on a loaded machine
            # outlasted drain's remainder: a bare TimeoutError)
            self.ws.sock.settimeout(left)
            try:
                msg = json.loads(self.ws.recv())
            except TimeoutError:
                break
            if msg.get("id") == mid:
                if "error" in msg:
                    raise BrowserError(f"{method}: {msg['error']}")
                return dict(msg.get("result", {}))
            self.on_event(msg)
        raise BrowserError(f"{method}: no answer within {timeout_s} s")

    def wait_event(self, name: str, timeout_s: float) -> bool:
        if any(e.get("method") == name for e in self.events):
            return True
        deadline = time.monotonic() + timeout_s
        self.ws.sock.settimeout(timeout_s)
        while time.monotonic() < deadline:
            try:
                msg = json.loads(self.ws.recv())
            except TimeoutError:
                return False
            self.on_event(msg)
            if msg.get("method") == name:
                return True
        return False

    def drain(self, seconds: float) -> None:
        """Collect events for a while (late console messages after load)."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self.ws.sock.settimeout(left)
            try:
                self.on_event(json.loads(self.ws.recv()))
            except TimeoutError:
                return

    def on_event(self, msg: dict[str, Any]) -> None:
        method = msg.get("method")
        if not method:
            return
        self.events.append({"method": method})
        p = msg.get("params", {})
        r = self.report
        if method == "Runtime.consoleAPICalled":
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
            r.console.append((p.get("type", "log"), text))
        elif method == "Runtime.exceptionThrown":
            d = p.get("exceptionDetails", {})
            r.exceptions.append(str(d.get("exception", {}).get("description") or d.get("text")))
        elif method == "Log.entryAdded":
            e = p.get("entry", {})
            r.console.append(
                (e.get("level", "info"), f"[{e.get('source')}] {e.get('text')} {e.get('url', '')}")
            )
        elif method == "Network.requestWillBeSent":
            r.requests.append(str(p.get("request", {}).get("url", ""))[:200])
        elif method == "Network.loadingFailed":
            r.failed.append(f"{p.get('errorText')} ({p.get('type')})")


def check_page(
    page: Path, *, width: int = 1400, height: int = 3000, timeout_s: float = 60.0, chromium: str | None = None
) -> PageReport:
    """Load ``page`` in headless Chromium; return its console, exceptions, requests and a screenshot."""
    exe = chromium or find_chromium()
    if exe is None:
        raise BrowserError("no chromium on PATH (Debian: apt-get install -y chromium)")
    report = PageReport()
    # Chromium's helper processes may still be writing the profile as the main one exits.
    with tempfile.TemporaryDirectory(prefix="hil-chromium-", ignore_cleanup_errors=True) as profile:
        proc = subprocess.Popen(
            [
                exe,
                *CHROMIUM_FLAGS,
                f"--user-data-dir={profile}",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # its own process group: the helpers go with it
            # its own temporary files (org.chromium.Chromium.*) in the profile, which goes with it:
            # a browser stopped by a signal leaves them behind in /tmp otherwise
            env={**os.environ, "TMPDIR": profile},
        )
        try:
            url = _devtools_url(proc, timeout_s)
            port = int(re.match(r"ws://[^:]+:(\d+)/", url).group(1))  # type: ignore[union-attr]
            req = urllib.request.Request(f"http://127.0.0.1:{port}/json/new?about:blank", method="PUT")
            with urllib.request.urlopen(req, timeout=timeout_s) as resp:
                target = json.loads(resp.read())
            ws = _Ws(target["webSocketDebuggerUrl"], timeout_s)
            try:
                cdp = _Cdp(ws, report, timeout_s)
                for domain in ("Runtime", "Log", "Network", "Page"):
                    cdp.call(f"{domain}.enable")
                cdp.call(
                    "Emulation.setDeviceMetricsOverride",
                    {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False},
                )
                cdp.call("Page.navigate", {"url": page.resolve().as_uri()})
                if not cdp.wait_event("Page.loadEventFired", timeout_s):
                    raise BrowserError(f"{page} did not finish loading within {timeout_s} s")
                cdp.drain(0.5)
                res = cdp.call(
                    "Runtime.evaluate", {"expression": "document.body.scrollHeight", "returnByValue": True}
                )
                report.height_px = int(res.get("result", {}).get("value", 0))
                shot = cdp.call("Page.captureScreenshot", {"format": "png"})
                report.screenshot = base64.b64decode(shot["data"])
            finally:
                ws.close()
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    return report


def _devtools_url(proc: subprocess.Popen[str], timeout_s: float) -> str:
    assert proc.stderr is not None
    deadline = time.monotonic() + timeout_s
    seen: list[str] = []
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line.rstrip())
        m = re.search(r"DevTools listening on (ws://\S+)", line)
        if m:
            # keep the pipe drained, or a chatty chromium blocks on a full stderr
            threading.Thread(target=lambda: [None for _ in proc.stderr or ()], daemon=True).start()
            return m.group(1)
    raise BrowserError("chromium did not start its DevTools server; it said:\n" + "\n".join(seen[-15:]))
