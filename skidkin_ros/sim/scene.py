"""An analytic 3D scene for the simulated lidar: ground, room walls, boxes, pillars and trees.

Every primitive has a vectorized ray intersection (numpy only): rays are origins (N, 3) and unit
directions (N, 3); each primitive returns the distance along each ray to its first hit (inf when
missed). The scene is the minimum over its primitives. Coordinates are the world frame of the
simulator (z up, the ground at z = 0).

Scenes (:data:`SCENE_NAMES`): :func:`default_scene`, a walled courtyard with boxes and pillars
(indoor-like); :func:`outdoor_scene`, an open field with a few hundred trees at random (a trunk
and a crown each) and nothing else, the kind of scan a robot sees in a forest clearing; the
same field with a few dozen trees over a larger area (``snowfield``: most returns are flat
ground, a tree every 10-20 m); and an open plain with a handful of far posts (``plain``: the
planar position is barely observable, a scene hard for ICP). The
cylinders are intersected all at once (one vectorized pass over every ray/cylinder pair whose
azimuth points at the cylinder), so a field of 800 cylinders casts a sweep in milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ['Box', 'Cylinder', 'Field', 'Room', 'Scene', 'SCENE_NAMES', 'default_scene',
           'make_scene', 'outdoor_scene', 'plain_scene', 'snowfield_scene']

# Rays closer than this to parallel with a face are treated as missing it.
_PARALLEL_EPS = 1e-12
# A hit closer than this to the origin is ignored (the sensor's own housing).
_MIN_HIT_M = 1e-6


def _plane_distance(target, start: np.ndarray, d: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """Return (target - start) / d where the ray faces the plane and hits ahead, else inf."""
    safe_d = np.where(facing, d, 1.0)
    t = (target - start) / safe_d
    return np.where(facing & (t > _MIN_HIT_M), t, np.inf)


def _safe_inverse(d: np.ndarray) -> np.ndarray:
    with np.errstate(divide='ignore'):
        return np.where(np.abs(d) < _PARALLEL_EPS, np.copysign(np.inf, d) * 1.0, 1.0 / d)


@dataclass(frozen=True)
class Box:
    """Axis-aligned solid box [lo, hi] (m), hit from the outside."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    def circle(self) -> tuple[float, float, float]:
        """Return the centre and radius of a circle around the footprint (m)."""
        return ((self.lo[0] + self.hi[0]) / 2, (self.lo[1] + self.hi[1]) / 2,
                float(np.hypot(self.hi[0] - self.lo[0], self.hi[1] - self.lo[1]) / 2))

    def intersect(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return the distance (m) to the box along each ray, inf when missed (slab method)."""
        inv = _safe_inverse(direction)
        lo = np.asarray(self.lo, dtype=float)
        hi = np.asarray(self.hi, dtype=float)
        with np.errstate(invalid='ignore'):
            t1 = (lo - origin) * inv
            t2 = (hi - origin) * inv
        t1 = np.nan_to_num(t1, nan=-np.inf)
        t2 = np.nan_to_num(t2, nan=np.inf)
        t_near = np.max(np.minimum(t1, t2), axis=-1)
        t_far = np.min(np.maximum(t1, t2), axis=-1)
        hit = (t_near <= t_far) & (t_near > _MIN_HIT_M)
        return np.where(hit, t_near, np.inf)


@dataclass(frozen=True)
class Cylinder:
    """Vertical solid cylinder (pillar, drum): centre (x, y), radius, z from z_lo to z_hi (m)."""

    x: float
    y: float
    radius: float
    z_lo: float
    z_hi: float

    def circle(self) -> tuple[float, float, float]:
        """Return the centre and radius of a circle around the footprint (m)."""
        return (self.x, self.y, self.radius)

    def intersect(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return the distance (m) to the mantle or the top/bottom caps, inf when missed."""
        n = origin.shape[0]
        return _cylinders_intersect(origin, direction, np.full(n, self.x), np.full(n, self.y),
                                    np.full(n, self.radius), np.full(n, self.z_lo),
                                    np.full(n, self.z_hi))


def _cylinders_intersect(origin: np.ndarray, direction: np.ndarray, cx: np.ndarray,
                         cy: np.ndarray, radius: np.ndarray, z_lo: np.ndarray,
                         z_hi: np.ndarray) -> np.ndarray:
    """Return the distance (m) from each ray to its own vertical cylinder (arrays per ray)."""
    ox = origin[:, 0] - cx
    oy = origin[:, 1] - cy
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    r2 = radius * radius
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - r2
    disc = b * b - 4.0 * a * c
    ok = (disc >= 0.0) & (a > _PARALLEL_EPS)
    root = np.sqrt(np.where(ok, disc, 0.0))
    safe_a = np.where(ok, a, 1.0)
    t_side = (-b - root) / (2.0 * safe_a)
    z_side = origin[:, 2] + t_side * dz
    side_hit = ok & (t_side > _MIN_HIT_M) & (z_side >= z_lo) & (z_side <= z_hi)
    best = np.where(side_hit, t_side, np.inf)
    vertical = np.abs(dz) > _PARALLEL_EPS
    for z_cap in (z_lo, z_hi):
        t_cap = _plane_distance(z_cap, origin[:, 2], dz, vertical)
        t_fin = np.where(np.isfinite(t_cap), t_cap, 0.0)
        px = ox + t_fin * dx
        py = oy + t_fin * dy
        cap_hit = np.isfinite(t_cap) & (px * px + py * py <= r2)
        best = np.minimum(best, np.where(cap_hit, t_cap, np.inf))
    return best


@dataclass(frozen=True)
class Room:
    """Ground plane z = 0 and the four walls of a rectangular room seen from inside (m).

    Walls are ``height`` tall; rays above them leave the room (open courtyard, no return).
    """

    x_lo: float
    x_hi: float
    y_lo: float
    y_hi: float
    height: float

    def intersect(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return the distance (m) to the ground or a wall, inf when the ray leaves the room."""
        dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
        t_ground = _plane_distance(np.zeros_like(dz), origin[:, 2], dz, dz < -_PARALLEL_EPS)
        t_x = np.minimum(_plane_distance(self.x_hi, origin[:, 0], dx, dx > _PARALLEL_EPS),
                         _plane_distance(self.x_lo, origin[:, 0], dx, dx < -_PARALLEL_EPS))
        t_y = np.minimum(_plane_distance(self.y_hi, origin[:, 1], dy, dy > _PARALLEL_EPS),
                         _plane_distance(self.y_lo, origin[:, 1], dy, dy < -_PARALLEL_EPS))
        t_wall = np.minimum(t_x, t_y)
        with np.errstate(invalid='ignore'):
            z_wall = origin[:, 2] + t_wall * dz
        t_wall = np.where(z_wall <= self.height, t_wall, np.inf)
        return np.minimum(t_ground, t_wall)


@dataclass(frozen=True)
class Field:
    """Open ground: the plane z = 0 and nothing else; the bounds only limit where one drives (m).

    Rays that do not point down leave the field (no return), as the sky does outdoors.
    """

    x_lo: float
    x_hi: float
    y_lo: float
    y_hi: float

    def intersect(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Return the distance (m) to the ground, inf for rays that do not point down."""
        dz = direction[:, 2]
        return _plane_distance(np.zeros_like(dz), origin[:, 2], dz, dz < -_PARALLEL_EPS)


@dataclass(frozen=True)
class Scene:
    """A room (or an open field) plus obstacles; ``cast`` returns the range of each ray's hit."""

    room: Room | Field
    boxes: tuple[Box, ...] = ()
    cylinders: tuple[Cylinder, ...] = ()

    def __post_init__(self) -> None:
        table = np.array([(c.x, c.y, c.radius, c.z_lo, c.z_hi) for c in self.cylinders],
                         dtype=float).reshape(-1, 5)
        # Cylinders on one axis (a trunk and its crown) are culled together, by their widest.
        centres, group = np.unique(table[:, :2], axis=0, return_inverse=True)
        order = np.argsort(group.ravel(), kind='stable')
        counts = np.bincount(group.ravel(), minlength=centres.shape[0])
        widest = np.zeros(centres.shape[0])
        np.maximum.at(widest, group.ravel(), table[:, 2])
        object.__setattr__(self, '_cylinder_table', table[order])
        object.__setattr__(self, '_axes', (centres, widest, counts,
                                           np.concatenate([[0], np.cumsum(counts)[:-1]])))

    def cast(self, origin: np.ndarray, direction: np.ndarray, group: int = 1) -> np.ndarray:
        """Return the distance (m) to the first surface along each ray (inf: no return).

        ``group``: rays come in runs of this length sharing origin and horizontal azimuth (the
        rings of one lidar column); obstacles are then tested only against the runs whose
        azimuth points at their bounding circle, which keeps a sweep fast.
        """
        origin = np.asarray(origin, dtype=float)
        direction = np.asarray(direction, dtype=float)
        best = self.room.intersect(origin, direction)
        if group < 1 or direction.shape[0] % group:
            raise ValueError(f'{direction.shape[0]} rays do not come in groups of {group}')
        head_origin = origin[::group]
        azimuth = np.arctan2(direction[::group, 1], direction[::group, 0])
        for primitive in self.boxes:
            heads = _heads_facing(head_origin, azimuth, *primitive.circle())
            if heads.size == 0:
                continue
            rays = (heads[:, None] * group + np.arange(group)[None, :]).ravel()
            hit = primitive.intersect(origin[rays], direction[rays])
            best[rays] = np.minimum(best[rays], hit)
        table = self._cylinder_table
        if table.shape[0]:
            centres, widest, counts, first = self._axes
            axis, heads = _pairs_facing(head_origin, azimuth, centres[:, 0], centres[:, 1],
                                        widest)
            per_pair = counts[axis]
            heads = np.repeat(heads, per_pair)
            which = (np.repeat(first[axis] - np.cumsum(per_pair) + per_pair, per_pair)
                     + np.arange(int(per_pair.sum())))
            if heads.size:
                rays = (heads[:, None] * group + np.arange(group)[None, :]).ravel()
                cyl = np.repeat(which, group)
                hit = _cylinders_intersect(origin[rays], direction[rays], table[cyl, 0],
                                           table[cyl, 1], table[cyl, 2], table[cyl, 3],
                                           table[cyl, 4])
                np.minimum.at(best, rays, hit)
        return best

    def inside(self, x: float, y: float, margin_m: float = 0.0) -> bool:
        """Tell whether (x, y) is in the room and clear of every obstacle by ``margin_m``."""
        room = self.room
        if not (room.x_lo + margin_m < x < room.x_hi - margin_m
                and room.y_lo + margin_m < y < room.y_hi - margin_m):
            return False
        for box in self.boxes:
            if box.lo[2] < 1.0 and (box.lo[0] - margin_m < x < box.hi[0] + margin_m
                                    and box.lo[1] - margin_m < y < box.hi[1] + margin_m):
                return False
        for cyl in self.cylinders:
            if cyl.z_lo < 1.0 and np.hypot(x - cyl.x, y - cyl.y) < cyl.radius + margin_m:
                return False
        return True


def _heads_facing(head_origin: np.ndarray, azimuth: np.ndarray, cx: float, cy: float,
                  radius: float) -> np.ndarray:
    """Return the indices of the ray groups whose azimuth points at a bounding circle."""
    _, heads = _pairs_facing(head_origin, azimuth, np.array([cx]), np.array([cy]),
                             np.array([radius]))
    return heads


def _pairs_facing(head_origin: np.ndarray, azimuth: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                  radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (circle, ray group) index pairs where the group's azimuth points at the circle.

    The rays of a group share their horizontal direction u, so their horizontal line passes
    within r of a centre c (seen from the origin o) when |u x (c - o)| <= r, ahead of the origin
    when u . (c - o) > -r. A small margin keeps the test conservative.
    """
    ux, uy = np.cos(azimuth)[None, :], np.sin(azimuth)[None, :]
    dx = cx[:, None] - head_origin[None, :, 0]
    dy = cy[:, None] - head_origin[None, :, 1]
    reach = radius[:, None] + 1e-6
    return np.nonzero((np.abs(ux * dy - uy * dx) <= reach) & (ux * dx + uy * dy > -reach))


def default_scene(half_size_m: float = 14.0, seed: int = 7) -> Scene:
    """Return a courtyard of 2 half_size_m square with pillars and boxes of varied sizes.

    Obstacles stand outside the central disc of radius half_size_m / 2 where the simulated robot
    drives, so the robot never drives through them; some boxes float (shelves, beams) to give
    the lidar structure at several heights. Deterministic for a given seed.
    """
    rng = np.random.default_rng(seed)
    h = float(half_size_m)
    room = Room(-h, h, -0.8 * h, 0.8 * h, 4.0)
    keep_out = 0.55 * h
    boxes = []
    cylinders = []
    while len(boxes) + len(cylinders) < 22:
        x, y = rng.uniform(-0.9 * h, 0.9 * h), rng.uniform(-0.72 * h, 0.72 * h)
        if np.hypot(x, y) < keep_out:
            continue
        if rng.random() < 0.45:
            cylinders.append(Cylinder(float(x), float(y), float(rng.uniform(0.15, 0.6)),
                                      0.0, float(rng.uniform(0.4, 3.5))))
        else:
            sx, sy = rng.uniform(0.3, 2.0, size=2)
            z_lo = 0.0 if rng.random() < 0.7 else float(rng.uniform(0.6, 1.5))
            z_hi = z_lo + float(rng.uniform(0.3, 2.5))
            boxes.append(Box((float(x - sx / 2), float(y - sy / 2), z_lo),
                             (float(x + sx / 2), float(y + sy / 2), z_hi)))
    return Scene(room, tuple(boxes), tuple(cylinders))


def outdoor_scene(clearing_radius_m: float = 7.7, field_half_m: float = 50.0,
                  n_trees: int = 400, seed: int = 11) -> Scene:
    """Return an open field (ground plane, no walls) with ``n_trees`` trees at random.

    Each tree is a trunk (radius 0.1-0.3 m, 1.5-4 m tall) and a crown (radius 0.8-2.5 m, 2-8 m
    tall, starting where the trunk ends). Trees stand in the square of half side
    ``field_half_m`` outside the central clearing of radius ``clearing_radius_m`` where the
    robot drives; the upper rings of a VLP-16-like lidar find crowns within a few tens of
    metres, the lower rings the ground. Deterministic for a given seed.
    """
    rng = np.random.default_rng(seed)
    half = float(field_half_m)
    cylinders: list[Cylinder] = []
    while len(cylinders) < 2 * n_trees:
        x, y = rng.uniform(-half, half, size=2)
        if np.hypot(x, y) < clearing_radius_m:
            continue
        trunk_r = float(rng.uniform(0.1, 0.3))
        trunk_h = float(rng.uniform(1.5, 4.0))
        crown_r = float(rng.uniform(0.8, 2.5))
        crown_h = float(rng.uniform(2.0, 8.0))
        cylinders.append(Cylinder(float(x), float(y), trunk_r, 0.0, trunk_h))
        cylinders.append(Cylinder(float(x), float(y), crown_r, trunk_h, trunk_h + crown_h))
    return Scene(Field(-half, half, -half, half), (), tuple(cylinders))


def snowfield_scene(clearing_radius_m: float = 7.7, seed: int = 13) -> Scene:
    """Return a sparse snow field: flat ground and scattered trees, about one per 50 m2.

    The field reaches 40 m beyond the driving disc; trees (as in :func:`outdoor_scene`) stand
    outside the disc, so most of a 16-ring scan is flat ground and a few trunks and crowns
    within 20-40 m carry the planar position. Deterministic for a given seed.
    """
    half = float(clearing_radius_m) + 40.0
    n_trees = int(round((2 * half) ** 2 / 50.0))
    return outdoor_scene(clearing_radius_m, half, n_trees, seed)


def plain_scene(clearing_radius_m: float = 7.7, seed: int = 17) -> Scene:
    """Return an open plain: flat ground and six thin posts 25-45 m from the centre.

    Hard for ICP: the ground fixes height, roll and pitch but not the planar position, which
    rests on a few dozen points of distant posts; kiss-icp may slide or stall here, and the
    guard's degeneracy test is meant to say so. Deterministic for a given seed.
    """
    rng = np.random.default_rng(seed)
    half = float(clearing_radius_m) + 45.0
    cylinders = []
    for k in range(6):
        angle = 2 * np.pi * k / 6 + float(rng.uniform(-0.4, 0.4))
        radius = float(clearing_radius_m) + float(rng.uniform(20.0, 40.0))
        cylinders.append(Cylinder(radius * float(np.cos(angle)), radius * float(np.sin(angle)),
                                  float(rng.uniform(0.1, 0.25)), 0.0,
                                  float(rng.uniform(2.0, 5.0))))
    return Scene(Field(-half, half, -half, half), (), tuple(cylinders))


# Scenes by name (SimConfig.scene): each takes the half size of the scene's driving area.
SCENE_NAMES: tuple[str, ...] = ('courtyard', 'forest', 'snowfield', 'plain')


def make_scene(name: str, half_size_m: float) -> Scene:
    """Return the named scene; the robot's obstacle-free disc has radius 0.55 half_size_m."""
    if name == 'courtyard':
        return default_scene(half_size_m)
    if name == 'forest':
        return outdoor_scene(clearing_radius_m=0.55 * half_size_m)
    if name == 'snowfield':
        return snowfield_scene(clearing_radius_m=0.55 * half_size_m)
    if name == 'plain':
        return plain_scene(clearing_radius_m=0.55 * half_size_m)
    raise ValueError(f'unknown scene {name!r}; expected one of {SCENE_NAMES}')
