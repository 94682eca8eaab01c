"""ros2: the pipeline as ROS 2 topics, on the wire exactly as ``rmw_zenoh`` publishes them.

Reads   ``vistrack/<robot>/control/cmd_vel``  (every one, in order)
        ``vistrack/<robot>/motion/estimate``  (latest-only, like every estimate reader)
        ``vistrack/<robot>/tuner/params``     (every one, in order)
Writes  ``<domain>/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_...``
        ``<domain>/vistrack/estimate/vistrack_msgs::msg::dds_::Estimate_/RIHS01_...``
        ``<domain>/vistrack/params/vistrack_msgs::msg::dds_::Params_/RIHS01_...``
        (CDR, each sample with rmw_zenoh's 33-byte attachment) and the liveliness tokens of a
        ROS 2 node ``vistrack`` and its three publishers (``@ros2_lv/<domain>/...``)

A ROS 2 robot running ``rmw_zenoh`` on the same Zenoh network takes ``/cmd_vel`` as from any
ROS 2 node; ``ros2 topic list`` and ``ros2 topic echo /vistrack/estimate`` (with
``vistrack_msgs`` built from ``deploy/ros2``) see the rest. Topic names are relative, so
``--namespace`` moves them (``/robot1/cmd_vel``); ``--remap FROM:=TO`` renames one.
Commands and parameters are published reliable with KEEP_ALL history (Zenoh's BLOCK
congestion control: none dropped), estimates reliable with the last 10 kept. A message that
does not decode is rejected, counted and logged, and the service goes on.

``/cmd_vel`` is the last hop before the motors: a command marked ``stale`` goes out as a stop
whatever its numbers, one stamped more than ``--max-age`` s ago (a replay, clocks out of step)
as a stop too, and every speed is clamped to ``--max-speed`` and ``--max-turn``
(:func:`safe_command`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import struct
import time
from dataclasses import dataclass
from typing import Any

from ...common import rmw_zenoh as rmw
from ...common import ros2types as r2
from ...common.bus import Node
from ...common.messages import CmdVel, Estimate, Params
from ..camera.ros2cam import default_domain
from ..runtime import REJECTED_LOG_S, add_service_args, decode_or_reject, ready, reject, serve
from ..usage import add_number

log = logging.getLogger("vistrack.ros2")


@dataclass(frozen=True)
class Bridge:
    """One contract key published as one ROS 2 topic."""

    attr: str            # the Keys attribute of the contract key
    cls: type            # its contract message
    topic: str           # default ROS 2 name (relative: under --namespace)
    qos: rmw.QoS
    latest: bool         # latest-only on the vistrack side


BRIDGES = (
    Bridge("cmd_vel", CmdVel, "cmd_vel", rmw.QOS_ALL, latest=False),
    Bridge("estimate", Estimate, "vistrack/estimate", rmw.QOS_DEFAULT, latest=True),
    Bridge("params", Params, "vistrack/params", rmw.QOS_ALL, latest=False),
)


def _remap(text: str) -> tuple[str, str]:
    src, sep, dst = text.partition(":=")
    if not sep or not src or not dst:
        raise argparse.ArgumentTypeError(f"{text!r}: expected FROM:=TO, e.g. "
                                          "cmd_vel:=/mobile_base/cmd_vel")
    return src, dst


def add_arguments(parser: argparse.ArgumentParser) -> None:
    ros = parser.add_argument_group("ROS 2")
    add_number(ros, "--domain", lo=rmw.DOMAIN_RANGE[0], hi=rmw.DOMAIN_RANGE[1], integer=True,
               default=default_domain(), metavar="ID",
               help="ROS domain id, %(allowed)s (default: $ROS_DOMAIN_ID, else 0)")
    ros.add_argument("--namespace", default="/", metavar="NS",
                     help="ROS namespace of the node and its topics (default: /)")
    ros.add_argument("--node-name", default="vistrack", metavar="NAME",
                     help="ROS node name (default: vistrack)")
    ros.add_argument("--remap", action="append", default=[], type=_remap, metavar="FROM:=TO",
                     help="rename a topic, as ROS 2's --remap does: cmd_vel, "
                          "vistrack/estimate or vistrack/params (or their full names) to a "
                          "relative or absolute name (repeatable)")
    base = parser.add_argument_group("the base (/cmd_vel: the last hop before the motors)")
    add_number(base, "--max-speed", lo=0.0, hi=100.0, lo_open=True, default=1.0, metavar="M/S",
               help="clamp linear.x and linear.y to +-this, %(allowed)s (default 1; the "
                    "controller commands at most 0.8)")
    add_number(base, "--max-turn", lo=0.0, hi=100.0, lo_open=True, default=1.0,
               metavar="RAD/S", help="clamp angular.z to +-this, %(allowed)s (default 1)")
    add_number(base, "--max-age", lo=0.0, hi=3600.0, default=1.0, metavar="S",
               help="send a stop instead of a command stamped longer ago than this (this "
                    "host's clock), %(allowed)s; 0: no check, for a simulator's clock "
                    "(default 1)")
    add_service_args(parser)


def topics(args: argparse.Namespace) -> dict[str, str]:
    """Contract attribute -> fully qualified ROS 2 topic, after namespace and remaps.

    Raises
    ------
    ValueError
        For a bad namespace, node name or topic, or a remap of no topic of this service.
    """
    rmw.validate_node_name(args.node_name)
    ns = rmw.validate_namespace(args.namespace)
    names = {b.attr: rmw.qualified_topic(b.topic, ns) for b in BRIDGES}
    for src, dst in args.remap:
        hits = [a for a, b in zip(names, BRIDGES, strict=True)
                if src in (b.topic, "/" + b.topic, names[a])]
        if not hits:
            raise ValueError(f"--remap {src}:={dst}: {src!r} is none of this service's topics "
                             f"({', '.join(sorted(names.values()))})")
        for attr in hits:
            names[attr] = rmw.qualified_topic(dst, ns)
    return names


def check_args(args: argparse.Namespace) -> None:
    topics(args)


def loop(node: Node, args: argparse.Namespace, participant: rmw.Participant | None = None
         ) -> int:
    """Republish the contract's commands, estimates and parameters as ROS 2 messages.

    ``participant`` (tests) is the ROS 2 node to publish with; by default one is declared on
    the node's own Zenoh session.
    """
    names = topics(args)
    own = participant is None
    if participant is None:
        participant = rmw.Participant(node.session,  # type: ignore[attr-defined]
                                      rmw.Rmw(args.domain, args.namespace, args.node_name))
    try:
        routes: dict[str, tuple[Bridge, Any]] = {}
        for b in BRIDGES:
            typename = r2.ROS_TYPES[b.cls.KEY]  # type: ignore[attr-defined]
            pub = participant.publisher(names[b.attr], typename, r2.type_hash(typename), b.qos)
            routes[getattr(node.keys, b.attr)] = (b, pub)
            node.subscribe(getattr(node.keys, b.attr), latest=b.latest)
            log.info("%s -> %s (%s)", getattr(node.keys, b.attr), names[b.attr], pub.key)
        node.status.extra.update({names[b.attr]: 0 for b in BRIDGES})
        ready(node)
        while True:
            # what came before the stop is passed on before the loop ends (recv returns None
            # once stopped only with nothing pending): the controller's last command, the
            # stop it sends as it exits, reaches the base (the launcher stops this last)
            item = node.recv(timeout=0.1)
            if item is None:
                if node.stop.is_set():
                    break
                continue
            key, payload = item
            bridge, pub = routes[key]
            msg = decode_or_reject(bridge.cls, payload, node, log)
            if msg is None:
                continue
            if isinstance(msg, CmdVel):
                msg = safe_command(msg, args, node)
            with node.status.timed():
                try:
                    cdr = r2.serialize(r2.to_ros(msg, payload=payload))
                except (struct.error, OverflowError, ValueError) as e:
                    # a valid message whose value the ROS 2 type cannot hold
                    reject(node, log, key, e,
                           f"rejected {key}: no ROS 2 {names[bridge.attr]}: {e}")
                    continue
                pub.put(cdr)
            node.status.count_published()
            node.status.extra[names[bridge.attr]] += 1
    finally:
        if own:
            participant.close()
    return 0


def safe_command(cmd: CmdVel, args: argparse.Namespace, node: Node) -> CmdVel:
    """The command the base gets: a stop where ``cmd`` is ``stale`` (a stop, whatever its
    numbers) or stamped more than ``--max-age`` s ago, its speeds clamped to ``--max-speed``
    and ``--max-turn``; each counted in the status (``stops_sent``, ``old_stopped``,
    ``clamped``) and logged at most once every 5 s. As the last hop before the motors this
    bridge passed on whatever came: a command an hour old, 1e6 m/s, ``stale`` with 0.5 m/s,
    and a replay's recorded moves ten seconds after they were made."""
    extra = node.status.extra
    vx, vy, wz, stale = cmd.vx, cmd.vy, cmd.wz, cmd.stale
    age = time.time() - cmd.stamp_ns * 1e-9
    if not stale and args.max_age > 0 and age > args.max_age:
        extra["old_stopped"] = extra.get("old_stopped", 0) + 1
        if node.status.say("old command", REJECTED_LOG_S) is not None:
            log.warning("control/cmd_vel seq %d is %.3g s old (--max-age %g s): a stop sent "
                        "instead (a replay? clocks out of step?)", cmd.seq, age, args.max_age)
        stale = True
    if stale:
        vx = vy = wz = 0.0
    top, turn = args.max_speed, args.max_turn
    cx, cy, cz = (min(max(vx, -top), top), min(max(vy, -top), top),
                  min(max(wz, -turn), turn))
    if (cx, cy, cz) != (vx, vy, wz):
        extra["clamped"] = extra.get("clamped", 0) + 1
        if node.status.say("clamped command", REJECTED_LOG_S) is not None:
            log.warning("control/cmd_vel seq %d (vx %g, vy %g, wz %g) clamped to --max-speed "
                        "%g m/s, --max-turn %g rad/s", cmd.seq, vx, vy, wz, top, turn)
    if (cx, cy, cz, stale) == (cmd.vx, cmd.vy, cmd.wz, cmd.stale):
        return cmd
    return dataclasses.replace(cmd, vx=cx, vy=cy, wz=cz, stale=stale)


def main(args: argparse.Namespace) -> int:
    return serve("ros2", args, loop)
