"""Run inside Blender (`blender -b --python blender_scene.py -- IN.npz OUT.npz`): simulate one of
our study scenes with Blender's own cloth solver and write the per-frame positions and timings.

IN.npz holds the cloth (`cloth_vertices`, `cloth_faces`, and `rest_vertices`: the rest metric
when it differs from the start), the collider's frames
(`collider_frames` (F+1, Vc, 3), `collider_faces`), optional `pinned` vertex ids with their
per-frame targets `pin_frames` (F+1, P, 3), and the settings (`fps`, `frames`, `quality`, the
preset values, `collision_distance`, `collision_quality`, `self_collision`,
`collider_thickness`, `collider_friction`). Blender is the benchmark's peer, never a dependency:
this script runs only inside Blender, started by datagen.study.blender.
"""

import sys
import time

import bpy
import numpy as np


def mesh_object(name, vertices, faces):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in vertices], [], [tuple(int(i) for i in f) for f in faces])
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def main():
    argv = sys.argv[sys.argv.index("--") + 1 :]
    src, dst = argv[0], argv[1]
    d = np.load(src)
    scene = bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj, do_unlink=True)
    fps = int(d["fps"])
    frames = int(d["frames"])
    scene.render.fps = fps
    scene.frame_start = 1
    scene.frame_end = frames + 1

    cloth = mesh_object("cloth", d["cloth_vertices"], d["cloth_faces"])
    mod = cloth.modifiers.new("cloth", "CLOTH")
    s = mod.settings
    s.quality = int(d["quality"])
    s.mass = float(d["mass"])
    s.tension_stiffness = float(d["tension"])
    s.compression_stiffness = float(d["compression"])
    s.shear_stiffness = float(d["shear"])
    s.bending_stiffness = float(d["bending"])
    s.tension_damping = float(d["tension_damping"])
    s.compression_damping = float(d["compression_damping"])
    s.shear_damping = float(d["shear_damping"])
    s.air_damping = float(d["air_damping"])
    s.bending_damping = float(d["bending_damping"])
    mod.point_cache.frame_start = 1
    mod.point_cache.frame_end = frames + 1
    base = np.asarray(d["cloth_vertices"], dtype=np.float32)
    rest = np.asarray(d["rest_vertices"], dtype=np.float32) if "rest_vertices" in d.files else base
    own_rest = bool(np.abs(rest - base).max() > 0)
    if own_rest or ("pinned" in d.files and len(d["pinned"])):
        cloth.shape_key_add(name="basis")
    if own_rest:
        # Left at value 0: it shapes nothing, the cloth reads its rest lengths and angles from it.
        key = cloth.shape_key_add(name="rest")
        key.data.foreach_set("co", rest.ravel())
        s.rest_shape_key = key
    c = mod.collision_settings
    c.use_collision = True
    c.distance_min = float(d["collision_distance"])
    c.collision_quality = int(d["collision_quality"])
    c.use_self_collision = bool(d["self_collision"])
    if "pinned" in d.files and len(d["pinned"]):
        pinned = [int(i) for i in d["pinned"]]
        group = cloth.vertex_groups.new(name="pin")
        group.add(pinned, 1.0, "REPLACE")
        s.vertex_group_mass = "pin"
        # Pinned vertices follow the cloth object's own (pre-simulation) mesh: animate it with
        # one shape key per frame that moves the pinned vertices to their targets.
        pins = d["pin_frames"]
        keys = []
        for k in range(len(pins)):
            key = cloth.shape_key_add(name=f"p{k}")
            co = base.copy()
            co[pinned] = pins[k]
            key.data.foreach_set("co", co.ravel())
            keys.append(key)
        for k, key in enumerate(keys):
            for f in range(len(keys)):
                key.value = 1.0 if f == k else 0.0
                key.keyframe_insert("value", frame=f + 1)
        for fc in cloth.data.shape_keys.animation_data.action.fcurves:
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"
        # The cloth modifier must come after the shape keys it reads: it does (modifiers run
        # on the shape-keyed mesh).

    frames_c = d["collider_frames"]
    collider = mesh_object("collider", frames_c[0], d["collider_faces"])
    collider.modifiers.new("collision", "COLLISION")
    collider.collision.thickness_outer = float(d["collider_thickness"])
    collider.collision.cloth_friction = float(d["collider_friction"])
    animated = len(frames_c) > 1 and np.abs(frames_c - frames_c[0]).max() > 0
    if animated:
        # Shape keys, one per frame, each fully on at its frame only: the collider moves with
        # Blender's own interpolation between frames (as an animated body would).
        collider.shape_key_add(name="basis")
        keys = []
        for k, verts in enumerate(frames_c):
            key = collider.shape_key_add(name=f"f{k}")
            key.data.foreach_set("co", np.asarray(verts, dtype=np.float32).ravel())
            keys.append(key)
        for k, key in enumerate(keys):
            for f in range(len(keys)):
                key.value = 1.0 if f == k else 0.0
                key.keyframe_insert("value", frame=f + 1)
            fc = collider.data.shape_keys.animation_data.action.fcurves[k]
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"

    n = len(d["cloth_vertices"])
    out = np.zeros((frames + 1, n, 3), dtype=np.float32)
    times = np.zeros(frames + 1)
    buf = np.zeros(n * 3, dtype=np.float32)
    for f in range(1, frames + 2):
        t = time.perf_counter()
        scene.frame_set(f)
        deps = bpy.context.evaluated_depsgraph_get()
        ev = cloth.evaluated_get(deps)
        ev.data.vertices.foreach_get("co", buf)
        times[f - 1] = time.perf_counter() - t
        out[f - 1] = buf.reshape(n, 3)
    np.savez(dst, positions=out, frame_seconds=times, version=bpy.app.version_string)


main()
