"""Procedural, corner-rich, non-repeating textures for the faces of the world.

A tile is a flat grey background covered with random polygons (rotated
rectangles, triangles, quadrilaterals) at several scales, 8 cm to 60 cm, drawn anti-aliased:
many well-spread corners for Shi-Tomasi at every viewing distance, and no periodic pattern
for KLT to alias on. A "bare" area keeps only a faint, smooth shading.
"""
import cv2
import numpy as np

# Polygon sizes (m) and how many of each per square metre.
SCALES = ((0.6, 0.8), (0.3, 3.0), (0.15, 8.0), (0.08, 16.0))
SUBPIXEL_BITS = 4


def smooth_field(rng, width_px, height_px, cell_px, amplitude):
    """Random field with features about `cell_px` wide, values in +-amplitude."""
    gw, gh = max(2, width_px // cell_px + 2), max(2, height_px // cell_px + 2)
    coarse = rng.uniform(-amplitude, amplitude, (gh, gw)).astype(np.float32)
    return cv2.resize(coarse, (width_px, height_px), interpolation=cv2.INTER_CUBIC)


def random_polygon(rng, cx, cy, size):
    kind = rng.integers(3)
    if kind == 0:    # rotated rectangle
        w, h = size * rng.uniform(0.4, 1.0), size * rng.uniform(0.4, 1.0)
        a = rng.uniform(0, np.pi)
        c, s = np.cos(a), np.sin(a)
        corners = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
        pts = corners @ np.array([[c, s], [-s, c]])
    else:            # triangle or irregular quadrilateral around the centre
        n = 3 if kind == 1 else 4
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        radii = size * rng.uniform(0.3, 0.6, n)
        pts = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    return pts + [cx, cy]


def textured_tile(rng, width_m, height_m, texels_per_m):
    w = max(2, int(round(width_m * texels_per_m)))
    h = max(2, int(round(height_m * texels_per_m)))
    # A flat background (not a shaded one): flat areas stay flat in the rendered image, which
    # is what lets the bag compress; the corners come from the polygons anyway.
    tile = np.full((h, w), int(rng.integers(80, 176)), np.uint8)
    area = width_m * height_m
    scale = 1 << SUBPIXEL_BITS
    for size, density in SCALES:
        count = rng.poisson(density * area)
        centres = rng.uniform([0, 0], [width_m, height_m], (count, 2))
        for cx, cy in centres:
            pts = random_polygon(rng, cx, cy, size) * texels_per_m
            grey = int(rng.integers(10, 246))
            cv2.fillPoly(tile, [np.round(pts * scale).astype(np.int32)], grey,
                         lineType=cv2.LINE_AA, shift=SUBPIXEL_BITS)
    return tile


def make_bare(tile, rng, texels_per_m, u0, u1, v0=None, v1=None):
    """Replace a region (metres) with a nearly uniform grey: only a faint smooth shading."""
    h, w = tile.shape
    c0, c1 = int(max(0, u0 * texels_per_m)), int(min(w, u1 * texels_per_m))
    r0 = 0 if v0 is None else int(max(0, v0 * texels_per_m))
    r1 = h if v1 is None else int(min(h, v1 * texels_per_m))
    if c1 <= c0 or r1 <= r0:
        return
    shade = 150 + smooth_field(rng, c1 - c0, r1 - r0, int(1.5 * texels_per_m), 3.0)
    tile[r0:r1, c0:c1] = np.clip(shade, 0, 255).astype(np.uint8)


def face_texture(rng, face, texels_per_m):
    tile = textured_tile(rng, face.width, face.height, texels_per_m)
    for u0, u1 in face.bare_spans:
        make_bare(tile, rng, texels_per_m, u0, u1)
    if face.bare_rect:
        u0, u1, v0, v1 = face.bare_rect
        make_bare(tile, rng, texels_per_m, u0, u1, v0, v1)
    return tile
