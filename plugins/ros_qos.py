"""Incompatible QoS between one of our ROS 2 endpoints and a peer's, reported with the topic, the policy and both
sides' values (shared by the ROS 2 bridge and the PAL gripper driver).

DDS connects neither side of such a pair and says nothing: a reliable subscription never hears a best-effort
publisher, a transient_local subscription never hears a volatile publisher. rclpy raises an "incompatible QoS"
event on each side, naming only the policy. For reliability and durability the other side's value follows from
ours (the only incompatible pairs are a reliable/transient_local subscription against a best-effort/volatile
publisher); for the other policies (deadline, liveliness, lease duration) it is looked up in the ROS graph. rclpy is
imported when a report is made, not with this module.
"""

from __future__ import annotations

import threading
from typing import Any, Callable

__all__ = ["QosReport", "policy_value", "RELIABILITY_VALUES"]

RELIABILITY_VALUES = ("reliable", "best_effort")
#: (policy, our side) -> the peer's value, where an incompatibility leaves only one
_PEER_VALUE = {("RELIABILITY", "subscription"): "best_effort", ("RELIABILITY", "publisher"): "reliable",
               ("DURABILITY", "subscription"): "volatile", ("DURABILITY", "publisher"): "transient_local"}
_ATTR = {"RELIABILITY": "reliability", "DURABILITY": "durability", "DEADLINE": "deadline",
         "LIVELINESS": "liveliness", "LIVELINESS_LEASE_DURATION": "liveliness_lease_duration"}
MAX_PROBLEMS = 20   # distinct (topic, policy) descriptions kept for status()


def policy_value(policy: str, qos: Any) -> str:
    """The value of QoS ``policy`` ('RELIABILITY', ...) in a QoSProfile, as written in a graph's params
    ('best_effort', 'transient_local', '0.1 s')."""
    attr = _ATTR.get(policy)
    if attr is None or qos is None:
        return "?"
    v = getattr(qos, attr, None)
    if v is None:
        return "?"
    if hasattr(v, "nanoseconds"):
        ns = int(v.nanoseconds)
        return "unset" if ns <= 0 or ns >= 2**63 - 1 else f"{ns * 1e-9:g} s"
    return str(getattr(v, "name", v)).lower()


class QosReport:
    """Counts the incompatible-QoS events of a node's endpoints and describes each (topic, policy, our value, the
    peer's value and, where the ROS graph already shows it, the peer's node), logged once per topic and policy.

    ``log(key, text)`` logs once per key; ``hint(policy, side)`` says what to set (may return "")."""

    def __init__(self, log: Callable[[Any, str], None], hint: Callable[[str, str], str] | None = None):
        self.log = log
        self.hint = hint or (lambda policy, side: "make the two QoS settings compatible")
        self.count = 0                          # events (one per incompatible peer found)
        self.problems: dict[tuple[str, str], tuple[Any, str, Any]] = {}   # (topic, policy) -> (node, side, qos)
        self._lock = threading.Lock()

    def subscription_callbacks(self, node: Callable[[], Any], topic: Callable[[], str], qos: Any) -> Any:
        """SubscriptionEventCallbacks for a subscription with ``qos`` (``node``/``topic``: looked up at the event,
        as the endpoint is made after its callbacks)."""
        from rclpy.event_handler import SubscriptionEventCallbacks

        return SubscriptionEventCallbacks(incompatible_qos=lambda info: self.on_event(
            node(), topic(), "subscription", qos, info))

    def publisher_callbacks(self, node: Callable[[], Any], topic: Callable[[], str], qos: Any) -> Any:
        """PublisherEventCallbacks for a publisher with ``qos`` (see :meth:`subscription_callbacks`)."""
        from rclpy.event_handler import PublisherEventCallbacks

        return PublisherEventCallbacks(incompatible_qos=lambda info: self.on_event(
            node(), topic(), "publisher", qos, info))

    def on_event(self, node: Any, topic: str, side: str, qos: Any, info: Any) -> str:
        """Count and describe one event (the executor thread); returns the description logged."""
        from rclpy.qos import qos_policy_name_from_kind

        policy = qos_policy_name_from_kind(info.last_policy_kind)
        with self._lock:
            self.count += max(1, int(getattr(info, "total_count_change", 1) or 1))
            if (topic, policy) in self.problems or len(self.problems) < MAX_PROBLEMS:
                self.problems[(topic, policy)] = (node, side, qos)
        text = self._describe(topic, policy, node, side, qos)
        self.log(("qos", topic, policy), text)
        return text

    def texts(self, topic: str | None = None) -> list[str]:
        """The descriptions (of one topic, or all), for status() or an error: made now, so that they name the
        peer's node once the ROS graph knows it (at the event it may not yet)."""
        with self._lock:
            found = [(tp, pol, *rest) for (tp, pol), rest in self.problems.items() if topic is None or tp == topic]
        return [self._describe(tp, pol, node, side, qos) for tp, pol, node, side, qos in found]

    def _describe(self, topic: str, policy: str, node: Any, side: str, qos: Any) -> str:
        other = "publisher" if side == "subscription" else "subscription"
        ours = policy_value(policy, qos)
        theirs, who = self._peer(node, topic, other, policy, ours)
        hint = self.hint(policy, side)
        return (f"topic {topic}: this {side} and a {other}{who} have incompatible QoS ({policy}: {ours} here, "
                f"{theirs} there): nothing flows between the two" + (f"; {hint}" if hint else ""))

    @staticmethod
    def _peer(node: Any, topic: str, other: str, policy: str, ours: str) -> tuple[str, str]:
        """(the peer's value, ' of node NAME' where the graph shows which one)."""
        side = "subscription" if other == "publisher" else "publisher"
        known = _PEER_VALUE.get((policy, side))
        try:
            infos = (node.get_publishers_info_by_topic(topic) if other == "publisher" else
                     node.get_subscriptions_info_by_topic(topic))
        except Exception:  # a diagnosis only (the context may be going down)
            infos = []
        me = (node.get_namespace(), node.get_name()) if node is not None else None
        found = []
        for i in infos:
            if (i.node_namespace, i.node_name) == me or i.node_name.startswith("_NODE_NAME_UNKNOWN"):
                continue   # ourselves, or a node whose name discovery has not brought yet
            value = policy_value(policy, i.qos_profile)
            if (known is not None and value == known) or (known is None and value != ours):
                found.append((value, f"{i.node_namespace.rstrip('/')}/{i.node_name}"))
        if known is not None:
            nodes = sorted({w for v, w in found})
            return known, (f" of node {', '.join(nodes)}" if nodes else "")
        if found:
            return found[0][0], f" of node {found[0][1]}"
        return "not known (not in the ROS graph yet)", ""
