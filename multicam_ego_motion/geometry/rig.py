"""The camera rig: names, topics and extrinsics (base_link -> camera optical frame).

Loaded from a YAML rig file in config/ and validated, so that a bad rig is rejected at start
with a message naming the camera and the problem (NaN, non-orthonormal rotation, ...).
Intrinsics are not here: they come from each camera's CameraInfo.
"""
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from multicam_ego_motion.errors import UserError

MAX_CAMERAS = 8
# image_transport's transports this graph reads: `raw` (sensor_msgs/Image on the image topic)
# or `compressed` (sensor_msgs/CompressedImage, JPEG or PNG, on <image topic>/compressed)
TRANSPORTS = {'raw': 'sensor_msgs/msg/Image', 'compressed': 'sensor_msgs/msg/CompressedImage'}
IMU_TOPIC = '/imu/data'      # an IMU's sensor_msgs/Imu unless the rig file names another


@dataclass
class CameraMount:
    name: str
    image_topic: str
    camera_info_topic: str
    frame_id: str
    translation: np.ndarray   # camera centre in base_link, metres
    rotation: np.ndarray      # 3x3, columns are the optical axes expressed in base_link
    transport: str = 'raw'    # TRANSPORTS: how its images come (image_transport's names)
    # mono16 images: bits that carry the signal (12 for a 12-bit sensor writing 0..4095);
    # the top 8 of them become the gray image (image_conversion)
    mono16_bits: int = 16

    @property
    def input_topic(self) -> str:
        """The topic its images come on: image_transport's `<image_topic>/compressed` for
        the compressed transport."""
        return self.image_topic + '/compressed' if self.transport == 'compressed' else self.image_topic

    @property
    def input_type(self) -> str:
        return TRANSPORTS[self.transport]

    @property
    def T_base_cam(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.translation
        return T

    def to_dict(self):
        q = Rotation.from_matrix(self.rotation).as_quat()
        d = {'name': self.name, 'image_topic': self.image_topic,
             'camera_info_topic': self.camera_info_topic, 'frame_id': self.frame_id,
             'translation': [round(float(v), 9) for v in self.translation],
             'rotation_xyzw': [round(float(v), 12) for v in q]}
        if self.transport != 'raw':
            d['transport'] = self.transport
        if self.mono16_bits != 16:
            d['mono16_bits'] = self.mono16_bits
        return d


@dataclass
class ImuMount:
    """Where an IMU sits: its frame (the sensor_msgs/Imu frame_id) in base_link."""
    frame_id: str
    translation: np.ndarray   # m, in base_link
    rotation: np.ndarray      # 3x3, the IMU's axes expressed in base_link
    topic: str = IMU_TOPIC

    def to_dict(self):
        q = Rotation.from_matrix(self.rotation).as_quat()
        return {'frame_id': self.frame_id, 'topic': self.topic,
                'translation': [round(float(v), 9) for v in self.translation],
                'rotation_xyzw': [round(float(v), 12) for v in q]}


@dataclass
class Rig:
    cameras: List[CameraMount] = field(default_factory=list)
    base_frame: str = 'base_link'
    # The base stands on a level floor at this height in base_frame (0 for a base_link on
    # the floor, REP-105's base_footprint); None: no such floor (a car rig whose base_link is
    # at a tilted camera, a handheld rig). Floor landmarks and planar motion need it.
    floor_z: Optional[float] = None
    # The floor is level everywhere (a building: the base never climbs or tilts, which the
    # general arbiter's planar_motion assumes), or only locally flat (a road with slopes:
    # floor landmarks still hold, planar motion does not).
    floor_level: bool = True
    # Cameras whose fields of view overlap (a stereo pair), as (name, name): each one's
    # quarters match their tracks into the other's image and triangulate metric landmarks
    # from a single frame (camera_pose_nodes/stereo_match.py). Named in the rig file, or
    # found from the extrinsics and CameraInfos when the file does not name any
    # (detect_stereo; stereo_match.overlapping_pairs).
    stereo_pairs: Tuple[Tuple[str, str], ...] = ()
    # False when the rig file names stereo_pairs (even an empty list): named pairs win
    detect_stereo: bool = True
    # An IMU (sensor_msgs/Imu) whose gyro the general arbiter fuses; None: cameras only
    imu: Optional[ImuMount] = None

    @property
    def metric_source(self) -> Optional[str]:
        """What gives this rig metric scale by itself: 'stereo' (stereo_pairs), 'floor'
        (floor_z) or None (then the general arbiter measures it from the quarters' tracks,
        which the quarter nodes publish only then)."""
        if self.stereo_pairs:
            return 'stereo'
        if self.floor_z is not None:
            return 'floor'
        return None

    @property
    def road_scale(self) -> bool:
        """A rig over a road (floor_z, floor_level false) without a stereo pair: the road is
        its only scale source, and one frame's road points hold the scale only as well as
        the camera's pitch to the road is known, so the general arbiter also measures the
        map's scale from the road between frames (scale_state, road_plane)."""
        return self.floor_z is not None and not self.floor_level and not self.stereo_pairs

    @property
    def sends_bearings(self) -> bool:
        """Whether the quarters publish their tracks for the general arbiter: for its scale
        without a metric source of the rig's own and over a road (road_scale), and for the
        gyro's bias with an IMU (general_fusion gyro_bias_from_tracks), and for the rotation
        of free-running cameras between their frames (lone_camera_track_rotation: whether
        the cameras are synchronised shows only in their stamps, so any rig of several)."""
        return (self.metric_source is None or self.road_scale or self.imu is not None
                or len(self.cameras) > 1)

    def stereo_partners(self, name: str) -> List[str]:
        """The cameras named with `name` in a stereo pair, in pair order."""
        return [b if a == name else a for a, b in self.stereo_pairs if name in (a, b)]

    def camera(self, name: str) -> CameraMount:
        for c in self.cameras:
            if c.name == name:
                return c
        raise UserError(f'rig has no camera {name!r} (it has: {", ".join(self.names)})')

    @property
    def names(self):
        return [c.name for c in self.cameras]

    def to_dict(self):
        d = {'base_frame': self.base_frame}
        if self.floor_z is not None:
            d['floor_z'] = float(self.floor_z)
            if not self.floor_level:
                d['floor_level'] = False
        if self.stereo_pairs or not self.detect_stereo:
            d['stereo_pairs'] = [list(p) for p in self.stereo_pairs]
        d['cameras'] = [c.to_dict() for c in self.cameras]
        if self.imu is not None:
            d['imu'] = self.imu.to_dict()
        return d

    def save(self, path):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        with open(path, 'w') as f:
            f.write('# Camera rig: extrinsics base_link -> <camera>_optical (REP-103/105).\n'
                    '# translation: camera centre in base_link (m); rotation_xyzw: the optical\n'
                    '# frame (z forward, x right, y down) expressed in base_link.\n'
                    '# floor_z (optional): the floor the base stands on, z in base_link;\n'
                    '# floor_level (optional, default true): false for a road with slopes.\n'
                    '# stereo_pairs (optional): [[left, right], ...] cameras whose views overlap;\n'
                    '# without it, overlapping pairs are found from the extrinsics and intrinsics.\n'
                    '# transport (optional, per camera): raw (sensor_msgs/Image on image_topic,\n'
                    '# default) or compressed (CompressedImage on <image_topic>/compressed);\n'
                    '# mono16_bits (optional): significant bits of a mono16 camera (default 16).\n'
                    '# imu (optional): frame_id, topic (sensor_msgs/Imu), translation and\n'
                    '# rotation_xyzw of the IMU\'s frame in base_link.\n'
                    '# Intrinsics come from each camera\'s CameraInfo.\n')
            yaml.safe_dump(self.to_dict(), f, sort_keys=False)


def rotation_from_quaternion(q, where: str) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise UserError(f'{where}: rotation_xyzw must be 4 finite numbers, got {q.tolist()}')
    n = np.linalg.norm(q)
    if abs(n - 1.0) > 1e-3:
        raise UserError(f'{where}: rotation_xyzw is not a unit quaternion (norm {n:.6f})')
    return Rotation.from_quat(q / n).as_matrix()


def validate_rotation_matrix(R, where: str) -> np.ndarray:
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise UserError(f'{where}: rotation must be a finite 3x3 matrix')
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-4 or np.linalg.det(R) < 0:
        raise UserError(f'{where}: rotation is not orthonormal (|R R^T - I| = {err:.3g}, '
                        f'det = {np.linalg.det(R):.4f})')
    return R


def parse_rig(data: dict, source: str = 'rig') -> Rig:
    if not isinstance(data, dict) or not isinstance(data.get('cameras'), list):
        raise UserError(f'{source}: expected a mapping with a list "cameras"')
    cams = []
    for i, c in enumerate(data['cameras']):
        where = f'{source}: camera {c.get("name", i) if isinstance(c, dict) else i}'
        if not isinstance(c, dict) or 'name' not in c:
            raise UserError(f'{where}: every camera needs a name')
        name = str(c['name'])
        t = np.asarray(c.get('translation', [np.nan] * 3), dtype=float)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise UserError(f'{where}: translation must be 3 finite numbers')
        if 'rotation' in c:
            R = validate_rotation_matrix(c['rotation'], where)
        else:
            R = rotation_from_quaternion(c.get('rotation_xyzw', [np.nan] * 4), where)
        transport = c.get('transport', 'raw')
        if transport not in TRANSPORTS:
            raise UserError(f'{where}: transport must be one of {", ".join(TRANSPORTS)}, got {transport!r}')
        bits = c.get('mono16_bits', 16)
        if not (isinstance(bits, int) and not isinstance(bits, bool) and 8 <= bits <= 16):
            raise UserError(f'{where}: mono16_bits must be a whole number of bits within 8..16, got {bits!r}')
        cams.append(CameraMount(
            name=name,
            image_topic=c.get('image_topic', f'/{name}/image_raw'),
            camera_info_topic=c.get('camera_info_topic', f'/{name}/camera_info'),
            frame_id=c.get('frame_id', f'{name}_optical'),
            translation=t, rotation=R, transport=transport, mono16_bits=bits))
    if not 1 <= len(cams) <= MAX_CAMERAS:
        raise UserError(f'{source}: a rig has 1 to {MAX_CAMERAS} cameras, this one has {len(cams)}')
    if len(set(c.name for c in cams)) != len(cams):
        raise UserError(f'{source}: camera names must be unique')
    floor_z = data.get('floor_z')
    if floor_z is not None:
        try:
            floor_z = float(floor_z)
        except (TypeError, ValueError):
            floor_z = float('nan')
        if not np.isfinite(floor_z):
            raise UserError(f'{source}: floor_z must be a finite number (m), got {data["floor_z"]!r}')
    floor_level = data.get('floor_level', True)
    if not isinstance(floor_level, bool):
        raise UserError(f'{source}: floor_level must be true or false, got {floor_level!r}')
    named = 'stereo_pairs' in data
    pairs = parse_stereo_pairs(data.get('stereo_pairs'), [c.name for c in cams], source) if named else ()
    return Rig(cameras=cams, base_frame=data.get('base_frame', 'base_link'), floor_z=floor_z,
               floor_level=floor_level, stereo_pairs=pairs, detect_stereo=not named,
               imu=parse_imu(data.get('imu'), source))


def parse_imu(value, source: str = 'rig') -> Optional[ImuMount]:
    if value is None:
        return None
    where = f'{source}: imu'
    if not isinstance(value, dict) or not isinstance(value.get('frame_id'), str):
        raise UserError(f'{where}: expected a mapping with frame_id (the sensor_msgs/Imu frame), '
                        f'translation and rotation_xyzw')
    t = np.asarray(value.get('translation', [np.nan] * 3), dtype=float)
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise UserError(f'{where}: translation must be 3 finite numbers')
    R = rotation_from_quaternion(value.get('rotation_xyzw', [np.nan] * 4), where)
    return ImuMount(value['frame_id'], t, R, str(value.get('topic', IMU_TOPIC)))


def parse_stereo_pairs(value, names, source: str = 'rig') -> Tuple[Tuple[str, str], ...]:
    """[[a, b], ...] -> ((a, b), ...): names of the rig's cameras, two distinct ones per
    pair, no pair twice (in either order)."""
    if value is None:
        return ()
    if not isinstance(value, list):
        raise UserError(f'{source}: stereo_pairs must be a list of [camera, camera] pairs, got {value!r}')
    pairs, seen = [], set()
    for i, p in enumerate(value):
        if not (isinstance(p, (list, tuple)) and len(p) == 2 and all(isinstance(n, str) for n in p)):
            raise UserError(f'{source}: stereo_pairs entry {i + 1} must be [camera, camera] '
                            f'(two camera names), got {p!r}')
        a, b = p
        for n in (a, b):
            if n not in names:
                raise UserError(f'{source}: stereo_pairs entry {i + 1} names camera {n!r}, '
                                f'which the rig does not have (it has: {", ".join(names)})')
        if a == b:
            raise UserError(f'{source}: stereo_pairs entry {i + 1} pairs camera {a!r} with itself')
        if frozenset(p) in seen:
            raise UserError(f'{source}: stereo_pairs names the pair {a!r}, {b!r} twice')
        seen.add(frozenset(p))
        pairs.append((a, b))
    return tuple(pairs)


def with_transport(rig: Rig, transport: str, what: str = 'transport') -> Rig:
    """The rig with every camera's images on `transport` (a node's image_transport
    parameter, which wins over the rig file); '' leaves each camera's as the file says."""
    if not transport:
        return rig
    if transport not in TRANSPORTS:
        raise UserError(f'{what} must be one of {", ".join(TRANSPORTS)} (or empty: the rig '
                        f'file\'s), got {transport!r}')
    return replace(rig, cameras=[replace(c, transport=transport) for c in rig.cameras])


def load_rig(path) -> Rig:
    path = Path(path)
    if not path.exists():
        raise UserError(f'rig file not found: {path}')
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise UserError(f'rig file {path} is not valid YAML ({e})') from None
    return parse_rig(data, str(path))


# Optical frame (z forward, x right, y down) looking along base_link +x, before yaw.
_OPTICAL_FORWARD = np.array([[0.0, 0.0, 1.0],
                             [-1.0, 0.0, 0.0],
                             [0.0, -1.0, 0.0]])


def optical_rotation(yaw: float, pitch: float = 0.0) -> np.ndarray:
    """Rotation of an optical frame looking at heading `yaw` (rad, about base z), tilted by
    `pitch` (rad, positive looks down)."""
    return (Rotation.from_euler('z', yaw).as_matrix()
            @ Rotation.from_euler('y', pitch).as_matrix() @ _OPTICAL_FORWARD)


def paper_rig(radius: float = 0.25, height: float = 0.5) -> Rig:
    """The paper's Fig. 1: two back-to-back pairs (front/back, left/right), axes perpendicular,
    `height` above the floor base_link stands on."""
    cams = []
    for name, yaw in (('front', 0.0), ('left', np.pi / 2), ('back', np.pi), ('right', -np.pi / 2)):
        cams.append(CameraMount(
            name=name, image_topic=f'/{name}/image_raw', camera_info_topic=f'/{name}/camera_info',
            frame_id=f'{name}_optical',
            translation=np.array([radius * np.cos(yaw), radius * np.sin(yaw), height]),
            rotation=optical_rotation(yaw)))
    return Rig(cameras=cams, floor_z=0.0)
