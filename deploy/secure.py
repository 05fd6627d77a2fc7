"""``argus up --secure``: TLS, one certificate and password per process, and an ACL, from a launch file.

For a site that leaves loopback. Every process of the launch file gets a login (its process name) with
a random password and a client certificate signed by a private CA; the router gets a server
certificate, the password dictionary and an access-control block (:mod:`deploy.acl`) in which a
subject must present *both* the certificate whose common name is its user name and that user's
password. The material lives in one folder (``[security] dir``, default
``~/.local/state/argus/secure/<site>``)::

    <dir>/ca.crt  ca.key                    the private CA (ca.key never leaves the server)
    <dir>/<name>/ca.crt cert.pem key.pem password zenoh.json5    one per process (and consumer)
    <dir>/router/router.json5 users.txt     rewritten at every start from the per-process folders
    <dir>/launcher/                         the `argus up` health view (reads liveliness and status)

Whatever exists is kept (certificates you made yourself included); what is missing is made with
the ``openssl`` command, and only where the local share includes the router (elsewhere: copy
``<dir>/<name>/`` and ``<dir>/launcher/`` over from the server). Rotate a credential by deleting
its folder and starting the router's share again (docs/SECURITY.md).
"""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
import shutil
import subprocess
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from deploy.acl import Principal, Role, access_control
from protocol.keys import validate_id

if TYPE_CHECKING:
    from deploy.up import LaunchFile, ProcessSpec

ROLE_OF_COMMAND: dict[str, Role] = {
    "edge-camera": "edge-camera", "robot-agent": "robot-agent", "mapper": "mapper", "planner": "planner",
    "worker": "worker",
}
DEFAULT_IDS = {"mapper": ("id", "mapper"), "planner": ("node_id", "planner"), "worker": ("id", "worker"),
               "edge-camera": ("id", None), "robot-agent": ("id", None)}
ROUTER_DIR, LAUNCHER = "router", "launcher"
CLIENT_FILE = "zenoh.json5"


class SecuritySpec(BaseModel):
    """The ``[security]`` table of a launch file (or ``argus up --secure``)."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = Field(default=True, description="TLS + per-process user/password + ACL for the whole stack")
    dir: Path | None = Field(
        default=None, description="folder of the CA, certificates and passwords (relative: from the launch "
        "file's folder; default ~/.local/state/argus/secure/<site>). Keep it private (mode 0700)",
    )
    consumers: list[str] = Field(
        default_factory=lambda: ["viewer"],
        description="read-only graph users to create (argus query --zenoh-config <dir>/<name>/zenoh.json5)",
    )
    router_hosts: list[str] = Field(
        default_factory=list, description="extra DNS names / IP addresses in the router certificate (the "
        "endpoint's host, 127.0.0.1 and localhost are always in it)",
    )
    days: int = Field(default=365, gt=0, le=3650, description="validity of generated certificates")

    @field_validator("consumers")
    @classmethod
    def _ids(cls, v: list[str]) -> list[str]:
        return [validate_id(c, "consumer name") for c in v]


def default_dir(site: str) -> Path:
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "argus" / "secure" / site


def _settings_of(spec: ProcessSpec, launch_dir: Path) -> dict[str, Any]:
    if spec.settings is not None:
        return spec.settings
    if spec.config is not None:
        path = spec.config if spec.config.is_absolute() else launch_dir / spec.config
        try:
            return tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as e:
            raise ValueError(f"process {spec.name!r}: cannot read {path} for its id: {e}") from None
    return {}


def principal_of(spec: ProcessSpec, launch_dir: Path) -> Principal:
    """The login of one (non-router) process: its name, role and the id it uses in its keys."""
    role = ROLE_OF_COMMAND.get(spec.command)
    if role is None:
        raise ValueError(f"process {spec.name!r}: command {spec.command!r} has no role in a secure stack "
                         f"(one of router, {', '.join(ROLE_OF_COMMAND)})")
    field, default = DEFAULT_IDS[spec.command]
    node_id = spec.node_id
    if node_id is None and "--id" in spec.args[:-1]:
        node_id = spec.args[spec.args.index("--id") + 1]
    settings = _settings_of(spec, launch_dir)
    node_id = node_id or settings.get(field) or default
    if not node_id or "{" in str(node_id):
        raise ValueError(f"process {spec.name!r}: a secure stack needs its id (settings {field} or --id)")
    local = 0
    if role == "mapper":  # its local worker processes log in with its credentials
        from mapper.work.config import OffloadConfig

        workers = settings.get("workers", {})
        try:
            local = OffloadConfig.model_validate(workers if isinstance(workers, dict) else {}).local
        except ValueError as e:
            raise ValueError(f"process {spec.name!r}: its [workers] settings: {e}") from None
    return Principal(user=spec.name, role=role, node_id=str(node_id), local_workers=local)


def principals(launch: LaunchFile, launch_dir: Path, sec: SecuritySpec) -> list[Principal]:
    """Every login of the site: the processes, the consumers and the launcher's health view."""
    out = [principal_of(p, launch_dir) for p in launch.process if p.command != "router"]
    out += [Principal(user=c, role="consumer", node_id=c) for c in sec.consumers]
    out.append(Principal(user=LAUNCHER, role="monitor", node_id=LAUNCHER))
    users = [p.user for p in out]
    clash = sorted({u for u in users if users.count(u) > 1} | ({ROUTER_DIR} & set(users)))
    if clash:
        raise ValueError(f"names used twice (process, consumer, or reserved {ROUTER_DIR}/{LAUNCHER}): {clash}")
    return out


# --- certificates (openssl command) --------------------------------------------------------------
def _openssl(*args: str) -> None:
    exe = shutil.which("openssl")
    if exe is None:
        raise ValueError("the openssl command is needed to make certificates (apt-get install openssl), or "
                         "put ca.crt and each process's cert.pem / key.pem in the security folder yourself")
    r = subprocess.run([exe, *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise ValueError(f"openssl {args[0]} failed: {r.stderr.strip()[-400:]}")


def _private(path: Path) -> None:
    path.chmod(0o600)


def make_ca(folder: Path, name: str, days: int) -> None:
    """A private CA: ``ca.key`` (EC P-256) and a self-signed ``ca.crt``."""
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
             "-days", str(days), "-subj", f"/CN={name}", "-keyout", str(folder / "ca.key"),
             "-out", str(folder / "ca.crt"), "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    _private(folder / "ca.key")


def _san(host: str) -> str:
    try:
        ipaddress.ip_address(host)
        return f"IP:{host}"
    except ValueError:
        return f"DNS:{host}"


def make_cert(ca_dir: Path, out: Path, common_name: str, hosts: list[str], days: int) -> None:
    """``out/cert.pem`` + ``out/key.pem`` signed by the CA in ``ca_dir``; usable as server and client."""
    with tempfile.TemporaryDirectory() as tmp:
        csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                 "-subj", f"/CN={common_name}", "-keyout", str(out / "key.pem"), "-out", str(csr))
        _private(out / "key.pem")
        sans = ",".join(_san(h) for h in dict.fromkeys(hosts))
        ext.write_text(f"subjectAltName={sans}\nbasicConstraints=critical,CA:FALSE\n"
                       "keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n")
        _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca_dir / "ca.crt"), "-CAkey", str(ca_dir / "ca.key"),
                 "-set_serial", "0x" + secrets.token_hex(16), "-days", str(days), "-extfile", str(ext),
                 "-out", str(out / "cert.pem"))


# --- the material --------------------------------------------------------------------------------
def _endpoint_host(endpoint: str) -> str:
    return endpoint.partition("/")[2].rsplit(":", 1)[0].strip("[]")


def _tls(folder: Path, side: str) -> dict[str, Any]:
    return {"root_ca_certificate": str(folder / "ca.crt"), "enable_mtls": True,
            f"{side}_private_key": str(folder / "key.pem"), f"{side}_certificate": str(folder / "cert.pem")}


def client_config(folder: Path, user: str) -> dict[str, Any]:
    """What one process adds to its Zenoh config: its certificate and its password (and it checks that
    the router's certificate names the host it connects to)."""
    password = (folder / "password").read_text().strip()
    tls = {**_tls(folder, "connect"), "verify_name_on_connect": True}
    return {"transport": {"auth": {"usrpwd": {"user": user, "password": password}}, "link": {"tls": tls}}}


@dataclass(frozen=True)
class SecureSite:
    """Prepared material of one site: where each process's Zenoh config file is."""

    dir: Path
    endpoint: str

    def client_file(self, user: str) -> Path:
        return self.dir / user / CLIENT_FILE

    @property
    def router_file(self) -> Path:
        return self.dir / ROUTER_DIR / "router.json5"


def _ensure_identity(root: Path, user: str, hosts: list[str], sec: SecuritySpec, create: bool) -> None:
    folder = root / user
    have = all((folder / f).exists() for f in ("cert.pem", "key.pem", "password"))
    if not have:
        if not create:
            raise ValueError(f"no credentials for {user!r} in {folder}: copy that folder (and {root / LAUNCHER}) "
                             "from the machine that runs the router, where `argus up --secure` made them")
        if not (root / "ca.key").exists():
            raise ValueError(f"{folder} lacks cert.pem/key.pem/password and there is no {root / 'ca.key'} "
                             "to sign a new certificate")
        folder.mkdir(mode=0o700, exist_ok=True)
        if not (folder / "cert.pem").exists():
            make_cert(root, folder, user, hosts, sec.days)
        if not (folder / "password").exists():
            (folder / "password").write_text(secrets.token_urlsafe(24) + "\n")
            _private(folder / "password")
    if not (folder / "ca.crt").exists():
        shutil.copy(root / "ca.crt", folder / "ca.crt")
    cfg = folder / CLIENT_FILE
    cfg.write_text(json.dumps(client_config(folder, user), indent=2) + "\n")
    _private(cfg)


def prepare(launch: LaunchFile, launch_dir: Path, sec: SecuritySpec, local: list[str],
            secure_dir: Path | None = None) -> SecureSite:
    """Make what is missing (on the router's machine) and write the Zenoh config files.

    ``local``: names of the processes this machine runs. Raises ``ValueError`` with the reason.
    """
    if not launch.endpoint.startswith("tls/"):
        raise ValueError(f"a secure stack needs a tls/ endpoint (have {launch.endpoint}; e.g. tls/127.0.0.1:7447)")
    root = secure_dir or sec.dir or default_dir(launch.site)
    root = (root if root.is_absolute() else launch_dir / root).resolve()
    everyone = principals(launch, launch_dir, sec)
    routers = [p.name for p in launch.process if p.command == "router"]
    create = bool(set(routers) & set(local)) or not routers
    root.mkdir(mode=0o700, parents=True, exist_ok=True)
    root.chmod(0o700)
    if not (root / "ca.crt").exists():
        if not create:
            raise ValueError(f"no {root / 'ca.crt'}: copy the security folder from the router's machine")
        make_ca(root, f"argus-{launch.site}-ca", sec.days)
    router_hosts = ["127.0.0.1", "localhost", _endpoint_host(launch.endpoint), *sec.router_hosts]
    if create:
        _ensure_identity(root, ROUTER_DIR, router_hosts, sec, create)
        for p in everyone:
            _ensure_identity(root, p.user, [p.user], sec, create)
        _write_router(root, launch, everyone)
    else:
        for user in [*local, LAUNCHER]:
            _ensure_identity(root, user, [user], sec, create)
    return SecureSite(dir=root, endpoint=launch.endpoint)


def _write_router(root: Path, launch: LaunchFile, everyone: list[Principal]) -> None:
    folder = root / ROUTER_DIR
    users = folder / "users.txt"
    users.write_text("".join(f"{p.user}:{(root / p.user / 'password').read_text().strip()}\n" for p in everyone))
    _private(users)
    password = (folder / "password").read_text().strip()
    conf = {
        "mode": "router",
        "listen": {"endpoints": [launch.endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "shared_memory": {"enabled": False},
            "auth": {"usrpwd": {"user": ROUTER_DIR, "password": password, "dictionary_file": str(users)}},
            "link": {"tls": _tls(folder, "listen")},
        },
        "access_control": access_control(everyone, launch.site, cert_names=True),
    }
    out = folder / "router.json5"
    out.write_text(json.dumps(conf, indent=2) + "\n")
    _private(out)
