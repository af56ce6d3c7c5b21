"""QoS choices of the player and the recorder.

Publishing: RELIABLE matches both reliable and best-effort subscribers; /tf_static is
TRANSIENT_LOCAL so nodes started late still get the static transforms (as tf2 expects).
Subscribing: match what the publishers offer, so no publisher is left unmatched.
"""
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

LATCHED_TOPICS = ('/tf_static',)


def publishing_qos(topic: str, depth: int = 100) -> QoSProfile:
    durability = (DurabilityPolicy.TRANSIENT_LOCAL if topic in LATCHED_TOPICS
                  else DurabilityPolicy.VOLATILE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE, durability=durability)


def subscribing_qos(publisher_profiles, depth: int = 1000) -> QoSProfile:
    """The subscription QoS that matches every given publisher QoS profile.

    Reliable (the default when no publisher is known yet) only if every publisher is reliable (a reliable subscription does not match a
    best-effort publisher); transient-local only if every publisher is transient-local.
    """
    profiles = list(publisher_profiles)
    reliable = not profiles or all(
        p.reliability == ReliabilityPolicy.RELIABLE for p in profiles)
    latched = bool(profiles) and all(
        p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
