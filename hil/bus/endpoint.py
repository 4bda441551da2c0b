"""How a running rig is found and joined: its endpoint file and its per-run credential.

``hil up`` with no router opens an embedded Zenoh hub on a free loopback port. Loopback alone
does not keep other users of the machine out (anyone could find the port with ``ss -ltnp``, join,
and publish on any key), so each run makes a secret and every listener of the rig -- the hub and
each service's own -- admits only sessions that prove it (Zenoh ``transport/auth/usrpwd``; a
session without it is refused at the handshake). The secret goes to the rig's own processes, and
to the user's viewers, through files in the user's runtime directory, which only that user can
read:

    <runtime>/<rig>-<pid>.users   the dictionary every listener checks ("user:password"), 0600
    <runtime>/<rig>-<pid>.json5   a Zenoh configuration that joins this run (hub endpoint, user,
                                  password, the dictionary for its own listeners), 0600
    <runtime>/<rig>.json5         the same, under the rig's name: where ``hil monitor --rig R``
                                  (and any zenoh program: ``zenoh.Config.from_file``) finds it

``<runtime>`` is ``$HIL_RUNTIME_DIR``, else ``$XDG_RUNTIME_DIR/hil``, else ``/tmp/hil-<uid>``;
it must be a directory owned by the user and closed to everyone else (0700), or nothing is
written or read there. The files go when the run ends (the name file only if it is still this
run's: two rigs of one name may overlap); a file left by a killed run names a process that is
gone and is ignored, and the next ``hil up`` of this user removes a killed run's own two files
(:func:`remove_stale_run_files`; its name file stays until the rig's next run replaces it: a
sweep could race that run's write). ``hil up --open-bus`` writes the
endpoint without a credential: then any local process may join (the hub still listens on loopback
only).

The first line of each ``.json5`` file is a comment, ``// hil-endpoint {JSON}``, with the rig, the
endpoint, the supervisor's pid and whether the run is authenticated.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import stat
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from hil.bus.session import BusConfig, BusConfigError

RUNTIME_ENV = "HIL_RUNTIME_DIR"
HEADER = "// hil-endpoint "
USER = "hil"
ZENOH_ENV = ("HIL_ZENOH_MODE", "HIL_ZENOH_CONNECT", "HIL_ZENOH_LISTEN", "HIL_ZENOH_CONFIG")


def runtime_dir(env: Mapping[str, str] | None = None, *, create: bool = False) -> Path:
    """The user's private directory for endpoint files; ``BusConfigError`` if it is not private."""
    env = os.environ if env is None else env
    if env.get(RUNTIME_ENV):
        path = Path(env[RUNTIME_ENV])
    elif env.get("XDG_RUNTIME_DIR"):
        path = Path(env["XDG_RUNTIME_DIR"]) / "hil"
    else:
        path = Path(tempfile.gettempdir()) / f"hil-{os.getuid()}"
    return private_dir(path, create=create)


def private_dir(path: Path, *, create: bool = False) -> Path:
    """``path`` if it is a directory only this user can enter (made so with ``create``)."""
    if create:
        with contextlib.suppress(FileExistsError):
            path.mkdir(mode=0o700, parents=False)
    try:
        st = path.lstat()
    except FileNotFoundError:
        return path  # nothing there yet: nothing to find, and create=False writes nothing
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise BusConfigError(
            f"{path} is not a private directory of this user (owner uid {st.st_uid}, mode "
            f"{stat.filemode(st.st_mode)}): remove it, or set {RUNTIME_ENV} to a directory only you can read"
        )
    return path


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` as mode 0600, atomically (a reader never sees half a file)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def run_pid(path: Path) -> int | None:
    """The pid in the name of a run's file (``<rig>-<pid>.<suffix>``, :class:`RigAccess`'s), or None."""
    pid = path.stem.rsplit("-", 1)[-1]
    return int(pid) if pid.isdigit() else None


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (another user's counts: it cannot be signalled, but is there)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_run_files(directory: Path) -> list[Path]:
    """Remove the files of killed runs in ``directory``: ``<rig>-<pid>.users`` and
    ``<rig>-<pid>.json5`` whose supervisor ``pid`` is gone (a ``.json5`` only when its own header
    names that pid: a rig's *name* file, ``<rig>.json5``, is never taken for one, whatever the rig
    is called). Returns what it removed."""
    removed = []
    for path in [*directory.glob("*-*.users"), *directory.glob("*-*.json5")]:
        pid = run_pid(path)
        if pid is None or pid_alive(pid):
            continue
        if path.suffix == ".json5":
            found = read_endpoint(path)
            if found is None or found.pid != pid:
                continue
        with contextlib.suppress(OSError):
            path.unlink()
            removed.append(path)
    return removed


@dataclass
class RigAccess:
    """One run's way in: the hub endpoint, and (unless open) the user name and secret."""

    rig: str
    endpoint: str
    pid: int
    authenticated: bool = True
    password: str = ""
    directory: Path | None = None

    @classmethod
    def new(cls, rig: str, endpoint: str, *, authenticated: bool = True) -> RigAccess:
        """A fresh secret for a run (not written yet: ``write``)."""
        return cls(
            rig=rig,
            endpoint=endpoint,
            pid=os.getpid(),
            authenticated=authenticated,
            password=secrets.token_hex(24) if authenticated else "",
            directory=runtime_dir(create=False),
        )

    # -- the files -------------------------------------------------------------------------------
    @property
    def dir(self) -> Path:
        return self.directory or runtime_dir()

    @property
    def config_path(self) -> Path:
        """This run's Zenoh configuration (its services' and its viewers')."""
        return self.dir / f"{self.rig}-{self.pid}.json5"

    @property
    def can_dir(self) -> Path:
        """This run's local CAN directory (``hil.can.local_bus``), where it has one."""
        return self.dir / f"{self.rig}-{self.pid}.can"

    @property
    def users_path(self) -> Path:
        return self.dir / f"{self.rig}-{self.pid}.users"

    @property
    def name_path(self) -> Path:
        """Where viewers look for the rig by name."""
        return self.dir / f"{self.rig}.json5"

    def zenoh_json(self) -> dict[str, object]:
        """The Zenoh configuration a session needs to join this run (a viewer's: no listener)."""
        conf: dict[str, object] = {
            "mode": "peer",
            "connect": {"endpoints": [self.endpoint]},
            "listen": {"endpoints": []},
            "scouting": {"multicast": {"enabled": False}},
        }
        if self.authenticated:
            conf["transport"] = {
                "auth": {
                    "usrpwd": {
                        "user": USER,
                        "password": self.password,
                        "dictionary_file": str(self.users_path),
                    }
                }
            }
        return conf

    def text(self) -> str:
        head = {"rig": self.rig, "endpoint": self.endpoint, "pid": self.pid}
        head["authenticated"] = self.authenticated
        return (
            f"{HEADER}{json.dumps(head)}\n"
            "// A Zenoh configuration that joins this running rig (zenoh.Config.from_file); written by\n"
            "// hil up for its user only, removed when the run ends. docs/deploy.md, Security.\n"
            + json.dumps(self.zenoh_json(), indent=2)
            + "\n"
        )

    def write(self) -> None:
        """Write the dictionary, the run's configuration and the rig's name file (all 0600)."""
        self.directory = private_dir(self.dir, create=True)
        if self.authenticated:
            _write_private(self.users_path, f"{USER}:{self.password}\n")
        text = self.text()
        _write_private(self.config_path, text)
        _write_private(self.name_path, text)

    def remove(self) -> None:
        """Remove this run's files; the name file only while it still names this run."""
        for p in (self.users_path, self.config_path):
            with contextlib.suppress(OSError):
                p.unlink()
        found = read_endpoint(self.name_path)
        if found is not None and found.pid == self.pid:
            with contextlib.suppress(OSError):
                self.name_path.unlink()

    # -- how the rig's own sessions use it --------------------------------------------------------
    def hub_config(self) -> BusConfig:
        """The supervisor's hub: a Zenoh router on the endpoint, checking the dictionary.

        A router, so every service reaches every other through it by construction. With a peer
        hub the services had to find each other by gossip and link pairwise; a pair whose link
        did not form (seen once in CI: the IMU emulator and the CAN bridge) never heard each
        other for the whole run, since a Zenoh 1.10 peer -- or router -- does not relay between
        two peers.
        """
        return BusConfig(mode="router", listen=(self.endpoint,), connect=(), config_file=self._config_file())

    def child_config(self) -> BusConfig:
        """A service: a client of the hub (no listener of its own, so nothing to guard but the
        hub's, which checks the dictionary)."""
        return BusConfig(
            mode="client",
            connect=(self.endpoint,),
            listen=(),
            config_file=self._config_file(),
        )

    def _config_file(self) -> str | None:
        return str(self.config_path) if self.authenticated else None


def read_endpoint(path: Path) -> RigAccess | None:
    """The run an endpoint file describes, or None when it is missing or not one."""
    try:
        first = path.read_text().split("\n", 1)[0]
    except OSError:
        return None
    if not first.startswith(HEADER):
        return None
    try:
        head = json.loads(first[len(HEADER) :])
        return RigAccess(
            rig=str(head["rig"]),
            endpoint=str(head["endpoint"]),
            pid=int(head["pid"]),
            authenticated=bool(head["authenticated"]),
            directory=path.parent,
        )
    except (ValueError, KeyError, TypeError):
        return None


def find_rig(rig: str, env: Mapping[str, str] | None = None) -> tuple[RigAccess | None, str]:
    """The running rig ``rig`` of this user, and a note saying why none (``""`` when found)."""
    try:
        directory = runtime_dir(env)
    except BusConfigError as err:
        return None, str(err)
    path = directory / f"{rig}.json5"
    found = read_endpoint(path)
    if found is None:
        return None, f"no endpoint file {path} (is hil up --rig {rig} running as this user?)"
    if not pid_alive(found.pid):
        return None, f"{path} is left from a run that ended (pid {found.pid} is gone)"
    return found, ""


def viewer_bus(rig: str, env: Mapping[str, str] | None = None) -> tuple[BusConfig, str]:
    """How a viewer (``hil monitor``, ``hil fault``, ``hil foxglove``) reaches rig ``rig``, and
    what it found: the environment's Zenoh settings when any is set (a router, another host);
    else the running rig's endpoint file; else the default (``BusConfig.from_env``)."""
    env = os.environ if env is None else env
    if any(env.get(k) for k in ZENOH_ENV):
        return BusConfig.from_env(env), "the HIL_ZENOH_* environment"
    found, why = find_rig(rig, env)
    if found is None:
        return BusConfig.from_env(env), why
    cfg = BusConfig(
        mode="peer",
        connect=(found.endpoint,),
        listen=(),
        config_file=str(found.name_path) if found.authenticated else None,
    )
    return cfg, f"{found.name_path} ({found.endpoint})"
