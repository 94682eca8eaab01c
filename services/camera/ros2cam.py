"""The ROS 2 camera source: ``--source ros2:TOPIC`` (e.g. ``ros2:/camera/image_raw``).

Reads   ``<domain>/<topic>/sensor_msgs::msg::dds_::Image_/*`` (``CompressedImage_`` when the
        topic's last name is ``compressed``, image_transport's convention): a ROS 2 camera
        publishing through ``rmw_zenoh``, the newest image converted (latest only)
Writes  ``vistrack/<robot>/camera/frame``; the liveliness tokens of a ROS 2 node
        ``vistrack_camera`` and its subscription (``@ros2_lv/<domain>/...``), so
        ``ros2 topic info`` counts vistrack among the topic's subscribers

Images in ``mono8``, ``mono16``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, raw Bayer
(``bayer_rggb8`` and the other three patterns) or YUV 4:2:2 (``yuv422_yuy2``/``yuyv``,
``yuv422``/``uyvy``; see :data:`~vistrack.common.ros2types.IMAGE_ENCODINGS`)
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
from ..runtime import ready, reject, wait_for_consumers

log = logging.getLogger("vistrack.camera")

PREFIX = "ros2:"
NODE_NAME = "vistrack_camera"
#: Seconds without an image after which the camera says where to look (once).
NO_IMAGE_S = 5.0
#: A publisher that sent nothing for this long has gone (s): one that comes then replaces it
PUBLISHER_GONE_S = 2.0


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
    """Publish a ``camera/frame`` for the images of the ROS 2 topic until stopped, latest only.

    Zenoh's callback keeps the newest image and wakes this loop, which converts and publishes
    it; an image still waiting when a newer one comes is dropped (counted in ``dropped``), as
    the sequence numbers of rmw_zenoh's attachments count the ones lost on the way. Converted
    in the callback itself (handing over cost as much again as the rest of the hop, ``vistrack
    bench ros2``), images that took longer to convert than the camera's period queued behind
    each other: a 4K JPEG stream at 30 Hz (50 ms a decode) ran 4.7 s behind after 5 s, every
    estimate late and the robot stopped by its controller.
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
        # waiting counts as waiting (a bare stop.wait() left the status's busy_s growing
        # with uptime, and vistrack up killed the camera as hung after its hang_timeout)
        started = time.monotonic()
        said = False
        while not node.stop.is_set():
            if node.wait_event(convert.waiting, 1.0):
                payload = convert.take()
                if payload is not None:
                    convert(payload)
            elif not said and time.monotonic() - started >= NO_IMAGE_S \
                    and not node.status.received:
                said = True
                log.warning("%s", no_image_said(session, topic, typename, args.domain))
    return 0


def no_image_said(session: zenoh.Session, topic: str, typename: str, domain: int) -> str:
    """What to say of a topic that sent no image in NO_IMAGE_S: where to look, and the
    publishers of a topic of that name the ROS 2 graph has on other domains or of another
    type (a domain, a namespace or a raw/compressed mismatch was total silence)."""
    text = (f"no image on {topic} ({typename}, ROS domain {domain}) in {NO_IMAGE_S:g} s: is "
            "the camera publishing that topic, on that domain (--domain, ROS_DOMAIN_ID)? A "
            "topic whose last name is 'compressed' is read as CompressedImage, any other as "
            "Image")
    env = os.environ.get("ROS_DOMAIN_ID", "")
    try:
        rmw.validate_domain(int(env))
    except ValueError:
        if env:
            text += (f"; ROS_DOMAIN_ID={env!r} is not a domain id "
                     f"{rmw.DOMAIN_RANGE[0]}..{rmw.DOMAIN_RANGE[1]}: the default was 0")
    name = rmw.mangle(topic)
    seen = set()
    try:
        for reply in session.liveliness().get(f"{rmw.ADMIN_SPACE}/**", timeout=1.0):
            if reply.ok is None:
                continue
            parts = rmw.token_parts(str(reply.ok.key_expr))
            if parts is not None and parts[1] == rmw.PUBLISHER and parts[2] == name:
                seen.add(f"domain {parts[0]} ({parts[3]})")
    except zenoh.ZError:
        pass  # the session is closing
    if seen:
        text += f"; publishers of a topic of that name: {', '.join(sorted(seen))}"
    return text


def frame_of_payload(payload: bytes, typename: str, seq: int,
                     size: tuple[int, int] | None = None, grey: Grey | None = None) -> Frame:
    """The ``camera/frame`` number ``seq`` of one CDR ``Image`` or ``CompressedImage``:
    8-bit grey (16-bit images scaled by ``grey``, the camera's: see :class:`Grey`), resized
    to ``size`` (width, height) if given, stamped with the header's stamp (an unstamped image,
    stamp 0, with the time of arrival). ValueError naming what was wrong for an image that
    cannot be converted."""
    scale = None if size is None else (lambda image: resize(image, size))
    frame = r2.frame_of_camera(r2.deserialize(payload, typename), seq=seq, grey=grey,
                               resize=scale)
    if not frame.stamp_ns:  # from a driver that does not stamp
        frame = Frame.from_image(frame.data, seq=seq, stamp_ns=time.time_ns())
    return frame


class _Converter:
    """ROS 2 images in, ``camera/frame`` out: one image at a time, the newest (see
    :func:`run_ros2`), numbered from 0, bad ones rejected and logged."""

    def __init__(self, node: Node, typename: str, size: tuple[int, int] | None) -> None:
        self.node, self.typename, self.size = node, typename, size
        self.seq = 0
        self.grey = Grey()  # 16-bit images: scaled by the depth of the camera's samples
        # publisher GID -> its last sequence number, and when it was seen (monotonic s)
        self._last: dict[bytes, tuple[int, float]] = {}
        self._said_first = False  # a publisher has been seen
        self._slot_lock = threading.Lock()  # Zenoh's callback against the loop
        self._newest: bytes | None = None  # the image waiting to be converted
        self.waiting = threading.Event()  # set while one waits
        node.status.extra["frames"] = 0

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh's callback: count, keep the image as the newest, wake the loop."""
        node = self.node
        node.status.count_received()
        if sample.attachment is not None:
            try:
                att = rmw.Attachment.decode(sample.attachment.to_bytes())
            except ValueError:
                pass  # not from rmw_zenoh: the image is what matters
            else:
                now = time.monotonic()
                seen = self._last.get(att.gid)
                if seen is not None and att.seq > seen[0] + 1:
                    node.status.count_dropped(att.seq - seen[0] - 1)
                if seen is None:
                    self._new_publisher(now)
                self._last[att.gid] = att.seq, now
        payload = sample.payload.to_bytes()
        with self._slot_lock:
            if self._newest is not None:
                node.status.count_dropped(1)  # overwritten before it was converted
            self._newest = payload
            self.waiting.set()

    def _new_publisher(self, now: float) -> None:
        """Say a new publisher: a second camera on the topic (a warning) where another one
        sent within :data:`PUBLISHER_GONE_S`, else the camera driver restarted (a restarted
        driver was said to be a second publisher, "N in all" growing with each restart).
        Publishers silent that long are forgotten."""
        for gid in [g for g, (_, t) in self._last.items() if now - t >= PUBLISHER_GONE_S]:
            del self._last[gid]
        if self._last:
            log.warning("a second publisher on the topic (%d in all): their images are "
                        "taken as one camera's", len(self._last) + 1)
        elif self._said_first:
            log.info("images from a new publisher on the topic (the camera driver "
                     "restarted?)")
        self._said_first = True

    def take(self) -> bytes | None:
        """The newest image waiting, if any (it is no longer waiting)."""
        with self._slot_lock:
            payload, self._newest = self._newest, None
            self.waiting.clear()
        return payload

    def __call__(self, payload: bytes) -> None:
        node = self.node
        with node.status.timed():  # on the loop's thread only
            try:
                frame = frame_of_payload(payload, self.typename, self.seq, self.size,
                                         self.grey)
            except ValueError as e:
                reject(node, log, self.typename, e)  # logged at most every REJECTED_LOG_S
                return
            node.publish(node.keys.frame, frame.encode(), reliable=False)
            self.seq += 1
            # an existing key's value: safe against the status reply copying the dict
            node.status.extra["frames"] = self.seq
