"""`colcon build` of this ament_python package installs what `ros2 run` looks for.

`ros2 run multicam_ego_motion NAME` finds the package prefix through the ament index
(share/ament_index/resource_index/packages/<pkg>) and runs the executable file
<prefix>/lib/multicam_ego_motion/NAME; setup.cfg's install_scripts puts the console scripts
there. This builds a copy of the package with colcon (from pip) and checks exactly that layout
(the build: conftest.py's `install_prefix`, shared with test_install_space.py).
"""
import os
import shutil
import subprocess
import sys

import pytest

from conftest import NOT_SOURCE, PACKAGE, REPO, colcon_command, install_site_packages

ENTRY_POINTS = {
    'quarter_node': 'camera_pose_nodes.quarter_node:main',
    'camera_arbiter': 'arbiter_node.camera_arbiter_node:main',
    'general_arbiter': 'arbiter_node.general_arbiter_node:main',
    'coordinator': 'multicam_ego_motion.coordinator.coordinator_node:main',
    'worker': 'multicam_ego_motion.coordinator.worker:main_remote',
    'ego-motion': 'multicam_ego_motion.cli:main',
}


def test_colcon_finds_only_this_package(tmp_path):
    colcon = colcon_command()
    # resource/tf2_msgs holds a package.xml too: colcon must not pick it up as a second
    # package of this repository (it stops descending at the package root).
    ws = tmp_path / 'ws'
    shutil.copytree(REPO, ws / 'src' / PACKAGE, ignore=NOT_SOURCE, symlinks=True)
    proc = subprocess.run([colcon, 'list', '--names-only', '--base-paths', 'src'],
                          cwd=ws, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == [PACKAGE]


def test_package_is_in_the_ament_index(install_prefix):
    marker = install_prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / PACKAGE
    assert marker.is_file()
    assert (install_prefix / 'share' / PACKAGE / 'package.xml').is_file()


@pytest.mark.parametrize('name', sorted(ENTRY_POINTS))
def test_entry_point_installed_where_ros2_run_looks(install_prefix, name):
    exe = install_prefix / 'lib' / PACKAGE / name
    found = sorted(os.listdir(exe.parent)) if exe.parent.is_dir() else 'no such directory'
    assert exe.is_file(), f'{exe} missing; {exe.parent}: {found}'
    assert os.access(exe, os.X_OK)
    text = exe.read_text()
    assert text.startswith('#!') and 'python' in text.splitlines()[0]
    # The script dispatches to this console_scripts entry (setuptools writes either form).
    assert (f"'console_scripts', '{name}'" in text
            or ENTRY_POINTS[name].split(':')[0] in text)


def test_entry_points_target_the_right_functions(install_prefix):
    # The installed metadata is what the scripts load at run time.
    site = install_site_packages(install_prefix)
    (egg_info,) = [p for p in site.iterdir() if p.name.endswith('.egg-info')]
    lines = (egg_info / 'entry_points.txt').read_text().splitlines()
    installed = dict(
        (k.strip(), v.strip()) for k, _, v in (ln.partition('=') for ln in lines) if _)
    assert installed == ENTRY_POINTS


def test_native_kernel_built_from_source_and_installed(install_prefix):
    # The copy held no built extension (NOT_SOURCE): colcon compiled it, and the installed
    # package imports it.
    site = install_site_packages(install_prefix)
    built = sorted((site / 'camera_pose_nodes').glob('_quarter_kernels*.so'))
    assert built, f'no native kernel in {site / "camera_pose_nodes"}'
    code = ('import sys; sys.path.insert(0, sys.argv[1]); '
            'from camera_pose_nodes import kernel; '
            'print(kernel.native.__file__, kernel.selected())')
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHONPATH', 'EGO_MOTION_KERNEL')}
    proc = subprocess.run([sys.executable, '-c', code, str(site)], capture_output=True, text=True,
                          env=env, cwd=install_prefix, timeout=60)
    assert proc.returncode == 0, proc.stderr
    path, selected = proc.stdout.split()
    assert path == str(built[0]) and selected == 'native'
