"""Service loops run in-process on MemoryNodes, for tests that wire them as Zenoh would."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from vistrack.common.bus import MemoryNode
from vistrack.services import cli

IDLE_S = 60.0  # a first frame may wait for numba's kernels to load


def parse(command: str, *argv: str):
    return cli.build_parser(command).parse_args([command, *argv])


class Running:
    """A service loop on a MemoryNode in a thread, stopped on exit: the command's ``loop``,
    or ``target(node, args, *extra)``."""

    def __init__(self, command: str, *argv: str, target: Callable[..., Any] | None = None,
                 extra: tuple = ()) -> None:
        module = cli.COMMANDS[command][0]
        loop = target or __import__(f"vistrack.services.{module}", fromlist=["loop"]).loop
        self.node = MemoryNode(command.replace("-", "_"))
        self.thread = threading.Thread(target=loop,
                                       args=(self.node, parse(command, *argv), *extra),
                                       daemon=True)

    def __enter__(self) -> Running:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.node.stop.set()
        self.thread.join(10)
        self.node.close()

    def feed(self, key: str, payload: bytes, *, wait: bool = True,
             reliable: bool = False) -> None:
        """Deliver ``payload`` (sent BLOCK if ``reliable``) once the loop has subscribed;
        ``wait``: until it is handled."""
        deadline = time.monotonic() + IDLE_S
        while not self.node.feed(key, payload, reliable=reliable):
            assert self.thread.is_alive() and time.monotonic() < deadline, key
            time.sleep(0.01)
        if wait:
            assert self.node.wait_idle(IDLE_S), f"{key}: not handled within {IDLE_S} s"
