"""Scene tables (one camera, one light) and a cube's OBJ, as the scene tests parse them."""

from __future__ import annotations

import numpy as np


def scene_table(**over):
    table = {
        "geometry": "sphere",
        "cameras": [
            {"origin": [0, -3, 0], "target": [0, 0, 0], "fov_x_deg": 40, "width": 8, "height": 8}
        ],
        "lights": [
            {
                "center": [2, -2, 2],
                "target": [0, 0, 0],
                "size": [0.5, 0.2],
                "power": 10.0,
                "temperature": 3200,
            }
        ],
    }
    table.update(over)
    return table


def one_camera(**keys) -> dict:
    """A scene table's cameras: one camera of `keys`."""
    return {"cameras": [keys]}


def calibrated(**extra) -> dict:
    """A scene table with one 8x6 perspective camera, plus `extra` camera keys."""
    return one_camera(fov_x_deg=40, origin=[0, -4, 0], target=[0, 0, 0], width=8, height=6, **extra)


# A cube of side 2 about `offset`: 8 shared vertices, 6 quads wound outward (counter-clockwise
# seen from outside).
CUBE_FACES = [
    (1, 2, 4, 3),  # -z ... each listed as 1-based indices of the corners below
    (5, 7, 8, 6),
    (1, 5, 6, 2),
    (3, 4, 8, 7),
    (1, 3, 7, 5),
    (2, 6, 8, 4),
]


def cube_obj(path, offset=(0.0, 0.0, 0.0), flip=(), normals=False):
    corners = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    lines = [f"v {x + offset[0]} {y + offset[1]} {z + offset[2]}" for x, y, z in corners]
    faces = [f[::-1] if i in flip else f for i, f in enumerate(CUBE_FACES)]
    if normals:  # one normal per face, its corners pointing at it
        for f in faces:
            n = np.sign(np.sum([corners[i - 1] for i in f], axis=0)).astype(int)
            lines.append(f"vn {n[0]} {n[1]} {n[2]}")
        lines += [f"f {' '.join(f'{i}//{k}' for i in f)}" for k, f in enumerate(faces, 1)]
    else:
        lines += [f"f {' '.join(map(str, f))}" for f in faces]
    path.write_text("\n".join(lines) + "\n")
    return path
