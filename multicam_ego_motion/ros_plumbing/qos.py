"""QoS profiles of the graph (DESIGN.md: images sensor-data, estimates and odometry reliable)."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                      reliability=ReliabilityPolicy.RELIABLE)
# Lockstep replay must not lose an image: it asks the nodes for reliable image subscriptions
# (a reliable publisher, as the player is, serves both kinds of subscriber).
RELIABLE_IMAGES = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                             reliability=ReliabilityPolicy.RELIABLE)
# Live images: best effort (a late frame is worth nothing), and deep enough to hold the frame
# a quarter is scheduled to take while its worker is busy (frame_schedule): the sensor-data
# profile's 5 were 170 ms at 30 Hz, and a worker handling a fused pose can be busier.
SENSOR_IMAGES = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                           reliability=ReliabilityPolicy.BEST_EFFORT,
                           durability=DurabilityPolicy.VOLATILE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def image_qos(name: str) -> QoSProfile:
    if name == 'reliable':
        return RELIABLE_IMAGES
    if name == 'sensor_data':
        return SENSOR_IMAGES
    raise ValueError(f'image_qos must be "sensor_data" or "reliable", got {name!r}')


# IMU samples (200 Hz and more): deep enough for a second of them while the general arbiter
# fuses; best effort live (as drivers publish), reliable in lockstep replay (none may be lost:
# the fusion must not depend on the transport).
def imu_qos(name: str) -> QoSProfile:
    if name not in ('reliable', 'sensor_data'):
        raise ValueError(f'imu_qos must be "sensor_data" or "reliable", got {name!r}')
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=500,
                      reliability=(ReliabilityPolicy.RELIABLE if name == 'reliable'
                                   else ReliabilityPolicy.BEST_EFFORT),
                      durability=DurabilityPolicy.VOLATILE)
