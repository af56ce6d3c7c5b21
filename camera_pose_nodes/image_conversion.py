"""Acquire: turn a sensor_msgs/Image or sensor_msgs/CompressedImage payload into the gray
uint8 array the tracker works on.

ROS-free: the node passes the message fields (encoding, height, width, step, data; or the
compressed format and data), so this can be tested on plain bytes. OpenCV does every
conversion (cvtColor, imdecode). Anything we cannot convert without guessing is rejected with
an error that names the encoding or format, because silently mis-reading pixels would
corrupt tracking.

mono16 (and 16-bit PNGs) become 8 bit by a fixed shift: the top 8 of the camera's
`mono16_bits` significant bits (rig file, default 16: the full 16-bit range, as cv_bridge
maps mono16 to mono8). Fixed rather than stretched per image: the tracker assumes a point
keeps its brightness from frame to frame, and every worker must see the same pixels.
"""
import numpy as np
import cv2

from multicam_ego_motion.errors import UserError

# ROS encoding (sensor_msgs/image_encodings.hpp, lower case) -> (bytes per pixel, OpenCV
# conversion to gray or None). OpenCV names a Bayer pattern after the 2x2 cell starting at
# pixel (1, 1), ROS after the one at (0, 0): ROS rggb is OpenCV's BG.
SUPPORTED_ENCODINGS = {
    'mono8': (1, None),
    '8uc1': (1, None),
    'bgr8': (3, cv2.COLOR_BGR2GRAY),
    'rgb8': (3, cv2.COLOR_RGB2GRAY),
    'bgra8': (4, cv2.COLOR_BGRA2GRAY),
    'rgba8': (4, cv2.COLOR_RGBA2GRAY),
    'bayer_rggb8': (1, cv2.COLOR_BayerBG2GRAY),
    'bayer_bggr8': (1, cv2.COLOR_BayerRG2GRAY),
    'bayer_gbrg8': (1, cv2.COLOR_BayerGR2GRAY),
    'bayer_grbg8': (1, cv2.COLOR_BayerGB2GRAY),
    'mono16': (2, None),
    'yuv422': (2, cv2.COLOR_YUV2GRAY_UYVY),         # ROS: U Y0 V Y1
    'uyvy': (2, cv2.COLOR_YUV2GRAY_UYVY),
    'yuv422_yuy2': (2, cv2.COLOR_YUV2GRAY_YUY2),    # ROS: Y0 U Y1 V
    'yuyv': (2, cv2.COLOR_YUV2GRAY_YUY2),
}
COMPRESSED_FORMATS = ('jpeg', 'png')


def mono16_to_gray(img: np.ndarray, mono16_bits: int = 16) -> np.ndarray:
    """uint16 -> uint8: the top 8 of `mono16_bits` significant bits (saturating above)."""
    shift = int(mono16_bits) - 8
    return np.minimum(img >> shift, 255).astype(np.uint8) if shift > 0 else \
        np.minimum(img, 255).astype(np.uint8)


def to_gray(encoding: str, height: int, width: int, step: int, data,
            expected_size=None, is_bigendian=False, mono16_bits: int = 16) -> np.ndarray:
    """Gray uint8 (height x width) from Image fields; `expected_size` = (width, height) of
    the CameraInfo, checked so intrinsics and pixels cannot silently disagree."""
    enc = str(encoding).lower()
    if enc not in SUPPORTED_ENCODINGS:
        raise UserError(f'image encoding {encoding!r} is not supported '
                        f'(supported: {", ".join(sorted(SUPPORTED_ENCODINGS))}); '
                        'convert the stream to one of them')
    pixel_bytes, code = SUPPORTED_ENCODINGS[enc]
    height, width, step = int(height), int(width), int(step)
    if height <= 0 or width <= 0:
        raise UserError(f'image has an empty size {width}x{height}')
    if enc.startswith(('bayer_', 'yuv', 'uyvy', 'yuyv')) and width % 2:
        raise UserError(f'{encoding} image has an odd width {width}')
    if step < width * pixel_bytes:
        raise UserError(f'image step {step} is smaller than width*bytes per pixel = '
                        f'{width * pixel_bytes} for {encoding}')
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)
    if buf.size != height * step:
        raise UserError(f'image data has {buf.size} bytes, expected height*step = '
                        f'{height}*{step} = {height * step}')
    check_size(width, height, expected_size)
    rows = buf.reshape(height, step)[:, :width * pixel_bytes]
    if enc == 'mono16':
        pixels = np.ascontiguousarray(rows).view('>u2' if is_bigendian else '<u2')
        return mono16_to_gray(pixels, mono16_bits)
    if code is None:
        return np.ascontiguousarray(rows)
    channels = 1 if enc.startswith('bayer_') else pixel_bytes
    return cv2.cvtColor(np.ascontiguousarray(rows.reshape(height, width, channels)), code)


def check_size(width: int, height: int, expected_size):
    if expected_size is not None and (width, height) != tuple(int(v) for v in expected_size):
        raise UserError(f'image is {width}x{height} but CameraInfo says '
                        f'{expected_size[0]}x{expected_size[1]}')


def compressed_format(fmt: str):
    """image_transport's format string -> (codec, encoding of the original image or None).

    'jpeg', 'png', 'bgr8; jpeg compressed bgr8', 'mono16; png compressed mono16': the codec
    is the word before 'compressed' (or the whole string), the original encoding the part
    before ';'."""
    text = str(fmt).strip().lower()
    original, _, rest = text.partition(';') if ';' in text else ('', '', text)
    codec = rest.strip().split(' ')[0] if rest.strip() else ''
    codec = {'jpg': 'jpeg'}.get(codec, codec)
    if codec not in COMPRESSED_FORMATS:
        raise UserError(f'compressed image format {fmt!r} is not supported '
                        f'(supported: {", ".join(COMPRESSED_FORMATS)}, as image_transport\'s '
                        '"compressed" writes them)')
    return codec, original.strip() or None


def compressed_to_gray(fmt: str, data, expected_size=None, mono16_bits: int = 16) -> np.ndarray:
    """Gray uint8 from CompressedImage fields (format, data)."""
    codec, original = compressed_format(fmt)
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)
    if buf.size == 0:
        raise UserError(f'{codec} image has no data')
    # JPEG: libjpeg gives the luma plane directly (no chroma upsampling nor colour conversion)
    flags = cv2.IMREAD_GRAYSCALE if codec == 'jpeg' else cv2.IMREAD_UNCHANGED
    try:
        img = cv2.imdecode(buf, flags)
    except cv2.error:
        img = None
    if img is None:
        raise UserError(f'{codec} image of {buf.size} bytes could not be decoded (corrupt or '
                        'not a ' + codec + ')')
    check_size(img.shape[1], img.shape[0], expected_size)
    if img.dtype == np.uint16:
        img = mono16_to_gray(img, mono16_bits)
    if img.ndim == 3:
        # (image_transport writes colour as BGR whatever the camera's order)
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    elif original is not None and original.startswith('bayer_') and original in SUPPORTED_ENCODINGS:
        img = cv2.cvtColor(img, SUPPORTED_ENCODINGS[original][1])   # a compressed mosaic
    return np.ascontiguousarray(img)


def bgr8_message(msg, img: np.ndarray, stamp, frame_id: str):
    """Fill an empty sensor_msgs/Image `msg` (duck-typed) with the bgr8 image `img` (H x W x 3
    uint8), stamped; returns it (the debug images of the quarters and camera arbiters)."""
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = img.shape[:2]
    msg.encoding, msg.step = 'bgr8', 3 * img.shape[1]
    msg.data = np.ascontiguousarray(img, np.uint8).tobytes()
    return msg


def image_msg_to_gray(msg, expected_size=None, mono16_bits: int = 16) -> np.ndarray:
    """Gray image from a sensor_msgs/Image or CompressedImage (duck-typed: no ROS import
    here; a CompressedImage has a `format`)."""
    if hasattr(msg, 'format'):
        return compressed_to_gray(msg.format, msg.data, expected_size, mono16_bits)
    return to_gray(msg.encoding, msg.height, msg.width, msg.step, msg.data, expected_size,
                   bool(msg.is_bigendian), mono16_bits)
