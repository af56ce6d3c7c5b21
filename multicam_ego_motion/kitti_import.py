"""`ego-motion import-kitti`: a KITTI odometry sequence folder -> a camera-rig bag.

Input layout: image_l/ and, for a stereo sequence, image_r/ (rectified 8-bit PNGs, same
names), calib.txt (P0 and P1, 3x4 row-major, optionally prefixed "P0:"), poses.txt
(optional: per frame the left camera's pose in the first left camera frame, 3x4 row-major,
optical axes), times.txt (optional: capture times in s; without it frames are 0.1 s apart).

Output rig: `left` and `right` named as a stereo pair (stereo_pairs), or with --no-stereo,
--halves or a monocular sequence cameras that know of no overlap (stereo_pairs: []: the road
is then the scale source). base_link sits on the road below the left camera (KITTI's camera
height, 1.65 m: the cameras at z = 1.65, floor_z = 0, and a base_footprint frame there in
/tf_static, REP-120; floor_level false: the road climbs and tilts, so no planar-motion
constraint) with REP-103 axes (x forward = optical z), so the right camera is `baseline`
metres along -y. Ground truth is base_link in odom (odom = base_link at the first frame),
twist in base_link from central differences.
"""
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

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
    p.add_argument('folder', help='KITTI sequence folder (image_l/, image_r/ unless monocular, calib.txt, poses.txt, times.txt)')
    p.add_argument('--out', required=True, help='bag folder to create (must not exist)')
    p.add_argument('--rig-out', default=None, help='also write the rig YAML here')
    p.add_argument('--max-frames', type=int, default=None, help='import only the first N frames')
    p.add_argument('--simulated-wheel', type=int, default=None, metavar='SEED',
                   help='also write /wheel/odom simulated from the ground truth with the scenario '
                        'generator\'s slip model (KITTI odometry has no wheel or IMU data; without '
                        'a metric prior a straight drive gives the rig no scale)')
    p.add_argument('--skip', type=int, default=0, metavar='N',
                   help='start at frame N (the drive already under way; odom starts there)')
    p.add_argument('--every', type=int, default=1, metavar='N',
                   help='keep every N-th frame (2: KITTI at 5 Hz, twice the motion between frames)')
    p.add_argument('--no-stereo', action='store_true',
                   help='a stereo sequence\'s two cameras as cameras that do not know they overlap '
                        '(stereo_pairs: []): the road is the scale source')
    p.add_argument('--halves', action='store_true',
                   help='a rig whose views do not overlap: a stereo sequence\'s outer image halves '
                        '(left camera left of the principal point, right camera right of it), a '
                        'monocular one\'s left and right halves as two cameras at one centre')


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


def list_images(folder: Path, stereo: bool):
    """Image names of the sequence: (left paths, right paths or None for a monocular one)."""
    left_dir, right_dir = folder / 'image_l', folder / 'image_r'
    if not left_dir.is_dir():
        raise UserError(f'KITTI folder {folder} has no image_l/ folder')
    left = sorted(p.name for p in left_dir.glob('*.png'))
    if not left:
        raise UserError(f'{left_dir} holds no .png images')
    if not stereo:
        return [left_dir / n for n in left], None
    if not right_dir.is_dir():
        raise UserError(f'KITTI folder {folder} has no image_r/ folder')
    right = set(p.name for p in right_dir.glob('*.png'))
    missing = [n for n in left if n not in right] + sorted(right - set(left))
    if missing:
        side = 'image_r' if missing[0] in left else 'image_l'
        raise UserError(f'{folder}: {side}/{missing[0]} is missing '
                        f'({len(missing)} image(s) without a stereo partner)')
    return [left_dir / n for n in left], [right_dir / n for n in left]


def read_times(folder: Path, count: int):
    """Capture times (s from the first) from times.txt, or None without one."""
    path = folder / 'times.txt'
    if not path.is_file():
        return None
    times = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            times.append(float(line))
        except ValueError:
            raise UserError(f'times {path} line {number}: not a number') from None
    if len(times) < count:
        raise UserError(f'times {path} has {len(times)} stamps for {count} images')
    t = np.array(times[:count])
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise UserError(f'times {path}: stamps must be finite and increasing')
    return t - t[0]


def read_mono(path: Path, shape=None):
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UserError(f'cannot read image {path} (missing or not an image)')
    if shape is not None and img.shape != shape:
        raise UserError(f'image {path} is {img.shape[1]}x{img.shape[0]}, the sequence is '
                        f'{shape[1]}x{shape[0]}')
    return img


@dataclass
class KittiCamera:
    """One camera of the imported rig: which image folder, which columns of it, where."""
    name: str
    side: int                  # 0: image_l (P0), 1: image_r (P1)
    columns: Tuple[int, int]   # [first, last + 1) of the source image
    lateral_m: float           # camera centre along base_link y (the right camera: -baseline)


def rig_cameras(mono: bool, halves: bool, width: int, cx: float, baseline: float) -> List[KittiCamera]:
    """The cameras a sequence gives. --halves makes a rig whose views share no pixel: for a
    stereo sequence the outer part of each image (left camera: the columns left of the
    principal point; right camera: those 40 columns and more right of it, since a near
    point's disparity moves it left in the right image, never into the left camera's part);
    for a monocular one the image's left and right halves, two cameras at one centre."""
    if mono:
        if not halves:
            return [KittiCamera('left', 0, (0, width), 0.0)]
        return [KittiCamera('left', 0, (0, width // 2), 0.0),
                KittiCamera('right', 0, (width // 2, width), 0.0)]
    if not halves:
        return [KittiCamera('left', 0, (0, width), 0.0),
                KittiCamera('right', 1, (0, width), -baseline)]
    return [KittiCamera('left', 0, (0, int(cx) - 1), 0.0),
            KittiCamera('right', 1, (int(math.ceil(cx)) + 39, width), -baseline)]


def kitti_rig(cameras: List[KittiCamera], stereo: bool, height: float = CAMERA_HEIGHT_M) -> Rig:
    """base_link on the road below the left camera, REP-103 axes (x forward = optical z);
    stereo: the two full images named as a pair, else stereo_pairs: [] (the cameras do not
    know they overlap; the road is their scale source)."""
    R = optical_rotation(0.0)
    mounts = [CameraMount(c.name, f'/{c.name}/image_raw', f'/{c.name}/camera_info',
                          f'{c.name}_optical', np.array([0.0, c.lateral_m, height]), R)
              for c in cameras]
    pairs = (('left', 'right'),) if stereo else ()
    return Rig(cameras=mounts, floor_z=0.0, floor_level=False, stereo_pairs=pairs,
               detect_stereo=False)


def base_poses(camera_poses, T_base_left):
    """Left-camera poses in the first camera frame -> base_link poses in odom (odom =
    base_link at the first frame)."""
    T_bo = np.asarray(T_base_left, float)
    T_ob = inv_T(T_bo)
    return [T_bo @ T @ T_ob for T in camera_poses]


def body_twists(poses, times):
    """(linear, angular) velocity of each pose in its own frame, central differences over
    the capture times `times` (s)."""
    n = len(poses)
    twists = []
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        if a == b:
            twists.append((np.zeros(3), np.zeros(3)))
            continue
        span = times[b] - times[a]
        R_i = poses[i][:3, :3]
        linear = R_i.T @ (poses[b][:3, 3] - poses[a][:3, 3]) / span
        angular = R_to_rotvec(poses[a][:3, :3].T @ poses[b][:3, :3]) / span
        twists.append((linear, angular))
    return twists


def simulated_wheel(twists, times, seed):
    """Per frame (pose, linear, angular, pose variances, twist variances) of a wheel
    odometry that measured the ground-truth forward speed and yaw rate with slip."""
    wheel = WheelOdometry(np.random.default_rng(seed))
    v, w = wheel.measure(np.array([t[0][0] for t in twists]), np.array([t[1][2] for t in twists]))
    times = np.asarray(times[:len(twists)], float)
    x, y, yaw = wheel.dead_reckon(times, v, w)
    return [(make_T(rotvec_to_R([0.0, 0.0, yaw[i]]), [x[i], y[i], 0.0]), (v[i], 0.0, 0.0), (0.0, 0.0, w[i]),
             *wheel.variances(times[i], x[i], y[i], v[i], w[i])) for i in range(len(twists))]


def import_kitti(folder, out, rig_out=None, max_frames=None, progress=True, wheel_seed=None,
                 every=1, stereo=True, halves=False, skip=0):
    """`skip`: start at that frame (odom and the ground truth start there); `every`: keep every N-th frame (5 Hz from KITTI's 10 with 2); `stereo` False: the two
    cameras of a stereo sequence do not know they overlap (stereo_pairs: []); `halves`: the
    rig of non-overlapping views described in rig_cameras. A sequence without image_r/ is
    monocular."""
    folder, out = Path(folder), Path(out)
    if not folder.is_dir():
        raise UserError(f'KITTI folder not found: {folder}')
    if out.exists() and (out.is_file() or any(out.iterdir())):
        raise UserError(f'output {out} already exists (choose another --out or remove it)')
    if every < 1:
        raise UserError(f'--every must be at least 1, got {every}')
    if skip < 0:
        raise UserError(f'--skip must be at least 0, got {skip}')
    mono = not (folder / 'image_r').is_dir()
    left, right = list_images(folder, stereo=not mono)
    P0, P1, baseline = read_calibration(folder)
    camera_poses = read_poses(folder)
    times = read_times(folder, len(left))
    if times is None:
        times = np.arange(len(left)) * FRAME_PERIOD_NS * 1e-9
    if wheel_seed is not None and not camera_poses:
        raise UserError(f'--simulated-wheel needs the ground truth it is simulated from: {folder / "poses.txt"}')
    if camera_poses and len(camera_poses) != len(left):
        log.warning('%d images but %d poses: ground truth covers the first %d frames',
                    len(left), len(camera_poses), min(len(left), len(camera_poses)))
    keep = list(range(skip, len(left), every))
    if not keep:
        raise UserError(f'--skip {skip}: the sequence has {len(left)} frames')
    if max_frames is not None:
        keep = keep[:max_frames]
    sources = [left, right]
    camera_poses = [camera_poses[i] for i in keep if i < len(camera_poses)]
    if camera_poses:     # the first kept frame is the origin
        first_inv = inv_T(camera_poses[0])
        camera_poses = [first_inv @ T for T in camera_poses]
    times = times[keep] - times[keep[0]]

    first = read_mono(left[0])
    h, w = first.shape
    cams = rig_cameras(mono, halves, w, P0[0, 2], baseline)
    for c in cams:
        if not 0 <= c.columns[0] < c.columns[1] - 8 <= w - 8:
            raise UserError(f'--halves: camera {c.name} would be columns {c.columns[0]}-{c.columns[1] - 1} '
                            f'of a {w}-column image (the principal point, column {P0[0, 2]:.1f}, '
                            'must leave both halves inside the image)')
    rig = kitti_rig(cams, stereo=stereo and not mono and not halves)
    P = (P0, P1)
    intr = {c.name: CameraIntrinsics(c.columns[1] - c.columns[0], h, P[c.side][0, 0], P[c.side][1, 1],
                                     P[c.side][0, 2] - c.columns[0], P[c.side][1, 2], tx=P[c.side][0, 3])
            for c in cams}
    poses = base_poses(camera_poses, rig.cameras[0].T_base_cam)
    twists = body_twists(poses, times)
    wheel = simulated_wheel(twists, times, wheel_seed) if wheel_seed is not None and twists else []

    with RigBagWriter(out, rig, intr) as bag:
        bag.write_static_transforms(STAMP_EPOCH_NS, footprint=True)
        for k, i in enumerate(tqdm(keep, unit='frame', desc='kitti', disable=not progress)):
            stamp = STAMP_EPOCH_NS + int(round(times[k] * 1e9))
            images = {}
            for side in {c.side for c in cams}:
                images[side] = read_mono(sources[side][i], (h, w))
            bag.write_images(stamp, {c.name: images[c.side][:, c.columns[0]:c.columns[1]]
                                     for c in cams})
            if k < len(poses):
                bag.write_odometry('/ground_truth/odom', stamp, poses[k], *twists[k],
                                   GROUND_TRUTH_VAR, GROUND_TRUTH_VAR)
            if k < len(wheel):
                bag.write_odometry('/wheel/odom', stamp, *wheel[k])
    rig.save(out / 'rig.yaml')
    if rig_out:
        rig.save(rig_out)
    return {'frames': len(keep), 'poses': len(poses), 'baseline': baseline, 'size': (w, h),
            'wheel': len(wheel), 'cameras': [c.name for c in cams], 'mono': mono,
            'rate_hz': (len(keep) - 1) / float(times[-1] - times[0]) if len(keep) > 1 else 0.0}


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    if args.max_frames is not None and args.max_frames < 1:
        raise UserError(f'--max-frames must be at least 1, got {args.max_frames}')
    s = import_kitti(args.folder, args.out, args.rig_out, args.max_frames, wheel_seed=args.simulated_wheel,
                     every=args.every, stereo=not args.no_stereo, halves=args.halves, skip=args.skip)
    wheel = f', simulated wheel odometry for {s["wheel"]} frames' if s['wheel'] else ''
    kind = 'monocular' if s['mono'] else 'stereo'
    print(f'{args.out}: {s["frames"]} {kind} frames {s["size"][0]}x{s["size"][1]} at '
          f'{s["rate_hz"]:.1f} Hz as cameras {", ".join(s["cameras"])}, '
          f'baseline {s["baseline"]:.3f} m, ground truth for {s["poses"]} frames{wheel}')
    return 0
