"""Acquire: turn a sensor_msgs/Image payload into the gray uint8 array the tracker works on.

ROS-free: the node passes the message fields (encoding, height, width, step, data), so this
can be tested on plain bytes. Anything we cannot convert without guessing is rejected with
an error that names the encoding, because silently mis-reading pixels would corrupt tracking.
"""
import numpy as np
import cv2

from multicam_ego_motion.errors import UserError

# encoding -> (channels, cv2 conversion to gray or None)
SUPPORTED_ENCODINGS = {
    'mono8': (1, None),
    '8uc1': (1, None),
    'bgr8': (3, cv2.COLOR_BGR2GRAY),
    'rgb8': (3, cv2.COLOR_RGB2GRAY),
    'bgra8': (4, cv2.COLOR_BGRA2GRAY),
    'rgba8': (4, cv2.COLOR_RGBA2GRAY),
}


def to_gray(encoding: str, height: int, width: int, step: int, data,
            expected_size=None) -> np.ndarray:
    """Gray uint8 (height x width) from Image fields; `expected_size` = (width, height) of
    the CameraInfo, checked so intrinsics and pixels cannot silently disagree."""
    enc = str(encoding).lower()
    if enc not in SUPPORTED_ENCODINGS:
        raise UserError(f'image encoding {encoding!r} is not supported '
                        f'(supported: {", ".join(sorted(SUPPORTED_ENCODINGS))}); '
                        'convert the stream to mono8/bgr8/rgb8')
    channels, code = SUPPORTED_ENCODINGS[enc]
    height, width, step = int(height), int(width), int(step)
    if height <= 0 or width <= 0:
        raise UserError(f'image has an empty size {width}x{height}')
    if step < width * channels:
        raise UserError(f'image step {step} is smaller than width*channels = {width * channels} '
                        f'for {encoding}')
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) \
        else np.ascontiguousarray(data, dtype=np.uint8).reshape(-1)
    if buf.size != height * step:
        raise UserError(f'image data has {buf.size} bytes, expected height*step = '
                        f'{height}*{step} = {height * step}')
    if expected_size is not None and (width, height) != tuple(int(v) for v in expected_size):
        raise UserError(f'image is {width}x{height} but CameraInfo says '
                        f'{expected_size[0]}x{expected_size[1]}')
    rows = buf.reshape(height, step)[:, :width * channels]
    if channels == 1:
        return np.ascontiguousarray(rows)
    return cv2.cvtColor(np.ascontiguousarray(rows.reshape(height, width, channels)), code)


def bgr8_message(msg, img: np.ndarray, stamp, frame_id: str):
    """Fill an empty sensor_msgs/Image `msg` (duck-typed) with the bgr8 image `img` (H x W x 3
    uint8), stamped; returns it (the debug images of the quarters and camera arbiters)."""
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = img.shape[:2]
    msg.encoding, msg.step = 'bgr8', 3 * img.shape[1]
    msg.data = np.ascontiguousarray(img, np.uint8).tobytes()
    return msg


def image_msg_to_gray(msg, expected_size=None) -> np.ndarray:
    """Gray image from a sensor_msgs/Image (duck-typed: no ROS import here)."""
    return to_gray(msg.encoding, msg.height, msg.width, msg.step, msg.data, expected_size)
