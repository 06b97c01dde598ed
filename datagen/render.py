"""Preview pictures: front and side views of a body and its garments, as PNG or animated GIF.

A small z-buffer rasteriser in Taichi (orthographic cameras, flat shading): no OpenGL, so it runs
headless on any machine the simulator runs on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

BODY_COLOUR = (0.72, 0.66, 0.62)
GARMENT_COLOURS = [
    (0.20, 0.40, 0.80),
    (0.85, 0.35, 0.20),
    (0.25, 0.65, 0.35),
    (0.65, 0.30, 0.70),
    (0.85, 0.70, 0.20),
]
VIEWS = {
    # name: (right axis, up axis, towards-viewer axis) in world coordinates
    "front": (np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])),
    "side": (np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.0, 0.0])),
}


@dataclass
class MeshLayer:
    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (T, 3)
    colour: tuple[float, float, float]
    two_sided: bool = False  # cloth is seen from both sides


def _frame_bounds(layers_per_frame: list[list[MeshLayer]]) -> tuple[np.ndarray, np.ndarray]:
    pts = np.concatenate([layer.vertices for layers in layers_per_frame for layer in layers])
    return pts.min(axis=0), pts.max(axis=0)


def _framing(lo: np.ndarray, hi: np.ndarray, height: int, width: int) -> float:
    """Pixels per metre that fit a box of corners lo, hi in every view's panel."""
    extent = (hi - lo) * 1.08 + 1e-6
    across = max(extent[0], extent[1])  # the front view shows x, the side view y
    return float(min(height / extent[2], width / across))


def render_views(
    layers: list[MeshLayer],
    views: tuple[str, ...] = ("front", "side"),
    height: int = 480,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    scale: float | None = None,
) -> np.ndarray:
    """An RGB uint8 image with the views side by side, framed on `bounds` (default: the layers'
    own box); `scale` (pixels per metre) fixes the zoom across the frames of a sequence."""
    import taichi as ti

    from datagen import render_kernels as RK
    from datagen.sim.backend import init_taichi

    init_taichi()
    lo, hi = bounds if bounds is not None else _frame_bounds([layers])
    centre = (lo + hi) / 2
    width = height * 3 // 4
    if scale is None:
        scale = _framing(lo, hi, height, width)
    panels = []
    for view in views:
        right, up, towards = VIEWS[view]
        depth = ti.ndarray(ti.f32, (height, width))
        image = ti.ndarray(ti.math.vec3, (height, width))
        RK.clear(depth, image, ti.math.vec3(1.0, 1.0, 1.0))
        for layer in layers:
            v = np.asarray(layer.vertices, dtype=np.float64) - centre
            sx = v @ right * scale + width / 2
            sy = height / 2 - v @ up * scale
            sz = -(v @ towards)
            pos = np.stack([sx, sy, sz], axis=1).astype(np.float32)
            f = np.asarray(layer.faces, dtype=np.int32)
            pos_nd = ti.ndarray(ti.math.vec3, len(pos))
            pos_nd.from_numpy(pos)
            faces_nd = ti.ndarray(ti.math.ivec3, len(f))
            faces_nd.from_numpy(f)
            col = ti.ndarray(ti.math.vec3, len(f))
            col.from_numpy(np.tile(np.asarray(layer.colour, np.float32), (len(f), 1)))
            # Screen y points down, so the screen-space normal of a front face points to -z;
            # the light comes from the viewer's upper left.
            light = ti.math.vec3(-0.55, -0.45, -0.70)
            RK.rasterise(pos_nd, faces_nd, col, depth, image, light, int(layer.two_sided))
        panels.append(image.to_numpy())
    out = np.concatenate(panels, axis=1)
    return (np.clip(out, 0, 1) * 255).astype(np.uint8)


def save_png(path: str | Path, image: np.ndarray) -> None:
    import imageio.v3 as iio

    iio.imwrite(path, image)


def save_gif(path: str | Path, images: list[np.ndarray], fps: float) -> None:
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(images), duration=1000.0 / fps, loop=0)


def render_sequence(
    frames: list[list[MeshLayer]], height: int = 360, views: tuple[str, ...] = ("front", "side")
) -> list[np.ndarray]:
    """Images of every frame at one zoom; the camera follows the subject across the floor (a
    walk stays in the picture) but not up and down (a jump is seen as one)."""
    boxes = [_frame_bounds([layers]) for layers in frames]
    lo_all, hi_all = _frame_bounds(frames)
    width = height * 3 // 4
    largest = np.max([hi - lo for lo, hi in boxes], axis=0)
    scale = _framing(np.zeros(3), np.append(largest[:2], hi_all[2] - lo_all[2]), height, width)
    images = []
    for layers, (lo, hi) in zip(frames, boxes, strict=True):
        mid = (lo + hi) / 2
        box_lo = np.array([mid[0], mid[1], lo_all[2]])
        box_hi = np.array([mid[0], mid[1], hi_all[2]])
        images.append(render_views(layers, views, height, (box_lo, box_hi), scale))
    return images


PREVIEW_SUFFIXES = (".gif", ".png")


def write_preview(path: str | Path, layers: Callable[[int], list[MeshLayer]], n_frames: int,
                  fps: float, every: int = 2, height: int = 320) -> list[int]:
    """Render frames 0..n_frames-1 of a sequence, each frame's meshes given by `layers`: an
    animated GIF of every `every`-th frame, or a PNG of four frames in a 2x2 grid, by the
    path's suffix (PREVIEW_SUFFIXES). Returns the frames drawn."""
    suffix = Path(path).suffix.lower()
    if suffix not in PREVIEW_SUFFIXES:
        raise ValueError(f"a preview is a .gif or .png file, got {str(path)!r}")
    if suffix == ".gif":
        picks = list(range(0, n_frames, every))
        save_gif(path, render_sequence([layers(f) for f in picks], height=height), fps=fps / every)
        return picks
    picks = [int(f) for f in np.linspace(0, n_frames - 1, 4).round()]
    images = render_sequence([layers(f) for f in picks], height=height)
    save_png(path, np.concatenate([np.concatenate(images[:2], axis=1),
                                   np.concatenate(images[2:], axis=1)], axis=0))
    return picks


def preview_record(path: str | Path, record, every: int = 2, height: int = 320) -> None:
    """Render a simulated sequence record: GIF (every `every`-th frame) or PNG (4 frames)."""
    body = record.body
    start = body.lead_in_frames
    colours = {g.name: GARMENT_COLOURS[k % len(GARMENT_COLOURS)]
               for k, g in enumerate(record.garments or [])}

    def layers(f: int) -> list[MeshLayer]:
        out = [MeshLayer(body.vertices[start + f], body.rest.faces, BODY_COLOUR)]
        for g in record.garments or []:
            out.append(MeshLayer(record.sim.vertices[g.name][f], g.faces, colours[g.name], True))
        return out

    write_preview(path, layers, body.n_frames - start, body.fps, every, height)
