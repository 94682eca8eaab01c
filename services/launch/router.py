"""router: a Zenoh router from the Python binding, for tools and services to meet at.

``vistrack router [-l ENDPOINT ...] [-e ENDPOINT ...] [-c CONFIG.json5] [--no-multicast-scouting]``
listens on ``tcp/127.0.0.1:7447`` unless ``-l`` or the config file says otherwise, prints one
``ready`` line and routes until SIGINT/SIGTERM. ``-e`` connects it to other routers (a mesh
across machines). ``-m`` may only be ``router``; ``--robot`` is accepted for uniformity with the
other subcommands and unused (a router carries every robot's keys).

``vistrack up`` embeds the same router through :func:`start_router`.
"""

from __future__ import annotations

import argparse
import json
import threading

import zenoh

from ...common.bus import (
    BusError,
    add_zenoh_args,
    config_from_args,
    install_signal_handlers,
    open_session,
)
from ..usage import print_error

#: Where the router listens when neither ``-l`` nor a config file names an endpoint.
DEFAULT_LISTEN = ("tcp/127.0.0.1:7447",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_zenoh_args(parser)


def router_config(listen: list[str] | None, config_file: str | None = None, *,
                  connect: list[str] | None = None,
                  multicast_scouting: bool = True) -> zenoh.Config:
    """The ``zenoh.Config`` of a router.

    ``listen`` None keeps the config file's endpoints, or :data:`DEFAULT_LISTEN` without a file
    (Zenoh's own default, every interface, is more than a local launcher needs).

    Raises
    ------
    BusError
        If the config file is missing or invalid, or an endpoint is malformed.
    """
    if listen is None and config_file is None:
        listen = list(DEFAULT_LISTEN)
    args = argparse.Namespace(mode="router", listen=listen, connect=connect, config=config_file,
                              no_multicast_scouting=not multicast_scouting)
    return config_from_args(args)


def listen_endpoints(conf: zenoh.Config) -> list[str]:
    """The endpoints a router built from ``conf`` listens on (the config may give them per mode)."""
    value = json.loads(conf.get_json("listen/endpoints"))
    if isinstance(value, dict):
        value = value.get("router") or []
    return [str(v) for v in value]


def start_router(listen: list[str] | None, config_file: str | None = None, *,
                 connect: list[str] | None = None,
                 multicast_scouting: bool = True) -> zenoh.Session:
    """Open a Zenoh session in router mode; the caller closes it (``with`` or ``close()``).

    Raises
    ------
    BusError
        If the configuration is invalid or the router cannot listen (e.g. the port is in use).
    """
    return open_session(router_config(listen, config_file, connect=connect,
                                      multicast_scouting=multicast_scouting))


def main(args: argparse.Namespace) -> int:
    if args.mode not in (None, "router"):
        print_error("router", f"-m {args.mode}: a router runs in mode router")
        return 2
    try:
        conf = router_config(args.listen, args.config, connect=args.connect,
                             multicast_scouting=not args.no_multicast_scouting)
    except BusError as e:  # a usage error: bad file or endpoint
        print_error("router", e)
        return 2
    try:
        session = open_session(conf)
    except BusError as e:  # e.g. the port is in use
        print_error("router", e)
        return 1
    stop = threading.Event()
    restore = install_signal_handlers(stop)
    try:
        with session:
            # tests and scripts wait for this line
            print(f"vistrack router: ready, listening on {', '.join(listen_endpoints(conf))} "
                  f"(zid {session.zid()})", flush=True)
            stop.wait()
    finally:
        restore()
    print("vistrack router: stopped", flush=True)
    return 0
