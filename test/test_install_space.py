"""The package run from a colcon install space, as on a ROS 2 install (issue 16, items 3, 4).

The install space is conftest.py's `install_prefix` (colcon build of a copy; the copy's source
and build folders removed afterwards). The commands run as `source install/setup.bash` would
have them: AMENT_PREFIX_PATH starts with the install prefix, PYTHONPATH is the install space's
site-packages only, the working directory an empty temporary folder; the default bag and its
rig are copied there too. So config/params.yaml and config/fastdds.xml can only come from the
install space's share/multicam_ego_motion/config, found through the ament index.

The launch file cannot be run (the `launch` package is not installable here): what can be
checked without it is; the coordinator is then started with the command line that launch_ros
builds from it (arguments, then `--ros-args -r __node:= -r __ns:= --params-file`).
"""
import ast
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from conftest import PACKAGE, REPO, env_without_ros_setup, install_site_packages

LAUNCH_FILE = 'multicam_ego_motion.launch.py'
LAUNCH_ARGUMENTS = {'rig_file', 'params_file', 'workers', 'namespace', 'use_sim_time'}


def installed_env(prefix):
    """What sourcing <ws>/install/setup.bash gives a shell, and nothing of the checkout."""
    env = env_without_ros_setup()
    env['AMENT_PREFIX_PATH'] = os.pathsep.join([str(prefix), *filter(None, [os.environ.get('AMENT_PREFIX_PATH')])])
    env['PYTHONPATH'] = str(install_site_packages(prefix))
    env['PATH'] = str(prefix / 'bin') + os.pathsep + env['PATH']
    return env


def installed(prefix, name):
    return prefix / 'lib' / PACKAGE / name


@pytest.fixture(scope='module')
def bag_copy(tmp_path_factory):
    dst = tmp_path_factory.mktemp('bag') / 'default'
    shutil.copytree(REPO / 'bags' / 'default', dst)
    return dst


def test_share_holds_config_and_launch_as_in_the_source(install_prefix):
    share = install_prefix / 'share' / PACKAGE
    for rel in ('config/params.yaml', 'config/fastdds.xml', 'config/rig_default.yaml', f'launch/{LAUNCH_FILE}'):
        assert (share / rel).is_file(), rel
        assert (share / rel).read_bytes() == (REPO / rel).read_bytes(), rel


def test_modules_and_config_come_from_the_install_space(install_prefix, tmp_path):
    code = ('import camera_pose_nodes, arbiter_node, multicam_ego_motion\n'
            'from multicam_ego_motion.ros_plumbing import dds_transport, package_share\n'
            'for m in (camera_pose_nodes, arbiter_node, multicam_ego_motion): print(m.__file__)\n'
            'print(package_share.share_dir()); print(package_share.default_params()); print(dds_transport.profile())\n')
    proc = subprocess.run([sys.executable, '-c', code], cwd=tmp_path, env=installed_env(install_prefix),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    *modules, share, params, profile = proc.stdout.split()
    site = str(install_site_packages(install_prefix))
    assert all(m.startswith(site + os.sep) for m in modules), modules
    assert share == str(install_prefix / 'share' / PACKAGE)
    assert params == f'{share}/config/params.yaml' and profile == f'{share}/config/fastdds.xml'


def test_unsourced_install_says_what_is_missing(install_prefix, tmp_path, bag_copy):
    # PYTHONPATH only, no AMENT_PREFIX_PATH: no silent fall back to the code's defaults
    env = installed_env(install_prefix)
    del env['AMENT_PREFIX_PATH']
    proc = subprocess.run([str(installed(install_prefix, 'ego-motion')), 'replay', str(bag_copy),
                           '--out', str(tmp_path / 'out'), '--duration', '1', '--workers', '1'],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    err = proc.stderr.strip()
    assert err.startswith('ego-motion: error: ') and 'AMENT_PREFIX_PATH=unset' in err, err
    assert 'setup.bash' in err and 'Traceback' not in err, err


def test_installed_ego_motion_replays_the_default_bag(install_prefix, tmp_path, bag_copy):
    out = tmp_path / 'out'
    proc = subprocess.run([str(installed(install_prefix, 'ego-motion')), 'replay', str(bag_copy),
                           '--out', str(out), '--duration', '2', '--workers', '1'],
                          cwd=tmp_path, env=installed_env(install_prefix), capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    share = install_prefix / 'share' / PACKAGE
    assert f'replay: rig {bag_copy / "rig.yaml"}; params {share / "config" / "params.yaml"}' in proc.stdout, proc.stdout
    assert (out / 'odometry.tum').is_file() and (out / 'output' / 'metadata.yaml').is_file()
    # 2 s of the bag at 8 Hz: every frame fused
    assert len((out / 'odometry.tum').read_text().split('\n')) >= 15


# ---- the launch file, checked without `launch` ------------------------------------------

def _call_name(call):
    f = call.func
    return f.attr if isinstance(f, ast.Attribute) else getattr(f, 'id', None)


def _calls(tree, name):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and _call_name(n) == name]


def _kw(call, name):
    return next((k.value for k in call.keywords if k.arg == name), None)


def _const(node):
    return node.value if isinstance(node, ast.Constant) else None


def launch_tree(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description' for n in tree.body)
    return tree


def test_launch_file_declares_its_arguments_and_uses_only_those(install_prefix):
    tree = launch_tree(install_prefix / 'share' / PACKAGE / 'launch' / LAUNCH_FILE)
    declared = {}
    for call in _calls(tree, 'DeclareLaunchArgument'):
        declared[_const(call.args[0])] = call
        assert _const(_kw(call, 'description')), f'{_const(call.args[0])}: no description'
        assert _kw(call, 'default_value') is not None, _const(call.args[0])
    assert set(declared) == LAUNCH_ARGUMENTS
    used = {_const(c.args[0]) for c in _calls(tree, 'LaunchConfiguration')}
    assert used == LAUNCH_ARGUMENTS
    # the default rig and params: files of the package's share (FindPackageShare + config/NAME)
    defaults = {}
    for name in ('rig_file', 'params_file'):
        joined = _kw(declared[name], 'default_value')
        assert _call_name(joined) == 'PathJoinSubstitution', name
        defaults[name] = [_const(e) for e in joined.args[0].elts if _const(e)]
    assert defaults == {'rig_file': ['rig_default.yaml'], 'params_file': ['params.yaml']}
    config = next(c for c in _calls(tree, 'PathJoinSubstitution')
                  if any(_call_name(e) == 'FindPackageShare' for e in c.args[0].elts))
    assert [_const(e) for e in config.args[0].elts if _const(e)] == ['config']
    for name in ('rig_default.yaml', 'params.yaml'):
        assert (install_prefix / 'share' / PACKAGE / 'config' / name).is_file()
    assert _const(_kw(declared['use_sim_time'], 'default_value')) == 'false'
    assert _const(_kw(declared['namespace'], 'default_value')) == ''


def test_launch_file_starts_the_installed_coordinator_with_flags_it_takes(install_prefix, tmp_path):
    tree = launch_tree(install_prefix / 'share' / PACKAGE / 'launch' / LAUNCH_FILE)
    (node,) = _calls(tree, 'Node')
    constants = {t.id: _const(a.value) for a in tree.body if isinstance(a, ast.Assign)
                 for t in a.targets if isinstance(t, ast.Name)}
    package = _kw(node, 'package')
    assert (_const(package) or constants.get(getattr(package, 'id', None))) == PACKAGE
    for call in _calls(tree, 'FindPackageShare'):
        assert (_const(call.args[0]) or constants.get(getattr(call.args[0], 'id', None))) == PACKAGE
    executable = _const(_kw(node, 'executable'))
    exe = installed(install_prefix, executable)
    assert exe.is_file() and os.access(exe, os.X_OK), exe
    assert ast.unparse(_kw(node, 'namespace')) == "LaunchConfiguration('namespace')"
    assert "'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)" in \
        ast.unparse(_kw(node, 'parameters'))
    args = _kw(node, 'arguments').elts
    flags = {_const(a): ast.unparse(b) for a, b in zip(args[::2], args[1::2])}
    assert flags == {'--rig': "LaunchConfiguration('rig_file')",
                     '--params': "LaunchConfiguration('params_file')",
                     '--workers': "LaunchConfiguration('workers')"}
    # the installed coordinator takes those flags
    proc = subprocess.run([str(exe), '--help'], cwd=tmp_path, env=installed_env(install_prefix),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert all(f in proc.stdout for f in flags), proc.stdout


def test_coordinator_as_launched_runs_the_graph_under_the_namespace_on_sim_time(
        install_prefix, tmp_path, bag_copy, rclpy_context):
    """What `ros2 launch ... rig_file:=RIG workers:=1 namespace:=robot1 use_sim_time:=true`
    runs (launch_ros: the arguments, then the node name, namespace and a params file of the
    parameters): the graph comes up under /robot1, its nodes on /clock; SIGINT (launch's
    shutdown) stops it and its workers."""
    from conftest import SpinningNode
    share = install_prefix / 'share' / PACKAGE
    launch_params = tmp_path / 'launch_params.yaml'
    launch_params.write_text('/**:\n  ros__parameters:\n    use_sim_time: true\n')
    logs = tmp_path / 'logs'
    cmd = [str(installed(install_prefix, 'coordinator')),
           '--rig', str(bag_copy / 'rig.yaml'), '--params', str(share / 'config' / 'params.yaml'),
           '--workers', '1', '--log-dir', str(logs),
           '--ros-args', '-r', '__node:=ego_motion_coordinator', '-r', '__ns:=/robot1',
           '--params-file', str(launch_params)]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=installed_env(install_prefix),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    probe = SpinningNode('install_space_probe')
    try:
        node = probe.node
        graph_nodes = 4 * 5 + 1           # 4 cameras: 4 quarters and an arbiter each; general arbiter
        expected = {'/robot1/ego_motion_coordinator', '/robot1/ego_motion_worker_0', '/robot1/general_arbiter',
                    '/robot1/front/q1/quarter_node', '/robot1/front/camera_arbiter'}
        deadline = time.monotonic() + 120
        names = set()
        # node names travel on their own discovery topic, apart from the endpoints: wait for both
        while time.monotonic() < deadline and proc.poll() is None:
            names = {f'{ns.rstrip("/")}/{n}' for n, ns in node.get_node_names_and_namespaces()}
            if (expected <= names and node.count_publishers('/robot1/odom') >= 1
                    and node.count_subscribers('/clock') >= graph_nodes + 1):
                break
            time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        assert expected <= names, sorted(names)
        assert node.count_publishers('/robot1/odom') == 1 and node.count_publishers('/odom') == 0
        assert node.count_subscribers('/robot1/front/image_raw') >= 1
        assert node.count_subscribers('/front/image_raw') == 0
        # use_sim_time reached every node of the graph (and the coordinator)
        assert node.count_subscribers('/clock') >= graph_nodes + 1
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        probe.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGINT, err[-3000:]
    assert 'coordinator: interrupted by SIGINT' in err and 'worker processes' in err, err[-3000:]
    log = (logs / 'worker_0.log').read_text()
    assert 'Traceback' not in log, log[-3000:]
