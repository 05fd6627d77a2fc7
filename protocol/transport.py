"""Transport helpers: frames as one sample, typed messages, bounded receive buffers, liveliness.

A frame is one Zenoh sample: payload = the JPEG bytes (encoding ``image/jpeg``, so any Zenoh tool
can show it), attachment = the codec-encoded :class:`~protocol.messages.FrameHeader`. Every other
message sample carries the encoding ``application/msgpack;argus/<kind>/<major>.<minor>``
(:func:`message_encoding`), so a reader knows the schema before it opens the payload.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from protocol.codec import MSGPACK_MIME, DecodeError, content_type, decode, encode
from protocol.messages import FrameHeader, Message, Status

if TYPE_CHECKING:
    import zenoh

log = logging.getLogger(__name__)
MAX_HEADER_BYTES = 64 * 1024
"""Largest frame-header attachment decode_frame_sample accepts (a real one is well under 2 KiB)."""
T = TypeVar("T")
M = TypeVar("M", bound=Message)


@dataclass(frozen=True)
class Frame:
    """A received frame: its header, the raw JPEG bytes and the key it arrived on."""

    header: FrameHeader
    jpeg: bytes
    key: str
    received_ns: int


def declare_frame_publisher(session: zenoh.Session, key: str, *, block: bool = False) -> zenoh.Publisher:
    """Publisher for frames: ``image/jpeg``, congestion control DROP (a slow link drops, never blocks);
    ``block``: BLOCK (frames that must not be lost, e.g. a robot's arrival frame)."""
    import zenoh

    return session.declare_publisher(
        key,
        encoding=zenoh.Encoding.IMAGE_JPEG,
        congestion_control=zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP,
        priority=zenoh.Priority.DATA,
    )


def message_encoding(cls: type[Message] | None = None, mime: str = MSGPACK_MIME) -> zenoh.Encoding:
    """Zenoh encoding of a ``cls`` sample: ``application/msgpack;argus/<kind>/<major>.<minor>``.

    Without ``cls``: plain ``application/msgpack`` (a publisher of several kinds).
    """
    import zenoh

    return zenoh.Encoding(content_type(cls, mime) if cls is not None else mime)


def declare_message_publisher(
    session: zenoh.Session,
    key: str,
    *,
    important: bool = True,
    message: type[Message] | None = None,
    mime: str = MSGPACK_MIME,
    block: bool | None = None,
) -> zenoh.Publisher:
    """Publisher for codec messages of class ``message`` (named in the sample encoding, see
    :func:`message_encoding`; ``mime`` ``application/json`` for a JSON view). ``important`` (goals, deltas):
    BLOCK and a higher priority; ``block`` overrides the congestion control alone (default: ``important``)."""
    import zenoh

    blocking = important if block is None else block
    return session.declare_publisher(
        key,
        encoding=message_encoding(message, mime),
        congestion_control=zenoh.CongestionControl.BLOCK if blocking else zenoh.CongestionControl.DROP,
        priority=zenoh.Priority.INTERACTIVE_HIGH if important else zenoh.Priority.DATA,
    )


class LatestValue:
    """A publisher whose newest payload also answers queries on its key: late joiners get it at once.

    Zenoh delivers a put only to subscribers that exist at that moment; a consumer that joins later
    would wait for the next put (seconds for status and robot state, longer for the point map). So the
    publishing process also declares a queryable on the same key that replies with the newest payload
    and encoding; any Zenoh binding reads the current value with a plain ``get`` (then subscribes for
    updates). Thread-safe; one payload is held, so memory is bounded by the largest message.
    """

    def __init__(self, session: zenoh.Session, publisher: zenoh.Publisher) -> None:
        self.publisher = publisher
        self.key = str(publisher.key_expr)
        self._lock = threading.Lock()
        self._latest: bytes | None = None
        self.queries = 0
        self._queryable = session.declare_queryable(self.key, self._on_query)

    def put(self, payload: bytes) -> None:
        """Publish ``payload`` and keep it as the value late joiners get."""
        with self._lock:
            self._latest = payload
        self.publisher.put(payload)

    @property
    def latest(self) -> bytes | None:
        with self._lock:
            return self._latest

    def _on_query(self, query: zenoh.Query) -> None:
        payload = self.latest
        if payload is None:
            return  # nothing published yet: the getter sees no reply, not a made-up value
        try:
            query.reply(self.key, payload, encoding=self.publisher.encoding)
            self.queries += 1
        except Exception as e:  # noqa: BLE001 - a callback must never raise into zenoh
            log.debug("latest-value reply on %s failed: %s", self.key, e)

    def undeclare(self) -> None:
        self._queryable.undeclare()
        self.publisher.undeclare()


def put_frame(publisher: zenoh.Publisher, header: FrameHeader, jpeg: bytes) -> None:
    """Put one frame sample: JPEG payload, encoded header as attachment."""
    publisher.put(jpeg, attachment=encode(header))


def decode_frame_sample(sample: zenoh.Sample) -> Frame:
    """Decode a frame sample; raises :class:`DecodeError` when the attachment is missing, over
    :data:`MAX_HEADER_BYTES` or bad.

    The JPEG bytes are not decoded here (that is the receiver's choice and cost).
    """
    att = sample.attachment
    if att is not None and len(att) > MAX_HEADER_BYTES:  # refused before it is copied out of Zenoh
        raise DecodeError(f"frame header attachment of {len(att)} bytes exceeds {MAX_HEADER_BYTES}")
    return decode_frame_bytes(str(sample.key_expr), None if att is None else att.to_bytes(), sample.payload.to_bytes())


def decode_frame_bytes(key: str, attachment: bytes | None, payload: bytes) -> Frame:
    """:func:`decode_frame_sample` on a sample's parts (its key, attachment bytes and payload bytes): what a
    replay or a benchmark hands the receiver to go the way a frame from the wire goes."""
    if attachment is None:
        raise DecodeError("frame sample has no header attachment")
    if len(attachment) > MAX_HEADER_BYTES:
        raise DecodeError(f"frame header attachment of {len(attachment)} bytes exceeds {MAX_HEADER_BYTES}")
    header = decode(attachment, FrameHeader)
    return Frame(header=header, jpeg=payload, key=key, received_ns=time.time_ns())


def decode_message_sample(sample: zenoh.Sample, expected: type[M]) -> M:
    """Decode the payload of a message sample as ``expected`` (raises :class:`DecodeError`)."""
    return decode(sample.payload.to_bytes(), expected)


class LatestSlots(Generic[T]):
    """Bounded receive buffer: per key a ring of the newest ``depth`` items; older ones are dropped.

    Thread-safe; ``dropped`` counts items evicted before anyone took them. A slow consumer therefore
    always works on fresh data and memory stays bounded: at most ``max_keys`` keys are held. A new key
    beyond that takes the slot of the least recently active key whose ring is empty (``evicted_keys``);
    only when every slot holds unread items is it refused (``refused_keys``). So made-up source ids
    cannot lock real sources out for good.

    With ``max_bytes`` (and ``size``, an item's byte count), the items buffered across all keys stay
    under ``max_bytes`` too: the oldest item of the least recently active key is dropped to make room,
    and an item bigger than ``max_bytes`` on its own is refused (``dropped`` counts both).
    """

    def __init__(self, depth: int = 1, max_keys: int = 256, max_bytes: int | None = None,
                 size: Callable[[T], int] | None = None) -> None:
        if depth < 1 or max_keys < 1 or (max_bytes is not None and (max_bytes < 1 or size is None)):
            raise ValueError("depth and max_keys must be >= 1; max_bytes needs size and must be >= 1")
        self.depth = depth
        self.max_keys = max_keys
        self.max_bytes = max_bytes
        self._size = size
        self._rings: collections.OrderedDict[str, collections.deque[T]] = collections.OrderedDict()
        self._cond = threading.Condition()
        self.dropped = 0
        self.refused_keys = 0
        self.evicted_keys = 0
        self.bytes = 0
        """Bytes buffered now (with ``max_bytes``)."""
        self._woken = False

    def _bytes_of(self, item: T) -> int:
        return self._size(item) if self._size is not None else 0

    def put(self, key: str, item: T) -> bool:
        """Buffer ``item`` under ``key``; False when the key was refused (all slots busy) or the item alone
        exceeds ``max_bytes``."""
        n = self._bytes_of(item)
        with self._cond:
            if self.max_bytes is not None and n > self.max_bytes:
                self.dropped += 1
                return False
            ring = self._rings.get(key)
            if ring is None:
                if len(self._rings) >= self.max_keys and not self._evict_idle():
                    self.refused_keys += 1
                    return False
                ring = self._rings[key] = collections.deque(maxlen=self.depth)
            self._rings.move_to_end(key)  # most recently active last
            if len(ring) == self.depth:
                self.dropped += 1
                self.bytes -= self._bytes_of(ring[0])
            ring.append(item)
            self.bytes += n
            if self.max_bytes is not None:
                self._make_room()
            self._cond.notify_all()
            return True

    def _make_room(self) -> None:
        assert self.max_bytes is not None
        while self.bytes > self.max_bytes:
            # Oldest item of the least recently active key (the newest item, just put, is last of all).
            ring = next(r for r in self._rings.values() if r)
            self.bytes -= self._bytes_of(ring.popleft())
            self.dropped += 1

    def _evict_idle(self) -> bool:
        for k, ring in self._rings.items():  # least recently active first
            if not ring:
                del self._rings[k]
                self.evicted_keys += 1
                return True
        return False

    def take_all(self, timeout: float | None = None) -> list[tuple[str, T]]:
        """Take every buffered item (oldest first per key); waits up to ``timeout`` for one, or for :meth:`wake`."""
        with self._cond:
            if timeout is not None and not any(self._rings.values()) and not self._woken:
                self._cond.wait(timeout)
            self._woken = False
            out = [(k, item) for k, ring in self._rings.items() for item in ring]
            for ring in self._rings.values():
                ring.clear()
            self.bytes = 0
            return out

    def wake(self) -> None:
        """End the :meth:`take_all` waiting now, or else the next one, at once (news of another kind arrived)."""
        with self._cond:
            self._woken = True
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return sum(len(r) for r in self._rings.values())


class Counters:
    """Thread-safe named counters for status reports."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, float] = {}

    def add(self, name: str, value: float = 1.0) -> None:
        with self._lock:
            self._values[name] = self._values.get(name, 0.0) + value

    def set(self, name: str, value: float) -> None:
        with self._lock:
            self._values[name] = float(value)

    def get(self, name: str) -> float:
        with self._lock:
            return self._values.get(name, 0.0)

    def ema(self, name: str, value: float, alpha: float = 0.2) -> None:
        """Move ``name`` towards ``value`` (exponential moving average); the first value is taken as is."""
        with self._lock:
            old = self._values.get(name, 0.0)
            self._values[name] = float(value) if old == 0.0 else (1 - alpha) * old + alpha * value

    def snapshot(self) -> dict[str, float]:
        with self._lock:
            return dict(self._values)


class LinkWatch:
    """Whether a session is linked to any router or peer; says so once when the link goes and comes back.

    A client whose router died keeps its session open and its puts go nowhere, silently. This checks
    the session's routers and peers (``session.info``) and keeps ``links`` (current count),
    ``link_losses`` and ``link_down_s`` (seconds without any link, growing while down) in ``counters``.
    """

    def __init__(self, session: zenoh.Session, counters: Counters, what: str) -> None:
        self._session, self.counters, self.what = session, counters, what
        self.linked: bool | None = None
        self._down_since = 0.0

    def check(self) -> bool:
        try:
            info = self._session.info
            links = len(list(info.routers_zid())) + len(list(info.peers_zid()))
        except Exception as e:  # noqa: BLE001 - a closing session: report no link, never raise
            log.debug("link check failed: %s", e)
            links = 0
        self.counters.set("links", links)
        now = time.monotonic()
        if links == 0:
            if self.linked is not False:
                self._down_since = now
                if self.linked is True:
                    self.counters.add("link_losses")
                    log.warning("%s: no Zenoh link (router gone?): nothing is delivered until it is back",
                                self.what)
            self.counters.set("link_down_s", now - self._down_since)
        elif self.linked is False:
            log.info("%s: Zenoh link back after %.1f s", self.what, now - self._down_since)
        self.linked = links > 0
        return self.linked


class StatusReporter:
    """Publishes a :class:`Status` for one process every ``period_s`` from a daemon thread.

    Each period it also checks the session's link (:class:`LinkWatch`): while there is none the
    state reads ``no_link`` (seen by whoever reads the status once the link is back, and in the log).
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        role: str,
        node_id: str,
        counters: Counters,
        period_s: float = 1.0,
        extra: Callable[[], dict[str, Any]] | None = None,
    ) -> None:
        self._pub = LatestValue(session, declare_message_publisher(session, key, important=False, message=Status))
        self.role, self.node_id, self.counters, self.period_s = role, node_id, counters, period_s
        self.link = LinkWatch(session, counters, f"{role} {node_id}")
        self.state = "ok"
        self.last_error: str | None = None
        self._extra = extra
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"status-{role}", daemon=True)

    def __enter__(self) -> StatusReporter:
        self.publish()  # at once, so a consumer (or a late joiner's get) sees the process without waiting a period
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.publish()
        try:
            self._pub.undeclare()
        except Exception as e:  # noqa: BLE001 - the session may already be closing
            log.debug("status undeclare failed: %s", e)

    def publish(self) -> Status:
        linked = self.link.check()
        counters = self.counters.snapshot()
        if self._extra is not None:
            counters.update({k: float(v) for k, v in self._extra().items()})
        msg = Status(
            role=self.role,
            node_id=self.node_id,
            stamp_ns=time.time_ns(),
            state=self.state if linked else "no_link",
            counters=counters,
            last_error=self.last_error,
        )
        try:
            self._pub.put(encode(msg))
        except Exception as e:  # noqa: BLE001 - a closed session at shutdown must not raise here
            log.debug("status publish failed: %s", e)
        return msg

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.publish()
