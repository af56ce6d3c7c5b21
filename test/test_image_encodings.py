"""Every image input a robot records, read as the raw image it came from: Bayer mosaics,
mono16 (both byte orders), yuv422 (UYVY, YUYV), JPEG and PNG CompressedImages with
image_transport's format strings; bad ones rejected naming the problem; and each image
decoded once per process however many quarters take it."""
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from camera_pose_nodes.decoded_images import DecodedImages
from camera_pose_nodes.image_conversion import (compressed_format, compressed_to_gray,
                                                image_msg_to_gray, to_gray)
from multicam_ego_motion.errors import UserError

H, W = 48, 64


def color_image():
    """Smooth, strongly coloured (red-heavy, little blue): a wrong Bayer pattern or channel
    order gives another gray."""
    rng = np.random.default_rng(3)
    bgr = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (7, 7), 2)
    bgr[..., 2] = np.clip(bgr[..., 2].astype(int) + 80, 0, 255)
    bgr[..., 0] //= 3
    return bgr


def gray_of(bgr):
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)


def mosaic(bgr, pattern):
    """The Bayer mosaic a sensor with the ROS `pattern` (e.g. 'rggb': R at (0, 0)) records."""
    channel = {'r': 2, 'g': 1, 'b': 0}
    out = np.zeros(bgr.shape[:2], np.uint8)
    for colour, (dy, dx) in zip(pattern, ((0, 0), (0, 1), (1, 0), (1, 1))):
        out[dy::2, dx::2] = bgr[dy::2, dx::2, channel[colour]]
    return out


def interior_error(a, b, border=4):
    return np.abs(a.astype(float) - b.astype(float))[border:-border, border:-border].mean()


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'gbrg', 'grbg'])
def test_bayer_demosaics_to_the_gray_of_the_colour_image(pattern):
    bgr = color_image()
    m = mosaic(bgr, pattern)
    gray = to_gray(f'bayer_{pattern}8', H, W, W, m.tobytes())
    assert gray.shape == (H, W) and gray.dtype == np.uint8
    assert interior_error(gray, gray_of(bgr)) < 2.0
    # the other patterns read the same mosaic wrong: what the right one must tell apart
    for other in {'rggb', 'bggr', 'gbrg', 'grbg'} - {pattern}:
        wrong = to_gray(f'bayer_{other}8', H, W, W, m.tobytes())
        assert interior_error(wrong, gray_of(bgr)) > 10.0, other


def test_yuv422_both_byte_orders():
    bgr = color_image()
    yuv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV).astype(int)     # full-resolution Y, U, V
    u = ((yuv[:, 0::2, 1] + yuv[:, 1::2, 1]) // 2).astype(np.uint8)
    v = ((yuv[:, 0::2, 2] + yuv[:, 1::2, 2]) // 2).astype(np.uint8)
    y = yuv[..., 0].astype(np.uint8)
    uyvy = np.stack([u, y[:, 0::2], v, y[:, 1::2]], axis=-1).reshape(H, 2 * W)
    yuyv = np.stack([y[:, 0::2], u, y[:, 1::2], v], axis=-1).reshape(H, 2 * W)
    for encoding, data in (('yuv422', uyvy), ('uyvy', uyvy), ('yuv422_yuy2', yuyv), ('yuyv', yuyv)):
        gray = to_gray(encoding, H, W, 2 * W, data.tobytes())
        assert np.array_equal(gray, y), encoding
        assert np.abs(gray.astype(int) - gray_of(bgr)).max() <= 1, encoding
    # the two orders are not interchangeable
    assert not np.array_equal(to_gray('yuyv', H, W, 2 * W, uyvy.tobytes()), y)


def test_mono16_both_byte_orders_and_significant_bits():
    gray = gray_of(color_image())
    full = gray.astype(np.uint16) * 256 + (255 - gray)       # low byte != high byte
    for big in (False, True):
        data = full.astype('>u2' if big else '<u2').tobytes()
        assert np.array_equal(to_gray('mono16', H, W, 2 * W, data, is_bigendian=big), gray)
    # a 12-bit sensor writing 0..4095: its top 8 bits with mono16_bits 12
    twelve = (gray.astype(np.uint16) << 4) | 0xF
    data = twelve.astype('<u2').tobytes()
    assert np.array_equal(to_gray('mono16', H, W, 2 * W, data, mono16_bits=12), gray)
    assert to_gray('mono16', H, W, 2 * W, data).max() <= 15   # read as 16 bits: dark
    # the byte order matters
    assert not np.array_equal(to_gray('mono16', H, W, 2 * W, full.astype('<u2').tobytes(),
                                      is_bigendian=True), gray)
    # padded rows
    padded = np.zeros((H, 2 * W + 6), np.uint8)
    padded[:, :2 * W] = full.astype('<u2').view(np.uint8)
    assert np.array_equal(to_gray('mono16', H, W, 2 * W + 6, padded.tobytes()), gray)


@pytest.mark.parametrize('fmt, ext, make, tolerance', [
    ('jpeg', '.jpg', lambda bgr: gray_of(bgr), 3.0),
    ('mono8; jpeg compressed mono8', '.jpg', lambda bgr: gray_of(bgr), 3.0),
    ('bgr8; jpeg compressed bgr8', '.jpg', lambda bgr: bgr, 3.0),
    ('rgb8; jpeg compressed bgr8', '.jpg', lambda bgr: bgr, 3.0),
    ('png', '.png', lambda bgr: gray_of(bgr), 0.0),
    ('bgr8; png compressed bgr8', '.png', lambda bgr: bgr, 0.0),
    ('bgra8; png compressed bgra8', '.png', lambda bgr: cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA), 0.0),
    ('mono16; png compressed mono16', '.png', lambda bgr: gray_of(bgr).astype(np.uint16) * 257, 0.0),
    ('bayer_rggb8; png compressed bayer_rggb8', '.png', lambda bgr: mosaic(bgr, 'rggb'), 2.0),
])
def test_compressed_images_read_as_the_raw_image(fmt, ext, make, tolerance):
    bgr = color_image()
    ok, data = cv2.imencode(ext, make(bgr), [cv2.IMWRITE_JPEG_QUALITY, 95] if ext == '.jpg' else [])
    assert ok
    msg = SimpleNamespace(format=fmt, data=data.tobytes(), header=None)
    gray = image_msg_to_gray(msg, expected_size=(W, H))
    assert gray.shape == (H, W) and gray.dtype == np.uint8
    assert interior_error(gray, gray_of(bgr)) <= tolerance + 0.5


def test_compressed_format_strings():
    assert compressed_format('jpeg') == ('jpeg', None)
    assert compressed_format('JPG') == ('jpeg', None)
    assert compressed_format('rgb8; jpeg compressed bgr8') == ('jpeg', 'rgb8')
    assert compressed_format('mono16; png compressed mono16') == ('png', 'mono16')


@pytest.mark.parametrize('fmt, data, msg', [
    ('16UC1; compressedDepth png', b'\x89PNG', "format '16UC1; compressedDepth png' is not supported"),
    ('webp', b'RIFF', "format 'webp' is not supported"),
    ('jpeg', b'', 'no data'),
    ('jpeg', b'\xff\xd8\xff\xe0 not a jpeg at all' * 10, 'could not be decoded'),
])
def test_bad_compressed_images_are_rejected(fmt, data, msg):
    with pytest.raises(UserError, match=msg):
        compressed_to_gray(fmt, data)


def test_truncated_jpeg_is_rejected_and_wrong_size_named():
    ok, data = cv2.imencode('.jpg', gray_of(color_image()))
    with pytest.raises(UserError, match='CameraInfo says 640x480'):
        compressed_to_gray('jpeg', data.tobytes(), expected_size=(640, 480))
    # cut in the middle of its entropy-coded data: libjpeg fills the rest and warns, or fails;
    # either way never a silently wrong size
    try:
        g = compressed_to_gray('jpeg', data.tobytes()[:40])
        assert g.shape == (H, W)
    except UserError as e:
        assert 'could not be decoded' in str(e)


@pytest.mark.parametrize('args, msg', [
    (('bayer_rggb8', 4, 5, 5, bytes(20)), 'odd width'),
    (('mono16', 4, 6, 6, bytes(24)), 'smaller than width'),
    (('yuv420', 4, 6, 6, bytes(24)), "'yuv420' is not supported"),
])
def test_bad_raw_images_are_rejected(args, msg):
    with pytest.raises(UserError, match=msg):
        to_gray(*args)


def image_msg(stamp_ns, data, fmt='jpeg'):
    return SimpleNamespace(format=fmt, data=data,
                           header=SimpleNamespace(stamp=SimpleNamespace(sec=stamp_ns // 10**9,
                                                                       nanosec=stamp_ns % 10**9)))


def test_each_image_is_decoded_once_for_every_quarter():
    cache = DecodedImages()
    ok, data = cv2.imencode('.jpg', gray_of(color_image()))
    msg = image_msg(1, data.tobytes())
    grays = [cache.gray('/front/image_raw/compressed', 1, msg, (W, H)) for _ in range(4)]
    assert cache.decodes == 1 and all(g is grays[0] for g in grays)
    assert not grays[0].flags.writeable              # shared: nobody may change it
    # another camera, another frame: decoded on their own
    cache.gray('/left/image_raw/compressed', 1, msg, (W, H))
    cache.gray('/front/image_raw/compressed', 2, image_msg(2, data.tobytes()), (W, H))
    assert cache.decodes == 3
    # a corrupt image: decoded (and failing) once, each quarter told
    bad = image_msg(3, b'\xff\xd8 broken')
    for _ in range(4):
        with pytest.raises(UserError, match='could not be decoded'):
            cache.gray('/front/image_raw/compressed', 3, bad, (W, H))
    assert cache.decodes == 4
    # only the newest frames are kept
    for k in range(10, 20):
        cache.gray('/front/image_raw/compressed', k, image_msg(k, data.tobytes()), (W, H))
    assert len(cache.by_topic['/front/image_raw/compressed']) == cache.frames_kept
