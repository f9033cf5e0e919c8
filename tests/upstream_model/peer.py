"""A model ROS 2 participant on rmw_zenoh 0.10.5 / 0.12.0, over plain zenoh-python.

- ``Participant``: ``rmw_context_impl_s.cpp`` (one Zenoh session, the graph's liveliness
  subscriber on ``@ros2_lv/<domain>/**`` with history, one id counter for node and entities)
  and ``rmw_node_data.cpp`` (the node token).
- ``Publisher``: ``rmw_publisher_data.cpp`` (``make``, ``publish``, ``publish_buffer_aware``,
  ``on_subscriber_discovered``, ``create_publisher_endpoint``).
- ``Subscription``: ``rmw_subscription_data.cpp`` (``make``, ``init``,
  ``on_publisher_discovered``, ``create_subscription_endpoint``, ``add_new_message``).
- ``legacy=True``: rmw_zenoh 0.10.4 and older (13-segment tokens, base key only, a publisher
  puts every message on the base key whoever listens).

Threads: the caller's and Zenoh's callback threads; each endpoint guards its state with a lock.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import logging
import os
import threading
import time
from typing import Any

import zenoh
import zenoh.ext

from tests.upstream_model import attachment, cdr
from tests.upstream_model import qos as qos_model
from tests.upstream_model.backends import FakeBackend
from tests.upstream_model.graph import GraphCache
from tests.upstream_model.liveliness import (NODE, PUBLISHER, SUBSCRIPTION, Entity, NodeInfo,
                                              TopicInfo, subscription_token)
from tests.upstream_model.messages import (buffer_fields, dds_type_name, make_typestore,
                                           scalar_summary, type_hash)

log = logging.getLogger("upstream_model")
CONFIG_URI_ENV = "ZENOH_SESSION_CONFIG_URI"
CPU_GROUP_SUFFIX = "/_buf_cpu"    # buffer_endpoint_helpers.hpp make_cpu_group_key
ACCELERATED_INFIX = "/_buf/"      # make_accelerated_key


def make_config(config_file: str | None = None, connect: list[str] | None = None,
                listen: list[str] | None = None) -> zenoh.Config:
    """A Zenoh configuration: ``config_file``, else ``$ZENOH_SESSION_CONFIG_URI`` (as
    rmw_zenoh reads it), else a router-less default (peer mode, multicast scouting on the
    loopback interface); ``connect`` / ``listen`` endpoints replace the file's."""
    path = config_file or os.environ.get(CONFIG_URI_ENV)
    if path:
        config = zenoh.Config.from_file(path)
    else:
        config = zenoh.Config.from_json5(
            '{mode: "peer", listen: {endpoints: ["tcp/127.0.0.1:0"]},'
            ' scouting: {multicast: {enabled: true, interface: "lo"}, gossip: {enabled: true}},'
            # Zenoh's shared memory names files in /dev/shm that a killed test peer would leave;
            # it is Zenoh's transport, below the rmw_zenoh protocol this package models.
            ' transport: {shared_memory: {enabled: false}}}')
    if connect:
        config.insert_json5("connect/endpoints", _json_list(connect))
    if listen:
        config.insert_json5("listen/endpoints", _json_list(listen))
    return config


def _json_list(items: list[str]) -> str:
    return "[" + ",".join(f'"{item}"' for item in items) + "]"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _route(base_key: str, key: str) -> str:
    """``base``, ``_buf_cpu`` or ``_buf/<gid>``: the key relative to the data key."""
    return "base" if key == base_key else key[len(base_key) + 1:]


class Participant:
    """One process's rmw context with one node."""

    def __init__(self, *, domain: int, node_name: str, namespace: str = "/",
                 enclave: str = "/", config: zenoh.Config | None = None, legacy: bool = False,
                 backends: dict[str, str] | None = None) -> None:
        self.domain = domain
        self.legacy = legacy
        self.store = make_typestore()
        self.backends = {name: FakeBackend(name, meta, self.store)
                         for name, meta in (backends or {}).items()}
        self.session = zenoh.open(config if config is not None else make_config())
        self.zid = str(self.session.zid())
        self.graph = GraphCache(self.zid, legacy=legacy)
        self._ids = itertools.count()
        self._closables: list[Any] = []
        self._graph_tokens: list[Any] = []
        self._graph_sub = self.session.liveliness().declare_subscriber(
            subscription_token(domain), self._on_liveliness, history=True)
        node_id = str(next(self._ids))
        self.node_info = NodeInfo(domain_id=domain, namespace=namespace, name=node_name,
                                  enclave=enclave)
        self.node = Entity(zid=self.zid, nid=node_id, id=node_id, kind=NODE,
                           node=self.node_info, legacy=legacy)
        self._node_token = self.session.liveliness().declare_token(self.node.keyexpr)

    def next_id(self) -> str:
        return str(next(self._ids))

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        """``update_graph_cache``: PUT -> parse_put, DELETE -> parse_del (local tokens too)."""
        key = str(sample.key_expr)
        if sample.kind == zenoh.SampleKind.PUT:
            self.graph.parse_put(key)
        elif sample.kind == zenoh.SampleKind.DELETE:
            self.graph.parse_del(key)

    def declare_graph_entity(self, kind: str, name: str, ros_type: str) -> None:
        """A token alone (graph only, nothing behind it): a service server (``SS``) or client
        (``SC``), as rclcpp's parameter services are, or a topic endpoint (``MP``/``MS``) of a
        type the model has no definition for (an action's feedback topic). Its type hash is a
        placeholder: nothing matches on it here."""
        topic = TopicInfo(domain_id=self.domain, name=name, type=dds_type_name(ros_type),
                          type_hash="RIHS01_" + "0" * 64, qos=qos_model.QoS())
        entity = Entity(zid=self.zid, nid=self.node.nid, id=self.next_id(), kind=kind,
                        node=self.node_info, topic=topic, legacy=self.legacy)
        self._graph_tokens.append(self.session.liveliness().declare_token(entity.keyexpr))

    def track(self, endpoint: Any) -> Any:
        self._closables.append(endpoint)
        return endpoint

    def close(self) -> None:
        for endpoint in reversed(self._closables):
            endpoint.close()
        for token in self._graph_tokens:
            token.undeclare()
        self._node_token.undeclare()
        self._graph_sub.undeclare()
        self.session.close()


def _topic_info(participant: Participant, topic: str, ros_type: str, qos: qos_model.QoS,
                metadata: dict[str, str] | None) -> TopicInfo:
    return TopicInfo(domain_id=participant.domain, name=topic, type=dds_type_name(ros_type),
                     type_hash=type_hash(participant.store, ros_type), qos=qos,
                     backend_metadata=metadata)


@dataclasses.dataclass
class DiscoveredSubscription:
    """rmw_publisher_data.hpp ``SubscriberInfo``."""

    gid: bytes
    endpoint_key: str
    uses_cpu_group: bool
    backend_metadata: dict[str, str]


@dataclasses.dataclass
class _PublisherEndpoint:
    key: str
    pub: zenoh.Publisher
    target_subscribers: list[bytes] = dataclasses.field(default_factory=list)


class Publisher:
    """A publisher as ``PublisherData`` behaves; ``buffer_backend`` names the installed fake
    backend the message's buffers live in ("cpu": ordinary host memory)."""

    def __init__(self, participant: Participant, topic: str, ros_type: str,
                 qos: qos_model.QoS = qos_model.QoS(), *, buffer_backend: str = "cpu") -> None:
        p = self.participant = participant
        if buffer_backend != "cpu" and buffer_backend not in p.backends:
            raise ValueError(f"buffer backend {buffer_backend!r} is not installed")
        self.ros_type = ros_type
        self.buffer_backend = buffer_backend
        self.qos = qos_model.adapt(qos)
        self.buffer_fields = buffer_fields(p.store, ros_type)
        # PublisherData::make: buffer endpoints for a type with buffer fields, unless transient
        # local; the publisher advertises every installed backend's metadata plus cpu.
        self.buffer_aware = (not p.legacy and bool(self.buffer_fields)
                             and self.qos.durability != qos_model.Durability.TRANSIENT_LOCAL)
        metadata = None
        if self.buffer_aware:
            metadata = {name: b.metadata for name, b in p.backends.items()}
            metadata.setdefault("cpu", "")
        self.topic = _topic_info(p, topic, ros_type, self.qos, metadata)
        self.entity = Entity(zid=p.zid, nid=p.node.nid, id=p.next_id(), kind=PUBLISHER,
                             node=p.node_info, topic=self.topic, legacy=p.legacy)
        self.base_key = self.topic.topic_keyexpr
        self.cpu_group_key = self.base_key + CPU_GROUP_SUFFIX
        self._lock = threading.Lock()
        self._closed = False
        self.sequence_number = 1
        self.discovered: list[DiscoveredSubscription] = []
        self.puts: list[dict[str, Any]] = []
        self.publish_calls = 0
        self.skipped = 0            # publish calls that put nothing (no subscription discovered)
        self.last_matched: int | None = None
        self._token = p.session.liveliness().declare_token(self.entity.keyexpr)
        self.endpoints: dict[str, _PublisherEndpoint] = {}
        self.endpoints[self.base_key] = self._create_endpoint(self.base_key)
        if self.buffer_aware:
            self.endpoints[self.cpu_group_key] = self._create_endpoint(self.cpu_group_key)
            p.graph.register_subscriber_discovery(topic, self.entity.gid,
                                                  self._on_subscriber_discovered)
            # Upstream adds its own entity by hand, so the topic and type are in the graph
            # before any remote subscription arrives (the first entity of a topic fires nothing).
            p.graph.parse_put(self.entity.keyexpr, False)
        p.track(self)

    def _create_endpoint(self, key: str) -> _PublisherEndpoint:
        """``create_publisher_endpoint``: DROP, BLOCK only for reliable keep-all."""
        reliable = self.qos.reliability == qos_model.Reliability.RELIABLE
        block = reliable and self.qos.history == qos_model.History.KEEP_ALL
        options = dict(congestion_control=(zenoh.CongestionControl.BLOCK if block
                                           else zenoh.CongestionControl.DROP),
                       reliability=(zenoh.Reliability.RELIABLE if reliable
                                    else zenoh.Reliability.BEST_EFFORT))
        if self.qos.durability == qos_model.Durability.TRANSIENT_LOCAL:
            # rmw_publisher_data.cpp: an AdvancedPublisher, detectable, caching `depth` samples,
            # with sporadic sample-miss heartbeats (500 ms) when reliable
            pub = zenoh.ext.declare_advanced_publisher(
                self.participant.session, key, **options, publisher_detection=True,
                cache=zenoh.ext.CacheConfig(max_samples=self.qos.depth),
                sample_miss_detection=(zenoh.ext.MissDetectionConfig(sporadic_heartbeat=0.5)
                                       if reliable else None))
        else:
            pub = self.participant.session.declare_publisher(key, **options)
        return _PublisherEndpoint(key=key, pub=pub)

    def _on_subscriber_discovered(self, entity: Entity) -> None:
        """``on_subscriber_discovered``: exactly-cpu metadata -> the shared CPU group, anything
        else (other backends, nothing advertised) -> the subscription's own ``_buf/<gid>``."""
        if entity.kind != SUBSCRIPTION or entity.topic is None:
            return
        metadata = dict(entity.topic.backend_metadata or {})
        cpu_group = len(metadata) == 1 and "cpu" in metadata
        with self._lock:
            if not self.buffer_aware or self._closed:
                return
            if any(sub.gid == entity.gid for sub in self.discovered):
                return
            key = (self.cpu_group_key if cpu_group
                   else self.base_key + ACCELERATED_INFIX + entity.gid_hex)
            if not cpu_group:
                for backend in self.participant.backends.values():
                    backend.on_discovering_endpoint(entity.gid, metadata)
            if key not in self.endpoints:
                self.endpoints[key] = self._create_endpoint(key)
            self.discovered.append(DiscoveredSubscription(entity.gid, key, cpu_group, metadata))
            self.endpoints[key].target_subscribers.append(entity.gid)
        log.info("discovered subscription %s -> %s", entity.gid_hex, key)

    def publish(self, message: Any, index: int) -> list[dict[str, Any]]:
        """``PublisherData::publish``; returns the puts it made."""
        with self._lock:
            if self._closed:
                raise RuntimeError("the publisher is closed")
            self.publish_calls += 1
            if self.buffer_aware:
                matched = self.participant.graph.count_matched_subscriptions(self.topic)
                self.last_matched = matched
                if matched <= len(self.discovered):
                    return self._publish_buffer_aware(message, index)
                # "Legacy subscribers present": fall through to the base key.
            payload = cdr.serialize(self.participant.store, message, self.ros_type)
            return [self._put(self.base_key, payload, index, "cpu")]

    def _publish_buffer_aware(self, message: Any, index: int) -> list[dict[str, Any]]:
        if not self.discovered:
            self.skipped += 1
            return []
        puts = []
        if self.endpoints[self.cpu_group_key].target_subscribers:
            payload = cdr.serialize(self.participant.store, message, self.ros_type)
            puts.append(self._put(self.cpu_group_key, payload, index, "cpu"))
        for sub in self.discovered:
            if sub.uses_cpu_group or sub.endpoint_key not in self.endpoints:
                continue
            forms = self._backend_forms(message, sub.gid)
            payload = cdr.serialize(self.participant.store, message, self.ros_type, forms)
            puts.append(self._put(sub.endpoint_key, payload, index,
                                  "backend" if forms else "cpu"))
        return puts

    def _backend_forms(self, message: Any, peer_gid: bytes) -> dict[str, cdr.BackendForm]:
        """``serialize_buffer_with_endpoint`` per buffer field: the backend's descriptor for
        this peer, or nothing (CPU bytes) where it returns null or the buffer is on the CPU."""
        if self.buffer_backend == "cpu":
            return {}
        backend = self.participant.backends[self.buffer_backend]
        forms = {}
        for name in self.buffer_fields:
            descriptor = backend.create_descriptor_with_endpoint(bytes(getattr(message, name)),
                                                                 peer_gid)
            if descriptor is not None:
                forms[name] = cdr.BackendForm(backend.name, descriptor, backend.descriptor_type)
        return forms

    def _put(self, key: str, payload: bytes, index: int, form: str) -> dict[str, Any]:
        """One put, one sequence number (every put takes the next one)."""
        seq = self.sequence_number
        self.sequence_number += 1
        self.endpoints[key].pub.put(payload, attachment=attachment.pack(
            seq, time.time_ns(), self.entity.gid))
        record = {"publish": index, "route": _route(self.base_key, key), "key": key, "seq": seq,
                  "size": len(payload), "sha256": _sha256(payload), "form": form}
        self.puts.append(record)
        return record

    def discovered_count(self) -> int:
        """Subscriptions this publisher routes to (buffer-aware) or that the graph matches."""
        if self.buffer_aware:
            with self._lock:
                return len(self.discovered)
        return self.participant.graph.count_matched_subscriptions(self.topic)

    def close(self) -> None:
        """``PublisherData::shutdown``: endpoints, then the token."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            endpoints = list(self.endpoints.values())
        self.participant.graph.unregister(self.entity.gid)
        for endpoint in endpoints:
            endpoint.pub.undeclare()
        self._token.undeclare()

    def report(self) -> dict[str, Any]:
        with self._lock:
            return {"token": self.entity.keyexpr, "gid": self.entity.gid_hex,
                    "base_key": self.base_key, "buffer_aware": self.buffer_aware,
                    "advertised_backends": self.topic.backend_metadata,
                    "buffer_backend": self.buffer_backend,
                    "publish_calls": self.publish_calls, "skipped": self.skipped,
                    "last_matched": self.last_matched, "puts": list(self.puts),
                    "discovered_subscriptions": [
                        {"gid": s.gid.hex(), "key": s.endpoint_key, "cpu_group": s.uses_cpu_group,
                         "backends": s.backend_metadata} for s in self.discovered]}


class Subscription:
    """A subscription as ``SubscriptionData`` behaves; records every sample it accepts."""

    def __init__(self, participant: Participant, topic: str, ros_type: str,
                 qos: qos_model.QoS = qos_model.QoS(), *,
                 acceptable_buffer_backends: str | None = None) -> None:
        p = self.participant = participant
        self.ros_type = ros_type
        self.qos = qos_model.adapt(qos)
        self.buffer_aware = (not p.legacy and bool(buffer_fields(p.store, ros_type))
                             and self.qos.durability != qos_model.Durability.TRANSIENT_LOCAL)
        self.backend_types: list[str] = []
        advertised = None
        if self.buffer_aware:
            self.backend_types, advertised = _acceptable_backends(
                acceptable_buffer_backends, p.backends)
        self.cpu_only = self.backend_types == ["cpu"]
        self.topic = _topic_info(p, topic, ros_type, self.qos, advertised)
        self.entity = Entity(zid=p.zid, nid=p.node.nid, id=p.next_id(), kind=SUBSCRIPTION,
                             node=p.node_info, topic=self.topic, legacy=p.legacy)
        self.base_key = self.topic.topic_keyexpr
        self._lock = threading.Lock()
        self._closed = False
        self.samples: list[dict[str, Any]] = []
        self.lost = 0
        self.lost_by_gid: dict[str, int] = {}
        self.dropped_no_attachment = 0
        self.dropped_bad_attachment = 0
        self._last_seq: dict[str, int] = {}
        self.discovered_publishers: dict[bytes, Entity] = {}
        # init(): the base key always; a buffer-aware one also _buf_cpu (CPU only) or its own
        # _buf/<gid>; then the token.
        session = p.session
        on_base = lambda s: self._on_sample(s, accelerated=False)  # noqa: E731
        if self.qos.durability == qos_model.Durability.TRANSIENT_LOCAL:
            # rmw_subscription_data.cpp: an AdvancedSubscriber, detectable, with history from
            # late-detected publishers (depth samples) and, when reliable, heartbeat recovery
            reliable = self.qos.reliability == qos_model.Reliability.RELIABLE
            self._subs = [zenoh.ext.declare_advanced_subscriber(
                session, self.base_key, on_base, subscriber_detection=True,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True,
                                                max_samples=self.qos.depth),
                recovery=zenoh.ext.RecoveryConfig(heartbeat=True) if reliable else None)]
        else:
            self._subs = [session.declare_subscriber(self.base_key, on_base)]
        self.keys = [self.base_key]
        if self.buffer_aware:
            key = (self.base_key + CPU_GROUP_SUFFIX if self.cpu_only
                   else self.base_key + ACCELERATED_INFIX + self.entity.gid_hex)
            accelerated = not self.cpu_only
            self._subs.append(session.declare_subscriber(
                key, lambda s: self._on_sample(s, accelerated=accelerated)))
            self.keys.append(key)
        self._token = session.liveliness().declare_token(self.entity.keyexpr)
        if self.buffer_aware:
            if not self.cpu_only:
                p.graph.register_publisher_discovery(topic, self.entity.gid,
                                                     self._on_publisher_discovered)
            p.graph.parse_put(self.entity.keyexpr, False)
        p.track(self)

    def _on_publisher_discovered(self, entity: Entity) -> None:
        """``on_publisher_discovered``: remember compatible publishers by gid (used to resolve
        the sender of an accelerated sample; an unknown sender still gets its message)."""
        if entity.kind != PUBLISHER or entity.topic is None:
            return
        metadata = dict(entity.topic.backend_metadata or {})
        if not backends_compatible(self.backend_types, [*metadata, "cpu"]) or self.cpu_only:
            return
        with self._lock:
            if self._closed or entity.gid in self.discovered_publishers:
                return
            for backend in self.participant.backends.values():
                backend.on_discovering_endpoint(entity.gid, metadata)
            self.discovered_publishers[entity.gid] = entity

    def _on_sample(self, sample: zenoh.Sample, *, accelerated: bool) -> None:
        """The sample callbacks of ``init`` / ``create_subscription_endpoint`` and
        ``add_new_message``. No deduplication: every sample is a message."""
        key = str(sample.key_expr)
        if sample.attachment is None:
            with self._lock:
                self.dropped_no_attachment += 1
            return
        att = attachment.unpack(sample.attachment.to_bytes())
        if att is None:
            with self._lock:
                self.dropped_bad_attachment += 1
            return
        payload = sample.payload.to_bytes()
        decoded = self._decode(payload, endpoint_aware=accelerated)
        with self._lock:
            if self._closed:
                return
            known = att.gid in self.discovered_publishers if accelerated else None
            # add_new_message: lost = |seq - last| - 1 per publisher, keyed by hash_gid, whose
            # text is each byte in hex WITHOUT zero padding.
            gid_key = "".join(f"{b:x}" for b in att.gid)
            last = self._last_seq.get(gid_key)
            if last is not None and abs(att.sequence_number - last) > 1:
                lost = min(abs(att.sequence_number - last) - 1, 2**31 - 1)
                self.lost += lost
                self.lost_by_gid[att.gid.hex()] = self.lost_by_gid.get(att.gid.hex(), 0) + lost
            self._last_seq[gid_key] = att.sequence_number
            self.samples.append({
                "route": _route(self.base_key, key), "key": key, "seq": att.sequence_number,
                "stamp_ns": att.source_timestamp, "gid": att.gid.hex(), "size": len(payload),
                "sha256": _sha256(payload), "publisher_known": known, "decoded": decoded})

    def _decode(self, payload: bytes, *, endpoint_aware: bool) -> dict[str, Any]:
        p = self.participant
        types = {name: b.descriptor_type for name, b in p.backends.items()}
        try:
            decoded = cdr.deserialize(p.store, payload, self.ros_type,
                                      endpoint_aware=endpoint_aware, descriptor_types=types)
            buffers = {}
            for name, frame in decoded.frames.items():
                if frame.form == "cpu":
                    data, extra = frame.data, {}
                else:
                    data = p.backends[frame.backend].from_descriptor(frame.descriptor)
                    extra = {"backend": frame.backend, "origin": frame.descriptor.origin}
                buffers[name] = {"form": frame.form, "size": len(data),
                                 "sha256": _sha256(data), **extra}
        except (cdr.CdrError, ValueError) as exc:
            return {"ok": False, "error": str(exc)}
        return {"ok": True, "fields": scalar_summary(p.store, self.ros_type, decoded.message),
                "buffers": buffers}

    def sample_count(self) -> int:
        with self._lock:
            return len(self.samples)

    def close(self) -> None:
        """``SubscriptionData::shutdown``: callbacks, token, then the Zenoh subscribers."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self.participant.graph.unregister(self.entity.gid)
        self._token.undeclare()
        for sub in self._subs:
            sub.undeclare()

    def report(self) -> dict[str, Any]:
        with self._lock:
            return {"token": self.entity.keyexpr, "gid": self.entity.gid_hex,
                    "base_key": self.base_key, "keys": list(self.keys),
                    "buffer_aware": self.buffer_aware,
                    "advertised_backends": self.topic.backend_metadata,
                    "backend_types": list(self.backend_types), "samples": list(self.samples),
                    "lost": self.lost, "lost_by_gid": dict(self.lost_by_gid),
                    "dropped_no_attachment": self.dropped_no_attachment,
                    "dropped_bad_attachment": self.dropped_bad_attachment,
                    "discovered_publishers": sorted(g.hex() for g in self.discovered_publishers)}


def backends_compatible(a: list[str], b: list[str]) -> bool:
    """rosidl_buffer_backend_registry ``backends_compatible``: any name in both lists."""
    return any(entry in b for entry in a)


class BackendNotInstalled(ValueError):
    """``SubscriptionData::make`` fails: a requested backend is not installed."""


def _acceptable_backends(requested: str | None, installed: dict[str, FakeBackend]
                         ) -> tuple[list[str], dict[str, str]]:
    """``SubscriptionData::make``: (my_backend_types, the advertised map) for
    ``acceptable_buffer_backends``: NULL, empty or only "cpu" -> CPU only (``cpu:``); "any"
    anywhere -> every installed backend (no cpu; possibly nothing); a list -> its non-cpu
    entries, each of which must be installed."""
    requested_list = []
    for token in (requested or "").split(","):
        token = token.strip(" \t")
        if token:
            requested_list.append(token)
    if "any" in requested_list:
        return list(installed), {name: b.metadata for name, b in installed.items()}
    if all(name == "cpu" for name in requested_list):
        return ["cpu"], {"cpu": ""}
    for name in requested_list:
        if name != "cpu" and name not in installed:
            raise BackendNotInstalled(
                f"Buffer backend '{name}' specified in acceptable_buffer_backends is not "
                f"installed. Available backends: {', '.join(installed)}")
    chosen = [name for name in requested_list if name != "cpu"]
    return chosen, {name: installed[name].metadata for name in chosen}
