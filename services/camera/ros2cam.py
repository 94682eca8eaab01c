"""The ROS 2 camera source: ``--source ros2:TOPIC`` (e.g. ``ros2:/camera/image_raw``).

Reads   ``<domain>/<topic>/sensor_msgs::msg::dds_::Image_/*`` (``CompressedImage_`` when the
        topic's last name is ``compressed``, image_transport's convention): a ROS 2 camera
        publishing through ``rmw_zenoh``, each image converted as it arrives
Writes  ``vistrack/<robot>/camera/frame``; the liveliness tokens of a ROS 2 node
        ``vistrack_camera`` and its subscription (``@ros2_lv/<domain>/...``), so
        ``ros2 topic info`` counts vistrack among the topic's subscribers

Images in ``mono8``, ``mono16``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, raw Bayer
(``bayer_rggb8`` and the other three patterns) or YUV 4:2:2 (``yuv422_yuy2``, ``yuv422``)
become 8-bit grey (:func:`~vistrack.common.ros2types.frame_of_camera`), resized by ``--size``
if given, and keep the header's stamp (an unstamped image, stamp 0, is stamped on arrival).
An image whose CDR, encoding or data size is wrong is rejected, counted and logged; the camera
goes on. Any type hash is accepted: the type name already fixes the layout, and a Humble
publisher sends none. Frames go out as the ROS 2 camera sends them: ``--fps``, ``--loop`` and
``--in-flight`` do not apply.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time

import zenoh

from ...common import rmw_zenoh as rmw
from ...common import ros2types as r2
from ...common.bus import Node
from ...common.messages import Frame
from ...common.sources import resize
from ...common.vision.preprocess import Grey
from ..runtime import ready, wait_for_consumers

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
    """Publish a ``camera/frame`` for every image of the ROS 2 topic until stopped.

    Over Zenoh each image is converted and published in Zenoh's callback, as a bare relay
    passes a sample on: handing it to the loop thread first cost as much again as the rest of
    the hop (``vistrack bench ros2``). A ROS 2 camera already paces its images; the
    sequence numbers of rmw_zenoh's attachments tell the ones lost on the way (``dropped``).
    In memory (tests) the loop receives them through the node, one at a time.
    """
    topic = topic_of(args.source)
    typename = type_of(topic)
    type_hash = r2.type_hash(typename)
    convert = _Converter(node, typename, size)
    # the graph tokens and the callback need the Zenoh session; a node in memory has none
    session = getattr(node, "session", None)
    if session is None:
        node.subscribe(rmw.topic_key(args.domain, topic, typename, "*"), latest=True)
        node.advertise(node.keys.frame, reliable=False)
        ready(node)
        while not node.stop.is_set():
            item = node.recv(timeout=0.1)
            if item is not None:
                convert(item[1])
        return 0
    node.advertise(node.keys.frame, reliable=False)
    # subscribe to the ROS 2 topic once camera/frame has a reader: a frame published before
    # this process has learnt of preprocessing's subscription reaches nobody (the first image
    # was lost so in two runs of five), and images nobody reads need no converting
    if not wait_for_consumers(node, node.keys.frame):
        return 0  # stopped first
    with rmw.Participant(session, rmw.Rmw(domain=args.domain, node=NODE_NAME)) as participant:
        participant.subscription(topic, typename, type_hash, rmw.QOS_SENSOR,
                                 convert.on_sample, any_hash=True)
        log.info("ROS 2 camera: %s (%s) on domain %d", topic, typename, args.domain)
        ready(node)
        # the images are Zenoh's callback's work: this loop only waits, and says so (a bare
        # stop.wait() left the status's busy_s growing with uptime, and vistrack up killed
        # the camera as hung after its hang_timeout, 5 s)
        while not node.sleep(1.0):
            pass
    return 0


def frame_of_payload(payload: bytes, typename: str, seq: int,
                     size: tuple[int, int] | None = None, grey: Grey | None = None) -> Frame:
    """The ``camera/frame`` number ``seq`` of one CDR ``Image`` or ``CompressedImage``:
    8-bit grey (16-bit images scaled by ``grey``, the camera's: see :class:`Grey`), resized
    to ``size`` (width, height) if given, stamped with the header's stamp (an unstamped image,
    stamp 0, with the time of arrival). ValueError naming what was wrong for an image that
    cannot be converted."""
    frame = r2.frame_of_camera(r2.deserialize(payload, typename), seq=seq, grey=grey)
    if (size is not None and (frame.width, frame.height) != size) \
            or not frame.stamp_ns:  # resized, or from a driver that does not stamp
        image = frame.data if size is None else resize(frame.data, size)
        frame = Frame.from_image(image, seq=seq, stamp_ns=frame.stamp_ns or time.time_ns())
    return frame


class _Converter:
    """ROS 2 images in, ``camera/frame`` out: one image at a time (a lock, since Zenoh may
    call from more than one thread), numbered from 0, bad ones rejected and logged."""

    def __init__(self, node: Node, typename: str, size: tuple[int, int] | None) -> None:
        self.node, self.typename, self.size = node, typename, size
        self.seq = 0
        self.grey = Grey()  # 16-bit images: scaled by the depth of the camera's samples
        self._last: dict[bytes, int] = {}  # publisher GID -> its last sequence number
        self._lock = threading.Lock()
        node.status.extra["frames"] = 0

    def on_sample(self, sample: zenoh.Sample) -> None:
        self.node.status.count_received()
        if sample.attachment is not None:
            try:
                att = rmw.Attachment.decode(sample.attachment.to_bytes())
            except ValueError:
                pass  # not from rmw_zenoh: the image is what matters
            else:
                last = self._last.get(att.gid)
                if last is not None and att.seq > last + 1:
                    self.node.status.count_dropped(att.seq - last - 1)
                self._last[att.gid] = att.seq
        self(sample.payload.to_bytes())

    def __call__(self, payload: bytes) -> None:
        node = self.node
        with self._lock, node.status.timed():
            try:
                frame = frame_of_payload(payload, self.typename, self.seq, self.size,
                                         self.grey)
            except ValueError as e:
                node.status.reject(e)
                log.error("rejected %s: %s", self.typename, e)
                return
            node.publish(node.keys.frame, frame.encode(), reliable=False)
            self.seq += 1
            # an existing key's value: safe against the status reply copying the dict
            node.status.extra["frames"] = self.seq
