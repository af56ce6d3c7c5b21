"""All face textures packed into one image, so a whole frame is textured by one cv2.remap.

The atlas has four channels: the texture prefiltered for footprints of 1, 2, 4 and 8
texels (a mip chain kept at full size, so one set of coordinates addresses every level).
The renderer blends the two levels that bracket each pixel's footprint: far and grazing
surfaces do not alias into flickering corners.
"""
import cv2
import numpy as np

from multicam_ego_motion.scenarios.textures import face_texture

PAD = 4              # texels of replicated border around each tile (bilinear never bleeds)
ATLAS_WIDTH = 4096
LEVEL_SIGMAS = (0.0, 1.0, 2.0, 4.0)


class TextureAtlas:
    def __init__(self, scene, rng, texels_per_m: float = 100.0):
        self.texels_per_m = texels_per_m
        tiles = [face_texture(rng, face, texels_per_m) for face in scene.faces]
        n = len(tiles)
        self.offset_x = np.zeros(n, np.float32)   # where a face's texel (0, 0) lands
        self.offset_y = np.zeros(n, np.float32)
        places, x, y, row_h = [], 0, 0, 0
        for i, tile in enumerate(tiles):
            h, w = tile.shape[0] + 2 * PAD, tile.shape[1] + 2 * PAD
            if w > ATLAS_WIDTH:
                raise ValueError(f'face {scene.faces[i].name} is too wide for the atlas')
            if x + w > ATLAS_WIDTH:
                x, y, row_h = 0, y + row_h, 0
            places.append((x, y))
            self.offset_x[i], self.offset_y[i] = x + PAD, y + PAD
            x, row_h = x + w, max(row_h, h)
        height = y + row_h
        if height >= 32767:
            raise ValueError('texture atlas too tall for cv2.remap')
        self.image = np.zeros((height, ATLAS_WIDTH, len(LEVEL_SIGMAS)), np.uint8)
        for tile, (x, y) in zip(tiles, places):
            padded = cv2.copyMakeBorder(tile, PAD, PAD, PAD, PAD, cv2.BORDER_REPLICATE)
            h, w = padded.shape
            for level, sigma in enumerate(LEVEL_SIGMAS):
                blurred = padded if sigma == 0 else cv2.GaussianBlur(
                    padded, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)
                self.image[y:y + h, x:x + w, level] = blurred
        self.max_level = float(len(LEVEL_SIGMAS) - 1)
