"""Which part of the image a quarter owns, and the crop it reads (owned part + KLT margin).

Quarters: 1 top-left, 2 top-right, 3 bottom-left, 4 bottom-right (paper Fig. 4). A track is
owned by the quarter its point is in; one that moves out is dropped here and re-extracted by
the neighbour, so no two quarters report the same feature. The margin lets the KLT window
and pyramid see pixels just across the border.
"""
from dataclasses import dataclass

import numpy as np

from multicam_ego_motion.errors import UserError


@dataclass(frozen=True)
class QuarterRegion:
    quarter: int
    x0: int          # owned rectangle [x0, x1) x [y0, y1), full-image pixels
    y0: int
    x1: int
    y1: int
    cx0: int         # crop rectangle (owned + margin, clipped to the image)
    cy0: int
    cx1: int
    cy1: int

    @classmethod
    def of(cls, quarter: int, width: int, height: int, margin: int) -> 'QuarterRegion':
        if quarter not in (1, 2, 3, 4):
            raise UserError(f'quarter must be 1..4 (1 top-left .. 4 bottom-right), got {quarter}')
        if width < 4 or height < 4:
            raise UserError(f'image {width}x{height} is too small to split into quarters')
        hw, hh = width // 2, height // 2
        col, row = (quarter - 1) % 2, (quarter - 1) // 2
        x0, x1 = (0, hw) if col == 0 else (hw, width)
        y0, y1 = (0, hh) if row == 0 else (hh, height)
        m = max(0, int(margin))
        return cls(quarter, x0, y0, x1, y1,
                   max(0, x0 - m), max(0, y0 - m), min(width, x1 + m), min(height, y1 + m))

    @property
    def offset(self) -> np.ndarray:
        """Full-image pixel of crop pixel (0, 0)."""
        return np.array([self.cx0, self.cy0], dtype=np.float32)

    @property
    def size(self):
        return self.x1 - self.x0, self.y1 - self.y0

    def crop(self, gray: np.ndarray) -> np.ndarray:
        return gray[self.cy0:self.cy1, self.cx0:self.cx1]

    def owns(self, px: np.ndarray) -> np.ndarray:
        """Boolean per full-image pixel row of Nx2: inside the owned rectangle."""
        px = np.asarray(px).reshape(-1, 2)
        return ((px[:, 0] >= self.x0) & (px[:, 0] < self.x1)
                & (px[:, 1] >= self.y0) & (px[:, 1] < self.y1))
