"""Synthetic indoor scenes: a room (floor, walls, ceiling), furniture-like boxes and wall pictures.

A scene is a list of one-sided textured rectangles. The world frame has z up; the room spans
``[0, Lx] x [0, Ly] x [0, Lz]``. Each scene also says where an arm may move the camera
(``workspace_centre``, ``workspace_radius``: free space, well clear of boxes and walls) and which way
there is something to look at (``look_yaw``: towards the room's far side).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nocal_ros.data.textures import texture_bank


@dataclass
class Rectangle:
    """A one-sided textured rectangle ``corner + a * edge_u + b * edge_v``, ``a, b`` in [0, 1].

    Visible from the side its normal ``edge_u x edge_v`` points to. ``edge_u`` and ``edge_v`` must be
    perpendicular. The texture repeats every ``repeat`` metres along both edges; ``gain`` is a fixed
    RGB factor (tint and view-independent shading), so a surface looks the same from every view.
    """

    corner: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: int
    repeat: float = 1.0
    offset: tuple[float, float] = (0.0, 0.0)
    gain: np.ndarray = field(default_factory=lambda: np.ones(3))

    def __post_init__(self) -> None:
        self.corner, self.edge_u, self.edge_v = (np.asarray(v, dtype=np.float64) for v in (self.corner, self.edge_u, self.edge_v))
        self.gain = np.asarray(self.gain, dtype=np.float64).reshape(3)
        if abs(np.dot(self.edge_u, self.edge_v)) > 1e-9 * np.linalg.norm(self.edge_u) * np.linalg.norm(self.edge_v):
            raise ValueError("rectangle edges must be perpendicular")

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n)

    @classmethod
    def centred(cls, centre, half_u, half_v, **kwargs) -> "Rectangle":
        """Rectangle from its centre and half-edge vectors (normal = ``half_u x half_v``)."""
        centre, half_u, half_v = (np.asarray(v, dtype=np.float64) for v in (centre, half_u, half_v))
        return cls(centre - half_u - half_v, 2 * half_u, 2 * half_v, **kwargs)


@dataclass
class Scene:
    """Rectangles plus the textures they index, and where a camera can go in it."""

    rectangles: list[Rectangle]
    textures: np.ndarray  # (T, S, S, 3) float32 in [0, 1]
    room_size: np.ndarray = field(default_factory=lambda: np.array([6.0, 5.0, 3.0]))
    workspace_centre: np.ndarray = field(default_factory=lambda: np.array([3.0, 2.5, 1.3]))
    workspace_radius: float = 0.35
    look_yaw: float = 0.0
    name: str = ""


def box_faces(centre_xy, yaw: float, size, rng: np.random.Generator, textures: list[int]) -> list[Rectangle]:
    """The five visible faces (no bottom) of a box standing on the floor, outward normals."""
    sx, sy, sz = (s / 2 for s in size)
    c, s = np.cos(yaw), np.sin(yaw)
    ex, ey, ez = np.array([c, s, 0.0]), np.array([-s, c, 0.0]), np.array([0.0, 0.0, 1.0])
    centre = np.array([centre_xy[0], centre_xy[1], sz])
    faces = [
        (centre + sz * ez, sx * ex, sy * ey),  # top: ex x ey = +z
        (centre + sx * ex, sy * ey, sz * ez),  # +x side: ey x ez = +ex
        (centre - sx * ex, sz * ez, sy * ey),  # -x side
        (centre + sy * ey, sz * ez, sx * ex),  # +y side: ez x ex = +ey
        (centre - sy * ey, sx * ex, sz * ez),  # -y side
    ]
    texture = int(rng.choice(textures))
    repeat = float(rng.uniform(0.3, 0.9))
    tint = rng.uniform(0.75, 1.0, 3)
    rectangles = []
    for index, (face_centre, half_u, half_v) in enumerate(faces):
        # fixed per-face shading, as from a light above: tops brightest; sides differ by orientation
        shade = 1.0 if index == 0 else 0.62 + 0.25 * (0.5 + 0.5 * np.dot(np.cross(half_u, half_v) / np.linalg.norm(np.cross(half_u, half_v)), [0.6, 0.8, 0]))
        rectangles.append(
            Rectangle.centred(face_centre, half_u, half_v, texture=texture, repeat=repeat,
                              offset=tuple(rng.uniform(0, 1, 2)), gain=tint * shade)
        )
    return rectangles


def random_room(seed: int | np.random.Generator, split: str = "train", num_boxes: int = 8,
                num_pictures: int = 4) -> Scene:
    """A randomised room for ``seed``, textured from the ``split`` bank (train and test are disjoint).

    About ``6 + 5 * num_boxes + num_pictures`` rectangles (50 by default). The workspace of the arm is
    kept 1 m from walls and ~0.8 m clear of boxes, so the camera never sits against a surface.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    bank, _ = texture_bank(split)
    # Pick the scene's own textures from the bank (and keep them contiguous for the renderer).
    chosen = rng.choice(len(bank), size=min(14, len(bank)), replace=False)
    textures = np.ascontiguousarray(bank[np.sort(chosen)])
    ids = list(range(len(textures)))
    lx, ly, lz = rng.uniform(4.5, 8.0), rng.uniform(4.0, 7.0), rng.uniform(2.5, 3.2)
    room = np.array([lx, ly, lz])

    def surface_kwargs(shade: float) -> dict:
        return dict(texture=int(rng.choice(ids)), repeat=float(rng.uniform(0.5, 1.4)),
                    offset=tuple(rng.uniform(0, 1, 2)), gain=rng.uniform(0.8, 1.0, 3) * shade)

    X, Y, Z = np.eye(3)
    rectangles = [
        Rectangle([0, 0, 0], lx * X, ly * Y, **surface_kwargs(0.85)),  # floor, normal +z
        Rectangle([0, 0, lz], ly * Y, lx * X, **surface_kwargs(0.95)),  # ceiling, normal -z
        Rectangle([0, 0, 0], ly * Y, lz * Z, **surface_kwargs(0.9)),  # x = 0 wall, normal +x
        Rectangle([lx, 0, 0], lz * Z, ly * Y, **surface_kwargs(0.8)),  # x = lx wall, normal -x
        Rectangle([0, 0, 0], lz * Z, lx * X, **surface_kwargs(0.75)),  # y = 0 wall, normal +y
        Rectangle([0, ly, 0], lx * X, lz * Z, **surface_kwargs(0.7)),  # y = ly wall, normal -y
    ]

    workspace_radius = 0.35
    centre = np.array([rng.uniform(1.0 + workspace_radius, lx - 1.0 - workspace_radius),
                       rng.uniform(1.0 + workspace_radius, ly - 1.0 - workspace_radius),
                       rng.uniform(1.1, 1.6)])
    # Look towards the farther half of the room so the view has depth.
    to_centre = room[:2] / 2 - centre[:2]
    look_yaw = float(np.arctan2(to_centre[1], to_centre[0])) if np.linalg.norm(to_centre) > 0.3 else float(rng.uniform(-np.pi, np.pi))

    placed = 0
    for _ in range(200):
        if placed == num_boxes:
            break
        size = np.array([rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.9)])
        footprint = 0.5 * np.hypot(size[0], size[1])
        xy = np.array([rng.uniform(footprint, lx - footprint), rng.uniform(footprint, ly - footprint)])
        if np.linalg.norm(xy - centre[:2]) < footprint + workspace_radius + 0.8:
            continue
        rectangles += box_faces(xy, float(rng.uniform(0, np.pi)), size, rng, ids)
        placed += 1

    walls = [(np.array([0.01, 0, 0]), Y, Z, ly), (np.array([lx - 0.01, 0, 0]), Z, Y, ly),
             (np.array([0, 0.01, 0]), Z, X, lx), (np.array([0, ly - 0.01, 0]), X, Z, lx)]
    for _ in range(num_pictures):
        origin, a, b, _ = walls[int(rng.integers(4))]
        along = a if a[2] == 0 else b  # the horizontal edge direction of this wall
        length = lx if along[0] else ly
        width, height = rng.uniform(0.4, 1.4), rng.uniform(0.3, 1.0)
        centre_pic = origin + along * rng.uniform(width / 2 + 0.1, length - width / 2 - 0.1) + Z * rng.uniform(0.9, lz - 0.6)
        half_a = a * (width / 2 if a is along else height / 2)
        half_b = b * (width / 2 if b is along else height / 2)
        rectangles.append(Rectangle.centred(centre_pic, half_a, half_b, texture=int(rng.choice(ids)),
                                            repeat=float(max(width, height)), offset=(0.0, 0.0),
                                            gain=rng.uniform(0.85, 1.0, 3)))
    return Scene(rectangles, textures, room, centre, workspace_radius, look_yaw, name=f"room({split})")
