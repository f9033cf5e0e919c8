"""The part of rmw_zenoh's graph cache that decides buffer routing.

Models ``graph_cache.cpp`` of 0.10.5 / 0.12.0: ``parse_put`` / ``parse_del`` over
``graph_topics_`` (topic name -> type -> QoS string -> publishers and subscriptions, entities
compared by gid), the discovery callbacks (``register_subscriber_discovery_callback`` replays
the subscriptions already known on the topic NAME, of any type; a later put fires the callbacks
only when the topic name AND type were already in the map: the first entity of a topic, or of a
type on it, fires nothing), and ``publisher_count_matched_subscriptions``.
Nodes, services, clients and QoS events are left out: they do not affect the data path.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable

from tests.upstream_model import qos as qos_model
from tests.upstream_model.liveliness import NODE, PUBLISHER, SUBSCRIPTION, Entity, TopicInfo, parse

DiscoveryCallback = Callable[[Entity], None]


@dataclasses.dataclass
class _TopicData:
    info: TopicInfo
    pubs: dict[bytes, Entity] = dataclasses.field(default_factory=dict)
    subs: dict[bytes, Entity] = dataclasses.field(default_factory=dict)

    def side(self, entity: Entity) -> dict[bytes, Entity]:
        return self.pubs if entity.kind == PUBLISHER else self.subs


class GraphCache:
    """One per process (context), keyed by the process's Zenoh session id."""

    def __init__(self, zid: str, *, legacy: bool = False) -> None:
        self.zid = zid
        self.legacy = legacy
        self._lock = threading.Lock()
        self.topics: dict[str, dict[str, dict[str, _TopicData]]] = {}
        # topic name -> owner gid -> callback (the owner is the local endpoint that registered)
        self._subscriber_discovery: dict[str, dict[bytes, DiscoveryCallback]] = {}
        self._publisher_discovery: dict[str, dict[bytes, DiscoveryCallback]] = {}

    # ------------------------------------------------------------------ liveliness input
    def parse_put(self, keyexpr: str, ignore_from_current_session: bool = False) -> None:
        """``GraphCache::parse_put``: add the entity, then run the discovery callbacks the put
        collected (outside the lock, as upstream)."""
        entity = parse(keyexpr, legacy=self.legacy)
        if entity is None or (ignore_from_current_session and entity.zid == self.zid):
            return
        with self._lock:
            callbacks = self._put(entity)
        for callback in callbacks:
            callback(entity)

    def parse_del(self, keyexpr: str, ignore_from_current_session: bool = False) -> None:
        """``GraphCache::parse_del``: remove the entity; a node's removal removes what is left
        of its endpoints. Discovery state held by endpoints is not touched (upstream never
        prunes a publisher's discovered subscriptions)."""
        entity = parse(keyexpr, legacy=self.legacy)
        if entity is None or (ignore_from_current_session and entity.zid == self.zid):
            return
        with self._lock:
            if entity.kind == NODE:
                for types in list(self.topics.values()):
                    for qos_map in list(types.values()):
                        for data in list(qos_map.values()):
                            for member in [*data.pubs.values(), *data.subs.values()]:
                                if (member.zid, member.nid) == (entity.zid, entity.nid):
                                    self._delete(member)
            elif entity.kind in (PUBLISHER, SUBSCRIPTION):
                self._delete(entity)

    # ------------------------------------------------------------------ discovery callbacks
    def register_subscriber_discovery(self, topic_name: str, owner_gid: bytes,
                                      callback: DiscoveryCallback) -> None:
        """``register_subscriber_discovery_callback`` (a buffer-aware publisher): store the
        callback, then replay every subscription already known on the topic name."""
        self._register(self._subscriber_discovery, "subs", topic_name, owner_gid, callback)

    def register_publisher_discovery(self, topic_name: str, owner_gid: bytes,
                                     callback: DiscoveryCallback) -> None:
        """``register_publisher_discovery_callback`` (a non-CPU-only buffer-aware subscription)."""
        self._register(self._publisher_discovery, "pubs", topic_name, owner_gid, callback)

    def unregister(self, owner_gid: bytes) -> None:
        """``unregister_discovery_callbacks``."""
        with self._lock:
            for table in (self._subscriber_discovery, self._publisher_discovery):
                for callbacks in table.values():
                    callbacks.pop(owner_gid, None)

    # ------------------------------------------------------------------ queries
    def count_matched_subscriptions(self, pub_topic: TopicInfo) -> int:
        """``publisher_count_matched_subscriptions``: subscriptions of the same topic name and
        type whose QoS is compatible with the publisher's."""
        with self._lock:
            qos_map = self.topics.get(pub_topic.name, {}).get(pub_topic.type, {})
            return sum(len(data.subs) for data in qos_map.values()
                       if data.subs and qos_model.compatible(pub_topic.qos, data.info.qos))

    # ------------------------------------------------------------------ internals
    def _register(self, table: dict[str, dict[bytes, DiscoveryCallback]], side: str,
                  topic_name: str, owner_gid: bytes, callback: DiscoveryCallback) -> None:
        with self._lock:
            table.setdefault(topic_name, {})[owner_gid] = callback
            known = [entity for qos_map in self.topics.get(topic_name, {}).values()
                     for data in qos_map.values() for entity in getattr(data, side).values()]
        for entity in known:
            callback(entity)

    def _put(self, entity: Entity) -> list[DiscoveryCallback]:
        """``update_topic_map_for_put(graph_topics_, entity, true)``."""
        if entity.kind not in (PUBLISHER, SUBSCRIPTION) or entity.topic is None:
            return []
        info = entity.topic
        qos_str = qos_model.to_keyexpr(info.qos)
        types = self.topics.get(info.name)
        if types is None:  # first entity of this topic name: no callbacks
            self.topics[info.name] = {info.type: {qos_str: self._new_data(entity)}}
            return []
        qos_map = types.get(info.type)
        if qos_map is None:  # first entity of this type on the topic: no callbacks
            types[info.type] = {qos_str: self._new_data(entity)}
            return []
        if qos_str in qos_map:
            qos_map[qos_str].side(entity)[entity.gid] = entity
        else:
            qos_map[qos_str] = self._new_data(entity)
        table = (self._publisher_discovery if entity.kind == PUBLISHER
                 else self._subscriber_discovery)
        return list(table.get(info.name, {}).values())

    @staticmethod
    def _new_data(entity: Entity) -> _TopicData:
        data = _TopicData(info=entity.topic)
        data.side(entity)[entity.gid] = entity
        return data

    def _delete(self, entity: Entity) -> None:
        """``update_topic_map_for_del``: empty QoS, type and topic entries are removed."""
        info = entity.topic
        types = self.topics.get(info.name)
        qos_map = types.get(info.type) if types else None
        qos_str = qos_model.to_keyexpr(info.qos)
        if not qos_map or qos_str not in qos_map:
            return
        data = qos_map[qos_str]
        data.side(entity).pop(entity.gid, None)
        if not data.pubs and not data.subs:
            del qos_map[qos_str]
        if not qos_map:
            del types[info.type]
        if not types:
            del self.topics[info.name]
