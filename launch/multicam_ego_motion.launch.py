"""Start the multi-camera ego-motion graph on a ROS 2 install:

    ros2 launch multicam_ego_motion multicam_ego_motion.launch.py rig_file:=RIG.yaml \
        [params_file:=PARAMS.yaml] [workers:=M] [namespace:=NS] [use_sim_time:=true]

One process is started, the coordinator; it starts the graph (a quarter node per camera
quarter, a camera arbiter per camera, the general arbiter) on M worker processes and keeps
it running: worker restarts, rebalancing on measured costs, its own /diagnostics entry.
Defaults: the package's config/rig_default.yaml (the rig of bags/default) and
config/params.yaml, one worker per CPU core, no namespace, the system clock.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'multicam_ego_motion'


def generate_launch_description():
    config = PathJoinSubstitution([FindPackageShare(PACKAGE), 'config'])
    arguments = [
        DeclareLaunchArgument(
            'rig_file', default_value=PathJoinSubstitution([config, 'rig_default.yaml']),
            description='rig YAML: camera names, image and camera_info topics, extrinsics '
                        'base_link -> camera optical frame'),
        DeclareLaunchArgument(
            'params_file', default_value=PathJoinSubstitution([config, 'params.yaml']),
            description="ROS params file of the graph's nodes"),
        DeclareLaunchArgument(
            'workers', default_value='0',
            description='worker processes hosting the nodes (0: one per CPU core)'),
        DeclareLaunchArgument(
            'namespace', default_value='',
            description='namespace of the whole graph, its nodes and topics, inputs and outputs '
                        '(robot1: /robot1/front/image_raw in, /robot1/odom and /robot1/tf out); '
                        '/clock stays global'),
        DeclareLaunchArgument(
            'use_sim_time', default_value='false',
            description="every node of the graph takes its time from /clock (a bag played "
                        "with its clock, a simulator)"),
    ]
    coordinator = Node(
        package=PACKAGE,
        executable='coordinator',
        name='ego_motion_coordinator',
        namespace=LaunchConfiguration('namespace'),
        arguments=['--rig', LaunchConfiguration('rig_file'),
                   '--params', LaunchConfiguration('params_file'),
                   '--workers', LaunchConfiguration('workers')],
        parameters=[{'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)}],
        output='screen',
    )
    return LaunchDescription(arguments + [coordinator])
