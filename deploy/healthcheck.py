"""Container healthcheck: is this container's service alive on the bus?

``HIL_SERVICE=<name>``: healthy when a ``ServiceStatus`` from that service arrives on
``hil/<HIL_RIG>/status/<name>`` within a few seconds and its state is not ``degraded``.
``HIL_SERVICE=router``: healthy when a client session to the local router opens and sees it.
Exit 0 healthy, 1 unhealthy (Docker's convention). Payloads are decoded as typed JSON (msgspec);
nothing from the wire is ever evaluated or unpickled.
"""

from __future__ import annotations

import os
import sys
import threading

import msgspec
import zenoh

from hil.bus.session import BusConfig, open_session

HEALTHY_STATES = ("starting", "waiting_run", "running", "stopping")


class _Status(msgspec.Struct):
    service: str
    state: str


def check_router(timeout_s: float) -> tuple[bool, str]:
    port = os.environ.get("HIL_ROUTER_PORT", "7447")
    cfg = BusConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=())
    try:
        session = open_session(cfg)
    except Exception as err:
        return False, f"router: no session on port {port}: {err}"
    try:
        routers = list(session.info.routers_zid())
        return bool(routers), f"router: {len(routers)} router(s) seen"
    finally:
        session.close()


def check_service(service: str, rig: str, timeout_s: float) -> tuple[bool, str]:
    got: list[_Status] = []
    event = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            got.append(msgspec.json.decode(sample.payload.to_bytes(), type=_Status))
            event.set()
        except msgspec.DecodeError:
            pass

    session = open_session(BusConfig.from_env())
    try:
        sub = session.declare_subscriber(f"hil/{rig}/status/{service}", on_sample)
        event.wait(timeout_s)
        sub.undeclare()
    finally:
        session.close()
    if not got:
        return False, f"{service}: no status on hil/{rig}/status/{service} in {timeout_s:g} s"
    st = got[-1]
    return st.state in HEALTHY_STATES, f"{service}: {st.state}"


def main() -> int:
    service = os.environ.get("HIL_SERVICE", "").strip()
    rig = os.environ.get("HIL_RIG", "bench").strip() or "bench"
    timeout_s = float(os.environ.get("HIL_HEALTH_TIMEOUT_S", "5"))
    if not service:
        sys.stdout.write("healthcheck: HIL_SERVICE is not set\n")
        return 1
    ok, why = check_router(timeout_s) if service == "router" else check_service(service, rig, timeout_s)
    sys.stdout.write(f"healthcheck: {why}\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
