"""Vectorized ray casting of the scene into mono8 images, one CameraRenderer per camera.

Why it is fast: the cameras are level (optical axis horizontal, no roll), so every pixel of
an image column shares one horizontal ray direction. Walls and boxes (vertical faces) are
intersected once per column in 2D; a box then covers a contiguous run of rows in that
column, and nearer boxes are painted over farther ones. The floor and ceiling distance of
each pixel is fixed for a camera at a fixed height and is precomputed. Textures come from
one atlas with a single cv2.remap per image.

Radial distortion is rendered by ray casting a larger pinhole canvas and warping it with
the plumb_bob model (cv2.undistortPoints gives each distorted pixel's ray).
"""
import cv2
import numpy as np

from multicam_ego_motion.geometry.camera_intrinsics import CameraIntrinsics
from multicam_ego_motion.errors import UserError

_FAR = 1e4


def mount_heading(rotation: np.ndarray) -> float:
    """Yaw of a level camera's optical axis in base_link; rejects tilted or rolled mounts."""
    z_axis, y_axis = rotation[:, 2], rotation[:, 1]
    if abs(z_axis[2]) > 1e-6 or abs(y_axis[2] + 1.0) > 1e-6:
        raise UserError('the scenario renderer needs level cameras (optical axis horizontal, '
                        'image y pointing down)')
    return float(np.arctan2(z_axis[1], z_axis[0]))


class CameraRenderer:
    def __init__(self, scene, atlas, intrinsics: CameraIntrinsics, mount):
        self.scene, self.atlas, self.intrinsics = scene, atlas, intrinsics
        self.mount_xy = np.asarray(mount.translation[:2], dtype=float)
        self.height = float(mount.translation[2])
        if not 0.0 < self.height < scene.height:
            raise UserError(f'camera {mount.name} is not between floor and ceiling')
        self.mount_yaw = mount_heading(mount.rotation)
        self._distortion_map = None
        canvas = intrinsics
        if intrinsics.is_distorted:
            canvas = self._prepare_distortion(intrinsics)
        self._prepare_pinhole(canvas)
        self._prepare_tables()

    # --- per-camera constants -------------------------------------------------------------

    def _prepare_distortion(self, intr):
        u, v = np.meshgrid(np.arange(intr.width, dtype=np.float32),
                           np.arange(intr.height, dtype=np.float32))
        pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        normalized = cv2.undistortPoints(pts, intr.K, intr.D).reshape(intr.height, intr.width, 2)
        lo, hi = normalized.reshape(-1, 2).min(0), normalized.reshape(-1, 2).max(0)
        x0 = int(np.floor(lo[0] * intr.fx)) - 2
        y0 = int(np.floor(lo[1] * intr.fy)) - 2
        width = int(np.ceil(hi[0] * intr.fx)) + 3 - x0
        height = int(np.ceil(hi[1] * intr.fy)) + 3 - y0
        self._distortion_map = ((normalized[..., 0] * intr.fx - x0).astype(np.float32),
                                (normalized[..., 1] * intr.fy - y0).astype(np.float32))
        return CameraIntrinsics(width, height, intr.fx, intr.fy, float(-x0), float(-y0))

    def _prepare_pinhole(self, c):
        self.width, self.height_px, self.fx, self.fy, self.cy = c.width, c.height, c.fx, c.fy, c.cy
        xn = (np.arange(c.width) - c.cx) / c.fx
        yn = (np.arange(c.height) - c.cy) / c.fy
        self.col_norm = np.sqrt(1.0 + xn ** 2)             # horizontal length of ray (xn, yn, 1)
        self.col_azimuth = np.arctan2(-xn, 1.0)            # image right is clockwise
        g = (yn[:, None] / self.col_norm[None, :])         # drop per metre of horizontal travel
        self.drop = g.astype(np.float32)
        with np.errstate(divide='ignore'):
            s_fc = np.where(g > 0, self.height / g, (self.height - self.scene.height) / g)
        s_fc = np.minimum(np.where(np.isfinite(s_fc), s_fc, _FAR), _FAR)
        self.s_floor_ceiling = s_fc.astype(np.float32)
        # Footprint on floor/ceiling: distance / (f * cos(incidence)), in texels.
        n2 = 1.0 + xn[None, :] ** 2 + yn[:, None] ** 2
        with np.errstate(divide='ignore'):
            footprint = s_fc * n2 / (self.col_norm[None, :] * np.abs(yn[:, None]) * c.fx)
        self.level_floor_ceiling = self._level(footprint).astype(np.float32)
        a, sc = self.atlas, self.scene
        D = a.texels_per_m
        is_floor = g > 0
        self.fc_x0 = np.where(is_floor, a.offset_x[sc.FLOOR], a.offset_x[sc.CEILING]) - D * sc.x0
        self.fc_y0 = np.where(is_floor, a.offset_y[sc.FLOOR], a.offset_y[sc.CEILING]) - D * sc.y0
        self.fc_x0 = self.fc_x0.astype(np.float32)
        self.fc_y0 = self.fc_y0.astype(np.float32)
        self.D_s_fc = (D * self.s_floor_ceiling).astype(np.float32)
        self.rows = np.arange(c.height, dtype=np.float32)[:, None]
        self.col_map = np.broadcast_to(np.arange(c.width, dtype=np.float32)[None, :],
                                       (c.height, c.width)).copy()

    def _prepare_tables(self):
        sc = self.scene
        b = np.array([[bx.x0, bx.x1, bx.y0, bx.y1, min(bx.height, sc.height)]
                      for bx in sc.boxes]).reshape(-1, 5)
        self.box_x0, self.box_x1, self.box_y0, self.box_y1, self.box_h = (
            b[:, i:i + 1] for i in range(5))
        self.face_height = np.array([f.height for f in sc.faces])

    def _level(self, footprint_m):
        with np.errstate(divide='ignore'):
            lvl = np.log2(np.maximum(footprint_m * self.atlas.texels_per_m, 1e-9))
        return np.clip(lvl, 0.0, self.atlas.max_level)

    # --- per frame ------------------------------------------------------------------------

    def render(self, x, y, yaw) -> np.ndarray:
        """mono8 image seen by this camera with the robot's base_link at (x, y, yaw)."""
        c, s = np.cos(yaw), np.sin(yaw)
        px = x + c * self.mount_xy[0] - s * self.mount_xy[1]
        py = y + s * self.mount_xy[0] + c * self.mount_xy[1]
        theta = yaw + self.mount_yaw + self.col_azimuth
        dx, dy = np.cos(theta), np.sin(theta)
        table = self._column_table(px, py, dx, dy)
        winner = self._paint_boxes(table)
        image = self._texture(px, py, dx, dy, table, winner)
        if self._distortion_map is not None:
            image = cv2.remap(image, *self._distortion_map, cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
        return image

    def _column_table(self, px, py, dx, dy):
        """Per column, the boxes hit (entry distance and face) and the wall behind them.
        Rows: boxes hit by at least one column, then the wall."""
        sc, a = self.scene, self.atlas
        with np.errstate(divide='ignore', invalid='ignore'):
            inv_dx, inv_dy = 1.0 / dx, 1.0 / dy
            tx = np.where(dx > 0, (sc.x1 - px) * inv_dx, (sc.x0 - px) * inv_dx)
            ty = np.where(dy > 0, (sc.y1 - py) * inv_dy, (sc.y0 - py) * inv_dy)
            tx = np.where(np.isfinite(tx), tx, _FAR)
            ty = np.where(np.isfinite(ty), ty, _FAR)
            wall_x = tx < ty
            s_wall = np.minimum(tx, ty)
            wall_face = np.where(wall_x, np.where(dx > 0, sc.EAST, sc.WEST),
                                 np.where(dy > 0, sc.NORTH, sc.SOUTH))
            wall_u = np.where(wall_x, py + s_wall * dy - sc.y0, px + s_wall * dx - sc.x0)
            wall_cos = np.where(wall_x, np.abs(dx), np.abs(dy))

            t1, t2 = (self.box_x0 - px) * inv_dx, (self.box_x1 - px) * inv_dx
            t3, t4 = (self.box_y0 - py) * inv_dy, (self.box_y1 - py) * inv_dy
            txn, txf = np.minimum(t1, t2), np.maximum(t1, t2)
            tyn, tyf = np.minimum(t3, t4), np.maximum(t3, t4)
            # A ray parallel to a slab is inside it for all t or never.
            inside_x = (self.box_x0 < px) & (px < self.box_x1)
            inside_y = (self.box_y0 < py) & (py < self.box_y1)
            txn = np.where(np.isnan(txn), np.where(inside_x, -np.inf, np.inf), txn)
            txf = np.where(np.isnan(txf), np.where(inside_x, np.inf, -np.inf), txf)
            tyn = np.where(np.isnan(tyn), np.where(inside_y, -np.inf, np.inf), tyn)
            tyf = np.where(np.isnan(tyf), np.where(inside_y, np.inf, -np.inf), tyf)
        s_in = np.maximum(txn, tyn)
        hit = (s_in < np.minimum(txf, tyf)) & (s_in > 1e-6) & (s_in < s_wall[None, :])
        used = np.flatnonzero(hit.any(axis=1))
        s_in, hit = s_in[used], hit[used]
        txn, tyn = txn[used], tyn[used]
        entered_x = txn > tyn
        side = np.where(entered_x, np.where(dx > 0, 0, 1), np.where(dy > 0, 2, 3))
        face = 6 + 4 * used[:, None] + side
        s_safe = np.where(hit, s_in, 0.0)
        box_u = np.where(entered_x, py + s_safe * dy - self.box_y0[used],
                         px + s_safe * dx - self.box_x0[used])
        box_cos = np.where(entered_x, np.abs(dx), np.abs(dy))

        s_all = np.vstack([np.where(hit, s_in, np.inf), s_wall[None, :]])
        face_all = np.vstack([face, wall_face[None, :]])
        u_all = np.vstack([box_u, wall_u[None, :]])
        cos_all = np.maximum(np.vstack([box_cos, wall_cos[None, :]]), 0.05)
        s_finite = np.where(np.isfinite(s_all), s_all, 0.0)
        D = a.texels_per_m
        table = np.empty(s_all.shape + (4,), np.float32)
        table[..., 0] = a.offset_x[face_all] + D * u_all
        table[..., 1] = a.offset_y[face_all] + D * (self.face_height[face_all] - self.height)
        table[..., 2] = D * s_finite
        table[..., 3] = self._level(s_finite / (cos_all * self.fx))
        # Rows covered by each box: floor level (bottom) up to the box top, at entry distance.
        with np.errstate(divide='ignore'):
            scale = self.fy * self.col_norm[None, :] / s_in
        top = np.where(hit, self.cy + scale * (self.height - self.box_h[used]), np.inf)
        bottom = np.where(hit, self.cy + scale * self.height, -np.inf)
        return {'table': table, 's': s_all, 'top': top, 'bottom': bottom, 'n_boxes': len(used),
                's_wall': s_wall}

    def _paint_boxes(self, t):
        """Row of the column table (as float32, for cv2.remap) of the surface each pixel
        sees: boxes painted far to near over the wall/floor/ceiling row."""
        n = t['n_boxes']
        winner = np.full((self.height_px, self.width), n, np.float32)
        if n == 0:
            return winner
        order = np.argsort(-t['s'][:n], axis=0)   # misses (inf) first, then far to near
        hits_per_column = np.isfinite(t['s'][:n]).sum(axis=0)
        for rank in range(n - int(hits_per_column.max()), n):
            idx = order[rank:rank + 1]
            top = np.take_along_axis(t['top'], idx, axis=0).astype(np.float32)
            bottom = np.take_along_axis(t['bottom'], idx, axis=0).astype(np.float32)
            covered = (self.rows >= top) & (self.rows <= bottom)
            np.copyto(winner, np.broadcast_to(idx.astype(np.float32), winner.shape), where=covered)
        return winner

    def _texture(self, px, py, dx, dy, t, winner):
        # Gather each pixel's column-table entry with a nearest-neighbour remap (fast, SIMD).
        picked = cv2.remap(t['table'], self.col_map, winner, cv2.INTER_NEAREST)
        D = self.atlas.texels_per_m
        n = t['n_boxes']
        on_floor_or_ceiling = (winner == n) & (self.s_floor_ceiling < t['s_wall'][None, :])
        dx32, dy32 = dx.astype(np.float32)[None, :], dy.astype(np.float32)[None, :]
        map_x = np.where(on_floor_or_ceiling, self.fc_x0 + np.float32(D * px) + self.D_s_fc * dx32,
                         picked[..., 0])
        map_y = np.where(on_floor_or_ceiling, self.fc_y0 + np.float32(D * py) + self.D_s_fc * dy32,
                         picked[..., 1] + self.drop * picked[..., 2])
        level = np.where(on_floor_or_ceiling, self.level_floor_ceiling, picked[..., 3])
        levels = cv2.remap(self.atlas.image, map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
        return blend_levels(levels, level)


def blend_levels(levels: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation across the prefiltered levels at each pixel's level."""
    f = levels.astype(np.float32)
    out = f[..., 0].copy()
    for k in range(1, levels.shape[2]):
        weight = np.clip(level - np.float32(k - 1), np.float32(0), np.float32(1))
        out += weight * (f[..., k] - f[..., k - 1])
    out += np.float32(0.5)
    return out.astype(np.uint8)
