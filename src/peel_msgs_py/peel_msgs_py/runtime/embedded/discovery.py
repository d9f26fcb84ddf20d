"""``ros_discovery_info``: how ROS 2 tools learn which nodes own which DDS readers and writers.

Like every rmw based on ``rmw_dds_common``, each participant publishes one
``rmw_dds_common/msg/ParticipantEntitiesInfo`` (its GUID, and per node the GUIDs of the node's
readers and writers) on the DDS topic ``ros_discovery_info`` (no ``rt`` prefix), reliable,
transient-local, keep-last 1, republished whenever a node or one of its entities comes or goes.
This is what makes ``ros2 node list`` / ``ros2 node info`` on a Jazzy machine show our nodes.
"""

from __future__ import annotations

import contextlib
from typing import Any

from cyclonedds.core import DDSException
from cyclonedds.pub import DataWriter

from .messages import Gid, NodeEntitiesInfo, ParticipantEntitiesInfo
from .qos import DurabilityPolicy, QoSProfile, to_dds

TOPIC = "ros_discovery_info"
QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _gid(entity: Any) -> Gid:
    return Gid(data=entity.get_guid().bytes)


def node_info(node: Any) -> NodeEntitiesInfo:
    """The GUIDs of a node's readers and writers (services/clients own one of each)."""
    readers = [s._reader for s in node._subscriptions]
    readers += [s._reader for s in node._services] + [c._reader for c in node._clients]
    writers = [p._writer for p in node._publishers]
    writers += [s._writer for s in node._services] + [c._writer for c in node._clients]
    return NodeEntitiesInfo(
        node_namespace=node.get_namespace(),
        node_name=node.get_name(),
        reader_gid_seq=[_gid(r) for r in readers],
        writer_gid_seq=[_gid(w) for w in writers],
    )


class DiscoveryPublisher:
    """Publishes this participant's ParticipantEntitiesInfo."""

    def __init__(self, context: Any) -> None:
        self._context = context
        participant = context.participant
        topic = context.topic(TOPIC, ParticipantEntitiesInfo)
        self._writer = DataWriter(participant, topic, qos=to_dds(QOS, writer=True))
        self._gid = _gid(participant)

    def publish(self, nodes: list[Any]) -> None:
        with contextlib.suppress(DDSException):
            infos = [node_info(n) for n in nodes]
            self._writer.write(ParticipantEntitiesInfo(gid=self._gid, node_entities_info_seq=infos))
