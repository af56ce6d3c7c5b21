"""ament_python package: multicam_ego_motion.

Three Python packages: the per-quarter estimator nodes (camera_pose_nodes), the camera and
general arbiters (arbiter_node), and the tooling around them that a user runs through the
`ego-motion` command (multicam_ego_motion: bags, scenarios, evaluation, coordinator).
"""
from glob import glob

from setuptools import find_packages, setup

package_name = 'multicam_ego_motion'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=['camera_pose_nodes*', 'arbiter_node*', 'multicam_ego_motion*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='multicam_ego_motion developers',
    maintainer_email='dev@multicam-ego-motion.invalid',
    description='Multi-camera (non-overlapping) ego-motion for ROS 2: KLT + EKF per camera quarter, arbiters, coordinator.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            # One entry point per node, for `ros2 run multicam_ego_motion <name>`.
            'quarter_node = camera_pose_nodes.quarter_node:main',
            'camera_arbiter = arbiter_node.camera_arbiter_node:main',
            'general_arbiter = arbiter_node.general_arbiter_node:main',
            'coordinator = multicam_ego_motion.coordinator.coordinator_node:main',
            # The user's command line: generate, import-kitti, play, record, evaluate, replay, bench.
            'ego-motion = multicam_ego_motion.cli:main',
        ],
    },
)
