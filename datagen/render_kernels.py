"""Taichi kernels of the preview rasteriser (z-buffer, flat shading)."""

import taichi as ti

F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
V3 = ti.types.ndarray(dtype=ti.math.vec3, ndim=1)
I3 = ti.types.ndarray(dtype=ti.math.ivec3, ndim=1)
IMG = ti.types.ndarray(dtype=ti.math.vec3, ndim=2)


@ti.kernel
def clear(depth: F2, image: IMG, background: ti.math.vec3):
    for i, j in depth:
        depth[i, j] = 1e30
        image[i, j] = background


@ti.kernel
def rasterise(
    pos: V3, faces: I3, colour: V3, depth: F2, image: IMG, light: ti.math.vec3, two_sided: ti.i32
):
    """`pos` are screen-space (x right, y down, z depth towards the viewer is smaller) per vertex;
    one colour per face. Serial on purpose: exact z-buffer without atomics, small images."""
    h = depth.shape[0]
    w = depth.shape[1]
    ti.loop_config(serialize=True)
    for t in range(faces.shape[0]):
        f = faces[t]
        a = pos[f[0]]
        b = pos[f[1]]
        c = pos[f[2]]
        n = (b - a).cross(c - a)
        nl = n.norm()
        if nl > 1e-12:
            n /= nl
            shade = n.dot(light)
            if two_sided != 0:
                shade = ti.abs(shade)
            shade = 0.18 + 0.82 * ti.max(shade, 0.0) ** 2
            x0 = ti.max(ti.cast(ti.floor(ti.min(a[0], ti.min(b[0], c[0]))), ti.i32), 0)
            x1 = ti.min(ti.cast(ti.ceil(ti.max(a[0], ti.max(b[0], c[0]))), ti.i32), w - 1)
            y0 = ti.max(ti.cast(ti.floor(ti.min(a[1], ti.min(b[1], c[1]))), ti.i32), 0)
            y1 = ti.min(ti.cast(ti.ceil(ti.max(a[1], ti.max(b[1], c[1]))), ti.i32), h - 1)
            area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            if ti.abs(area) > 1e-12:
                for py in range(y0, y1 + 1):
                    for px in range(x0, x1 + 1):
                        sx = px + 0.5
                        sy = py + 0.5
                        w0 = ((b[0] - sx) * (c[1] - sy) - (b[1] - sy) * (c[0] - sx)) / area
                        w1 = ((c[0] - sx) * (a[1] - sy) - (c[1] - sy) * (a[0] - sx)) / area
                        w2 = 1.0 - w0 - w1
                        if w0 >= 0.0 and w1 >= 0.0 and w2 >= 0.0:
                            z = w0 * a[2] + w1 * b[2] + w2 * c[2]
                            if z < depth[py, px]:
                                depth[py, px] = z
                                image[py, px] = colour[t] * shade
