"""ROS 2 on the wire as ``rmw_zenoh`` puts it: key expressions, liveliness tokens, attachments.

A Zenoh session that follows these formats is a ROS 2 node to every ``rmw_zenoh`` process on
the network (``ros2 topic list``, ``ros2 topic echo``, ``ros2 node list`` see it), with no
bridge and no ROS installed. The formats are those of ``docs/design.md`` of ``ros2/rmw_zenoh``
(sections "Topic and Service name mapping to Zenoh key expressions", "Graph Cache",
"Publishers") and of ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` (``TopicInfo``,
``Entity``, ``qos_to_keyexpr``, ``mangle_name``) and ``attachment_helpers.cpp``: the format of
rmw_zenoh_cpp as released since April 2025 (rmw_zenoh's PR #601: Jazzy 0.2.4, Humble 0.1.2,
Rolling 0.6.0, Kilted). Earlier releases labelled each field of the attachment
(``sequence_number``, ``source_timestamp``, ``source_gid``) and throw on the unlabelled one:
their samples are read (:meth:`Attachment.decode`), ours are not read by them.

* data: ``<domain>/<fully qualified topic without leading slash>/<DDS type>/<RIHS01 hash>``,
  the payload CDR with its 4-byte encapsulation header (:mod:`.ros2types`), and an attachment
  of 33 bytes: int64 LE sequence number (from 1), int64 LE source timestamp (ns since the Unix
  epoch), the GID's length (16) and the 16-byte GID. rmw_zenoh writes it with zenoh's
  ``ext::Serializer``; so does :func:`attachment` (zenoh-python's ``zenoh.ext``).
* graph: a liveliness token per node (``NN``) and per publisher (``MP``) and subscription
  (``MS``), ``@ros2_lv/<domain>/<session zid>/<node id>/<entity id>/<kind>/<enclave>/
  <namespace>/<node name>[/<topic>/<DDS type>/<hash>/<qos>]``, each name with ``/`` replaced
  by ``%``. An entity's GID is XXH3-128 of its token, as rmw_zenoh computes it.

:class:`Participant` declares these on a Zenoh session (one ROS 2 node per participant).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import re
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import xxhash
import zenoh
import zenoh.ext

log = logging.getLogger(__name__)

ADMIN_SPACE = "@ros2_lv"
#: Entity kinds of a liveliness token (design.md, "Graph Cache").
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"
#: ``ROS_DOMAIN_ID`` values a ROS 2 system accepts (DDS' limit; rmw_zenoh inherits it).
DOMAIN_RANGE = (0, 232)
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
#: The labels before each field of the attachment of rmw_zenoh's releases before April 2025
#: (Jazzy 0.2.0 to 0.2.3, Humble 0.1.0 and 0.1.1), and that form's size: each label a
#: LEB128 length and its bytes
LABELS = ("sequence_number", "source_timestamp", "source_gid")
LABELLED_SIZE = sum(1 + len(label) for label in LABELS) + ATTACHMENT_SIZE

# rmw/types.h enum values, as qos_to_keyexpr writes them
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2

# A ROS 2 name token: letters, digits and '_', not starting with a digit (design article
# "Topic and Service names"); '~' and substitutions are rclcpp's business, not the wire's.
_TOKEN_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Rmw(NamedTuple):
    """How one ROS 2 node is named on the wire: domain id, namespace, node name, enclave."""

    domain: int = 0
    namespace: str = "/"
    node: str = "vistrack"
    enclave: str = "/"


# -- names ------------------------------------------------------------------------------------

def is_name_token(text: str) -> bool:
    """Whether ``text`` is one token of a ROS 2 name (letters, digits and ``_``, not
    starting with a digit)."""
    return _TOKEN_RE.fullmatch(text) is not None


def validate_domain(domain: object) -> int:
    lo, hi = DOMAIN_RANGE
    if isinstance(domain, bool) or not isinstance(domain, int) or not lo <= domain <= hi:
        raise ValueError(f"ROS domain id {domain!r} is out of range: allowed {lo}..{hi}")
    return domain


def validate_namespace(namespace: str) -> str:
    """``namespace`` made absolute (``""`` and ``"/"`` are the root); ValueError if it is not
    a ROS 2 namespace (tokens of letters, digits and ``_``, not starting with a digit)."""
    if namespace in ("", "/"):
        return "/"
    ns = namespace if namespace.startswith("/") else "/" + namespace
    if ns.endswith("/") or not all(_TOKEN_RE.fullmatch(t) for t in ns[1:].split("/")):
        raise ValueError(f"ROS namespace {namespace!r} is not valid: '/'-separated tokens of "
                         "letters, digits and '_', each not starting with a digit")
    return ns


def validate_node_name(name: str) -> str:
    if not _TOKEN_RE.fullmatch(name):
        raise ValueError(f"ROS node name {name!r} is not valid: letters, digits and '_', not "
                         "starting with a digit")
    return name


def qualified_topic(topic: str, namespace: str = "/") -> str:
    """The fully qualified name of ``topic``: absolute names as they are, relative ones under
    ``namespace``. ValueError naming the topic if it is not a valid ROS 2 topic name."""
    if not isinstance(topic, str) or not topic or topic.endswith("/") or "//" in topic:
        raise ValueError(f"ROS topic {topic!r} is not valid: '/'-separated tokens of letters, "
                         "digits and '_' (e.g. /camera/image_raw)")
    ns = validate_namespace(namespace)
    name = topic if topic.startswith("/") else (ns.rstrip("/") + "/" + topic)
    if not all(_TOKEN_RE.fullmatch(t) for t in name[1:].split("/")):
        raise ValueError(f"ROS topic {topic!r} is not valid: '/'-separated tokens of letters, "
                         "digits and '_', each not starting with a digit (e.g. "
                         "/camera/image_raw)")
    return name


def mangle(name: str) -> str:
    """``name`` with every ``/`` replaced by ``%`` (``mangle_name``): one key chunk."""
    return name.replace("/", "%")


def dds_type(typename: str) -> str:
    """``pkg/msg/Type`` -> ``pkg::msg::dds_::Type_``, the type name as declared in DDS."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def topic_key(domain: int, topic: str, typename: str, type_hash: str) -> str:
    """Key expression of a topic's data: ``<domain>/<fully qualified name without the leading
    slash>/<DDS type>/<type hash>`` (design.md, "Topic and Service name mapping")."""
    return f"{validate_domain(domain)}/{topic.strip('/')}/{dds_type(typename)}/{type_hash}"


# -- QoS ---------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class QoS:
    """The QoS policies rmw_zenoh encodes in a token; ``None`` durations are the default
    (infinite). ``depth`` is the history depth (KEEP_LAST)."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42

    #: rmw_zenoh's defaults (``qos.cpp``): what its token leaves empty
    DEFAULT_DEPTH = 42

    def keyexpr(self) -> str:
        """``qos_to_keyexpr``: ``rel:dur:hist,depth:deadline s,ns:lifespan s,ns:liveliness,
        lease s,ns``, each field empty where it equals rmw_zenoh's default."""
        def field(value: int, default: int) -> str:
            return "" if value == default else str(value)
        return (f"{field(self.reliability, RELIABLE)}:{field(self.durability, VOLATILE)}:"
                f"{field(self.history, KEEP_LAST)},{field(self.depth, self.DEFAULT_DEPTH)}"
                ":,:,:,,")

    @property
    def congestion(self) -> zenoh.CongestionControl:
        """rmw_zenoh's publisher mapping: BLOCK for reliable KEEP_ALL, DROP otherwise."""
        return (zenoh.CongestionControl.BLOCK
                if self.reliability == RELIABLE and self.history == KEEP_ALL
                else zenoh.CongestionControl.DROP)

    @property
    def zenoh_reliability(self) -> zenoh.Reliability:
        return (zenoh.Reliability.RELIABLE if self.reliability == RELIABLE
                else zenoh.Reliability.BEST_EFFORT)


#: Commands and parameters: nothing lost (reliable, KEEP_ALL: BLOCK congestion control).
QOS_ALL = QoS(history=KEEP_ALL)
#: Estimates: reliable, the last 10 (rclcpp's default profile).
QOS_DEFAULT = QoS(depth=10)
#: Camera images: rclcpp's sensor-data profile (best effort, the last 5).
QOS_SENSOR = QoS(reliability=BEST_EFFORT, depth=5)


# -- liveliness tokens and GIDs ----------------------------------------------------------------

def liveliness_token(rmw: Rmw, zid: str, node_id: int, entity_id: int, kind: str,
                     topic: str | None = None, typename: str | None = None,
                     type_hash: str | None = None, qos: QoS | None = None) -> str:
    """The liveliness key of a node (``kind`` NN, no topic) or of one of its publishers (MP)
    or subscriptions (MS) on the fully qualified ``topic`` (design.md, "Graph Cache";
    ``Entity::Entity`` in liveliness_utils.cpp)."""
    parts = [ADMIN_SPACE, str(validate_domain(rmw.domain)), zid, str(node_id),
             str(entity_id), kind, mangle(rmw.enclave), mangle(validate_namespace(rmw.namespace)),
             mangle(validate_node_name(rmw.node))]
    if kind != NODE:
        if topic is None or typename is None or type_hash is None or qos is None:
            raise ValueError(f"a {kind} token needs a topic, a type, its hash and a QoS")
        parts += [mangle(topic), mangle(dds_type(typename)), mangle(type_hash), qos.keyexpr()]
    return "/".join(parts)


def token_parts(key: str) -> tuple[str, str, str | None, str | None] | None:
    """(domain, kind, mangled topic, DDS type) of a liveliness key laid out as
    :func:`liveliness_token` makes it (topic and type None for a node's), None for another
    key."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE:
        return None
    if len(parts) < 11:
        return parts[1], parts[5], None, None
    return parts[1], parts[5], parts[9], parts[10]


def gid(token: str) -> bytes:
    """The entity's GID: XXH3-128 of its liveliness key, low 64 bits then high, each little
    endian (``Entity::Entity``: memcpy of ``low64`` and ``high64`` on a little-endian host)."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


# -- attachments -------------------------------------------------------------------------------

class Attachment(NamedTuple):
    """What rmw_zenoh attaches to every sample (design.md, "Publishers")."""

    seq: int
    stamp_ns: int
    gid: bytes

    def encode(self) -> bytes:
        """33 bytes, written by zenoh's serializer as rmw_zenoh does (``AttachmentData::
        serialize_to_zbytes``): int64, int64, then the GID as a length-prefixed sequence."""
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"GID of {len(self.gid)} bytes: expected {GID_SIZE}")
        return zenoh.ext.z_serialize((zenoh.ext.Int64(self.seq),
                                      zenoh.ext.Int64(self.stamp_ns), bytes(self.gid))
                                     ).to_bytes()

    @classmethod
    def decode(cls, data: bytes | None) -> Attachment:
        """The 33 bytes of today's rmw_zenoh, or the labelled form of its releases before
        April 2025 (:data:`LABELS`, 77 bytes). Raises ValueError naming what is wrong
        (missing, wrong size, GID length)."""
        if data is None:
            raise ValueError("sample has no attachment (rmw_zenoh sends 33 bytes)")
        if len(data) == LABELLED_SIZE:
            with contextlib.suppress(zenoh.ZError, ValueError, TypeError):
                l0, seq, l1, stamp, l2, gid_ = zenoh.ext.z_deserialize(
                    tuple[str, zenoh.ext.Int64, str, zenoh.ext.Int64, str, bytes],
                    zenoh.ZBytes(data))
                if (l0, l1, l2) == LABELS and len(gid_) == GID_SIZE:
                    return cls(int(seq), int(stamp), bytes(gid_))
        if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
            raise ValueError(f"attachment of {len(data)} bytes: expected {ATTACHMENT_SIZE} "
                             f"(int64 seq, int64 stamp, GID length {GID_SIZE}, GID)")
        seq, stamp, gid_ = zenoh.ext.z_deserialize(
            tuple[zenoh.ext.Int64, zenoh.ext.Int64, bytes], zenoh.ZBytes(data))
        return cls(int(seq), int(stamp), bytes(gid_))


# -- a ROS 2 node on a Zenoh session -----------------------------------------------------------

class Publisher:
    """One ROS 2 publisher: a Zenoh publisher on the topic's key and its ``MP`` token.

    :meth:`put` numbers samples from 1 and stamps each with the time it is sent, as
    ``PublisherData::publish`` does.
    """

    def __init__(self, session: zenoh.Session, key: str, token: str, qos: QoS) -> None:
        self.key, self.token, self.qos = key, token, qos
        self.gid = gid(token)
        self._seq = 0
        self._lock = threading.Lock()
        self._pub = session.declare_publisher(key, congestion_control=qos.congestion,
                                              reliability=qos.zenoh_reliability)
        try:
            self._token = session.liveliness().declare_token(token)
        except BaseException:
            self._pub.undeclare()
            raise

    def put(self, cdr: bytes) -> int:
        """Publish CDR bytes; return the sample's sequence number."""
        with self._lock:
            self._seq += 1
            seq = self._seq
        self._pub.put(cdr, attachment=Attachment(seq, time.time_ns(), self.gid).encode())
        return seq

    def matched(self) -> bool:
        """Whether a subscriber anywhere matches the key (a ROS 2 subscription is there)."""
        status = self._pub.matching_status
        return bool(getattr(status, "matching", status))

    def undeclare(self) -> None:
        for entity in (self._token, self._pub):
            try:
                entity.undeclare()
            except zenoh.ZError as err:
                log.debug("undeclare failed: %s", err)


class Participant:
    """A ROS 2 node on a Zenoh session: its ``NN`` token, and publishers and subscriptions
    declared as rmw_zenoh declares them. Undeclares everything on :meth:`close` (the session
    stays open: it belongs to the caller).

    Parameters
    ----------
    session : an open Zenoh session (rmw_zenoh: one per context).
    rmw : domain id, namespace, node name and enclave.
    node_id : the node's id within the session (rmw_zenoh counts nodes of a context from 0).
    """

    def __init__(self, session: zenoh.Session, rmw: Rmw, node_id: int = 0) -> None:
        self.session, self.rmw, self.node_id = session, rmw, node_id
        self.zid = str(session.zid())
        self._next_id = node_id + 1
        self._entities: list[Any] = []
        self.node_token = liveliness_token(rmw, self.zid, node_id, node_id, NODE)
        self._entities.append(session.liveliness().declare_token(self.node_token))

    def _entity(self, kind: str, topic: str, typename: str, type_hash: str, qos: QoS
                ) -> tuple[str, str, str]:
        name = qualified_topic(topic, self.rmw.namespace)
        token = liveliness_token(self.rmw, self.zid, self.node_id, self._next_id, kind, name,
                                 typename, type_hash, qos)
        self._next_id += 1
        return name, topic_key(self.rmw.domain, name, typename, type_hash), token

    def publisher(self, topic: str, typename: str, type_hash: str, qos: QoS) -> Publisher:
        """Declare a publisher of ``typename`` on ``topic`` (relative names are resolved in
        the node's namespace)."""
        _, key, token = self._entity(PUBLISHER, topic, typename, type_hash, qos)
        pub = Publisher(self.session, key, token, qos)
        self._entities.append(pub)
        return pub

    @property
    def publishers(self) -> list[Publisher]:
        """The publishers declared so far, in order."""
        return [e for e in self._entities if isinstance(e, Publisher)]

    def subscription(self, topic: str, typename: str, type_hash: str, qos: QoS,
                     callback: Callable[[zenoh.Sample], Any] | None = None, *,
                     any_hash: bool = False) -> str:
        """Declare the ``MS`` token of a subscription and, with ``callback``, a Zenoh
        subscriber on the topic's key; return that key. ``any_hash`` subscribes to every
        type hash of the type (a Humble publisher sends ``TypeHashNotSupported``)."""
        _, key, token = self._entity(SUBSCRIPTION, topic, typename, type_hash, qos)
        if any_hash:
            key = key.rsplit("/", 1)[0] + "/*"
        self._entities.append(self.session.liveliness().declare_token(token))
        if callback is not None:
            self._entities.append(self.session.declare_subscriber(key, callback))
        return key

    def close(self) -> None:
        """Undeclare every entity, subscribers first (no callback runs against a closing
        session), then publishers and tokens."""
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError as err:
                log.debug("undeclare failed: %s", err)
        self._entities.clear()

    def __enter__(self) -> Participant:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
