"""Shared test setup: an isolated ROS 2 network per test process, rclpy, the CLI runner, a
colcon install space of the package."""
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Before anything imports rclpy: this process (and the subprocesses it starts, which inherit
# the environment) talk only to each other.
from multicam_ego_motion.ros_plumbing.ros_domain import reserve_domain  # noqa: E402  (no rclpy inside)
os.environ['ROS_DOMAIN_ID'] = str(reserve_domain())
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
# One BLAS thread, as the product runs (multicam_ego_motion/cli.py says why).
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')


def run_cli(*args, timeout=60, **kw):
    """Run `ego-motion ARGS` as `python -m multicam_ego_motion.cli`, capture its output."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    return subprocess.run([sys.executable, '-m', 'multicam_ego_motion.cli', *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=env, **kw)


def check_suite(suite, root: Path, timeout: int) -> dict:
    """`ego-motion check SUITE` into root; its results.json. Exit 1 (a regression) is for the
    per-bag tests to name (assert_suite_bag); anything else is a broken run."""
    out = root / 'check'
    r = run_cli('check', suite, '--out', out, '--bags-cache', root / 'bags', timeout=timeout)
    assert r.returncode in (0, 1), r.stdout + r.stderr
    import json
    return json.loads((out / 'results.json').read_text())


def assert_suite_bag(results: dict, name: str, frames: int):
    """One bag of a check run: replayed whole, /odom for every frame, every figure in bounds."""
    bag = results['bags'][name]
    assert bag['error'] is None, f'{name}: replay failed: {bag["error"]}'
    f = bag['figures']
    assert f['frames'] == frames, f'{name}: {f["frames"]} of {frames} frames played'
    assert f['frames_with_odometry'] == f['odometry_poses'] == frames, \
        f'{name}: odometry for {f["frames_with_odometry"]} of {frames} frames'
    summary = ', '.join(f'{c["figure"]} ' + ('n/a' if c['value'] is None else f'{c["value"]:.4f}')
                        + f' ({c["condition"]})' for c in bag['checks'])
    failed = [c['figure'] for c in bag['checks'] if not c['passed']]
    assert not failed, f'{name}: {", ".join(failed)} out of bounds ({summary})'


def start_cli(*args):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get('PYTHONPATH', ''))
    return subprocess.Popen([sys.executable, '-m', 'multicam_ego_motion.cli', *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


@pytest.fixture(scope='session')
def rclpy_context():
    import rclpy
    rclpy.init()
    yield rclpy.get_default_context()
    rclpy.try_shutdown()


class SpinningNode:
    """A test node spun by its own executor in a background thread."""

    def __init__(self, name):
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        self.node = Node(name)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def close(self):
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


# Session fixtures of the fault-injection suite (faulty bags and one replay of each).
pytest_plugins = ['fault_replays']


def read_bag(path):
    """(topics {name: (type, count)}, messages [(topic, log time, message)]) read by the
    independent `rosbags` reader, not the product's own."""
    from rosbags.highlevel import AnyReader
    with AnyReader([Path(path)]) as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        messages = [(c.topic, t, reader.deserialize(raw, c.msgtype))
                    for c, t, raw in reader.messages()]
    return topics, messages


# ---- a colcon install space of this package (test_package_build, test_install_space) -----

PACKAGE = 'multicam_ego_motion'
# Everything a checkout may hold that is not the package's source: venvs, build outputs
# (including the tf2_msgs workspace and the native kernel built in place), caches.
NOT_SOURCE = shutil.ignore_patterns(
    '.git', '.venv', 'build', 'install', 'log', 'out', '__pycache__', '*.egg-info',
    '.pytest_cache', '*.so')


def colcon_command():
    try:
        import colcon_core  # noqa: F401
    except ImportError:
        pytest.skip('colcon is not importable in this interpreter (pip install -r requirements.txt)')
    exe = os.path.join(os.path.dirname(sys.executable), 'colcon')
    if not os.access(exe, os.X_OK):
        pytest.skip(f'colcon_core is importable but no colcon command beside {sys.executable}')
    return exe


def env_without_ros_setup():
    """This interpreter's environment with no sourced ROS or colcon setup leaking in."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('COLCON', 'AMENT_')) and k != 'PYTHONPATH'}
    env['PATH'] = os.path.dirname(sys.executable) + os.pathsep + env.get('PATH', '')
    return env


@pytest.fixture(scope='session')
def install_prefix(tmp_path_factory):
    """`colcon build` of a copy of the package (the slow part, 1-2 min: the native kernel is
    compiled), once per session; the copy's source and build folders are then removed, so
    that only the install space holds the package: <ws>/install/multicam_ego_motion."""
    colcon = colcon_command()
    ws = tmp_path_factory.mktemp('colcon_ws')
    shutil.copytree(REPO, ws / 'src' / PACKAGE, ignore=NOT_SOURCE, symlinks=True)
    # colcon's python setup.py step must run in this interpreter's environment
    proc = subprocess.run(
        [colcon, 'build', '--base-paths', 'src', '--event-handlers', 'console_direct+'],
        cwd=ws, env=env_without_ros_setup(), capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    shutil.rmtree(ws / 'src')
    shutil.rmtree(ws / 'build')
    return ws / 'install' / PACKAGE


def install_site_packages(prefix):
    return prefix / 'lib' / f'python{sys.version_info.major}.{sys.version_info.minor}' / 'site-packages'
