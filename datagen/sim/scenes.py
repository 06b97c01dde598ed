"""Simple reference scenes for tests, benchmarks and the accuracy study: a sheet on a sphere, a
skirt-like tube on a moving cylinder. Both sides (ours and Blender's) build them from these
functions, so they simulate the same geometry."""

from __future__ import annotations

import numpy as np
import trimesh

from datagen.types import Garment


def grid_sheet(
    n: int, size: float, height: float, name: str = "sheet", fabric: str = "cotton"
) -> Garment:
    """A square sheet of (n+1)^2 vertices, `size` metres wide, horizontal at `height`, centred
    over the origin; triangles alternate their diagonal so the sheet has no preferred shear
    direction. The uv pattern coordinates are the flat positions (grain along x and y)."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, height)], axis=1)
    faces = []
    for i in range(n):
        for j in range(n):
            a, b = i * (n + 1) + j, (i + 1) * (n + 1) + j
            c, d = b + 1, a + 1
            if (i + j) % 2 == 0:
                faces += [[a, b, c], [a, c, d]]
            else:
                faces += [[a, b, d], [b, c, d]]
    return Garment(
        name=name,
        category="sheet",
        vertices=v,
        faces=np.asarray(faces, dtype=np.int32),
        fabric=fabric,
        uv=v[:, :2].copy(),
    )


def icosphere(radius: float, subdivisions: int = 4, center=(0.0, 0.0, 0.0)):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(mesh.vertices) + np.asarray(center), np.asarray(mesh.faces, dtype=np.int32)


def cylinder_mesh(radius: float, height: float, sections: int = 48, rings: int = 24):
    """A closed cylinder along z from 0 to `height`, `rings` rows of quads around it (split
    into triangles) and fan caps; outward normals."""
    ang = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    zs = np.linspace(0, height, rings + 1)
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], axis=1)
    verts = [np.column_stack([ring, np.full(sections, z)]) for z in zs]
    v = np.concatenate(verts + [np.array([[0.0, 0.0, 0.0], [0.0, 0.0, height]])])
    bottom, top = len(v) - 2, len(v) - 1
    faces = []
    for k in range(rings):
        for i in range(sections):
            a, b = k * sections + i, k * sections + (i + 1) % sections
            c, d = b + sections, a + sections
            faces += [[a, b, c], [a, c, d]]
    for i in range(sections):
        a, b = i, (i + 1) % sections
        faces.append([bottom, b, a])
        faces.append([top, rings * sections + a, rings * sections + b])
    return v, np.asarray(faces, dtype=np.int32)


def tube(
    radius: float,
    length: float,
    n_around: int,
    n_along: int,
    top: float,
    name: str = "tube",
    fabric: str = "cotton",
    flare: float = 0.0,
) -> Garment:
    """An open tube (a skirt without its waistband), axis z, hanging from `top` downwards,
    radius growing by `flare` metres from top to hem. The top loop is named 'waist', the bottom
    'hem'; uv is the unrolled pattern."""
    ang = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    zs = np.linspace(0, length, n_along + 1)
    verts, uv = [], []
    for k, z in enumerate(zs):
        r = radius + flare * k / n_along
        for a in ang:
            verts.append([r * np.cos(a), r * np.sin(a), top - z])
            uv.append([a * radius, z])
    faces = []
    for k in range(n_along):
        for i in range(n_around):
            a = k * n_around + i
            b = k * n_around + (i + 1) % n_around
            c = (k + 1) * n_around + (i + 1) % n_around
            d = (k + 1) * n_around + i
            if (i + k) % 2 == 0:
                faces += [[a, d, c], [a, c, b]]
            else:
                faces += [[a, d, b], [b, d, c]]
    loops = {
        "waist": np.arange(n_around),
        "hem": np.arange(n_along * n_around, (n_along + 1) * n_around),
    }
    return Garment(
        name=name,
        category="skirt",
        vertices=np.asarray(verts),
        faces=np.asarray(faces, dtype=np.int32),
        fabric=fabric,
        uv=np.asarray(uv),
        loops=loops,
    )


def drum(radius: float, length: float = 0.4, sections: int = 128):
    """A closed cylinder lying along x, centred on the origin (cylinder_mesh turned on its
    side): what a strip is draped over in the capstan scenes."""
    v, f = cylinder_mesh(radius, length, sections=sections, rings=4)
    return np.column_stack([v[:, 2] - length / 2, v[:, 0], v[:, 1]]), f


def strip_over_drum(short: float, long: float, radius: float, width: float = 0.08,
                    spacing: float = 0.01, name: str = "strip", fabric: str = "silk") -> Garment:
    """A strip `width` wide draped over a drum along x (`drum`), resting at `radius` from its
    axis: `short` metres hanging down the -y side, half a turn over the top, `long` metres down
    the +y side. Its rest shape is flat (uv: across, arc length from the short end), so it starts
    unstretched. Vertices row by row from the short end, `width / spacing + 1` to a row."""
    arc = np.pi * radius
    total = short + arc + long
    s = np.linspace(0.0, total, int(round(total / spacing)) + 1)
    angle = (s - short) / radius
    y = np.where(s < short, -radius, np.where(s > short + arc, radius, -radius * np.cos(angle)))
    z = np.where(s < short, s - short,
                 np.where(s > short + arc, short + arc - s, radius * np.sin(angle)))
    across = np.linspace(-width / 2, width / 2, int(round(width / spacing)) + 1)
    m = len(across)
    uv = np.column_stack([np.tile(across, len(s)), np.repeat(s, m)])
    v = np.column_stack([uv[:, 0], np.repeat(y, m), np.repeat(z, m)])
    faces = []
    for k in range(len(s) - 1):
        for i in range(m - 1):
            a, c = k * m + i, (k + 1) * m + i
            faces += [[a, c, c + 1], [a, c + 1, a + 1]]
    return Garment(name=name, category="sheet", vertices=v, faces=np.asarray(faces, np.int32),
                   fabric=fabric, rest_vertices=np.column_stack([uv, np.zeros(len(uv))]), uv=uv)


def capstan_hold_limit(mu: float, short: float, radius: float) -> float:
    """The longest tail a uniform belt hanging `short` metres down one side of a fixed
    horizontal drum (half a turn of wrap at `radius`) holds on the other side with Coulomb
    friction mu, its own weight on the drum included (independent of the weight per length w).
    At the verge of slipping the tension along the wrap, at angle phi from the short side,
    obeys dT/dphi = mu T + w R (cos phi + mu sin phi): the normal load is the tension's pull
    T plus the wrap's weight, and gravity pulls along the wrap by w R cos phi. From
    T(0) = w * short, T(pi) / w is the limit:

        short e^(mu pi) + R 2 mu (e^(mu pi) + 1) / (1 + mu^2),

    Euler-Eytelwein's short e^(mu pi) plus what the wrap's weight adds."""
    grip = float(np.exp(mu * np.pi))
    return short * grip + radius * 2.0 * mu * (grip + 1.0) / (1.0 + mu * mu)
