"""Build a rig from a bag when no rig file is given: extrinsics from /tf_static
(base_link -> <cam>_optical) and camera names from the `/<cam>/image_raw` topics (or
image_transport's `/<cam>/image_raw/compressed`, when the bag has only those). A
`base_footprint` frame (REP-120: the robot's projection on the ground) gives the floor:
floor_z is its z in base_link."""
import numpy as np

from multicam_ego_motion.errors import UserError
from multicam_ego_motion.geometry.rig import CameraMount, Rig, rotation_from_quaternion


def rig_from_bag(reader, base_frame: str = 'base_link') -> Rig:
    if '/tf_static' not in reader.topics:
        raise UserError(f'bag {reader.path} has no /tf_static and no rig file was given: '
                        'cannot know where the cameras are (pass --rig RIG.yaml)')
    transforms = static_transforms(reader)
    cams = []
    for topic in sorted(reader.topics):
        transport = 'raw'
        if topic.endswith('/image_raw/compressed') and topic[:-len('/compressed')] not in reader.topics:
            topic, transport = topic[:-len('/compressed')], 'compressed'
        if not topic.endswith('/image_raw'):
            continue
        name = topic[1:-len('/image_raw')].strip('/')
        frame = f'{name}_optical'
        t = transforms.get(frame)
        if t is None or t.header.frame_id != base_frame:
            raise UserError(f'bag {reader.path}: /tf_static has no {base_frame} -> {frame} '
                            f'for camera topic {topic}')
        cams.append(CameraMount(name, topic, f'/{name}/camera_info', frame, *mount(t),
                                transport=transport))
    if not cams:
        raise UserError(f'bag {reader.path} has no */image_raw (nor */image_raw/compressed) topic')
    return Rig(cameras=cams, base_frame=base_frame, floor_z=footprint_z(transforms, base_frame))


def static_transforms(reader) -> dict:
    """{child frame: TransformStamped} of the bag's /tf_static (none without it)."""
    transforms = {}
    if '/tf_static' in reader.topics:
        for _, msg, _ in reader.decoded(['/tf_static']):
            for t in msg.transforms:
                transforms[t.child_frame_id] = t
    return transforms


def mount(t):
    """(translation, 3x3 rotation) of a TransformStamped: the child frame in the parent."""
    tr, rq = t.transform.translation, t.transform.rotation
    return (np.array([tr.x, tr.y, tr.z]),
            rotation_from_quaternion([rq.x, rq.y, rq.z, rq.w], f'/tf_static {t.child_frame_id}'))


def footprint_z(transforms, base_frame: str = 'base_link'):
    """z of base_footprint in base_frame (either direction of the transform), or None."""
    t = transforms.get('base_footprint')
    if t is not None and t.header.frame_id == base_frame:
        return float(t.transform.translation.z)
    t = transforms.get(base_frame)
    if t is not None and t.header.frame_id == 'base_footprint':
        # base_footprint -> base_link: base_link's origin in base_footprint; the footprint
        # lies level below it (REP-120), so its z in base_link is minus that height
        tr, rq = t.transform.translation, t.transform.rotation
        R = rotation_from_quaternion([rq.x, rq.y, rq.z, rq.w], f'/tf_static {base_frame}')
        return float(-(R.T @ np.array([tr.x, tr.y, tr.z]))[2])
    return None
