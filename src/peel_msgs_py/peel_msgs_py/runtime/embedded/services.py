"""Services and clients carried as ``rmw_cyclonedds_cpp`` carries them, and rclpy's Future.

On the wire (rmw_cyclonedds_cpp ``serdata.hpp`` / ``rmw_node.cpp``):

* request topic ``rq<service>Request``, type ``<pkg>::srv::dds_::<Srv>_Request_``; reply topic
  ``rr<service>Reply``, type ``<pkg>::srv::dds_::<Srv>_Response_``;
* every sample starts with ``cdds_request_header_t {uint64 guid; int64 seq}`` inline, followed
  by the request/response fields: ``guid`` is the client's request-writer instance handle,
  ``seq`` a per-process request counter; the reply echoes both and a client keeps only replies
  carrying its own ``guid``;
* the client's request writer and reply reader carry user data ``clientid=<id>;``, the
  service's ``serviceid=<id>;`` (id = participant GUID prefix + counter). Like rmw_cyclonedds,
  a service holds a reply back until the requesting client's reply reader has matched (rmw
  waits 100 ms and then drops it; here it stays queued while the client's writer exists, up to
  :data:`REPLY_HOLD_S`).
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
import types
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import cyclonedds.idl.types as t
from cyclonedds.core import DDSException, Policy, ReadCondition
from cyclonedds.idl import IdlStruct
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader

from ...errors import PeelError
from .context import DdsEntity, csid_to_string
from .entities import ANY_STATE
from .names import dds_reply, dds_request
from .qos import QoSProfile, to_dds

if TYPE_CHECKING:
    from .node import Node

#: How long a service keeps a reply for a client whose reply reader has not matched yet (s).
REPLY_HOLD_S = 10.0

_U64 = (1 << 64) - 1
_GUID = "client_guid_"
_SEQ = "sequence_number_"
_wire_cache: dict[type[Any], type[Any]] = {}
_seq_counter = itertools.count(1)
_seq_lock = threading.Lock()


def wire_type(msg_cls: type[Any]) -> type[Any]:
    """The DDS sample type: request header (guid, seq) inline, then the fields of ``msg_cls``."""
    cached = _wire_cache.get(msg_cls)
    if cached is not None:
        return cached
    annotations: dict[str, Any] = {_GUID: t.uint64, _SEQ: t.int64}
    for f in dataclasses.fields(msg_cls):
        annotations[f.name] = f.type

    def body(ns: dict[str, Any]) -> None:
        ns["__annotations__"] = annotations
        ns["__module__"] = __name__

    cls = types.new_class(
        msg_cls.__name__ + "_wire",
        (IdlStruct,),
        {"typename": msg_cls.__idl_typename__},
        body,
    )
    cls = dataclasses.dataclass(cls)
    _wire_cache[msg_cls] = cls
    return cls


def to_wire(msg: Any, guid: int, seq: int) -> Any:
    cls = wire_type(type(msg))
    values = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
    return cls(**{_GUID: guid, _SEQ: seq}, **values)


def from_wire(sample: Any, msg_cls: type[Any]) -> Any:
    return msg_cls(**{f.name: getattr(sample, f.name) for f in dataclasses.fields(msg_cls)})


def _user_data_key(qos: Any, key: str) -> str | None:
    if qos is None:
        return None
    pol = qos[Policy.Userdata]
    if pol is None:
        return None
    for item in pol.data.decode("ascii", "replace").split(";"):
        k, _, v = item.partition("=")
        if k == key:
            return v
    return None


class Future:
    """``rclpy.task.Future``: ``done()``, ``result()``, ``add_done_callback(cb)``."""

    def __init__(self) -> None:
        self._done = False
        self._cancelled = False
        self._result: Any = None
        self._exception: BaseException | None = None
        self._callbacks: list[Callable[[Future], None]] = []
        self._lock = threading.Lock()

    def done(self) -> bool:
        return self._done

    def cancelled(self) -> bool:
        return self._cancelled

    def cancel(self) -> None:
        if not self._done:
            self._cancelled = True
            self._finish()

    def result(self) -> Any:
        if self._exception is not None:
            raise self._exception
        return self._result

    def exception(self) -> BaseException | None:
        return self._exception

    def set_result(self, result: Any) -> None:
        self._result = result
        self._finish()

    def set_exception(self, exception: BaseException) -> None:
        self._exception = exception
        self._finish()

    def _finish(self) -> None:
        with self._lock:
            self._done = True
            callbacks, self._callbacks = self._callbacks, []
        for cb in callbacks:
            cb(self)

    def add_done_callback(self, callback: Callable[[Future], None]) -> None:
        with self._lock:
            if not self._done:
                self._callbacks.append(callback)
                return
        callback(self)


def _open_endpoints(
    node: Node, srv_type: type[Any], name: str, qos: QoSProfile, *, server: bool
) -> tuple[int, DataReader, DataWriter, ReadCondition]:
    """The DDS reader/writer pair of one service end, as rmw_cyclonedds lays it out.

    A server reads ``rq/<name>Request`` and writes ``rr/<name>Reply``; a client the other way
    round. Both carry their id in the USER_DATA QoS (``serviceid=`` / ``clientid=``).
    Returns (id, reader, writer, read condition).
    """
    ctx = node.context
    ident = ctx.next_client_service_id()
    udata = f"{'serviceid' if server else 'clientid'}={csid_to_string(ident)};".encode()
    req_topic = ctx.topic(dds_request(name), wire_type(srv_type.Request))
    rep_topic = ctx.topic(dds_reply(name), wire_type(srv_type.Response))
    read_topic, write_topic = (req_topic, rep_topic) if server else (rep_topic, req_topic)
    try:
        reader = DataReader(ctx.participant, read_topic, qos=to_dds(qos, udata, writer=False))
        writer = DataWriter(ctx.participant, write_topic, qos=to_dds(qos, udata, writer=True))
        return ident, reader, writer, ReadCondition(reader, ANY_STATE)
    except DDSException as exc:
        what = "service" if server else "client for"
        raise PeelError(f"cannot create {what} {name}: {exc}") from None


class Service(DdsEntity):
    """``rclpy.service.Service``: ``callback(request, response) -> response``."""

    def __init__(
        self, node: Node, srv_type: type[Any], name: str, callback: Callable, qos: QoSProfile
    ) -> None:
        self.srv_type = srv_type
        self.srv_name = name
        self.callback = callback
        self.qos_profile = qos
        self._node = node
        self._id, self._reader, self._writer, self._cond = _open_endpoints(
            node, srv_type, name, qos, server=True)
        #: replies waiting for the client's reply reader: (wire sample, writer handle, id, t0)
        self._pending: list[tuple[Any, int, str | None, float]] = []

    @property
    def service_name(self) -> str:
        return self.srv_name

    def _client_ready(self, writer_handle: int, clientid: str | None) -> bool | None:
        """True: reply can go; False: wait; None: the client is gone."""
        try:
            matched = {h & _U64 for h in self._reader.get_matched_publications()}
            if writer_handle & _U64 not in matched:
                return None
            if clientid is None:
                return True
            for h in self._writer.get_matched_subscriptions():
                ep = self._writer.get_matched_subscription_data(h)
                if ep is not None and _user_data_key(ep.qos, "clientid") == clientid:
                    return True
        except DDSException:
            return None
        return False

    def _flush(self) -> None:
        keep = []
        for item in self._pending:
            wire, wh, cid, t0 = item
            ready = self._client_ready(wh, cid)
            if ready:
                self._writer.write(wire)
            elif ready is False and time.monotonic() - t0 < REPLY_HOLD_S:
                keep.append(item)
        self._pending = keep

    def _take_work(self) -> Callable[[], None] | None:
        while samples := self._reader.take(N=1):
            sample = samples[0]
            info = getattr(sample, "sample_info", None)
            if info is None or not info.valid_data:
                continue
            guid, seq = getattr(sample, _GUID), getattr(sample, _SEQ)
            request = from_wire(sample, self.srv_type.Request)
            wh = info.publication_handle
            return lambda: self._serve(request, guid, seq, wh)
        return None

    def _serve(self, request: Any, guid: int, seq: int, writer_handle: int) -> None:
        response = self.callback(request, self.srv_type.Response())
        if response is None:
            self._node.get_logger().error(f"service {self.srv_name}: callback returned None")
            return
        if not isinstance(response, self.srv_type.Response):
            self._node.get_logger().error(
                f"service {self.srv_name}: callback returned {type(response).__name__}"
            )
            return
        clientid = None
        try:
            ep = self._reader.get_matched_publication_data(writer_handle)
            clientid = _user_data_key(ep.qos if ep is not None else None, "clientid")
        except DDSException:  # writer already gone: reply without waiting for its match
            pass
        self._pending.append((to_wire(response, guid, seq), writer_handle, clientid, time.monotonic()))
        self._flush()

    def _dds_handles(self) -> tuple[Any, ...]:
        return (self._cond, self._reader, self._writer,)


class Client(DdsEntity):
    """``rclpy.client.Client``: ``call_async``, ``wait_for_service``, ``service_is_ready``."""

    def __init__(self, node: Node, srv_type: type[Any], name: str, qos: QoSProfile) -> None:
        self.srv_type = srv_type
        self.srv_name = name
        self.qos_profile = qos
        self._node = node
        self._id, self._reader, self._writer, self._cond = _open_endpoints(
            node, srv_type, name, qos, server=False)
        self._guid = self._writer.get_instance_handle() & _U64
        self._futures: dict[int, Future] = {}

    @property
    def service_name(self) -> str:
        return self.srv_name

    def service_is_ready(self) -> bool:
        try:
            return bool(self._writer.get_matched_subscriptions()) and bool(
                self._reader.get_matched_publications()
            )
        except DDSException:
            return False

    def wait_for_service(self, timeout_sec: float | None = None) -> bool:
        """Block (without spinning) until a server is matched; False on timeout."""
        end = None if timeout_sec is None else time.monotonic() + timeout_sec
        while not self.service_is_ready():
            if not self._node.context.ok():
                return False
            if end is not None and time.monotonic() >= end:
                return False
            time.sleep(0.01)
        return True

    def call_async(self, request: Any) -> Future:
        if not isinstance(request, self.srv_type.Request):
            raise TypeError(
                f"expected {self.srv_type.__rostype__} request, got {type(request).__name__}"
            )
        with _seq_lock:
            seq = next(_seq_counter)
        future = Future()
        self._futures[seq] = future
        self._writer.write(to_wire(request, self._guid, seq))
        return future

    def remove_pending_request(self, future: Future) -> None:
        for seq, fut in list(self._futures.items()):
            if fut is future:
                del self._futures[seq]

    def _take_work(self) -> Callable[[], None] | None:
        while samples := self._reader.take(N=1):
            sample = samples[0]
            info = getattr(sample, "sample_info", None)
            if info is None or not info.valid_data or getattr(sample, _GUID) != self._guid:
                continue
            future = self._futures.pop(getattr(sample, _SEQ), None)
            if future is None or future.done():
                continue
            response = from_wire(sample, self.srv_type.Response)
            return lambda: future.set_result(response)
        return None

    def _dds_handles(self) -> tuple[Any, ...]:
        return (self._cond, self._reader, self._writer,)
