"""ament_python package: multicam_ego_motion.

Three Python packages: the per-quarter estimator nodes (camera_pose_nodes), the camera and
general arbiters (arbiter_node), and the tooling around them that a user runs through the
`ego-motion` command (multicam_ego_motion: bags, scenarios, evaluation, coordinator).
"""
import os
import sys
from glob import glob

from pybind11.setup_helpers import Pybind11Extension
from setuptools import find_packages, setup

package_name = 'multicam_ego_motion'

EIGEN_HINT = ('pip install cmeel-eigen (pinned in requirements.txt and pyproject.toml): '
              'its headers are <site-packages>/cmeel.prefix/include/eigen3')


def eigen_include() -> str:
    """Eigen's headers from the cmeel-eigen wheel: <site-packages>/cmeel.prefix/include/eigen3,
    found beside the cmeel package, else on any sys.path entry."""
    candidates = []
    try:
        import cmeel
        from cmeel.consts import CMEEL_PREFIX
        site = os.path.dirname(os.path.dirname(os.path.abspath(cmeel.__file__)))
        candidates.append(os.path.join(site, CMEEL_PREFIX, 'include', 'eigen3'))
    except ImportError:
        pass
    candidates += [os.path.join(p, 'cmeel.prefix', 'include', 'eigen3') for p in sys.path if p]
    for inc in candidates:
        if os.path.isfile(os.path.join(inc, 'Eigen', 'Dense')):
            return inc
    sys.exit(f'multicam_ego_motion: Eigen headers not found (looked in {candidates}); {EIGEN_HINT}')


# The per-quarter estimator's native kernel (camera_pose_nodes/kernel.py selects it).
quarter_kernels = Pybind11Extension(
    'camera_pose_nodes._quarter_kernels',
    ['camera_pose_nodes/native/quarter_kernels.cpp'],
    cxx_std=17,
    # Eigen as a system include: its own warnings are not ours. No fused multiply-add
    # contraction: the same roundings as numpy's elementwise arithmetic.
    extra_compile_args=['-O2', '-ffp-contract=off', '-isystem', eigen_include()],
)

# The general arbiter's per-frame rig-motion refinement (arbiter_node/rig_motion_fit.py).
rig_motion_kernel = Pybind11Extension(
    'arbiter_node._rig_motion_kernel',
    ['arbiter_node/native/rig_motion_kernel.cpp'],
    cxx_std=17,
    extra_compile_args=['-O2', '-isystem', eigen_include()],
)

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=['camera_pose_nodes*', 'arbiter_node*', 'multicam_ego_motion*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        # found through the ament index at run time (multicam_ego_motion/ros_plumbing/package_share.py)
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        # `ros2 launch multicam_ego_motion multicam_ego_motion.launch.py`
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    ext_modules=[quarter_kernels, rig_motion_kernel],
    install_requires=['setuptools'],
    zip_safe=False,
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
            'worker = multicam_ego_motion.coordinator.worker:main_remote',
            # The user's command line: generate, import-kitti, play, record, evaluate, replay, bench.
            'ego-motion = multicam_ego_motion.cli:main',
        ],
    },
)
