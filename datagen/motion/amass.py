"""AMASS-style .npz -> canonical `Motion`, at the file's own frame rate.

Fields: `poses` (F, >= 72) SMPL axis-angle poses (SMPL-H / SMPL-X files have 156 / 165 values: the
first 22 body joints are kept and SMPL's two hand joints are set to zero), `trans` (F, 3),
`mocap_framerate` (or `mocap_frame_rate`). `betas` and `gender` are optional and not read: the
pose retargets onto the reference skeleton, whatever the subject's shape.

AMASS root rotations act on the y-up SMPL body inside a z-up world, so the root converts with
`skeleton.smpl_root_to_canonical` (an upright AMASS body, root = +90 degrees about x, becomes the
canonical identity); the other joints are SMPL's and are used verbatim. AMASS `trans` is SMPL's
translation (pelvis = template pelvis + trans); it is used as the pelvis position (the template
offset is a constant shift) and the motion is then grounded exactly as BVH imports are
(`datagen.motion.bvh.ground_trans`). `pelvis_height` is REFERENCE_PELVIS_HEIGHT.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from datagen.errors import InputError
from datagen.motion.bvh import ground_trans
from datagen.skeleton import NUM_JOINTS, REFERENCE_PELVIS_HEIGHT, smpl_root_to_canonical
from datagen.types import Motion

_BODY_VALUES = 22 * 3  # root + 21 body joints, shared by SMPL, SMPL-H and SMPL-X
_FPS_KEYS = ("mocap_framerate", "mocap_frame_rate")


def _array(npz: np.lib.npyio.NpzFile, path: Path, key: str, expected: str) -> np.ndarray:
    try:
        arr = np.asarray(npz[key])
    except ValueError as e:  # object arrays need pickle, which we refuse
        raise InputError(path, key, expected, str(e)) from None
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise InputError(path, key, expected, f"dtype {arr.dtype}")
    return arr.astype(np.float64)


def load_amass(path: str | Path, label: str | None = None) -> Motion:
    """An AMASS-style .npz as a canonical Motion (see the module docstring)."""
    path = Path(path)
    expected_file = "an AMASS .npz archive (numpy.savez)"
    try:
        with path.open("rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise InputError(path, None, expected_file, e.strerror or str(e)) from None
    # np.load would take a text or pickle file for pickled data and say so, which misleads.
    if not magic.startswith(b"PK"):
        raise InputError(path, None, expected_file, "not a zip archive")
    try:
        npz = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(path, None, expected_file, f"unreadable: {e}") from None

    with npz:
        expected_poses = "an (F, 72) array of axis-angle poses"
        if "poses" not in npz.files:
            raise InputError(path, "poses", expected_poses, "missing")
        poses = _array(npz, path, "poses", expected_poses)
        if poses.ndim != 2 or poses.shape[1] < NUM_JOINTS * 3 or poses.shape[0] < 1:
            raise InputError(
                path, "poses", expected_poses + " (or wider, SMPL-H/SMPL-X)", f"shape {poses.shape}"
            )

        expected_trans = f"an ({poses.shape[0]}, 3) array of root translations"
        if "trans" not in npz.files:
            raise InputError(path, "trans", expected_trans, "missing")
        trans = _array(npz, path, "trans", expected_trans)
        if trans.shape != (poses.shape[0], 3):
            raise InputError(
                path, "trans", expected_trans + " (one per pose)", f"shape {trans.shape}"
            )

        fps_key = next((k for k in _FPS_KEYS if k in npz.files), None)
        expected_fps = "a positive frame rate (mocap_framerate or mocap_frame_rate)"
        if fps_key is None:
            raise InputError(path, "mocap_framerate", expected_fps, "missing")
        fps_arr = _array(npz, path, fps_key, expected_fps)
        if fps_arr.size != 1:
            raise InputError(path, fps_key, expected_fps, f"shape {fps_arr.shape}")
        fps = float(fps_arr.reshape(()))
        if not (np.isfinite(fps) and fps > 0):
            raise InputError(path, fps_key, expected_fps, fps)

    for key, arr in (("poses", poses), ("trans", trans)):
        bad = ~np.isfinite(arr)
        if bad.any():
            frame = int(np.argmax(bad.reshape(arr.shape[0], -1).any(axis=1)))
            raise InputError(path, key, "finite values", f"non-finite value in frame {frame}")

    body = np.zeros((poses.shape[0], NUM_JOINTS * 3))
    if poses.shape[1] == NUM_JOINTS * 3:
        body[:] = poses
    else:  # SMPL-H/SMPL-X: the hand joints' slots hold finger or jaw values, not SMPL's hands
        body[:, :_BODY_VALUES] = poses[:, :_BODY_VALUES]
    canonical = smpl_root_to_canonical(body)
    return Motion(
        poses=canonical,
        trans=ground_trans(canonical, trans),
        fps=fps,
        label=label if label is not None else path.stem,
        source=f"amass:{path.name}",
        pelvis_height=REFERENCE_PELVIS_HEIGHT,
    )
