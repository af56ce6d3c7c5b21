"""Acquire-side conversions: Image fields -> gray, CameraInfo -> intrinsics."""
import numpy as np
import pytest

from camera_pose_nodes.camera_model import CameraIntrinsics
from camera_pose_nodes.image_conversion import to_gray
from multicam_ego_motion.errors import UserError


def test_encodings_to_gray():
    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 256, (4, 6, 3), dtype=np.uint8)
    g_bgr = to_gray('bgr8', 4, 6, 18, bgr.tobytes())
    g_rgb = to_gray('rgb8', 4, 6, 18, bgr[..., ::-1].tobytes())
    assert g_bgr.shape == (4, 6) and g_bgr.dtype == np.uint8 and np.array_equal(g_bgr, g_rgb)
    padded = np.zeros((4, 8), np.uint8)
    padded[:, :6] = 7
    assert np.all(to_gray('mono8', 4, 6, 8, padded.tobytes(), expected_size=(6, 4)) == 7)


@pytest.mark.parametrize('args, msg', [
    (('32FC1', 4, 6, 24, bytes(96)), "'32FC1' is not supported"),
    (('mono8', 4, 6, 6, bytes(20)), 'expected height\\*step'),
    (('mono8', 4, 6, 6, bytes(24), (640, 480)), 'CameraInfo says 640x480'),
])
def test_bad_images_are_rejected(args, msg):
    with pytest.raises(UserError, match=msg):
        to_gray(*args)


def test_undistort_and_project_round_trip():
    k = [400, 0, 320, 0, 410, 240, 0, 0, 1]
    px = np.array([[10.0, 20.0], [320, 240], [600, 400]])
    for model, d in (('plumb_bob', [-0.2, 0.05, 0.001, -0.001, 0.0]), ('none', []),
                     ('equidistant', [0.01, -0.002, 0.0, 0.0])):
        cam = CameraIntrinsics.from_camera_info(k, d, model, 640, 480)
        assert np.allclose(cam.project(cam.undistort_points(px)), px, atol=1e-3)
    assert np.allclose(CameraIntrinsics.from_camera_info(k, [], 'none', 640, 480)
                       .undistort_points([[720, 650]]), [[1.0, 1.0]])


@pytest.mark.parametrize('k, d, model, msg', [
    ([np.nan] * 9, [], 'plumb_bob', 'NaN'),
    ([0, 0, 320, 0, 0, 240, 0, 0, 1], [], 'plumb_bob', 'focal length'),
    ([400, 0, 320, 0, 400, 240, 0, 0, 1], [0.1], 'fancy', "'fancy' not supported"),
])
def test_bad_camera_info_is_rejected(k, d, model, msg):
    with pytest.raises(UserError, match=msg):
        CameraIntrinsics.from_camera_info(k, d, model, 640, 480, camera='front')
