"""What every service process shares: flags, logging, the session, parameters in force.

A service module defines ``loop(node, args)`` (the dora-style loop over ``node.recv``) and calls
:func:`serve` from its ``main``; this keeps each ``service.py`` to its loop.
"""

from __future__ import annotations

import argparse
import gc
import logging
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import cv2

from ..common.bus import (
    BusError,
    Node,
    ZenohNode,
    add_zenoh_args,
    config_from_args,
    install_signal_handlers,
)
from ..common.messages import MessageError, Params
from ..common.params import ParamError, TrackerParams
from .usage import add_param_flags, params_from_args, print_error

log = logging.getLogger("vistrack")

LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"


def setup_logging(level: str = "info") -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), format=LOG_FORMAT,
                        datefmt="%H:%M:%S", stream=sys.stderr, force=True)


def add_service_args(parser: argparse.ArgumentParser, *, tracker_params: bool = False) -> None:
    """Zenoh flags, ``--log-level``, and optionally the initial tracker parameters."""
    add_zenoh_args(parser)
    parser.add_argument("--log-level", default="info",
                        choices=("debug", "info", "warning", "error"))
    if tracker_params:
        add_param_flags(parser)


def serve(service: str, args: argparse.Namespace,
          loop: Callable[[Node, argparse.Namespace], int | None]) -> int:
    """Open the service's Zenoh node, run ``loop`` until it returns or SIGINT/SIGTERM, and
    close the session (always: a callback subscriber left open hangs the interpreter)."""
    setup_logging(args.log_level)
    logger = logging.getLogger(f"vistrack.{service}")
    # One thread of OpenCV per service: the pipeline's parallelism is its processes. OpenCV's
    # own pool splits a 256x256 filter across threads that then spin waiting for work, which
    # cost pre-processing 240 us of CPU a frame on 2 cores shared by six processes.
    cv2.setNumThreads(1)
    command = service.replace("_", "-")
    try:
        if hasattr(args, "max_features"):  # the tracker parameter flags: check before Zenoh
            params_from_args(args)
        conf = config_from_args(args)
    except (BusError, ParamError) as e:
        print_error(command, e)
        return 2
    try:
        node = ZenohNode(service, conf, args.robot)
    except BusError as e:  # the session did not open: a port in use, an absent interface
        print_error(command, e)
        return 1
    with node:
        restore = install_signal_handlers(node.stop)
        try:
            rc = loop(node, args)
        finally:
            restore()
    logger.info("stopped")
    return int(rc or 0)


M = TypeVar("M")


def decode_or_reject(cls: type[M], payload: bytes, node: Node, logger: logging.Logger
                     ) -> M | None:
    """Decode a contract message; a bad one is counted in the status, logged with what was
    wrong, and None is returned so the loop goes on to the next input."""
    try:
        return cls.decode(payload)  # type: ignore[attr-defined, no-any-return]
    except MessageError as e:
        node.status.reject(e)
        logger.error("rejected %s: %s", getattr(cls, "KEY", cls.__name__), e)
        return None


def ready(node: Node) -> None:
    """Log the line launchers and tests wait for: call it once the loop has warmed up and
    subscribed to its inputs, so nothing published after the line is missed.

    Everything allocated so far (numba's and llvmlite's compiler objects among it: hundreds of
    thousands) is frozen out of the garbage collector: a full collection walked all of it,
    a pause of milliseconds in the hot path, and the collector ran often because every
    estimate allocates a hundred small lists.
    """
    gc.collect()
    gc.freeze()
    logging.getLogger(f"vistrack.{node.service}").info(
        "ready (robot %s, liveliness token %s)", node.robot, node.keys.alive(node.service))


def wait_for_consumers(node: Node, key: str, *, reliable: bool = False) -> bool:
    """Block until something subscribes to ``key`` (False if the node is stopped first).

    A source that must lose nothing (a file camera, a lockstep simulator) calls it before its
    first publish: a process that has just joined learns of the subscriptions already declared
    only a moment after its session opens, and what it publishes before then reaches nobody
    (the first frame of a file was lost that way about once in twenty runs). Logs once if no
    one has subscribed after 2 s.
    """
    logger = logging.getLogger(f"vistrack.{node.service}")
    if node.wait_for_subscribers(key, reliable=reliable, timeout=2.0):
        return True
    if node.stop.is_set():
        return False
    logger.info("waiting for a subscriber of %s", key)
    while not node.wait_for_subscribers(key, reliable=reliable, timeout=1.0):
        if node.stop.is_set():
            return False
    logger.info("%s has a subscriber: starting", key)
    return True


@dataclass
class ParamsInForce:
    """The tracker parameters a service runs with and how it accepts ``tuner/params``.

    An update is validated first and applied only if it is valid and newer (a larger
    ``params_id``) than what is in force: a bad or stale update is rejected with a logged error
    naming the field and range, counted, and the old parameters stay (validate-then-apply, as
    ROS 2 parameter callbacks do).
    """

    params: TrackerParams
    params_id: int = 0
    source: str = "flags"
    reason: str = "start-up"

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ParamsInForce:
        return cls(params_from_args(args))

    def apply(self, payload: bytes, node: Node, logger: logging.Logger) -> bool:
        """Apply an encoded ``tuner/params``; return True when the parameters changed."""
        try:
            msg = Params.decode(payload)
            new = msg.tracker_params(self.params)
        except (MessageError, ParamError) as e:
            node.status.reject(e)
            logger.error("rejected tuner/params: %s; keeping params_id %d", e, self.params_id)
            return False
        if msg.params_id == self.params_id and new == self.params:
            return False  # the tuner's periodic reminder of what is in force
        if msg.params_id <= self.params_id:
            node.status.reject(f"stale params_id {msg.params_id} <= {self.params_id}")
            logger.warning("ignored tuner/params with params_id %d: %d is in force",
                           msg.params_id, self.params_id)
            return False
        self.params, self.params_id = new, msg.params_id
        self.source, self.reason = msg.source, msg.reason
        self.publish_status(node)
        logger.info("params_id %d from %s (%s): %s", msg.params_id, msg.source,
                    msg.reason or "no reason given", new.factors())
        return True

    def publish_status(self, node: Node) -> None:
        node.status.set_params({**self.params.factors(), "params_id": self.params_id,
                                "source": self.source, "reason": self.reason})
