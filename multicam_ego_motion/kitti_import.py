"""`ego-motion import-kitti`: a KITTI odometry sequence folder -> a two-camera rig bag.

Input layout: image_l/ and image_r/ (rectified 8-bit PNGs, same names), calib.txt (P0 and
P1, 3x4 row-major, optionally prefixed "P0:"), poses.txt (optional: per frame the left
camera's pose in the first left camera frame, 3x4 row-major, optical axes).

Output rig: `left` and `right`, named as a stereo pair (stereo_pairs); base_link sits on the
road below the left camera (KITTI's camera height, 1.65 m: the cameras at z = 1.65, floor_z
= 0; floor_level false: the road climbs and tilts, so no planar-motion constraint) with REP-103 axes (x forward = optical z), so the right camera is `baseline` metres
along -y. Ground truth is base_link in odom (odom = base_link at the first frame), twist in
base_link from central differences. Frames are 0.1 s apart (KITTI is 10 Hz).
"""
import logging
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from multicam_ego_motion.bag.rig_bag_writer import STAMP_EPOCH_NS, RigBagWriter
from multicam_ego_motion.geometry.camera_intrinsics import CameraIntrinsics
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import CameraMount, Rig, optical_rotation
from multicam_ego_motion.scenarios.wheel_odometry import WheelOdometry
from multicam_ego_motion.geometry.se3 import R_to_rotvec, inv_T, make_T, rotvec_to_R

log = logging.getLogger(__name__)

FRAME_PERIOD_NS = 100_000_000
CAMERA_HEIGHT_M = 1.65     # KITTI's cameras above the road (the Velodyne setup's paper)
GROUND_TRUTH_VAR = (1e-4,) * 6


def configure_parser(p):
    p.add_argument('folder', help='KITTI sequence folder (image_l/, image_r/, calib.txt, poses.txt)')
    p.add_argument('--out', required=True, help='bag folder to create (must not exist)')
    p.add_argument('--rig-out', default=None, help='also write the rig YAML here')
    p.add_argument('--max-frames', type=int, default=None, help='import only the first N frames')
    p.add_argument('--simulated-wheel', type=int, default=None, metavar='SEED',
                   help='also write /wheel/odom simulated from the ground truth with the scenario '
                        'generator\'s slip model (KITTI odometry has no wheel or IMU data; without '
                        'a metric prior a straight drive gives the rig no scale)')


def read_matrix_lines(path: Path, what: str):
    """Rows of 12 floats, one per non-empty line (an optional 'NAME:' prefix is dropped)."""
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.split(':', 1)[1] if ':' in line else line
        if not text.strip():
            continue
        try:
            values = [float(v) for v in text.split()]
        except ValueError:
            raise UserError(f'{what} {path} line {number}: not a list of numbers') from None
        if len(values) != 12 or not np.all(np.isfinite(values)):
            raise UserError(f'{what} {path} line {number}: expected 12 finite numbers '
                            f'(a 3x4 matrix), got {len(values)}')
        rows.append(np.array(values).reshape(3, 4))
    return rows


def read_calibration(folder: Path):
    path = folder / 'calib.txt'
    if not path.is_file():
        raise UserError(f'KITTI folder {folder} has no calib.txt')
    rows = read_matrix_lines(path, 'calibration')
    if len(rows) < 2:
        raise UserError(f'calibration {path} needs P0 and P1 (two 3x4 matrices), found {len(rows)}')
    P0, P1 = rows[0], rows[1]
    fx = P0[0, 0]
    if not fx > 0 or not P0[1, 1] > 0:
        raise UserError(f'calibration {path}: P0 has no positive focal length')
    baseline = (P0[0, 3] - P1[0, 3]) / fx
    if not 0.01 < baseline < 10.0:
        raise UserError(f'calibration {path}: stereo baseline {baseline:.3f} m from P0/P1 '
                        'is not plausible (expected the right camera to the right of the left)')
    return P0, P1, baseline


def read_poses(folder: Path):
    path = folder / 'poses.txt'
    if not path.is_file():
        log.warning('%s has no poses.txt: the bag gets no /ground_truth/odom', folder)
        return []
    poses = []
    for i, P in enumerate(read_matrix_lines(path, 'poses')):
        R = P[:, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
            raise UserError(f'poses {path} entry {i + 1}: the rotation part is not a rotation')
        T = np.eye(4)
        T[:3, :] = P
        poses.append(T)
    return poses


def list_images(folder: Path):
    left_dir, right_dir = folder / 'image_l', folder / 'image_r'
    for d in (left_dir, right_dir):
        if not d.is_dir():
            raise UserError(f'KITTI folder {folder} has no {d.name}/ folder')
    left = sorted(p.name for p in left_dir.glob('*.png'))
    right = set(p.name for p in right_dir.glob('*.png'))
    if not left:
        raise UserError(f'{left_dir} holds no .png images')
    missing = [n for n in left if n not in right] + sorted(right - set(left))
    if missing:
        side = 'image_r' if missing[0] in left else 'image_l'
        raise UserError(f'{folder}: {side}/{missing[0]} is missing '
                        f'({len(missing)} image(s) without a stereo partner)')
    return [(left_dir / n, right_dir / n) for n in left]


def read_mono(path: Path, shape=None):
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UserError(f'cannot read image {path} (missing or not an image)')
    if shape is not None and img.shape != shape:
        raise UserError(f'image {path} is {img.shape[1]}x{img.shape[0]}, the sequence is '
                        f'{shape[1]}x{shape[0]}')
    return img


def stereo_rig(baseline: float, height: float = CAMERA_HEIGHT_M) -> Rig:
    R = optical_rotation(0.0)
    return Rig(cameras=[
        CameraMount('left', '/left/image_raw', '/left/camera_info', 'left_optical',
                    np.array([0.0, 0.0, height]), R),
        CameraMount('right', '/right/image_raw', '/right/camera_info', 'right_optical',
                    np.array([0.0, -baseline, height]), R)],
        floor_z=0.0, floor_level=False, stereo_pairs=(('left', 'right'),))


def base_poses(camera_poses, T_base_left):
    """Left-camera poses in the first camera frame -> base_link poses in odom (odom =
    base_link at the first frame)."""
    T_bo = np.asarray(T_base_left, float)
    T_ob = inv_T(T_bo)
    return [T_bo @ T @ T_ob for T in camera_poses]


def body_twists(poses, dt):
    """(linear, angular) velocity of each pose in its own frame, central differences."""
    n = len(poses)
    twists = []
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        if a == b:
            twists.append((np.zeros(3), np.zeros(3)))
            continue
        span = (b - a) * dt
        R_i = poses[i][:3, :3]
        linear = R_i.T @ (poses[b][:3, 3] - poses[a][:3, 3]) / span
        angular = R_to_rotvec(poses[a][:3, :3].T @ poses[b][:3, :3]) / span
        twists.append((linear, angular))
    return twists


def simulated_wheel(twists, seed):
    """Per frame (pose, linear, angular, pose variances, twist variances) of a wheel
    odometry that measured the ground-truth forward speed and yaw rate with slip."""
    wheel = WheelOdometry(np.random.default_rng(seed))
    v, w = wheel.measure(np.array([t[0][0] for t in twists]), np.array([t[1][2] for t in twists]))
    times = np.arange(len(twists)) * FRAME_PERIOD_NS * 1e-9
    x, y, yaw = wheel.dead_reckon(times, v, w)
    return [(make_T(rotvec_to_R([0.0, 0.0, yaw[i]]), [x[i], y[i], 0.0]), (v[i], 0.0, 0.0), (0.0, 0.0, w[i]),
             *wheel.variances(times[i], x[i], y[i], v[i], w[i])) for i in range(len(twists))]


def import_kitti(folder, out, rig_out=None, max_frames=None, progress=True, wheel_seed=None):
    folder, out = Path(folder), Path(out)
    if not folder.is_dir():
        raise UserError(f'KITTI folder not found: {folder}')
    if out.exists() and (out.is_file() or any(out.iterdir())):
        raise UserError(f'output {out} already exists (choose another --out or remove it)')
    pairs = list_images(folder)
    P0, P1, baseline = read_calibration(folder)
    camera_poses = read_poses(folder)
    if wheel_seed is not None and not camera_poses:
        raise UserError(f'--simulated-wheel needs the ground truth it is simulated from: {folder / "poses.txt"}')
    if max_frames is not None:
        pairs = pairs[:max_frames]
    if camera_poses and len(camera_poses) != len(pairs):
        log.warning('%d image pairs but %d poses: ground truth covers the first %d frames',
                    len(pairs), len(camera_poses), min(len(pairs), len(camera_poses)))
    camera_poses = camera_poses[:len(pairs)]

    rig = stereo_rig(baseline)
    first = read_mono(pairs[0][0])
    h, w = first.shape
    intr = {'left': CameraIntrinsics(w, h, P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2], tx=P0[0, 3]),
            'right': CameraIntrinsics(w, h, P1[0, 0], P1[1, 1], P1[0, 2], P1[1, 2], tx=P1[0, 3])}
    poses = base_poses(camera_poses, rig.cameras[0].T_base_cam)
    twists = body_twists(poses, FRAME_PERIOD_NS * 1e-9)
    wheel = simulated_wheel(twists, wheel_seed) if wheel_seed is not None and twists else []

    with RigBagWriter(out, rig, intr) as bag:
        bag.write_static_transforms(STAMP_EPOCH_NS)
        for i, (left, right) in enumerate(tqdm(pairs, unit='frame', desc='kitti',
                                               disable=not progress)):
            stamp = STAMP_EPOCH_NS + i * FRAME_PERIOD_NS
            bag.write_images(stamp, {'left': read_mono(left, (h, w)),
                                     'right': read_mono(right, (h, w))})
            if i < len(poses):
                bag.write_odometry('/ground_truth/odom', stamp, poses[i], *twists[i],
                                   GROUND_TRUTH_VAR, GROUND_TRUTH_VAR)
            if i < len(wheel):
                bag.write_odometry('/wheel/odom', stamp, *wheel[i])
    rig.save(out / 'rig.yaml')
    if rig_out:
        rig.save(rig_out)
    return {'frames': len(pairs), 'poses': len(poses), 'baseline': baseline, 'size': (w, h),
            'wheel': len(wheel)}


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f'--max-frames must be at least 1, got {args.max_frames}')
    s = import_kitti(args.folder, args.out, args.rig_out, args.max_frames, wheel_seed=args.simulated_wheel)
    wheel = f', simulated wheel odometry for {s["wheel"]} frames' if s['wheel'] else ''
    print(f'{args.out}: {s["frames"]} stereo frames {s["size"][0]}x{s["size"][1]} at 10 Hz, '
          f'baseline {s["baseline"]:.3f} m, ground truth for {s["poses"]} frames{wheel}')
    return 0
