"""`datagen validate`: check a dataset folder or one shard against docs/shard-format.md.

Every finding is a `Problem` (file, sequence, what is wrong, severity) rather than an
exception: a damaged shard must not hide the state of the others. Errors are what makes a
dataset unusable or untrustworthy (format, checksums, shapes, non-finite values, QA limits,
manifest disagreement); warnings are harmless leftovers (unfinished `.tmp` files).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from datagen import qa as qa_bounds
from datagen.io.shard import (
    FORMAT,
    FORMAT_VERSION,
    SHARD_SUFFIX,
    TMP_SUFFIX,
    h5py_reason,
    read_positions,
    unreadable_reason,
)

MANIFEST = "manifest.jsonl"
QA_SERIES = ("strain_mean", "strain_max", "strain_p999", "over_strain_share", "inside_share",
             "deep_share", "kinetic_energy")
SHARES = ("over_strain_share", "inside_share", "deep_share")
QA_MODES = ("error", "warning", "off")
_BLOCK_BYTES = 32 << 20  # checksums are computed in blocks of rows to bound memory


@dataclass(frozen=True)
class Problem:
    file: str
    sequence: str | None
    message: str
    severity: str = "error"  # "error" | "warning"

    def __str__(self) -> str:
        where = f"{self.file}: {self.sequence}" if self.sequence else self.file
        return f"{self.severity}: {where}: {self.message}"

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Report:
    path: str
    shards: list[str] = field(default_factory=list)
    sequences: int = 0
    rejected: int = 0
    problems: list[Problem] = field(default_factory=list)

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "warning"]

    @property
    def ok(self) -> bool:
        return not self.errors

    def summary(self) -> str:
        verdict = "OK" if self.ok else "FAILED"
        return (f"{verdict}: {len(self.shards)} shard(s), {self.sequences} sequence(s), "
                f"{self.rejected} rejected; {len(self.errors)} error(s), "
                f"{len(self.warnings)} warning(s)")

    def as_dict(self) -> dict:
        return {
            "path": self.path, "ok": self.ok, "shards": self.shards, "sequences": self.sequences,
            "rejected": self.rejected, "errors": len(self.errors),
            "warnings": len(self.warnings), "problems": [p.as_dict() for p in self.problems],
        }


def validate(path: str | Path, qa: str = "error") -> list[Problem]:
    """Problems of a dataset folder (shards, manifest, leftovers) or of one shard file.
    `qa` is the severity of QA limits that are exceeded: error, warning or off."""
    return validate_report(path, qa).problems


def validate_report(path: str | Path, qa: str = "error") -> Report:
    if qa not in QA_MODES:
        raise ValueError(f"qa must be one of {QA_MODES}, got {qa!r}")
    path = Path(path)
    report = Report(str(path))
    if path.is_file():
        shard = _check_shard(path, qa)
        report.shards, report.problems = [str(path)], shard.problems
        report.sequences, report.rejected = len(shard.sequences), len(shard.rejected)
        return report
    if not path.is_dir():
        report.problems.append(Problem(str(path), None, "no such file or folder"))
        return report
    for tmp in sorted(path.glob("*" + TMP_SUFFIX)):
        report.problems.append(Problem(
            str(tmp), None, "leftover temporary file of an interrupted write (not part of the "
            "dataset; delete it, or resume the run to redo that shard)", "warning"))
    shard_files = sorted(p for p in path.glob("*" + SHARD_SUFFIX) if p.is_file())
    report.shards = [str(p) for p in shard_files]
    if not shard_files:
        report.problems.append(Problem(str(path), None, "no shard files (*.h5) in this folder"))
        return report
    where: dict[str, tuple[Path, str]] = {}  # id -> (shard, status)
    unreadable: set[Path] = set()
    for shard_path in shard_files:
        shard = _check_shard(shard_path, qa)
        report.problems += shard.problems
        if not shard.readable:
            unreadable.add(shard_path)
            continue
        report.sequences += len(shard.sequences)
        report.rejected += len(shard.rejected)
        for sid, status in [(s, "ok") for s in shard.sequences] + \
                [(s, "rejected") for s in shard.rejected]:
            if sid in where and where[sid][0] != shard_path:
                report.problems.append(Problem(
                    str(shard_path), sid, f"sequence id also in {where[sid][0].name} (a "
                    "sequence id must be in one shard only)"))
                continue
            where[sid] = (shard_path, status)
    report.problems += _check_manifest(path, where, unreadable)
    return report


# -- one shard ---------------------------------------------------------------------------------
@dataclass
class _ShardResult:
    problems: list[Problem]
    readable: bool = False
    sequences: list[str] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)


def _check_shard(path: Path, qa: str) -> _ShardResult:
    result = _ShardResult([])
    name = str(path)
    try:
        f = h5py.File(path, "r")
    except Exception as exc:  # noqa: BLE001 - any failure to open is one problem, not a crash
        text = unreadable_reason(exc)
        result.problems.append(Problem(name, None, f"unreadable shard: {text}"))
        return result
    with f:
        fmt = _attr(f, "format")
        if fmt != FORMAT:
            result.problems.append(Problem(name, None, f"format is {fmt!r}, expected {FORMAT!r}"))
            return result
        version = _attr(f, "format_version")
        if version != FORMAT_VERSION:
            result.problems.append(Problem(
                name, None, f"format_version is {version!r}, this datagen reads "
                f"{FORMAT_VERSION}: regenerate the shard or use the matching datagen"))
            return result
        if not isinstance(f.get("sequences"), h5py.Group):
            result.problems.append(Problem(name, None, "no /sequences group"))
            return result
        result.readable = True
        result.sequences = sorted(f["sequences"])
        rejected = f.get("rejected")
        result.rejected = sorted(rejected) if isinstance(rejected, h5py.Group) else []
        for sid in result.sequences:
            check = _SequenceCheck(name, sid, qa)
            try:
                check.run(f["sequences"][sid])
            except Exception as exc:  # noqa: BLE001 - damaged metadata: report, go on
                check.error(f"unreadable ({type(exc).__name__}: {h5py_reason(exc)})")
            result.problems += check.problems
        for sid in result.rejected:
            check = _SequenceCheck(name, sid, qa)
            try:
                check.rejected(rejected[sid])
            except Exception as exc:  # noqa: BLE001
                check.error(f"unreadable rejection ({type(exc).__name__}: {h5py_reason(exc)})")
            if sid in result.sequences:
                check.error("both finished (/sequences) and rejected (/rejected)")
            result.problems += check.problems
    return result


def _attr(obj: Any, key: str, default: Any = None) -> Any:
    value = obj.attrs.get(key, default)
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    return value


def _scan(ds: h5py.Dataset) -> tuple[str, bool]:
    """SHA-256 of the dataset's bytes (C order, as the writer hashed them) and whether every
    value is finite, reading blocks of rows."""
    h = hashlib.sha256()
    finite = True
    is_float = ds.dtype.kind in "fc"
    if ds.ndim == 0:
        blocks = iter([np.asarray(ds[()])])
    else:
        row = max(1, int(np.prod(ds.shape[1:], dtype=np.int64)) * ds.dtype.itemsize)
        step = max(1, _BLOCK_BYTES // row)
        blocks = (ds[i:i + step] for i in range(0, ds.shape[0], step))
    for block in blocks:
        h.update(np.ascontiguousarray(block).tobytes())
        if is_float and finite:
            finite = bool(np.isfinite(block).all())
    return h.hexdigest(), finite


def _read(ds: h5py.Dataset | None) -> np.ndarray | None:
    """The data, or None when absent or unreadable (the checksum pass reports that)."""
    if ds is None:
        return None
    try:
        return ds[()]
    except Exception:  # noqa: BLE001
        return None


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join("*" if d is None else str(d) for d in shape) + ")"


class _SequenceCheck:
    """The checks of one /sequences/<id> (or /rejected/<id>) group, collecting problems."""

    def __init__(self, file: str, sid: str, qa: str) -> None:
        self.file, self.sid, self.qa = file, sid, qa
        self.problems: list[Problem] = []

    def error(self, message: str, severity: str = "error") -> None:
        self.problems.append(Problem(self.file, self.sid, message, severity))

    # -- datasets ------------------------------------------------------------------------------
    def expect(self, group: h5py.Group, path: str, shape: tuple, dtypes: tuple[str, ...],
               optional: bool = False) -> h5py.Dataset | None:
        """The dataset at `path` if it has the expected shape (None: any size) and dtype."""
        item = group.get(path)
        if item is None:
            if not optional:
                self.error(f"{self.rel(group, path)}: missing")
            return None
        if not isinstance(item, h5py.Dataset):
            self.error(f"{self.rel(group, path)}: a group where a dataset was expected")
            return None
        ok = True
        if len(item.shape) != len(shape) or any(
                e is not None and e != s for e, s in zip(shape, item.shape, strict=False)):
            self.error(f"{self.rel(group, path)}: shape {tuple(item.shape)}, expected "
                       f"{_shape_text(shape)}")
            ok = False
        if str(item.dtype) not in dtypes:
            self.error(f"{self.rel(group, path)}: dtype {item.dtype}, expected "
                       f"{' or '.join(dtypes)}")
            ok = False
        return item if ok else None

    def rel(self, group: h5py.Group, path: str = "") -> str:
        base = f"/sequences/{self.sid}"
        name = group.name[len(base) + 1:] if group.name.startswith(base) else group.name
        return f"{name}/{path}".strip("/") if path else name

    def index_range(self, ds: h5py.Dataset | None, upper: int, what: str) -> None:
        """Every index in ds lies in [0, upper)."""
        values = _read(ds)
        if values is None or values.size == 0:
            return
        lo, hi = int(values.min()), int(values.max())
        if lo < 0 or hi >= upper:
            self.error(f"{self.rel(ds.parent, ds.name.rsplit('/', 1)[1])}: indices in "
                       f"[{lo}, {hi}], expected [0, {upper - 1}] ({what})")

    def checksums(self, group: h5py.Group) -> None:
        """Every dataset's sha256 against its bytes, and finiteness of float data."""
        datasets: list[h5py.Dataset] = []
        group.visititems(lambda _n, o: datasets.append(o) if isinstance(o, h5py.Dataset)
                         else None)
        for ds in datasets:
            rel = self.rel(ds.parent, ds.name.rsplit("/", 1)[1])
            stored = _attr(ds, "sha256")
            try:
                digest, finite = _scan(ds)
            except Exception as exc:  # noqa: BLE001 - a damaged chunk fails to decompress
                self.error(f"{rel}: cannot read its data ({h5py_reason(exc)})")
                continue
            if stored is None:
                self.error(f"{rel}: no sha256 attribute")
            elif digest != stored:
                self.error(f"{rel}: checksum mismatch (its bytes changed after writing)")
            if not finite:
                self.error(f"{rel}: non-finite values (NaN or inf)")

    # -- a finished sequence -------------------------------------------------------------------
    def run(self, g: h5py.Group) -> None:
        from datagen.errors import InputError
        from datagen.spec import SceneSpec

        try:
            spec = SceneSpec.from_json(_attr(g, "spec", ""), source=self.file)
            if spec.sequence_id != self.sid:
                self.error(f"spec's sequence_id is {spec.sequence_id!r}, not the group name")
        except InputError as exc:
            self.error(f"@spec: {exc}")
        if _attr(g, "split") not in ("train", "test"):
            self.error(f"@split is {_attr(g, 'split')!r}, expected 'train' or 'test'")
        frames = _attr(g, "frames")
        if not isinstance(frames, int) or frames < 1:
            self.error(f"@frames is {frames!r}, expected a positive frame count")
            frames = None  # shapes are still checked, without the frame count
        fps = _attr(g, "fps")
        if not isinstance(fps, (int, float)) or not fps > 0:
            self.error(f"@fps is {fps!r}, expected a positive frame rate")
        self.checksums(g)
        if isinstance(g.get("body"), h5py.Group):
            self.body(g["body"], frames)
        else:
            self.error("body: missing")
        garments = g.get("garments")
        simulated = False
        if isinstance(garments, h5py.Group):
            for name in sorted(garments):
                simulated |= self.garment(garments[name], frames)
        if simulated:
            if not isinstance(g.get("sim"), h5py.Group):
                self.error("sim: missing (garments were simulated)")
            self.qa_series(g, frames)

    def body(self, b: h5py.Group, F: int | None) -> None:
        self.expect(b, "poses", (F, 72), ("float64",))
        self.expect(b, "trans", (F, 3), ("float64",))
        names = _attr(b, "shape_names", [])
        self.expect(b, "shape", (len(names),), ("float64",))
        rest = self.expect(b, "rest_vertices", (None, 3), ("float32",))
        faces = self.expect(b, "faces", (None, 3), ("int32",))
        V = rest.shape[0] if rest is not None else None
        T = faces.shape[0] if faces is not None else None
        if V is not None:
            self.index_range(faces, V, f"{V} body vertices")
        self.expect(b, "rest_joints", (24, 3), ("float32",))
        self.expect(b, "joints", (F, 24, 3), ("float32",))
        labels = self.expect(b, "part_labels", (V,), ("int16",))
        self.index_range(labels, len(_attr(b, "part_names", [])), "part_names")
        self.expect(b, "collider_face_mask", (T,), ("bool",))
        storage = _attr(b, "storage")
        if storage == "vertices":
            self.expect(b, "vertices", (F, V, 3), ("float32",))
        elif storage == "skinning":
            s = b.get("skinning")
            if not isinstance(s, h5py.Group):
                self.error("body/skinning: missing (@storage = 'skinning')")
                return
            self.expect(s, "rest_vertices", (V, 3), ("float64",))
            weights = self.expect(s, "weights", (V, None), ("float32",))
            K = weights.shape[1] if weights is not None else None
            bones = self.expect(s, "bones", (V, K), ("int32",))
            transforms = self.expect(s, "transforms", (F, None, 3, 4), ("float32",))
            if transforms is not None:
                self.index_range(bones, transforms.shape[1], f"{transforms.shape[1]} bones")
            rf = self.expect(s, "repair_frame", (None,), ("int32",))
            R = rf.shape[0] if rf is not None else None
            rv = self.expect(s, "repair_vertex", (R,), ("int32",))
            self.expect(s, "repair_offset", (R, 3), ("float32",))
            if F is not None:
                self.index_range(rf, F, f"{F} frames")
            if V is not None:
                self.index_range(rv, V, f"{V} body vertices")
        else:
            self.error(f"body/@storage is {storage!r}, expected 'skinning' or 'vertices'")

    def garment(self, g: h5py.Group, F: int | None) -> bool:
        """Checks one garment; True when it holds simulated positions."""
        rest = self.expect(g, "rest_vertices", (None, 3), ("float32",))
        V = rest.shape[0] if rest is not None else None
        faces = self.expect(g, "faces", (None, 3), ("int32",))
        if V is not None:
            self.index_range(faces, V, f"{V} garment vertices")
        self.expect(g, "start_vertices", (V, 3), ("float32",))
        self.expect(g, "uv", (V, 2), ("float32",), optional=True)
        self.expect(g, "regions", (V,), ("int16",), optional=True)
        loops = g.get("loops")
        if isinstance(loops, h5py.Group) and V is not None:
            for role in loops:
                self.index_range(self.expect(loops, role, (None,), ("int32",)), V,
                                 f"{V} garment vertices")
        for key in ("type", "fabric", "layer"):
            if key not in g.attrs:
                self.error(f"{self.rel(g)}/@{key}: missing")
            elif key != "layer" and not _attr(g, key):
                self.error(f"{self.rel(g)}/@{key}: empty")
        tightness = g.attrs.get("tightness")
        if tightness is None or np.shape(tightness) != (2,):
            self.error(f"{self.rel(g)}/@tightness: expected 2 values, got {tightness!r}")
        if "vertices" not in g:
            return False
        positions = self.expect(g, "vertices", (F, V, 3), ("float32", "int16"))
        if positions is not None and positions.dtype == np.int16:
            step = _attr(positions, "quantized_step")
            if not isinstance(step, float) or not step > 0:
                self.error(f"{self.rel(g)}/vertices: int16 without a positive @quantized_step")
            if _attr(positions, "reference") != "body/trans":
                self.error(f"{self.rel(g)}/vertices: int16 without @reference = 'body/trans'")
        return True

    def qa_series(self, g: h5py.Group, F: int | None) -> None:
        qa = g.get("qa")
        if not isinstance(qa, h5py.Group):
            self.error("qa: missing (garments were simulated)")
            return
        series = {}
        for name in QA_SERIES:
            values = _read(self.expect(qa, name, (F,), ("float32",)))
            if values is not None:
                series[name] = values.astype(np.float64)
        self.check_fabric_parameters(g)
        if self.qa == "off":
            return

        for name in SHARES:
            v = series.get(name)
            if v is not None and v.size and (v.min() < 0 or v.max() > 1):
                self.error(f"qa/{name}: values outside [0, 1]", self.qa)
        for name in ("kinetic_energy", "strain_mean"):
            v = series.get(name)
            if v is not None and v.size and v.min() < 0:
                self.error(f"qa/{name}: negative value {v.min():.4g}", self.qa)
        for breach in qa_bounds.breaches(series):
            self.error(str(breach), self.qa)
        self.neckline_slips(g)

    def neckline_slips(self, g: h5py.Group) -> None:
        """The gate's neckline bound (stages.slipped_necklines), judged again from the stored
        frames: each garment with a neckline against the body's neck joint. Missing or
        misshapen arrays are reported by the structural checks, not here."""
        body, garments = g.get("body"), g.get("garments")
        if not isinstance(body, h5py.Group) or not isinstance(garments, h5py.Group):
            return
        neck = qa_bounds.NECK_JOINT
        joints, rest = _read(body.get("joints")), _read(body.get("rest_joints"))
        if joints is None or rest is None or joints.ndim != 3 or rest.ndim != 2:
            return
        for name in sorted(garments):
            garment = garments[name]
            loops = garment.get("loops")
            if (not isinstance(loops, h5py.Group) or "neck" not in loops
                    or "vertices" not in garment or "start_vertices" not in garment):
                continue
            try:
                loop = np.asarray(loops["neck"][()], dtype=np.int64)
                breach = qa_bounds.neckline_breach(
                    read_positions(garment, "vertices")[:, loop],
                    garment["start_vertices"][()][loop], joints[:, neck], rest[neck],
                    str(_attr(garment, "category", name)))
            except (ValueError, IndexError):
                continue
            if breach is not None:
                self.error(f"garments/{name}: {breach}", self.qa)

    def check_fabric_parameters(self, g: h5py.Group) -> None:
        """Each garment's fabric as simulated (@fabric_parameters, absent in shards written
        before they were stored): a Fabric's fields, of the garment's fabric, and a warning
        where a built-in fabric was simulated with other values than this datagen's. (The
        strain bound needs none of it: qa/over_strain_share holds each spring to its own
        fabric's max_strain as simulated.)"""
        from datagen.config import from_mapping
        from datagen.errors import InputError
        from datagen.io.reader import fabric_parameters
        from datagen.sim.fabrics import FABRICS, Fabric

        garments = g.get("garments")
        if not isinstance(garments, h5py.Group):
            return
        for name in sorted(garments):
            fabric = str(_attr(garments[name], "fabric"))
            where = f"garments/{name}/@fabric_parameters"
            try:
                values = fabric_parameters(garments[name])
            except ValueError as exc:
                self.error(f"{where}: expected JSON, got {exc}")
                continue
            if values is None:
                continue
            try:
                if not isinstance(values, dict):
                    raise InputError(None, where, "a JSON mapping", type(values).__name__)
                stored = from_mapping(Fabric, values, None, where)
            except InputError as exc:
                self.error(str(exc))
                continue
            if stored.name != fabric:
                self.error(f"{where}: the parameters of {stored.name!r}, expected those of the "
                           f"garment's fabric {fabric!r}")
            elif fabric in FABRICS and stored != FABRICS[fabric]:
                self.error(f"{where}: {fabric!r} was simulated with other values than this "
                           "datagen's built-in", "warning")

    # -- a rejected sequence -------------------------------------------------------------------
    def rejected(self, g: h5py.Group) -> None:
        from datagen.errors import InputError
        from datagen.spec import SceneSpec

        try:
            SceneSpec.from_json(_attr(g, "spec", ""), source=self.file)
        except InputError as exc:
            self.error(f"rejected @spec: {exc}")
        if _attr(g, "stage") not in ("body", "simulate", "qa"):
            self.error(f"rejected @stage is {_attr(g, 'stage')!r}, expected body, simulate or qa")
        if not _attr(g, "reason"):
            self.error("rejected without a @reason")
        if np.shape(g.attrs.get("frames")) != (2,):
            self.error("rejected @frames: expected (first, last)")


# -- manifest ----------------------------------------------------------------------------------
def _check_manifest(root: Path, where: dict[str, tuple[Path, str]],
                    unreadable: set[Path]) -> list[Problem]:
    path = root / MANIFEST
    name = str(path)
    if not path.is_file():
        return [Problem(name, None, "missing: a dataset folder has a manifest.jsonl")]
    problems: list[Problem] = []
    seen: dict[str, list[int]] = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            problems.append(Problem(name, None, f"line {number}: not JSON ({exc.msg})"))
            continue
        missing = [k for k in ("id", "shard", "status")
                   if not isinstance(row, dict) or k not in row]
        if missing:
            problems.append(Problem(name, None, f"line {number}: no {', '.join(missing)}"))
            continue
        sid, status = str(row["id"]), row["status"]
        seen.setdefault(sid, []).append(number)
        listed = (root / str(row["shard"])).resolve()
        if status not in ("ok", "rejected"):
            problems.append(Problem(name, sid, f"line {number}: status {status!r}, expected "
                                    "'ok' or 'rejected'"))
        if not listed.is_file():
            problems.append(Problem(name, sid, f"line {number}: shard {row['shard']!r} does "
                                    "not exist"))
            continue
        if listed in {p.resolve() for p in unreadable}:
            continue  # that shard's own problem says it all
        if sid not in where:
            problems.append(Problem(name, sid, f"line {number}: not in {row['shard']} (nor in "
                                    "any other shard)"))
            continue
        actual, actual_status = where[sid]
        if actual.resolve() != listed:
            problems.append(Problem(name, sid, f"line {number}: listed in {row['shard']} but "
                                    f"it is in {actual.name}"))
        elif status != actual_status:
            state = "finished" if actual_status == "ok" else "rejected"
            problems.append(Problem(name, sid, f"line {number}: status {status!r} but "
                                    f"{actual.name} has it {state}"))
    for sid, lines in sorted(seen.items()):
        if len(lines) > 1:
            problems.append(Problem(name, sid, f"listed {len(lines)} times (lines "
                                    f"{', '.join(map(str, lines))}); expected once"))
    for sid, (shard, _status) in sorted(where.items()):
        if sid not in seen:
            problems.append(Problem(name, sid, f"in {shard.name} but missing from the manifest"))
    return problems
