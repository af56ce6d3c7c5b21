"""The nodes of the graph for a rig: one quarter node per camera quarter (paper T_kl), one
camera arbiter per camera (T_k5) and one general arbiter (T_5). ROS-free description that a
worker process turns into rclpy nodes.

A namespace (the coordinator's own, e.g. `ros2 launch ... namespace:=robot1`) moves the whole
graph under it: the nodes (/robot1/front/q1/quarter_node, /robot1/general_arbiter) and every
topic they use, inputs and outputs (/robot1/front/image_raw, /robot1/odom, /robot1/tf,
/robot1/diagnostics); only /clock stays global. The nodes name most of their topics
absolutely, which a node namespace leaves alone: `remappings()` gives the rules (rcl's
`-r FROM:=TO`) that move those.
"""
from dataclasses import asdict, dataclass, field, replace
from typing import Dict, Iterable, List, Tuple

from multicam_ego_motion.coordinator.allocation import QUARTERS
from multicam_ego_motion.geometry.rig import TRANSPORTS, Rig


@dataclass
class NodeSpec:
    key: str                  # 'front/q1', 'front/arbiter', 'general_arbiter'
    kind: str                 # 'quarter', 'camera_arbiter', 'general_arbiter'
    namespace: str
    parameters: Dict[str, object] = field(default_factory=dict)

    def to_dict(self):
        return asdict(self)


def normalize_namespace(namespace: str) -> str:
    """'' or '/' -> '' (none); 'robot1', '/robot1/' -> '/robot1'."""
    ns = (namespace or '').strip().strip('/')
    return f'/{ns}' if ns else ''


def under(namespace: str, name: str) -> str:
    """The absolute `name` ('/odom', '/' for the root) moved under `namespace`."""
    ns = normalize_namespace(namespace)
    if name == '/':
        return ns or '/'
    return ns + name


def graph_nodes(rig: Rig, rig_file: str, quarters: int = 4, overrides: Dict[str, Dict] = None,
                namespace: str = '') -> List[NodeSpec]:
    """Every node of the graph; `overrides` maps kind -> parameter values for all of that kind."""
    overrides = overrides or {}
    nodes = []
    for cam in rig.cameras:
        for q in range(1, quarters + 1):
            nodes.append(NodeSpec(f'{cam.name}/q{q}', 'quarter', under(namespace, f'/{cam.name}/q{q}'),
                                  {'camera': cam.name, 'quarter': q, 'rig_file': rig_file,
                                   **overrides.get('quarter', {})}))
        nodes.append(NodeSpec(f'{cam.name}/arbiter', 'camera_arbiter', under(namespace, f'/{cam.name}'),
                              {'camera': cam.name, 'quarters': quarters,
                               **overrides.get('camera_arbiter', {})}))
    nodes.append(NodeSpec('general_arbiter', 'general_arbiter', under(namespace, '/'),
                          {'rig_file': rig_file, **overrides.get('general_arbiter', {})}))
    return nodes


# Topics the nodes (and their worker) name absolutely in their code: outputs, links, inputs.
FIXED_TOPICS = ('/odom', '/tf', '/diagnostics', '/ego_motion/fused_pose', '/ego_motion/path',
                '/ego_motion/frame_schedule', '/ego_motion/map_scale', '/ego_motion/road_normal')
# Their topic parameters, per node name of the params file and kind of the overrides.
TOPIC_PARAMETERS = {('quarter_node', 'quarter'): ('fused_pose_topic', 'frame_schedule_topic', 'map_scale_topic',
                                                 'road_normal_topic'),
                    ('general_arbiter', 'general_arbiter'): ('wheel_odometry_topic',)}


def topic_parameter_values(params_file: str = None, overrides: Dict[str, Dict] = None) -> List[str]:
    """The values the nodes' topic parameters take: the overrides', else the params file's,
    else the nodes' defaults."""
    from arbiter_node.general_arbiter_node import NODE_PARAMETERS as GENERAL
    from camera_pose_nodes.quarter_node import NODE_PARAMETERS as QUARTER
    from multicam_ego_motion.params_file import node_params
    defaults = {'quarter_node': QUARTER, 'general_arbiter': GENERAL}
    overrides = overrides or {}
    values = []
    for (node_name, kind), names in TOPIC_PARAMETERS.items():
        given = node_params(params_file, node_name, set(names)) if params_file else {}
        given.update({k: v for k, v in overrides.get(kind, {}).items() if k in names})
        values += [str(given.get(n, defaults[node_name][n][0])) for n in names]
    return values


def bearings_topic(camera: str, quarter: int) -> str:
    """A quarter's tracks for the general arbiter (its node publishes `bearings` in its
    namespace /<camera>/q<quarter>)."""
    return f'/{camera}/q{quarter}/bearings'


def graph_topics(rig: Rig, topic_parameters: Iterable[str] = ()) -> List[str]:
    """Every absolute topic name the graph's nodes use (what a namespace must move)."""
    names = list(FIXED_TOPICS)
    for cam in rig.cameras:
        # every transport's topic: a quarter's image_transport parameter can override the rig's
        names += [replace(cam, transport=t).input_topic for t in TRANSPORTS]
        names += [cam.image_topic, cam.camera_info_topic, f'/{cam.name}/pose']
        names += [bearings_topic(cam.name, q) for q in range(1, QUARTERS + 1)]
    if getattr(rig, 'imu', None) is not None:
        names.append(rig.imu.topic)
    names += list(topic_parameters)
    return sorted({n for n in names if n.startswith('/')})


def remappings(rig: Rig, namespace: str, topic_parameters: Iterable[str] = ()) -> List[Tuple[str, str]]:
    """(from, to) rules that move the graph's absolute topics under `namespace` (none without
    one). Given to every process of the graph as global `--ros-args -r FROM:=TO`."""
    if not normalize_namespace(namespace):
        return []
    return [(n, under(namespace, n)) for n in graph_topics(rig, topic_parameters)]


def ros_args(rules: List[Tuple[str, str]]) -> List[str]:
    """The command-line form of `remappings()`: ['--ros-args', '-r', 'FROM:=TO', ...]."""
    if not rules:
        return []
    args = ['--ros-args']
    for src, dst in rules:
        args += ['-r', f'{src}:={dst}']
    return args
