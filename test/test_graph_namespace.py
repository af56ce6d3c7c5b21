"""A namespaced graph (the coordinator's namespace, e.g. `ros2 launch ... namespace:=robot1`):
every node and every topic it uses moves under the namespace, only /clock (and rclpy's own
/rosout and /parameter_events) stay global. The nodes are real, created as a worker creates
them (worker.create_node) in an rclpy context given the coordinator's remappings; no graph
runs."""
import pytest

from conftest import REPO
from multicam_ego_motion.coordinator.graph_spec import (graph_nodes, normalize_namespace, remappings,
                                                        ros_args, topic_parameter_values, under)
from multicam_ego_motion.coordinator.worker import create_node
from multicam_ego_motion.geometry.rig import load_rig

RIG = REPO / 'config' / 'rig_default.yaml'
PARAMS = REPO / 'config' / 'params.yaml'
GLOBAL = ('/clock', '/rosout', '/parameter_events')


@pytest.mark.parametrize('given, expected', [('', ''), ('/', ''), ('robot1', '/robot1'),
                                             ('/robot1/', '/robot1'), ('fleet/robot1', '/fleet/robot1')])
def test_namespace_forms(given, expected):
    assert normalize_namespace(given) == expected
    assert under(given, '/') == (expected or '/')
    assert under(given, '/odom') == expected + '/odom'


def test_no_namespace_no_remapping():
    rig = load_rig(RIG)
    assert remappings(rig, '', ['/wheel/odom']) == [] and ros_args([]) == []
    assert {n.namespace for n in graph_nodes(rig, str(RIG))} == (
        {'/'} | {f'/{c}' for c in rig.names} | {f'/{c}/q{q}' for c in rig.names for q in range(1, 5)})


def test_topic_parameters_from_overrides_then_params_file_then_defaults(tmp_path):
    params = tmp_path / 'params.yaml'
    params.write_text('/**/general_arbiter:\n  ros__parameters:\n    wheel_odometry_topic: /base/odom\n')
    assert topic_parameter_values(str(params)) == [
        '/ego_motion/fused_pose', '/ego_motion/frame_schedule', '/ego_motion/map_scale', '/ego_motion/road_normal',
        '/base/odom']
    assert topic_parameter_values(str(params), {'general_arbiter': {'wheel_odometry_topic': '/w'}})[-1] == '/w'


def test_every_node_and_topic_of_a_namespaced_graph_is_under_the_namespace():
    import rclpy
    from rclpy.context import Context

    rig = load_rig(RIG)
    ns = '/robot1'
    overrides = {'general_arbiter': {'use_wheel_odometry': True}}
    rules = remappings(rig, ns, topic_parameter_values(str(PARAMS), overrides))
    ctx = Context()
    rclpy.init(args=['worker', *ros_args(rules)], context=ctx)
    nodes = []
    try:
        camera = rig.names[0]
        specs = [s.to_dict() for s in graph_nodes(rig, str(RIG), overrides=overrides, namespace=ns)
                 if s.key in (f'{camera}/q1', f'{camera}/arbiter', 'general_arbiter')]
        for spec in specs:
            nodes.append(create_node(spec, str(PARAMS), context=ctx))
        names = {}
        for node in nodes:
            assert node.get_namespace().startswith(ns + '/') or node.get_namespace() == ns
            topics = [e.topic_name for e in list(node.publishers) + list(node.subscriptions)]
            names[node.get_fully_qualified_name()] = topics
        used = {t for topics in names.values() for t in topics}
        outside = sorted(t for t in used if not t.startswith(ns + '/') and t not in GLOBAL)
        assert outside == [], names
        # the links between the nodes, the inputs and the outputs all moved
        for topic in (f'/{camera}/image_raw', f'/{camera}/camera_info', f'/{camera}/q1/pose',
                      f'/{camera}/pose', '/ego_motion/fused_pose', '/ego_motion/frame_schedule',
                      '/odom', '/tf', '/diagnostics', '/wheel/odom'):
            assert ns + topic in used, (topic, names)
        assert '/robot1/general_arbiter' in names
    finally:
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
