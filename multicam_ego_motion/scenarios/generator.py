"""`ego-motion generate`: render a scenario into a rosbag2 (MCAP) bag plus its rig file.

The rig file is always written into the bag folder (`<bag>/rig.yaml`, so a bag describes
itself), and also to `--rig-out` when given. Output is deterministic for a seed.
"""
import logging
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from multicam_ego_motion.bag.rig_bag_writer import STAMP_EPOCH_NS, RigBagWriter
from multicam_ego_motion.geometry.camera_intrinsics import CameraIntrinsics
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import MAX_CAMERAS, CameraMount, Rig, optical_rotation, paper_rig
from multicam_ego_motion.scenarios.photometry import LightingEffects
from multicam_ego_motion.scenarios.renderer import CameraRenderer
from multicam_ego_motion.scenarios.scene import CAMERA_HEIGHT, scene_for
from multicam_ego_motion.scenarios.texture_atlas import TextureAtlas
from multicam_ego_motion.scenarios.trajectories import SCENARIOS
from multicam_ego_motion.scenarios.wheel_odometry import WheelOdometry

GROUND_TRUTH_POSE_VAR = (1e-6,) * 6
GROUND_TRUTH_TWIST_VAR = (1e-6,) * 6


def configure_parser(p):
    p.add_argument('--scenario', required=True, help=f'one of: {", ".join(SCENARIOS)}')
    p.add_argument('--out', required=True, help='bag folder to create (must not exist)')
    p.add_argument('--seed', type=int, default=0, help='textures, noise and wheel slip')
    p.add_argument('--duration', type=float, default=30.0, help='seconds (default 30)')
    p.add_argument('--rate', type=float, default=30.0, help='frames per second (default 30)')
    p.add_argument('--width', type=int, default=640)
    p.add_argument('--height', type=int, default=480)
    p.add_argument('--fx', type=float, default=None,
                   help='focal length in pixels, fx = fy (default 400 * width / 640)')
    p.add_argument('--k1', type=float, default=0.0, help='radial distortion (plumb_bob k1)')
    p.add_argument('--cameras', type=int, default=4,
                   help='1..8 level cameras, evenly spaced headings; 4 = the paper rig')
    p.add_argument('--rig', choices=('ring', 'stereo'), default='ring',
                   help='ring: --cameras level cameras at evenly spaced headings (default); '
                        'stereo: a forward-looking stereo pair left/right, named in stereo_pairs')
    p.add_argument('--baseline', type=float, default=0.3,
                   help='--rig stereo: distance between the two cameras (m, default 0.3)')
    p.add_argument('--rig-out', default=None, help='also write the rig YAML here')
    p.add_argument('--compression', choices=('zstd', 'lz4', 'none'), default='zstd')


def evenly_spaced_rig(n: int, radius: float = 0.25) -> Rig:
    """The paper's rig for 4 cameras; otherwise cam0..camN-1 looking at yaw 2 pi k / n."""
    if not 1 <= n <= MAX_CAMERAS:
        raise UserError(f'--cameras must be 1 to {MAX_CAMERAS}, got {n}')
    if n == 4:
        return paper_rig(radius=radius, height=CAMERA_HEIGHT)
    cams = []
    for k in range(n):
        yaw = 2 * np.pi * k / n
        name = f'cam{k}'
        cams.append(CameraMount(name, f'/{name}/image_raw', f'/{name}/camera_info',
                                f'{name}_optical',
                                np.array([radius * np.cos(yaw), radius * np.sin(yaw), CAMERA_HEIGHT]),
                                optical_rotation(yaw)))
    return Rig(cameras=cams, floor_z=0.0)     # the renderer's floor is base_link's z = 0


def stereo_pair_rig(baseline: float) -> Rig:
    """Two level cameras looking forward, `baseline` apart (left at +y), base_link midway
    between them on the floor; named as a stereo pair."""
    if not 0.01 <= baseline <= 5.0:
        raise UserError(f'--baseline must be within 0.01..5 m, got {baseline}')
    cams = [CameraMount(name, f'/{name}/image_raw', f'/{name}/camera_info', f'{name}_optical',
                        np.array([0.0, y, CAMERA_HEIGHT]), optical_rotation(0.0))
            for name, y in (('left', 0.5 * baseline), ('right', -0.5 * baseline))]
    return Rig(cameras=cams, floor_z=0.0, stereo_pairs=(('left', 'right'),))


def check_output_free(path: Path):
    if path.exists() and (path.is_file() or any(path.iterdir())):
        raise UserError(f'output {path} already exists (choose another --out or remove it)')


def validate(args):
    if args.scenario not in SCENARIOS:
        raise UserError(f'unknown scenario {args.scenario!r} (choose one of: {", ".join(SCENARIOS)})')
    if not 0.5 <= args.duration <= 600:
        raise UserError(f'--duration must be between 0.5 and 600 s, got {args.duration}')
    if not 1 <= args.rate <= 120:
        raise UserError(f'--rate must be between 1 and 120 Hz, got {args.rate}')
    if not (16 <= args.width <= 4096 and 16 <= args.height <= 4096):
        raise UserError(f'image size {args.width}x{args.height} must be within 16..4096')
    if args.fx is not None and not args.fx > 0:
        raise UserError(f'--fx must be positive, got {args.fx}')
    if not -0.5 <= args.k1 <= 0.5:
        raise UserError(f'--k1 must be within -0.5..0.5, got {args.k1}')


def pose_matrix(x, y, yaw):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('z', yaw).as_matrix()
    T[:2, 3] = (x, y)
    return T


def generate(scenario, out, seed=0, duration=30.0, rate=30.0, width=640, height=480, fx=None,
             k1=0.0, cameras=4, rig_out=None, compression='zstd', progress=True,
             rig_kind='ring', baseline=0.3):
    """Render the bag; returns a summary dict (frames, seconds, bag size)."""
    out = Path(out)
    check_output_free(out)
    if rig_kind not in ('ring', 'stereo'):
        raise UserError(f'unknown rig {rig_kind!r} (ring or stereo)')
    rig = stereo_pair_rig(baseline) if rig_kind == 'stereo' else evenly_spaced_rig(cameras)
    intr = CameraIntrinsics.default(width, height, k1)
    if fx is not None:
        intr = CameraIntrinsics(width, height, fx, fx, intr.cx, intr.cy, intr.distortion)
    texture_seed, noise_seed, wheel_seed = np.random.SeedSequence(seed).spawn(3)

    trajectory = SCENARIOS[scenario](duration)
    n_frames = int(round(duration * rate)) + 1     # both ends: a closed loop ends at its start
    times = np.arange(n_frames) / rate
    x, y, yaw, speed, yaw_rate = trajectory.sample(times)
    T_world_start_inv = np.linalg.inv(pose_matrix(*trajectory.start_pose()))
    wheel = WheelOdometry(np.random.default_rng(wheel_seed))
    wheel_v, wheel_w = wheel.measure(speed, yaw_rate)
    wx, wy, wyaw = wheel.dead_reckon(times, wheel_v, wheel_w)
    stamps = STAMP_EPOCH_NS + np.round(times * 1e9).astype(np.int64)

    scene = scene_for(scenario)
    atlas = TextureAtlas(scene, np.random.default_rng(texture_seed))
    renderers = [CameraRenderer(scene, atlas, intr, cam) for cam in rig.cameras]
    effects = (LightingEffects(np.random.default_rng(noise_seed), intr.fx)
               if scenario == 'lighting' else None)

    started = time.perf_counter()
    with RigBagWriter(out, rig, {c.name: intr for c in rig.cameras}, compression) as bag:
        bag.write_static_transforms(int(stamps[0]))
        for i in tqdm(range(n_frames), unit='frame', desc=f'{scenario}', disable=not progress):
            images = {}
            for k, (cam, r) in enumerate(zip(rig.cameras, renderers)):
                img = r.render(x[i], y[i], yaw[i])
                if effects is not None:
                    img = effects.apply(img, times[i], k, yaw_rate[i])
                images[cam.name] = img
            stamp = int(stamps[i])
            bag.write_images(stamp, images)
            bag.write_odometry('/ground_truth/odom', stamp,
                               T_world_start_inv @ pose_matrix(x[i], y[i], yaw[i]),
                               (speed[i], 0.0, 0.0), (0.0, 0.0, yaw_rate[i]),
                               GROUND_TRUTH_POSE_VAR, GROUND_TRUTH_TWIST_VAR)
            bag.write_odometry('/wheel/odom', stamp, pose_matrix(wx[i], wy[i], wyaw[i]),
                               (wheel_v[i], 0.0, 0.0), (0.0, 0.0, wheel_w[i]),
                               *wheel.variances(times[i], wx[i], wy[i], wheel_v[i], wheel_w[i]))
    elapsed = time.perf_counter() - started
    rig.save(out / 'rig.yaml')
    if rig_out:
        rig.save(rig_out)
    size = sum(f.stat().st_size for f in out.iterdir())
    return {'frames': n_frames, 'seconds': elapsed, 'fps': n_frames / elapsed, 'bytes': size,
            'path_length': trajectory.path_length, 'cameras': rig.names}


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    validate(args)
    summary = generate(args.scenario, args.out, args.seed, args.duration, args.rate, args.width,
                       args.height, args.fx, args.k1, args.cameras, args.rig_out,
                       args.compression, rig_kind=args.rig, baseline=args.baseline)
    print(f'{args.out}: {summary["frames"]} frames x {len(summary["cameras"])} cameras '
          f'({", ".join(summary["cameras"])}), path {summary["path_length"]:.1f} m, '
          f'rendered and written in {summary["seconds"]:.1f} s ({summary["fps"]:.1f} frames/s), '
          f'{summary["bytes"] / 1e6:.1f} MB')
    return 0
