"""Geometry without a renderer: the procedural cup mesh (numpy) and OBJ checks.

The cup is a body of revolution (outer wall, rounded rim, inner wall, base, with fillets, so its
profile and normals are smooth) plus a handle swept along a half ellipse. UVs: the body's `u` runs
around the axis (0 to 1, seam duplicated so textures and masks tile), `v` along the profile from the
outer base centre (0) over the rim to the inner base centre (1); the handle's UVs lie in the outer
wall's band of `v`.
"""

from __future__ import annotations

from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import CaptureError
from .files import require_utf8


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh: positions (N, 3), faces (M, 3) int, normals (N, 3), uvs (N, 2)."""

    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray

    @staticmethod
    def concatenate(*parts: MeshData) -> MeshData:
        offsets = np.cumsum([0] + [len(p.positions) for p in parts[:-1]])
        return MeshData(
            np.concatenate([p.positions for p in parts]),
            np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
            np.concatenate([p.normals for p in parts]),
            np.concatenate([p.uvs for p in parts]),
        )


@dataclass(frozen=True)
class CupShape:
    """Dimensions of the procedural cup, in metres (a 300 ml mug by default)."""

    height: float = 0.095
    radius_top: float = 0.041
    radius_bottom: float = 0.034
    wall: float = 0.0045
    base: float = 0.007
    fillet: float = 0.004
    handle: bool = True
    segments: int = 128

    def __post_init__(self):
        if not 0 < self.wall < min(self.radius_top, self.radius_bottom) / 2:
            raise ValueError(f"cup: wall = {self.wall} must be in (0, radius / 2)")
        if not 0 < self.fillet < self.radius_bottom - self.wall:
            raise ValueError(f"cup: fillet = {self.fillet} must be in (0, radius_bottom - wall)")
        if not self.wall < self.base < self.height / 2:
            raise ValueError(f"cup: base = {self.base} must be in (wall, height / 2)")
        if self.segments < 8:
            raise ValueError(f"cup: segments = {self.segments} must be >= 8")


def _arc(center, radius, start, stop, n):
    angles = np.linspace(start, stop, n)
    return np.stack([center[0] + radius * np.cos(angles), center[1] + radius * np.sin(angles)], 1)


def _line(a, b, n):
    return np.linspace(a, b, n)


def cup_profile(shape: CupShape) -> np.ndarray:
    """(r, z) points of the cup's cross-section: a G1-continuous polyline from the outer base
    centre, out, up the outer wall, over the rounded rim, down the inner wall, to the inner base
    centre. Fillets join the base and the walls."""
    s, f, t = shape, shape.fillet, shape.wall
    wall = np.arctan2(s.height, s.radius_top - s.radius_bottom)  # direction of the walls
    out = wall - np.pi / 2  # outward normal angle of the walls
    n_out = np.array([np.cos(out), np.sin(out)])

    def fillet_centre(point_on_wall, z):
        """Centre at height z, distance f inside the wall line through `point_on_wall`."""
        return np.array(
            [point_on_wall[0] + ((z - point_on_wall[1]) * np.cos(wall) - f) / np.sin(wall), z]
        )

    top_out = np.array([s.radius_top, s.height])
    top_in = top_out - t * n_out
    foot = _arc(fillet_centre(top_out, f), f, -np.pi / 2, out, 8)
    rim = _arc(top_out - t / 2 * n_out, t / 2, out, out + np.pi, 16)
    inner_foot = _arc(fillet_centre(top_in, s.base + f), f, out, -np.pi / 2, 8)
    return np.concatenate(
        [
            _line([0.0, 0.0], foot[0], 12)[:-1],
            foot,
            _line(foot[-1], top_out, 40)[1:-1],
            rim,
            _line(top_in, inner_foot[0], 40)[1:-1],
            inner_foot,
            _line(inner_foot[-1], [0.0, s.base], 12)[1:],
        ]
    )


def _revolve(profile: np.ndarray, segments: int) -> MeshData:
    """Revolve an (r, z) polyline around z; normals from the profile's tangents."""
    tangent = np.gradient(profile, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal2d = np.stack([tangent[:, 1], -tangent[:, 0]], 1)  # tangent turned clockwise: outward
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(profile, axis=0), axis=1))])
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)
    rows, cols = len(profile), segments + 1
    cos, sin, ones = np.cos(phi)[None, :], np.sin(phi)[None, :], np.ones((1, cols))
    r, z = profile[:, :1], profile[:, 1:]
    nr, nz = normal2d[:, :1], normal2d[:, 1:]
    positions = np.stack([r * cos, r * sin, z * ones], -1).reshape(-1, 3)
    normals = np.stack([nr * cos, nr * sin, nz * ones], -1).reshape(-1, 3)
    u, v = np.meshgrid(phi / (2 * np.pi), arc / arc[-1])
    uvs = np.stack([u, v], -1).reshape(-1, 2)
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    # Drop the zero-area triangles at the axis (the rows at r = 0)
    e1 = positions[faces[:, 1]] - positions[faces[:, 0]]
    e2 = positions[faces[:, 2]] - positions[faces[:, 0]]
    faces = faces[np.linalg.norm(np.cross(e1, e2), axis=1) > 1e-14]
    return MeshData(positions, faces.astype(np.uint32), normals, uvs)


def _handle(shape: CupShape, sweep: int = 48, around: int = 20) -> MeshData:
    """A tube along a half ellipse on the +x side, its ends buried in the wall."""
    s = shape
    z_top, z_bottom = 0.78 * s.height, 0.28 * s.height
    zc, az = (z_top + z_bottom) / 2, (z_top - z_bottom) / 2
    wall_r = s.radius_bottom + (s.radius_top - s.radius_bottom) * zc / s.height
    xc, ax, tube = wall_r - 0.004, 0.034, 0.0055
    theta = np.linspace(np.pi / 2 + 0.15, -np.pi / 2 - 0.15, sweep)
    centre = np.stack([xc + ax * np.cos(theta), np.zeros_like(theta), zc + az * np.sin(theta)], 1)
    d = np.stack([-ax * np.sin(theta), np.zeros_like(theta), az * np.cos(theta)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    binormal = np.array([0.0, 1.0, 0.0])
    normal = np.cross(binormal, d)
    psi = np.linspace(0, 2 * np.pi, around + 1)
    ring = np.cos(psi)[None, :, None] * normal[:, None] + np.sin(psi)[None, :, None] * binormal
    # a slightly flattened tube (wider across than deep), like a real handle
    positions = centre[:, None] + tube * ring * np.array([1.0, 1.5, 1.0])
    normals = ring * np.array([1.5, 1.0, 1.5])
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    # UVs: u along the handle, v around it inside the band of the body's outer wall (0.25-0.45),
    # so painted masks that vary with v treat the handle like the middle of the outer wall
    u, v = np.meshgrid(np.linspace(0, 1, sweep), 0.25 + 0.2 * psi / (2 * np.pi), indexing="ij")
    idx = np.arange(sweep * (around + 1)).reshape(sweep, around + 1)
    a, b, c, e = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate(
        [np.stack([a, c, e], -1).reshape(-1, 3), np.stack([a, e, b], -1).reshape(-1, 3)]
    )
    return MeshData(
        positions.reshape(-1, 3),
        faces.astype(np.uint32),
        normals.reshape(-1, 3),
        np.stack([u, v], -1).reshape(-1, 2),
    )


def cup_mesh(shape: CupShape | None = None) -> MeshData:
    """The procedural cup: a body of revolution with wall thickness, and a handle."""
    shape = shape or CupShape()
    body = _revolve(cup_profile(shape), shape.segments)
    return MeshData.concatenate(body, _handle(shape)) if shape.handle else body


def winding_numbers(positions: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The generalised winding number of a triangle mesh at each point (Jacobson et al. 2013):
    the triangles' signed solid angles seen from the point over 4 pi. About +-1 inside a closed
    mesh (the sign its winding's), 0 outside; in between near the holes of an open one."""
    positions, faces = np.asarray(positions, np.float64), np.asarray(faces)
    out = np.zeros(len(points))
    for k, point in enumerate(np.asarray(points, np.float64)):
        a, b, c = (positions[faces[:, i]] - point for i in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=1) for v in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        dots = (
            la * lb * lc
            + np.einsum("ij,ij->i", a, b) * lc
            + np.einsum("ij,ij->i", b, c) * la
            + np.einsum("ij,ij->i", c, a) * lb
        )
        out[k] = np.sum(2.0 * np.arctan2(det, dots)) / (4.0 * np.pi)
    return out


def closed(positions: np.ndarray, faces: np.ndarray) -> bool:
    """Whether a triangle mesh is closed: every edge, its corners welded by position, shared by
    exactly two triangles (whichever way they are wound)."""
    faces = np.asarray(faces)
    if len(faces) == 0:
        return False
    _, weld = np.unique(np.asarray(positions), axis=0, return_inverse=True)
    corners = np.ravel(weld)[faces]
    a, b = corners.ravel(), np.roll(corners, -1, axis=1).ravel()
    keep = a != b  # a degenerate triangle's collapsed side joins nothing
    edges = np.stack([np.minimum(a[keep], b[keep]), np.maximum(a[keep], b[keep])], axis=1)
    return bool(np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2))


#: `crossings` casts its rays along these directions (skew to the axes: a ray along an axis of
#: an axis-aligned mesh runs along its edges).
_RAY_DIRECTIONS = np.array([[0.5377, 0.6919, 0.4817], [-0.7071, 0.1, -0.7], [0.2, -0.9, 0.3873]])


def crossings(positions: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(points, rays): how many triangles each ray of `_RAY_DIRECTIONS` from each point crosses
    (Moller-Trumbore): odd inside a closed mesh, whichever way its faces are wound."""
    v0, v1, v2 = (np.asarray(positions, np.float64)[faces[:, i]] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    directions = _RAY_DIRECTIONS / np.linalg.norm(_RAY_DIRECTIONS, axis=1, keepdims=True)
    # per direction, what does not depend on the point
    ps = [np.cross(d, e2) for d in directions]
    dets = [np.einsum("ij,ij->i", e1, p) for p in ps]
    points = np.atleast_2d(np.asarray(points, np.float64))
    out = np.zeros((len(points), len(directions)), np.int64)
    for k, point in enumerate(points):
        s = point - v0
        q = np.cross(s, e1)
        t_num = np.einsum("ij,ij->i", e2, q)
        for j, (d, p, det) in enumerate(zip(directions, ps, dets, strict=True)):
            ok = np.abs(det) > 1e-300
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            u, v, t = np.einsum("ij,ij->i", s, p) * inv, (q @ d) * inv, t_num * inv
            out[k, j] = np.sum(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0))
    return out


def obj_triangles(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(positions, triangles) of an OBJ that `check_obj` accepted: each face fanned from its first
    corner (0-based vertex indices)."""
    positions, triangles = [], []
    for line in Path(path).read_text(errors="replace").splitlines():
        words = line.split()
        if words and words[0] == "v":
            positions.append([float(x) for x in words[1:4]])
        elif words and words[0] == "f":
            corners = [int(c.split("/")[0]) - 1 for c in words[1:]]
            triangles += [
                (corners[0], corners[i], corners[i + 1]) for i in range(1, len(corners) - 1)
            ]
    return np.asarray(positions, np.float64), np.asarray(triangles, np.int64).reshape(-1, 3)


_FLOAT32_MAX = float(np.finfo(np.float32).max)
#: How many numbers each OBJ vertex record takes: positions 3 (4 with a weight, 6 or 7 with a
#: colour, as some exporters write), texture coordinates 1 to 3, normals 3.
_NUMBERS = {"v": (3, 7), "vt": (2, 3), "vn": (3, 3)}  # Mitsuba refuses a vt of one number
#: The longest line Mitsuba's OBJ loader reads, in characters without the line's end (measured:
#: 1023 load with "\n", fail with "\r\n": "excessively long line"; a large polygon's face or a
#: long comment).
MAX_OBJ_LINE = 1022


def _check_numbers(path: Path, number: int, words: list[str]) -> list[float]:
    """A vertex record's numbers: as many as its kind takes, each finite in float32 (what the
    renderer keeps)."""
    kind, values = words[0], words[1:]
    low, high = _NUMBERS[kind]
    if not low <= len(values) <= high:
        take = f"{low}" if low == high else f"{low} to {high}"
        raise CaptureError(
            f"{path}: line {number}: '{kind}' has {len(values)} numbers, takes {take}; fix the "
            "file (export it again)"
        )
    try:
        floats = [float(x) for x in values]
    except ValueError:
        raise CaptureError(
            f"{path}: line {number}: '{kind}' holds {' '.join(values)!r}, not numbers; fix the "
            "file (export it again)"
        ) from None
    if not all(abs(x) <= _FLOAT32_MAX for x in floats):  # NaN compares False
        raise CaptureError(
            f"{path}: line {number}: '{kind}' holds a value that is not finite in float32 "
            f"({' '.join(values)}); fix the file (export it again)"
        )
    return floats


def check_obj_has_uvs(path: str | Path) -> None:
    """Raise `CaptureError` unless the OBJ at `path` is a mesh the renderer can load (see
    `check_obj`) with texture coordinates on every face (layer masks and noise live in UV)."""
    check = check_obj(path)
    faces, without = check.faces, check.without_uvs
    if without:
        raise CaptureError(
            f"{path}: the OBJ has no texture coordinates on {without} of {faces} faces; layer "
            "masks and textures need UVs: unwrap it (e.g. Blender: UV > Smart UV Project) and "
            "export with UVs"
        )


@dataclass(frozen=True)
class ObjCheck:
    """What `check_obj` found: the face count, how many faces lack texture coordinates, and
    warnings on how the renderer will shade the mesh (one line each, naming the file and fix)."""

    faces: int
    without_uvs: int
    warnings: tuple[str, ...] = ()
    bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    """The lowest and highest corner of its vertices' box."""


def check_obj(path: str | Path, face_normals: bool = False) -> ObjCheck:
    """Raise `CaptureError` unless the OBJ at `path` is a mesh the renderer can load: faces of 3
    or more corners whose vertex, texture and normal indices exist, not all of zero area. Its
    warnings (`shading_warnings`) say where the renderer's shading will not be the object's."""
    path = Path(path)
    require_utf8(path, CaptureError)
    try:
        text = path.read_text(errors="replace")
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such OBJ file") from None
    except IsADirectoryError:
        raise CaptureError(f"{path}: is a folder; give an OBJ file") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot read ({err.strerror})") from None
    if text.startswith("\ufeff") and text[1:].lstrip(" \t")[:1] not in ("#", "\n", "\r", ""):
        raise CaptureError(  # Mitsuba skips the marked line: a vertex lost, the faces shifted
            f"{path}: starts with a byte-order mark (U+FEFF) on a record, which the renderer "
            "skips (every vertex after it shifts); save the file as UTF-8 without BOM"
        )
    text = text.removeprefix("\ufeff")
    counts = {"v": 0, "vt": 0, "vn": 0}
    faces, faces_with_vt, without_normal, zero_normal = 0, 0, 0, None
    # every vertex (x, y, z); each face's first three corners, all faces' vertex and texture
    # indices (0-based) and their corner counts: typed arrays, a fifth of lists' memory (a
    # million-face scan took 726 MB with lists)
    positions, triangles = array("d"), array("q")
    corners_v, corners_t, sizes = array("q"), array("q"), array("q")
    for number, line in enumerate(text.splitlines(), 1):
        if len(line) > MAX_OBJ_LINE:
            raise CaptureError(
                f"{path}: line {number} is {len(line):,} characters long; the renderer reads "
                f"lines of at most {MAX_OBJ_LINE:,}: triangulate its large polygons (Blender: "
                "Triangulate modifier) or shorten the line, and export it again"
            )
        words = line.split()
        if not words:
            continue
        if words[0] in counts:
            counts[words[0]] += 1
            numbers = _check_numbers(path, number, words)
            if words[0] == "v":
                positions.extend(numbers[:3])
            elif words[0] == "vn" and zero_normal is None and sum(x * x for x in numbers) < 1e-36:
                zero_normal = number, line.strip()  # its square underflows float32
        elif words[0] == "f":
            faces += 1
            corners = words[1:]
            if len(corners) < 3:
                raise CaptureError(
                    f"{path}: line {number}: a face needs 3 or more corners; fix or remove it"
                )
            textured = True
            for corner in corners:
                parts = corner.split("/")
                if len(parts) > 3:
                    raise CaptureError(
                        f"{path}: line {number}: face corner {corner!r} has {len(parts)} "
                        "indices; a corner is v, v/vt, v//vn or v/vt/vn: fix the file (export "
                        "it again)"
                    )
                without_normal += len(parts) < 3 or parts[2] == ""
                read = [-1, -1]  # its vertex and texture indices (0-based; -1: none)
                for k, (kind, index) in enumerate(zip(("v", "vt", "vn"), parts, strict=False)):
                    if index == "" and kind != "v":
                        continue
                    try:
                        i = int(index)
                    except ValueError:
                        raise CaptureError(
                            f"{path}: line {number}: face corner {corner!r} is not made of "
                            "integer indices; fix the file (export it again)"
                        ) from None
                    if i < 0:  # relative indices: valid OBJ, but Mitsuba's loader reads them
                        # as huge unsigned ones ("reference to invalid vertex 4294967254")
                        raise CaptureError(
                            f"{path}: line {number}: face index {i} ({kind}) is relative "
                            "(negative), which the renderer cannot load; export with absolute "
                            "indices (or renumber them)"
                        )
                    if i == 0 or i > counts[kind]:
                        raise CaptureError(
                            f"{path}: line {number}: face index {i} ({kind}) is out of range "
                            f"(1 to {counts[kind]} at that line); fix the file (export it again)"
                        )
                    if k < 2:
                        read[k] = i - 1
                corners_v.append(read[0])
                corners_t.append(read[1])
                textured = textured and read[1] >= 0
            triangles.extend(corners_v[-len(corners) :][:3])
            sizes.append(len(corners))
            faces_with_vt += textured
    if faces == 0:
        what = "is not an OBJ text file" if not positions else "the OBJ has no faces"
        raise CaptureError(f"{path}: {what}; give a triangle mesh (OBJ text)")
    if zero_normal is not None and not face_normals:  # face normals discard them
        raise CaptureError(
            f"{path}: line {zero_normal[0]}: normal '{zero_normal[1]}' has no direction (the "
            "renderer refuses it); export the normals again, or set face_normals = true in the "
            "geometry table"
        )
    if counts["vn"] and without_normal and not face_normals:
        # with normals in the file Mitsuba keeps them and computes none: a corner without one
        # reads uninitialised memory (measured: normals of 1e21, faces black or lit at random)
        raise CaptureError(
            f"{path}: has normals (vn), but {without_normal:,} of its {len(corners_v):,} face "
            "corners name none (v or v/vt, not v//vn or v/vt/vn), and the renderer then has no "
            "normal there; export with normals on every face, delete the vn lines (normals "
            "interpolated), or set face_normals = true in the geometry table"
        )
    p = np.frombuffer(positions, np.float64).reshape(-1, 3)
    t = np.frombuffer(triangles, np.int64).reshape(-1, 3)
    area = np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]]), axis=1)
    extent = float(np.ptp(p[t.ravel()], axis=0).max())
    if not np.any(area > 1e-12 * extent**2):
        raise CaptureError(
            f"{path}: every one of its {faces} faces has zero area (its corners on one point or "
            "line): nothing to render; check the export"
        )
    warnings = shading_warnings(
        path,
        p,
        np.asarray(corners_v),
        np.asarray(sizes),
        counts["vn"] > 0,
        face_normals,
        np.asarray(corners_t),
    )
    bounds = (tuple(p.min(axis=0).tolist()), tuple(p.max(axis=0).tolist()))
    return ObjCheck(faces, faces - faces_with_vt if counts["vt"] else faces, warnings, bounds)


#: The dihedral angle (degrees) above which an edge is sharp: interpolated normals round it.
SHARP_DEGREES = 45.0


def _edge_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For directed edges `a -> b` (one per polygon side): the two sides of each edge that
    exactly two sides share (`first`, `second`, indices into `a`), and how often each side's
    edge is used."""
    undirected = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)
    _, edge, uses = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    edge = edge.ravel()
    pair = np.flatnonzero(uses[edge] == 2)
    order = pair[np.argsort(edge[pair], kind="stable")]
    return order[0::2], order[1::2], uses[edge]


def shading_warnings(
    path: Path,
    positions: np.ndarray,
    corners: np.ndarray,
    sizes: np.ndarray,
    has_normals: bool,
    face_normals: bool = False,
    texcoords: np.ndarray | None = None,
) -> tuple[str, ...]:
    """Where a mesh's renders will not show the object it describes, as one-line warnings.

    Without `vn` normals Mitsuba interpolates vertex normals over the faces that share a vertex
    (a vertex being a position and its texture coordinates: a UV seam splits it), so a sharp edge
    inside a UV island renders rounded (measured on a cube of 8 shared vertices: the image off by
    half its mean next to the same cube with its faces apart, and a fit to photographs of the
    sharp cube missed pigment by 0.27). And a face's front follows its corners' order, so faces
    wound against their neighbours, or a closed part wound inside out, are seen from behind:
    black under the one-sided materials (a sphere with half its faces reversed rendered 40 %
    black). With `vn` normals (and `face_normals` off) the renderer shades by them and neither
    applies. `corners`: every face's vertex indices in order, `sizes`: each face's corner count,
    `texcoords`: each corner's texture index (-1: none)."""
    if has_normals and not face_normals:
        return ()
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    face_of = np.repeat(np.arange(len(sizes)), sizes)
    following = np.arange(len(corners)) + 1
    following[starts + sizes - 1] = starts  # each polygon's last corner joins its first
    anchor = positions[corners[np.repeat(starts, sizes)]]
    # each face's normal: the sum of its fan's triangles (Newell's for a planar polygon)
    normals = np.zeros((len(sizes), 3))
    sides = np.cross(positions[corners] - anchor, positions[corners[following]] - anchor)
    np.add.at(normals, face_of, sides)
    length = np.linalg.norm(normals, axis=1)
    ok = length > 0
    normals[ok] /= length[ok, None]
    a, b = corners, corners[following]
    keep = a != b
    out = []
    textured = texcoords is not None and bool(np.any(texcoords >= 0))
    if not (has_normals or face_normals):  # shaded by normals interpolated over shared vertices
        t = np.zeros_like(corners) if texcoords is None else texcoords + 1
        vertex = corners.astype(np.int64) * (int(t.max(initial=0)) + 1) + t
        first, second, _ = _edge_pairs(vertex[keep], vertex[following][keep])
        faces = face_of[keep]
        same_way = vertex[keep][first] == vertex[keep][second]
        cosine = np.sum(normals[faces[first]] * normals[faces[second]], axis=1)
        cosine = np.where(same_way, -cosine, cosine)  # as if the two faces were wound alike
        valid = ok[faces[first]] & ok[faces[second]]
        sharp = int(np.sum(valid & (cosine < np.cos(np.radians(SHARP_DEGREES)))))
        if sharp:
            out.append(
                f"{path}: has no vertex normals (vn), so the renderer interpolates normals "
                f"across its edges and rounds the {sharp} sharper than {SHARP_DEGREES:.0f} "
                f"degrees{' (those inside a UV island)' if textured else ''}; export "
                "it with normals (sharp edges "
                "split), or set face_normals = true in its geometry table for a faceted object"
            )
    fix = (
        "flip those faces (Blender: Mesh > Normals > Recalculate Outside) and export it again"
        if face_normals
        else "recalculate its normals outside (Blender: Mesh > Normals > Recalculate Outside) "
        "and export it again, with normals"
    )
    shading = "with face_normals" if face_normals else "with no vertex normals to shade by"
    # the faces' sides joined where their corners share a position (a "triangle soup", every
    # face with corners of its own, is one object all the same: its parts were each face alone)
    _, weld = np.unique(positions, axis=0, return_inverse=True)
    weld = weld.ravel()
    a, b = weld[corners], weld[corners[following]]
    keep = a != b
    first, second, uses = _edge_pairs(a[keep], b[keep])
    flipped = int(np.sum(a[keep][first] == a[keep][second]))
    if flipped:
        out.append(
            f"{path}: {flipped} of its {len(first)} shared edges join faces wound in opposite "
            f"directions, and {shading} a face's front follows its corners' order: faces seen "
            f"from behind render black (the materials are one-sided); {fix}"
        )
        return tuple(out)
    # each closed part (every edge shared by two faces) wound alike: inside out if its volume
    # is negative
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(positions)
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    _, part = connected_components(graph, directed=False)
    part_of_corner = part[a]
    open_parts = np.unique(part_of_corner[keep][uses != 2])
    volume = np.bincount(
        part_of_corner, weights=np.sum(sides * anchor, axis=1) / 6, minlength=part.max() + 1
    )
    inside_out = [k for k in np.flatnonzero(volume < 0) if k not in set(open_parts.tolist())]
    if inside_out:
        out.append(
            f"{path}: {len(inside_out)} of its closed parts are wound inside out (negative "
            f"volume), and {shading} the renderer sees their faces from behind: black (the "
            "materials are one-sided); flip their normals (Blender: Mesh > Normals > Flip) and "
            "export it again" + ("" if face_normals else ", with normals")
        )
    return tuple(out)


# Height fields from normal maps ------------------------------------------------------------------

#: The steepest slope a normal map's normal gives the height field (|dz/dx|, about 87 degrees):
#: normals at a silhouette lie in the image plane, whose slope is infinite.
MAX_SLOPE = 20.0


def _integrate_slopes(p: np.ndarray, q: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Heights z on `mask` (pixels, rows downwards) whose differences between neighbouring masked
    pixels best match the mean of their slopes `p` = dz/dx (x right) and `q` = dz/dy (y up), in
    the least-squares sense; each connected part's mean height is 0."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    index = np.full(mask.shape, -1, np.int64)
    index[mask] = np.arange(int(mask.sum()))
    rhs = []
    # right neighbours: z[i, j+1] - z[i, j] = (p[i, j] + p[i, j+1]) / 2
    pair = mask[:, :-1] & mask[:, 1:]
    a, b = index[:, :-1][pair], index[:, 1:][pair]
    rhs.append((p[:, :-1][pair] + p[:, 1:][pair]) / 2)
    # lower neighbours (one row down is y - 1): z[i+1, j] - z[i, j] = -(q[i, j] + q[i+1, j]) / 2
    pair_v = mask[:-1, :] & mask[1:, :]
    c, d = index[:-1, :][pair_v], index[1:, :][pair_v]
    rhs.append(-(q[:-1, :][pair_v] + q[1:, :][pair_v]) / 2)
    first, second = np.concatenate([a, c]), np.concatenate([b, d])
    n_eq, n = len(first), int(mask.sum())
    rows = np.concatenate([np.arange(n_eq), np.arange(n_eq)])
    cols = np.concatenate([first, second])
    values = np.concatenate([-np.ones(n_eq), np.ones(n_eq)])
    A = sparse.csr_matrix((values, (rows, cols)), shape=(n_eq, n))
    # a tiny pull towards 0 fixes each part's free constant without bending it
    normal = (A.T @ A + 1e-8 * sparse.identity(n)).tocsc()
    z = spsolve(normal, A.T @ np.concatenate(rhs))
    heights = np.zeros(mask.shape)
    heights[mask] = z
    return heights


def normal_map_mesh(
    normals: np.ndarray, mask: np.ndarray, scale: int = 1, frame: tuple[int, int] | None = None
) -> MeshData:
    """The surface a normal map sees, as a height field in front of an orthographic camera.

    `normals` (H, W, 3): unit normals in the camera's frame (x right, y up, z towards the
    camera), as photometric-stereo benchmarks store them; `mask` (H, W): the object's pixels.
    One vertex per masked pixel centre, at x = column + 0.5 - W / 2, y = H / 2 - (row + 0.5)
    (pixels, the image centre at 0), its height integrated from the normals' slopes (least
    squares, `MAX_SLOPE` at most), its shading normal the given one; two triangles per 2 x 2
    block of masked pixels, facing +z. UVs: the pixel's place in the image (u right, v up).
    Depth jumps (an occluding edge) are bridged by the integration, so the height field's cast
    shadows are only approximate; the shading at each pixel is the given normal's.

    With `scale` k the map's pixels are k x k blocks of an image of `frame` (H, W) pixels (the
    positions, heights and UVs in that image's pixels)."""
    h, w = frame if frame is not None else mask.shape
    n = np.asarray(normals, np.float64)
    nz = np.maximum(n[..., 2], 1.0 / MAX_SLOPE)
    p = np.clip(-n[..., 0] / nz, -MAX_SLOPE, MAX_SLOPE)
    q = np.clip(-n[..., 1] / nz, -MAX_SLOPE, MAX_SLOPE)
    heights = _integrate_slopes(p, q, mask) * scale
    quad = mask[:-1, :-1] & mask[:-1, 1:] & mask[1:, :-1] & mask[1:, 1:]
    used = np.zeros_like(mask)
    mh, mw = mask.shape
    for di in (0, 1):
        for dj in (0, 1):
            used[di : mh - 1 + di, dj : mw - 1 + dj] |= quad
    index = np.full(mask.shape, -1, np.int64)
    index[used] = np.arange(int(used.sum()))
    rows, columns = np.nonzero(used)
    x, y = (columns + 0.5) * scale, (rows + 0.5) * scale  # in the image's pixels
    positions = np.stack([x - w / 2, h / 2 - y, heights[rows, columns]], -1)
    unit = n[rows, columns]
    unit = unit / np.maximum(np.linalg.norm(unit, axis=-1, keepdims=True), 1e-12)
    # UVs: the image's coordinates, u to the right and v down, as Mitsuba reads a bitmap's rows:
    # a texture fitted on it reads like the photographs (its first row at their top)
    uvs = np.stack([x / w, y / h], -1)
    qi, qj = np.nonzero(quad)
    a, b = index[qi, qj], index[qi, qj + 1]  # top left, top right
    c, d = index[qi + 1, qj], index[qi + 1, qj + 1]  # bottom left, bottom right
    faces = np.concatenate([np.stack([a, c, d], -1), np.stack([a, d, b], -1)])
    return MeshData(positions, faces.astype(np.uint32), unit, uvs)


def block_normals(normals: np.ndarray, mask: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """A normal map and its mask averaged over k x k blocks: (normals, mask) of
    (H // k, W // k) blocks; a block is in the mask when all its pixels are (its normal the
    mean of theirs, made unit)."""
    h, w = (mask.shape[0] // k) * k, (mask.shape[1] // k) * k
    blocks = mask[:h, :w].reshape(h // k, k, w // k, k).all(axis=(1, 3))
    mean = normals[:h, :w].reshape(h // k, k, w // k, k, 3).mean(axis=(1, 3))
    length = np.linalg.norm(mean, axis=-1, keepdims=True)
    return np.where(blocks[..., None], mean / np.maximum(length, 1e-12), 0.0), blocks


def covered_blocks(mask: np.ndarray, k: int, shape: tuple[int, int]) -> np.ndarray:
    """`covered_pixels` of a mask of k x k blocks, as the image's pixels (of `shape`)."""
    covered = np.kron(covered_pixels(mask), np.ones((k, k), bool))
    out = np.zeros(shape, bool)
    out[: covered.shape[0], : covered.shape[1]] = covered
    return out


def covered_pixels(mask: np.ndarray) -> np.ndarray:
    """The pixels of `mask` that `normal_map_mesh(..., mask)` covers whole (all eight neighbours
    masked: the four quads around the pixel's centre exist)."""
    from scipy.ndimage import binary_erosion

    return binary_erosion(mask, np.ones((3, 3), bool), border_value=0)
