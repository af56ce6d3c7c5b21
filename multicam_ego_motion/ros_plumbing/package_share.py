"""Where the package's shared files are: config/params.yaml, config/fastdds.xml,
config/rig_default.yaml, launch/.

* A checkout (or an editable install of one): the source tree this module is part of, which
  holds package.xml beside config/.
* An install space (`colcon build`, then `source install/setup.bash`): the package's share
  directory found through the ament index, share/multicam_ego_motion (what
  ament_index_python's get_package_share_directory says: AMENT_PREFIX_PATH).
* A `pip install .` into an environment: the data files under <sys.prefix>/share.

The checkout comes first: the code that runs reads the files that came with it, even when an
older install of the package is sourced too. Nothing found is an error that says where it
looked; never a silent fall back to the code's own defaults.
"""
import os
import sys
from pathlib import Path

from multicam_ego_motion.errors import UserError

PACKAGE = 'multicam_ego_motion'
SOURCE_ROOT = Path(__file__).resolve().parents[2]     # <checkout>/multicam_ego_motion/ros_plumbing/


def _checkout():
    if (SOURCE_ROOT / 'package.xml').is_file() and (SOURCE_ROOT / 'config').is_dir():
        return SOURCE_ROOT
    return None


def _ament_index():
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError:
        return None
    try:
        return Path(get_package_share_directory(PACKAGE))
    except (PackageNotFoundError, OSError, ValueError):   # not indexed; AMENT_PREFIX_PATH unset
        return None


def _prefix_share():
    share = Path(sys.prefix) / 'share' / PACKAGE
    return share if (share / 'package.xml').is_file() else None


def share_dir() -> Path:
    """The folder holding config/ and launch/ of this package (see the module docstring)."""
    for find in (_checkout, _ament_index, _prefix_share):
        found = find()
        if found is not None:
            return found
    raise UserError(
        f'the package\'s shared files (config/params.yaml, ...) were not found: {SOURCE_ROOT} is '
        f'not a checkout (no package.xml and config/ there), {PACKAGE} is not in the ament index '
        f'(AMENT_PREFIX_PATH={os.environ.get("AMENT_PREFIX_PATH") or "unset"}: source the install '
        f'space\'s setup.bash) and {Path(sys.prefix) / "share" / PACKAGE} does not exist')


def config_file(name: str) -> Path:
    """config/NAME of the package; an error naming the folder when it is not there."""
    path = share_dir() / 'config' / name
    if not path.is_file():
        raise UserError(f'{path} not found (the package\'s config/{name}; '
                        f'its shared files are in {path.parent.parent})')
    return path


def default_params() -> Path:
    """config/params.yaml: the nodes' parameters when the user gives no params file."""
    return config_file('params.yaml')
