"""``argus router``: a Zenoh router run from Python (the eclipse-zenoh package embeds one).

Example::

    argus router --listen tcp/127.0.0.1:7447
    argus router --config deploy/zenoh/router.json5
    argus router --config router-tls.json5 --listen tls/192.168.1.10:7447     # a LAN: TLS only

Listening on a non-loopback address without TLS is refused unless ``--insecure`` is given.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from protocol.keys import Keys
from protocol.runtime import install_stop_handlers, setup_logging
from protocol.session import ENV_CONNECT, ENV_SITE, ZenohSettings, default_endpoints, default_site, open_session

log = logging.getLogger("argus.router")


def unsupported_plugins(config_file: Path) -> list[str]:
    """Names of the plugins (e.g. ``storage_manager``) a json5 config asks for. The router embedded in
    the eclipse-zenoh Python package loads no plugins, so such a config would start and silently do
    nothing; the ``zenohd`` binary runs them."""
    import json

    import zenoh

    plugins = json.loads(zenoh.Config.from_file(str(config_file)).get_json("plugins") or "{}")
    return sorted(plugins) if isinstance(plugins, dict) else []


def run(settings: ZenohSettings, site: str = "default", ready_file: Path | None = None) -> int:
    """Run a router until SIGINT/SIGTERM. Declares ``alive/router/<zid>`` while up."""
    stop = install_stop_handlers()
    with open_session(settings) as session:
        zid = str(session.info.zid())
        token = session.liveliness().declare_token(Keys(site).alive("router", zid[:32]))
        log.info("router %s listening on %s", zid, ", ".join(settings.listen) or "(config file)")
        if ready_file is not None:  # atomic, so a watcher never reads it half-written
            tmp = ready_file.with_name(ready_file.name + ".tmp")
            tmp.write_text(zid)
            os.replace(tmp, ready_file)
        stop.wait()
        log.info("router shutting down")
        token.undeclare()
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="argus router",
        description="Run a Zenoh router. Every other Argus process connects to it in client mode.",
        epilog="example: argus router --listen tcp/127.0.0.1:7447",
    )
    p.add_argument("--listen", action="append", default=None,
                   help=f"endpoint to listen on (repeatable; default ${ENV_CONNECT} or tcp/127.0.0.1:7447)")
    p.add_argument("--connect", action="append", default=[], help="other routers to connect to (repeatable)")
    p.add_argument("--config", type=Path, default=None, help="json5 Zenoh config file (e.g. deploy/zenoh/router.json5)")
    p.add_argument("--site", default=None, help=f"site name for the liveliness token (default ${ENV_SITE} or default)")
    p.add_argument("--insecure", action="store_true",
                   help="allow a plaintext listen endpoint on a non-loopback address (logs a warning; "
                   "refused otherwise, use tls/ endpoints: docs/SECURITY.md)")
    p.add_argument("--ready-file", type=Path, default=None, help="write the router id here once listening")
    p.add_argument("--log-level", default="INFO")
    a = p.parse_args(argv)
    setup_logging("router", a.log_level)
    listen = a.listen if a.listen is not None else ([] if a.config else default_endpoints())
    try:
        plugins = unsupported_plugins(a.config) if a.config else []
        if plugins:
            raise ValueError(
                f"{a.config} configures Zenoh plugins ({', '.join(plugins)}), which the Python router cannot load;"
                " run the zenohd binary for storages, or remove the plugins section"
            )
        settings = ZenohSettings(mode="router", connect=a.connect, listen=listen, config_file=a.config,
                                 insecure=a.insecure)
        return run(settings, a.site or default_site(), a.ready_file)
    except Exception as e:  # noqa: BLE001 - configuration errors end the process with a message
        print(f"argus router: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
