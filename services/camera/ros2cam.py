"""The ROS 2 camera source: ``--source ros2:TOPIC`` (e.g. ``ros2:/camera/image_raw``).

Reads   ``<domain>/<topic>/sensor_msgs::msg::dds_::Image_/*`` (``CompressedImage_`` when the
        topic's last name is ``compressed``, image_transport's convention): a ROS 2 camera
        publishing through ``rmw_zenoh``, received latest-only like any frame
Writes  ``vistrack/<robot>/camera/frame``; the liveliness tokens of a ROS 2 node
        ``vistrack_camera`` and its subscription (``@ros2_lv/<domain>/...``), so
        ``ros2 topic info`` counts vistrack among the topic's subscribers

Images in ``mono8``, ``mono16``, ``rgb8``, ``bgr8``, ``rgba8`` or ``bgra8`` become 8-bit grey
(:func:`~vistrack.common.ros2types.frame_of_camera`), resized by ``--size`` if given, and keep
the header's stamp (an unstamped image, stamp 0, is stamped on arrival). An image whose CDR,
encoding or data size is wrong is rejected, counted and logged; the camera goes on. Any type
hash is accepted: the type name already fixes the layout, and a Humble publisher sends none.
Frames go out as the ROS 2 camera sends them: ``--fps``, ``--loop`` and ``--in-flight`` do not
apply.
"""

from __future__ import annotations

import argparse
import logging
import os
import time

import cv2

from ...common import rmw_zenoh as rmw
from ...common import ros2types as r2
from ...common.bus import Node
from ...common.messages import Frame
from ..runtime import ready

log = logging.getLogger("vistrack.camera")

PREFIX = "ros2:"
NODE_NAME = "vistrack_camera"


def is_ros2(spec: str) -> bool:
    return spec.startswith(PREFIX)


def topic_of(spec: str) -> str:
    """The fully qualified topic of ``ros2:TOPIC``; ValueError naming it if it is not one."""
    topic = spec[len(PREFIX):]
    if not topic:
        raise ValueError(f"--source {spec!r} names no topic: give ros2:TOPIC, e.g. "
                         "ros2:/camera/image_raw")
    return rmw.qualified_topic(topic)


def type_of(topic: str) -> str:
    return r2.COMPRESSED_IMAGE if topic.rsplit("/", 1)[-1] == "compressed" else r2.IMAGE


def default_domain() -> int:
    """``ROS_DOMAIN_ID`` when it is set and valid, else 0."""
    value = os.environ.get("ROS_DOMAIN_ID", "")
    try:
        return rmw.validate_domain(int(value))
    except ValueError:
        return 0


def run_ros2(node: Node, args: argparse.Namespace, size: tuple[int, int] | None) -> int:
    """Publish a ``camera/frame`` for every image of the ROS 2 topic until stopped."""
    topic = topic_of(args.source)
    typename = type_of(topic)
    type_hash = r2.type_hash(typename)
    key = rmw.topic_key(args.domain, topic, typename, type_hash).rsplit("/", 1)[0] + "/*"
    # the graph tokens need the Zenoh session; a node in memory (tests) has none
    session = getattr(node, "session", None)
    participant = (rmw.Participant(session, rmw.Rmw(domain=args.domain, node=NODE_NAME))
                   if session is not None else None)
    try:
        node.subscribe(key, latest=True)
        node.advertise(node.keys.frame, reliable=False)
        if participant is not None:
            participant.subscription(topic, typename, type_hash, rmw.QOS_SENSOR)
        log.info("ROS 2 camera: %s (%s) on domain %d", topic, typename, args.domain)
        ready(node)
        return _run(node, typename, size)
    finally:
        if participant is not None:
            participant.close()


def _run(node: Node, typename: str, size: tuple[int, int] | None) -> int:
    seq = 0
    while not node.stop.is_set():
        item = node.recv(timeout=0.1)
        if item is None:
            continue
        _, payload = item
        with node.status.timed():
            try:
                frame = r2.frame_of_camera(r2.deserialize(payload, typename), seq=seq)
            except ValueError as e:
                node.status.reject(e)
                log.error("rejected %s: %s", typename, e)
                continue
            if (size is not None and (frame.width, frame.height) != size) \
                    or not frame.stamp_ns:  # resized, or from a driver that does not stamp
                image = frame.data if size is None else cv2.resize(
                    frame.data, size, interpolation=cv2.INTER_AREA)
                frame = Frame.from_image(image, seq=seq, stamp_ns=frame.stamp_ns
                                         or time.time_ns())
            node.publish(node.keys.frame, frame.encode(), reliable=False)
        seq += 1
        node.status.extra["frames"] = seq
    return 0
