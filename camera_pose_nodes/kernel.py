"""Which implementation runs the per-quarter estimator's numeric core.

PoseEKF and LandmarkMap have two: the numpy/filterpy code in their modules (the reference,
always there) and the native kernel camera_pose_nodes._quarter_kernels (C++/Eigen, built with
the package), which does each step (predict, update, epipolar update, realignment,
triangulation with its checks) in one call instead of thousands of small numpy ones. Both
keep the same filter and map state, so a state handed over from one runs on the other.

The native kernel is used when it is built, the numpy one otherwise; the environment variable
EGO_MOTION_KERNEL=numpy|native forces one (read when a PoseEKF or LandmarkMap is made);
EGO_MOTION_KERNEL=numpy also puts the general arbiter's rig-motion refinement
(arbiter_node/rig_motion_fit, its own native kernel) on its numpy path.
"""
import os

from multicam_ego_motion.errors import UserError

ENV = 'EGO_MOTION_KERNEL'
KERNELS = ('native', 'numpy')
BUILD_HINT = ('build it with `pip install -e .` (or `python setup.py build_ext --inplace` in '
              'the source tree; needs pybind11 and cmeel-eigen from requirements.txt)')

try:
    from camera_pose_nodes import _quarter_kernels as native
    _IMPORT_ERROR = None
except ImportError as exc:          # not built (or built for another Python)
    native = None
    _IMPORT_ERROR = exc


def native_available() -> bool:
    """Whether the native kernel is built and imports."""
    return native is not None


def selected() -> str:
    """The kernel in use: 'native' or 'numpy' (EGO_MOTION_KERNEL, else native when built)."""
    want = os.environ.get(ENV, '').strip().lower()
    if not want:
        return 'native' if native is not None else 'numpy'
    if want not in KERNELS:
        raise UserError(f'{ENV}={want!r}: expected one of {", ".join(KERNELS)}')
    if want == 'native' and native is None:
        raise UserError(f'{ENV}=native but the native kernel camera_pose_nodes._quarter_kernels '
                        f'does not import ({_IMPORT_ERROR}); {BUILD_HINT}')
    return want


def use_native() -> bool:
    return selected() == 'native'
