"""The nodes of the graph for a rig: one quarter node per camera quarter (paper T_kl), one
camera arbiter per camera (T_k5) and one general arbiter (T_5). ROS-free description that a
worker process turns into rclpy nodes."""
from dataclasses import asdict, dataclass, field
from typing import Dict, List

from multicam_ego_motion.rig import Rig


@dataclass
class NodeSpec:
    key: str                  # 'front/q1', 'front/arbiter', 'general_arbiter'
    kind: str                 # 'quarter', 'camera_arbiter', 'general_arbiter'
    namespace: str
    parameters: Dict[str, object] = field(default_factory=dict)

    def to_dict(self):
        return asdict(self)


def graph_nodes(rig: Rig, rig_file: str, quarters: int = 4, overrides: Dict[str, Dict] = None) -> List[NodeSpec]:
    """Every node of the graph; `overrides` maps kind -> parameter values for all of that kind."""
    overrides = overrides or {}
    nodes = []
    for cam in rig.cameras:
        for q in range(1, quarters + 1):
            nodes.append(NodeSpec(f'{cam.name}/q{q}', 'quarter', f'/{cam.name}/q{q}',
                                  {'camera': cam.name, 'quarter': q, 'rig_file': rig_file,
                                   **overrides.get('quarter', {})}))
        nodes.append(NodeSpec(f'{cam.name}/arbiter', 'camera_arbiter', f'/{cam.name}',
                              {'camera': cam.name, 'quarters': quarters,
                               **overrides.get('camera_arbiter', {})}))
    nodes.append(NodeSpec('general_arbiter', 'general_arbiter', '/',
                          {'rig_file': rig_file, **overrides.get('general_arbiter', {})}))
    return nodes
