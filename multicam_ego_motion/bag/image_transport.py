"""Which image_transport a bag holds for each camera: `raw` (sensor_msgs/Image on the
camera's image topic) or `compressed` (sensor_msgs/CompressedImage on `<image topic>/compressed`).

A rig says which transport a camera's images come on (geometry/rig.py); a bag recorded on a
robot often has only the compressed stream. `replay`, `check` and the sequential pipeline
take whichever the bag has: the rig's own when the bag has it, else the other one.
"""
from dataclasses import replace
from typing import List, Tuple

from multicam_ego_motion.geometry.rig import TRANSPORTS, Rig


def with_bag_transports(reader, rig: Rig) -> Tuple[Rig, List[str]]:
    """The rig with each camera's transport set to one the bag has (unchanged where the bag
    has the rig's, or neither), and one line per camera that was changed."""
    cams, said = [], []
    for cam in rig.cameras:
        if cam.input_topic not in reader.topics:
            for transport in TRANSPORTS:
                other = replace(cam, transport=transport)
                if other.input_topic in reader.topics:
                    said.append(f'camera {cam.name}: the bag has its {transport} images '
                                f'({other.input_topic}, not {cam.input_topic}): using them')
                    cam = other
                    break
        cams.append(cam)
    return (replace(rig, cameras=cams) if said else rig), said
