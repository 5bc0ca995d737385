"""ROS 2 names and domain ids, checked when a graph is validated or before DDS starts (shared by the ROS 2 bridge
and the PAL gripper driver; pure Python, no rclpy import).

Names follow design.ros2.org "Topic and Service name mapping": tokens of letters, digits and '_' that do not start
with a digit, separated by '/'. rclpy refuses others, and a topic name longer than 247 characters once expanded
(RMW_TOPIC_MAX_NAME_LENGTH, 255 - 8), only at start-up, naming no field. A domain id above 232 makes
Fast DDS end the whole process (DDS's port formula, 7400 + 250 * domain + ..., leaves no room above it), without a
message and without a safe state for the other devices, so ROS_DOMAIN_ID is checked before DDS sees it.
"""

from __future__ import annotations

import os
import re

__all__ = ["TOKEN", "TOKEN_RULE", "MAX_DOMAIN_ID", "MAX_TOPIC_LENGTH", "check_name", "expand_topic", "too_long",
           "domain_id"]

TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
TOKEN_RULE = "tokens of letters, digits and '_' separated by '/', none starting with a digit"
MAX_DOMAIN_ID = 232
MAX_TOPIC_LENGTH = 247   # RMW_TOPIC_MAX_NAME_LENGTH: rcl refuses a longer topic name once it is expanded


def check_name(pattern: re.Pattern[str], value: str, expected: str, note: str = "") -> str:
    """``value`` if ``pattern`` matches all of it, else a ValueError: 'expected EXPECTED (TOKEN_RULE; NOTE), got
    VALUE'."""
    if not pattern.fullmatch(value):
        raise ValueError(f"expected {expected} ({TOKEN_RULE}{'; ' + note if note else ''}), got {value!r}")
    return value


def expand_topic(topic: str, namespace: str, node: str | None) -> str | None:
    """The full name rcl makes of a valid ``topic``: absolute as it is, relative under ``namespace``, private
    ('~/a') under ``namespace``/``node``; None for a private name while the node name is not known."""
    if topic.startswith("/"):
        return topic
    if topic.startswith("~"):
        if node is None:
            return None
        parts = (namespace.strip("/"), node, topic[2:])
    else:
        parts = (namespace.strip("/"), topic)
    return "/" + "/".join(x for x in parts if x)


def too_long(full: str, remedy: str) -> str:
    """Why rcl would refuse the expanded topic name ``full`` ('' if it takes it): 'NAME is N characters once
    expanded: ROS 2 allows at most 247 in a topic name (REMEDY)'."""
    if len(full) <= MAX_TOPIC_LENGTH:
        return ""
    shown = full if len(full) <= 60 else f"{full[:40]}...{full[-16:]}"
    return (f"'{shown}' is {len(full)} characters once expanded: ROS 2 allows at most {MAX_TOPIC_LENGTH} in a topic "
            f"name ({remedy})")


def domain_id(param: int | None, error: type[Exception]) -> int | None:
    """The domain to join: ``param``, else ROS_DOMAIN_ID checked here (rcl refuses a word with an obscure error, and
    Fast DDS ends the process for a number above 232); None: neither is set. A bad value raises ``error``."""
    if param is not None:
        return param
    env = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not env:
        return None
    try:
        value = int(env)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise error(f"ROS_DOMAIN_ID={env!r}: expected an integer from 0 to {MAX_DOMAIN_ID} (or set the node's "
                    f"domain_id param)")
    return value
