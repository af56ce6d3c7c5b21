"""The indoor worlds: an axis-aligned room (floor, ceiling, four walls) with boxes and pillars.

Every box stands on the floor and is at least as tall as the cameras (0.5 m), so its top is
never visible and the renderer only meets vertical faces, the floor and the ceiling.
World frame: x east, y north, z up; metres.
"""
from dataclasses import dataclass, field
from typing import List, Tuple

CAMERA_HEIGHT = 0.5


@dataclass(frozen=True)
class Box:
    x0: float
    x1: float
    y0: float
    y1: float
    height: float


@dataclass
class Face:
    """A textured rectangle of the world, `width` x `height` metres of texture."""
    name: str
    width: float
    height: float
    bare_spans: Tuple[Tuple[float, float], ...] = ()   # [u0, u1] ranges (m) left nearly bare
    bare_rect: Tuple[float, float, float, float] = ()   # (u0, u1, v0, v1) left nearly bare


@dataclass
class Scene:
    x0: float
    x1: float
    y0: float
    y1: float
    height: float
    boxes: List[Box] = field(default_factory=list)
    bare_north_wall: Tuple[float, float] = ()   # x range of the north wall left bare
    faces: List[Face] = field(default_factory=list)

    # Face order: floor, ceiling, walls east/west/north/south, then 4 faces per box
    # (west, east, south, north).
    FLOOR, CEILING, EAST, WEST, NORTH, SOUTH = range(6)

    def __post_init__(self):
        w, d, h = self.x1 - self.x0, self.y1 - self.y0, self.height
        bare_wall = ((self.bare_north_wall[0] - self.x0, self.bare_north_wall[1] - self.x0),) \
            if self.bare_north_wall else ()
        # The floor strip in front of the bare wall is bare too, so that the bottom of a
        # camera image looking at the wall has no texture either.
        bare_floor = (bare_wall[0][0], bare_wall[0][1], d - 1.6, d) if bare_wall else ()
        self.faces = [Face('floor', w, d, bare_rect=bare_floor), Face('ceiling', w, d),
                      Face('wall_east', d, h), Face('wall_west', d, h),
                      Face('wall_north', w, h, bare_spans=bare_wall), Face('wall_south', w, h)]
        for i, b in enumerate(self.boxes):
            if not (self.x0 < b.x0 < b.x1 < self.x1 and self.y0 < b.y0 < b.y1 < self.y1):
                raise ValueError(f'box {i} is not inside the room')
            if b.height < CAMERA_HEIGHT + 0.05:
                raise ValueError(f'box {i} is lower than the cameras')
            dx, dy, bh = b.x1 - b.x0, b.y1 - b.y0, min(b.height, self.height)
            self.faces += [Face(f'box{i}_west', dy, bh), Face(f'box{i}_east', dy, bh),
                           Face(f'box{i}_south', dx, bh), Face(f'box{i}_north', dx, bh)]

    def box_face(self, box_index: int, side: int) -> int:
        return 6 + 4 * box_index + side

    def contains_free_point(self, x, y, margin=0.3) -> bool:
        if not (self.x0 + margin < x < self.x1 - margin and self.y0 + margin < y < self.y1 - margin):
            return False
        return not any(b.x0 - margin < x < b.x1 + margin and b.y0 - margin < y < b.y1 + margin
                       for b in self.boxes)


def room(bare_stretch: bool = False) -> Scene:
    """14 m x 10 m x 3 m room. The loop (x in +-4.2, y in +-2.6) runs between a central
    group of pillars and boxes and the boxes along the walls, so objects are 1-6 m away."""
    boxes = [
        # Inside the loop.
        Box(-2.0, -1.6, -0.3, 0.1, 3.0),      # pillar
        Box(1.6, 2.0, -0.1, 0.3, 3.0),        # pillar
        Box(-0.6, 0.6, -0.9, -0.1, 1.0),      # crate
        Box(-0.3, 0.5, 0.6, 1.3, 1.6),        # tall crate
        Box(-3.0, -2.4, 0.8, 1.4, 0.8),
        Box(2.6, 3.1, -1.4, -0.8, 1.2),
        # Along the south wall.
        Box(-5.0, -3.8, -4.9, -4.1, 1.2),
        Box(-1.2, 0.2, -4.9, -4.3, 0.7),
        Box(2.5, 3.3, -4.8, -4.0, 1.9),
        # Along the east and west walls.
        Box(5.8, 6.8, -3.0, -1.8, 1.0),
        Box(6.2, 6.8, 0.5, 2.0, 2.2),
        Box(-6.8, -6.0, -1.0, 0.4, 1.4),
        Box(-6.9, -6.3, 2.2, 2.8, 3.0),       # pillar near the wall
        # Along the north wall, clear of the bare_wall drive (y = 3.6).
        Box(-6.9, -6.4, 4.4, 4.9, 1.1),
        Box(4.3, 5.3, 4.4, 4.9, 1.5),
    ]
    return Scene(-7.0, 7.0, -5.0, 5.0, 3.0, boxes,
                 bare_north_wall=(-3.0, 1.0) if bare_stretch else ())


def corridor() -> Scene:
    """34 m x 5 m x 3 m corridor with cabinets and pillars along both sides."""
    boxes = []
    for k, x in enumerate(range(-14, 16, 4)):
        depth = 0.4 + 0.2 * (k % 3)
        height = (1.0, 2.2, 0.8, 3.0)[k % 4]
        boxes.append(Box(x - 0.5, x + 0.5 + 0.3 * (k % 2), 2.45 - depth, 2.45, height))
        boxes.append(Box(x + 1.2, x + 2.0, -2.45, -2.45 + 0.3 + 0.2 * ((k + 1) % 3),
                         (1.4, 0.9, 3.0, 1.8)[k % 4]))
    return Scene(-17.0, 17.0, -2.5, 2.5, 3.0, boxes)


def scene_for(scenario: str) -> Scene:
    if scenario == 'corridor':
        return corridor()
    return room(bare_stretch=(scenario == 'bare_wall'))
