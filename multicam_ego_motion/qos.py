"""QoS profiles of the graph (DESIGN.md: images sensor-data, estimates and odometry reliable)."""
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                      reliability=ReliabilityPolicy.RELIABLE)
# Lockstep replay must not lose an image: it asks the nodes for reliable image subscriptions
# (a reliable publisher, as the player is, serves both kinds of subscriber).
RELIABLE_IMAGES = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def image_qos(name: str) -> QoSProfile:
    if name == 'reliable':
        return RELIABLE_IMAGES
    if name == 'sensor_data':
        return qos_profile_sensor_data
    raise ValueError(f'image_qos must be "sensor_data" or "reliable", got {name!r}')
