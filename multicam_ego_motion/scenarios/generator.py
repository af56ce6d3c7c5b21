"""`ego-motion generate`: render a scenario into a rosbag2 (MCAP) bag plus its rig file.

The rig file is always written into the bag folder (`<bag>/rig.yaml`, so a bag describes
itself), and also to `--rig-out` when given. Output is deterministic for a seed.
"""
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from multicam_ego_motion.bag.rig_bag_writer import IMAGE_CODECS, STAMP_EPOCH_NS, RigBagWriter
from multicam_ego_motion.geometry.camera_intrinsics import CameraIntrinsics
from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import (MAX_CAMERAS, CameraMount, ImuMount, Rig, optical_rotation,
                                             paper_rig)
from multicam_ego_motion.scenarios.imu import (IMU_FAULTS, IMU_FRAME, IMU_ROTATION, IMU_TRANSLATION, ImuNoise,
                                              publish, simulate_imu)
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
    p.add_argument('--compressed', choices=IMAGE_CODECS, default=None,
                   help='write the images as a robot\'s image_transport "compressed" stream: '
                        'sensor_msgs/CompressedImage on /<cam>/image_raw/compressed, JPEG or PNG '
                        '(default: raw mono8 Image on /<cam>/image_raw)')
    p.add_argument('--jpeg-quality', type=int, default=90, help='--compressed jpeg: quality 1..100 (default 90)')
    p.add_argument('--camera-offsets-ms', default=None, metavar='MS,MS,...',
                   help='free-running cameras: each camera\'s capture time after the frame '
                        'clock, one value per camera in rig order (e.g. 0,8,16,24); each image '
                        'is rendered at and stamped with its own capture instant')
    p.add_argument('--camera-phases', choices=('random',), default=None,
                   help='random: free-running cameras, each with a random capture phase in [0, '
                        'its frame period), drawn from --seed (instead of --camera-offsets-ms)')
    p.add_argument('--imu-rate', type=float, default=0.0, metavar='HZ',
                   help='also write an IMU on /imu/data at this rate (200 for a robot\'s MEMS '
                        'IMU: white noise, turn-on bias and bias random walk, its frame imu_link '
                        'off base_link in /tf_static); default 0: none')
    p.add_argument('--imu-fault', choices=IMU_FAULTS, default=None,
                   help='with --imu-rate: a bad IMU from --imu-fault-at on: its samples in '
                        'base_link instead of imu_link (wrong_frame), its gyro clipped at 0.5 rad/s '
                        '(saturated), repeating one sample (stuck), no samples (silent), stamps '
                        'jittered by 1.5 periods either way (out_of_order, seeded), a gyro bias '
                        'running away at 0.02 rad/s per second (bias_drift); the rest of the bag '
                        'is the one without the fault')
    p.add_argument('--imu-fault-at', type=float, default=0.0, metavar='S',
                   help='--imu-fault: from this many seconds after the start (default 0)')
    p.add_argument('--camera-rates', default=None, metavar='HZ,HZ,...',
                   help='per-camera frame rates, one value per camera in rig order (e.g. '
                        '30,30,15,15; default: --rate for every camera); the wheel stays at --rate')


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
    if not 1 <= getattr(args, 'jpeg_quality', 90) <= 100:
        raise UserError(f'--jpeg-quality must be within 1..100, got {args.jpeg_quality}')
    # (callers such as a regression suite's generate spec may leave the rig options out)
    n = rig_camera_count(args)
    if getattr(args, 'camera_phases', None) and getattr(args, 'camera_offsets_ms', None) is not None:
        raise UserError('--camera-phases and --camera-offsets-ms exclude each other')
    camera_timing(n, args.rate,
                  parse_camera_list(getattr(args, 'camera_offsets_ms', None), n, '--camera-offsets-ms'),
                  parse_camera_list(getattr(args, 'camera_rates', None), n, '--camera-rates'))


def rig_camera_count(args) -> int:
    """Cameras of the rig the options make (a stereo pair is two, whatever --cameras says)."""
    return 2 if getattr(args, 'rig', 'ring') == 'stereo' else args.cameras


def parse_camera_list(text, cameras: int, option: str):
    """'0,8,16,24' -> [0.0, 8.0, 16.0, 24.0] (None: not given); camera_timing checks the count."""
    if text is None:
        return None
    try:
        values = [float(v) for v in str(text).split(',')]
    except ValueError:
        raise UserError(f'{option} must be comma-separated numbers, got {text!r}') from None
    if not all(np.isfinite(values)):
        raise UserError(f'{option} must be finite numbers, got {text!r}')
    return values


def camera_timing(cameras: int, rate: float, offsets_ms=None, rates=None):
    """(offsets s, rates Hz) per camera, checked: a per-camera rate within 1..120 Hz (the
    frame rate itself is checked by the CLI; the library renders sparse stills too), an
    offset within [0, its camera's frame period)."""
    for option, values in (('--camera-offsets-ms', offsets_ms), ('--camera-rates', rates)):
        if values is not None and len(values) != cameras:
            raise UserError(f'{option} has {len(values)} value(s) but the rig has {cameras} cameras '
                            '(one value per camera, in rig order)')
    given = rates is not None
    rates = [float(rate)] * cameras if rates is None else [float(r) for r in rates]
    offsets_ms = [0.0] * cameras if offsets_ms is None else [float(o) for o in offsets_ms]
    for k, r in enumerate(rates):
        if given and not 1 <= r <= 120:
            raise UserError(f'--camera-rates: camera {k} rate must be between 1 and 120 Hz, got {r:g}')
    for k, (o, r) in enumerate(zip(offsets_ms, rates)):
        if not 0 <= o < 1000.0 / r:
            raise UserError(f'--camera-offsets-ms: camera {k} offset must be within 0 and its '
                            f'frame period ({1000.0 / r:g} ms at {r:g} Hz), got {o:g} ms')
    return [o * 1e-3 for o in offsets_ms], rates


def random_phases_ms(seed: int, rates) -> list:
    """One capture phase per camera, uniform in [0, its frame period), whole microseconds;
    deterministic for the seed (its own stream: textures and noise stay as without it)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED_FA5E]))
    return [float(np.floor(rng.uniform(0.0, 1000.0 / r) * 1000.0) / 1000.0) for r in rates]


def pose_matrix(x, y, yaw):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('z', yaw).as_matrix()
    T[:2, 3] = (x, y)
    return T


def generate(scenario, out, seed=0, duration=30.0, rate=30.0, width=640, height=480, fx=None,
             k1=0.0, cameras=4, rig_out=None, compression='zstd', progress=True,
             rig_kind='ring', baseline=0.3, camera_offsets_ms=None, camera_rates=None,
             image_codec=None, jpeg_quality=90, camera_phases=None, imu_rate=0.0,
             imu_fault=None, imu_fault_at=0.0):
    """Render the bag; returns a summary dict (frames, seconds, bag size).

    camera_offsets_ms / camera_rates (one per camera): free-running cameras, each captured
    at offset + n / rate; ground truth is written at every capture instant (and at the
    wheel's), the wheel at `rate` as for a synchronised rig. image_codec ('jpeg', 'png'):
    the cameras' images as CompressedImage (transport `compressed` in the rig). imu_rate
    (Hz, > 0): an IMU on /imu/data (scenarios/imu.py), its own noise stream: the images and
    the wheel are the same as without it. imu_fault (scenarios/imu.IMU_FAULTS): that IMU
    goes bad from imu_fault_at (s) on, its own seeded stream; everything else as without it."""
    out = Path(out)
    check_output_free(out)
    if rig_kind not in ('ring', 'stereo'):
        raise UserError(f'unknown rig {rig_kind!r} (ring or stereo)')
    rig = stereo_pair_rig(baseline) if rig_kind == 'stereo' else evenly_spaced_rig(cameras)
    if image_codec is not None:
        rig = replace(rig, cameras=[replace(c, transport='compressed') for c in rig.cameras])
    intr = CameraIntrinsics.default(width, height, k1)
    if fx is not None:
        intr = CameraIntrinsics(width, height, fx, fx, intr.cx, intr.cy, intr.distortion)
    # (a child per stream: a fifth one leaves the first four as they were)
    texture_seed, noise_seed, wheel_seed, imu_seed, imu_fault_seed = np.random.SeedSequence(seed).spawn(5)
    if imu_rate < 0 or not np.isfinite(imu_rate):
        raise UserError(f'--imu-rate must be >= 0 Hz, got {imu_rate}')
    if imu_fault is not None and imu_fault not in IMU_FAULTS:
        raise UserError(f'unknown --imu-fault {imu_fault!r} (one of: {", ".join(IMU_FAULTS)})')
    if imu_fault is not None and not imu_rate > 0:
        raise UserError('--imu-fault needs an IMU: give --imu-rate too')
    if not (np.isfinite(imu_fault_at) and imu_fault_at >= 0):
        raise UserError(f'--imu-fault-at must be >= 0 s, got {imu_fault_at}')

    if camera_phases not in (None, 'random'):
        raise UserError(f'unknown camera phases {camera_phases!r} (random)')
    if camera_phases and camera_offsets_ms is not None:
        raise UserError('--camera-phases and --camera-offsets-ms exclude each other')
    if camera_phases == 'random':
        _, cam_rates = camera_timing(len(rig.cameras), rate, None, camera_rates)
        camera_offsets_ms = random_phases_ms(seed, cam_rates)
    offsets, rates = camera_timing(len(rig.cameras), rate, camera_offsets_ms, camera_rates)
    trajectory = SCENARIOS[scenario](duration)
    n_frames = int(round(duration * rate)) + 1     # both ends: a closed loop ends at its start
    times = np.arange(n_frames) / rate
    wheel_stamps = STAMP_EPOCH_NS + np.round(times * 1e9).astype(np.int64)
    # Capture instants per camera (a synchronised rig: every camera at the wheel's times).
    captures = {}
    for cam, offset, r in zip(rig.cameras, offsets, rates):
        # (as many frames as a synchronised camera: the last frame has every camera, a little
        # after the end for a late one, where the trajectory holds its end pose)
        t_cam = offset + np.arange(int(round(duration * r)) + 1) / r
        for t, stamp in zip(t_cam, STAMP_EPOCH_NS + np.round(t_cam * 1e9).astype(np.int64)):
            captures.setdefault(int(stamp), (t, []))[1].append(cam.name)
    for t, stamp in zip(times, wheel_stamps):
        captures.setdefault(int(stamp), (t, []))
    stamps = sorted(captures)
    event_times = np.array([captures[s][0] for s in stamps])
    x, y, yaw, speed, yaw_rate = trajectory.sample(event_times)
    _, _, _, wheel_speed, wheel_yaw_rate = trajectory.sample(times)
    T_world_start_inv = np.linalg.inv(pose_matrix(*trajectory.start_pose()))
    wheel = WheelOdometry(np.random.default_rng(wheel_seed))
    wheel_v, wheel_w = wheel.measure(wheel_speed, wheel_yaw_rate)
    wx, wy, wyaw = wheel.dead_reckon(times, wheel_v, wheel_w)
    wheel_index = {int(s): i for i, s in enumerate(wheel_stamps)}
    imu = simulate_imu(trajectory, imu_rate, np.random.default_rng(imu_seed)) if imu_rate > 0 else None
    if imu is not None:
        rig = replace(rig, imu=ImuMount(IMU_FRAME, np.array(IMU_TRANSLATION), IMU_ROTATION))
    published = (publish(imu, imu_fault, imu_fault_at, np.random.default_rng(imu_fault_seed))
                 if imu is not None else None)

    def to_ns(seconds):
        return STAMP_EPOCH_NS + np.round(seconds * 1e9).astype(np.int64)

    imu_log_ns = to_ns(published.log_times) if imu is not None else []
    imu_stamps = to_ns(published.stamps) if imu is not None else []
    imu_variances = ImuNoise().sample_variances(imu_rate) if imu is not None else None
    imu_next = 0

    def write_imu_until(bag, stamp):
        # in log-time order with the frames: every sample up to and including `stamp`
        nonlocal imu_next
        while imu_next < len(imu_log_ns) and imu_log_ns[imu_next] <= stamp:
            bag.write_imu(rig.imu.topic, int(imu_log_ns[imu_next]), published.frame_ids[imu_next],
                          published.gyro[imu_next], published.accel[imu_next], *imu_variances,
                          stamp_ns=int(imu_stamps[imu_next]))
            imu_next += 1

    scene = scene_for(scenario)
    atlas = TextureAtlas(scene, np.random.default_rng(texture_seed))
    renderers = {cam.name: CameraRenderer(scene, atlas, intr, cam) for cam in rig.cameras}
    effects = (LightingEffects(np.random.default_rng(noise_seed), intr.fx)
               if scenario == 'lighting' else None)

    started = time.perf_counter()
    images_written = 0
    with RigBagWriter(out, rig, {c.name: intr for c in rig.cameras}, compression,
                      image_codec or 'jpeg', jpeg_quality) as bag:
        bag.write_static_transforms(int(stamps[0]))
        for i in tqdm(range(len(stamps)), unit='frame', desc=f'{scenario}', disable=not progress):
            stamp = int(stamps[i])
            write_imu_until(bag, stamp)
            images = {}
            for k, cam in enumerate(rig.cameras):
                if cam.name not in captures[stamp][1]:
                    continue
                img = renderers[cam.name].render(x[i], y[i], yaw[i])
                if effects is not None:
                    img = effects.apply(img, event_times[i], k, yaw_rate[i])
                images[cam.name] = img
            if images:
                bag.write_images(stamp, images)
                images_written += len(images)
            bag.write_odometry('/ground_truth/odom', stamp,
                               T_world_start_inv @ pose_matrix(x[i], y[i], yaw[i]),
                               (speed[i], 0.0, 0.0), (0.0, 0.0, yaw_rate[i]),
                               GROUND_TRUTH_POSE_VAR, GROUND_TRUTH_TWIST_VAR)
            j = wheel_index.get(stamp)
            if j is not None:
                bag.write_odometry('/wheel/odom', stamp, pose_matrix(wx[j], wy[j], wyaw[j]),
                                   (wheel_v[j], 0.0, 0.0), (0.0, 0.0, wheel_w[j]),
                                   *wheel.variances(times[j], wx[j], wy[j], wheel_v[j], wheel_w[j]))
        if imu is not None and len(imu_log_ns):
            write_imu_until(bag, int(imu_log_ns[-1]))
    elapsed = time.perf_counter() - started
    rig.save(out / 'rig.yaml')
    if rig_out:
        rig.save(rig_out)
    size = sum(f.stat().st_size for f in out.iterdir())
    return {'frames': n_frames, 'images': images_written, 'offsets_ms': [o * 1e3 for o in offsets], 'seconds': elapsed,
            'fps': n_frames / elapsed, 'bytes': size,
            'path_length': trajectory.path_length, 'cameras': rig.names}


def run(args) -> int:
    logging.basicConfig(level=logging.INFO, format='%(levelname)s %(name)s: %(message)s')
    validate(args)
    n_cameras = rig_camera_count(args)
    summary = generate(args.scenario, args.out, args.seed, args.duration, args.rate, args.width,
                       args.height, args.fx, args.k1, args.cameras, args.rig_out,
                       args.compression, rig_kind=args.rig, baseline=args.baseline,
                       camera_offsets_ms=parse_camera_list(args.camera_offsets_ms, n_cameras,
                                                           '--camera-offsets-ms'),
                       camera_rates=parse_camera_list(args.camera_rates, n_cameras, '--camera-rates'),
                       image_codec=args.compressed, jpeg_quality=args.jpeg_quality,
                       camera_phases=args.camera_phases, imu_rate=args.imu_rate,
                       imu_fault=args.imu_fault, imu_fault_at=args.imu_fault_at)
    print(f'{args.out}: {summary["frames"]} frames x {len(summary["cameras"])} cameras '
          f'({", ".join(summary["cameras"])}), path {summary["path_length"]:.1f} m, '
          f'rendered and written in {summary["seconds"]:.1f} s ({summary["fps"]:.1f} frames/s), '
          f'{summary["bytes"] / 1e6:.1f} MB'
          + (f', capture offsets {", ".join(f"{o:g}" for o in summary["offsets_ms"])} ms'
             if any(summary['offsets_ms']) else ''))
    return 0
