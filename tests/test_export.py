"""`datagen export` (OBJ, PC2, PLY read back against the stored positions) and `datagen preview`."""

from __future__ import annotations

import sys
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))
import shard_factory as sf  # noqa: E402

from datagen.io.commands import export, preview  # noqa: E402
from datagen.io.export import read_pc2  # noqa: E402
from datagen.io.reader import DatasetReader  # noqa: E402

SEQ = "7-000000"  # lower + upper, 10 frames, in shard-00000.h5


def run_cli(*args) -> tuple[int, str]:
    group = click.Group(commands={"export": export, "preview": preview})
    result = CliRunner().invoke(group, list(map(str, args)))
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result.exit_code, result.output


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    v, f = [], []
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            v.append([float(x) for x in line.split()[1:]])
        elif line.startswith("f "):
            f.append([int(x.split("/")[0]) - 1 for x in line.split()[1:]])
    return np.asarray(v), np.asarray(f)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    assert header[1] == "format binary_little_endian 1.0"
    counts = {line.split()[1]: int(line.split()[2]) for line in header
              if line.startswith("element")}
    v = np.frombuffer(data, "<f4", counts["vertex"] * 3, end).reshape(-1, 3)
    rows = np.frombuffer(data, [("n", "u1"), ("i", "<i4", (3,))], counts["face"],
                         end + v.nbytes)
    assert (rows["n"] == 3).all() and end + v.nbytes + rows.nbytes == len(data)
    return v, rows["i"]


@pytest.fixture(scope="module", params=["lossless", "quantised"])
def dataset(request, tmp_path_factory) -> sf.SyntheticDataset:
    return sf.make_dataset(tmp_path_factory.mktemp(request.param),
                           quantize=request.param == "quantised")


@pytest.fixture(scope="module")
def stored(dataset) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (positions (F, V, 3), faces) as the reader decodes them, body included."""
    with DatasetReader(dataset.root) as reader:
        out = {n: (g["vertices"], g["faces"]) for n, g in reader.garments(SEQ).items()}
        body = reader.body(SEQ)
    out["body"] = (body["vertices"], body["faces"])
    return out


def test_export_pc2(dataset, stored, tmp_path):
    # a dataset folder as FILE: the shard holding the sequence is found
    code, out = run_cli("export", dataset.root, "--sequence", SEQ, "--format", "pc2",
                        "--out", tmp_path)
    assert code == 0, out
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "body.obj", "body.pc2", "lower.obj", "lower.pc2", "upper.obj", "upper.pc2"]
    for name, (positions, faces) in stored.items():
        cache = read_pc2(tmp_path / f"{name}.pc2")
        np.testing.assert_array_equal(cache, positions)  # bit-exact float32
        v, f = read_obj(tmp_path / f"{name}.obj")
        np.testing.assert_array_equal(f, faces)
        np.testing.assert_allclose(v, positions[0], atol=1e-6)  # OBJ: 6 decimals
    # the stored positions themselves are the simulated ones (quantised: within half a step)
    synth = dataset.sequences[SEQ]
    for name in ("upper", "lower"):
        np.testing.assert_allclose(read_pc2(tmp_path / f"{name}.pc2"),
                                   synth.record.sim.vertices[name], rtol=0, atol=5.1e-5)


def test_export_obj(dataset, stored, tmp_path):
    shard = dataset.shards[0]
    code, out = run_cli("export", shard, "--sequence", SEQ, "--format", "obj", "--out", tmp_path)
    assert code == 0, out
    files = sorted(tmp_path.iterdir())
    assert len(files) == 3 * 10
    for name, (positions, faces) in stored.items():
        for f in (0, 9):
            v, tri = read_obj(tmp_path / f"{name}_{f:04d}.obj")
            np.testing.assert_array_equal(tri, faces)
            np.testing.assert_allclose(v, positions[f], atol=1e-6)


def test_export_ply(dataset, stored, tmp_path):
    code, out = run_cli("export", dataset.shards[0], "--sequence", SEQ, "--format", "ply",
                        "--out", tmp_path, "--no-body")
    assert code == 0, out
    assert len(list(tmp_path.glob("*.ply"))) == 2 * 10
    assert not list(tmp_path.glob("body_*"))
    for name in ("upper", "lower"):
        positions, faces = stored[name]
        for f in range(10):
            v, tri = read_ply(tmp_path / f"{name}_{f:04d}.ply")
            np.testing.assert_array_equal(v, positions[f])
            np.testing.assert_array_equal(tri, faces)


def test_export_errors(dataset, tmp_path):
    code, out = run_cli("export", dataset.root, "--sequence", "7-000042", "--format", "obj",
                        "--out", tmp_path)
    assert code == 2 and "7-000042" in out and "7-000000" in out
    code, out = run_cli("export", dataset.root, "--format", "obj", "--out", tmp_path)
    assert code == 2 and "--sequence" in out  # three sequences: which one?
    code, out = run_cli("export", dataset.shards[1], "--format", "obj", "--out", tmp_path)
    assert code == 0 and "7-000003" in out  # the only sequence of that shard


def test_preview(tmp_path):
    import imageio.v3 as iio

    from datagen.render import BODY_COLOUR, GARMENT_COLOURS

    dataset = sf.make_dataset(tmp_path / "ds")
    png = tmp_path / "p.png"
    code, out = run_cli("preview", dataset.root, "--sequence", SEQ, "--out", png,
                        "--height", 96)
    assert code == 0, out
    image = iio.imread(png)
    assert image.shape == (2 * 96, 2 * 2 * 72, 3)  # 2x2 frames, each front + side
    # Flat shading darkens colours; the hue tells the meshes apart: the body is grey-brown,
    # the inner garment (lower) blue, the outer (upper) orange.
    pixels = image.reshape(-1, 3).astype(int)
    blue = (pixels[:, 2] > pixels[:, 0] + 40).mean()
    orange = (pixels[:, 0] > pixels[:, 2] + 60).mean()
    grey = ((np.abs(pixels[:, 0] - pixels[:, 2]) < 40) & (pixels.max(axis=1) < 200)).mean()
    assert blue > 0.02 and orange > 0.02 and grey > 0.005
    assert GARMENT_COLOURS[0][2] > GARMENT_COLOURS[0][0] and BODY_COLOUR[0] > BODY_COLOUR[2]
    gif = tmp_path / "p.gif"
    code, out = run_cli("preview", dataset.shards[0], "--sequence", SEQ, "--out", gif,
                        "--every", 3, "--height", 64)
    assert code == 0, out
    frames = iio.imread(gif, index=None)
    assert frames.shape[0] == 4  # frames 0, 3, 6, 9
    code, out = run_cli("preview", dataset.root, "--sequence", SEQ, "--out", tmp_path / "x.jpg")
    assert code == 2 and ".gif (animated) or .png" in out
