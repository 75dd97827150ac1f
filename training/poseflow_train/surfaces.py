"""Object surfaces as point sets, for the coarse pose's verification in an
exported encoder (`Encoder.set_surfaces`): each object's mesh vertices,
thinned by farthest-point sampling so that dense and sparse parts of a
mesh weigh alike.

Units: BOP models directories are in millimetres; the points returned are
metres, in the object frame.

`twin_turns` reads which of the check's turns are symmetries of each
object's shape (`models_info_shape.json`, `poseflow import-model
--shape-symmetries`): the mesh cannot tell those apart, so the check leaves
them to the network, which sees the print of a real object."""

import json
from pathlib import Path

import numpy as np
import torch

from . import se3
from .evaluate import symmetries

# Surface points per object: the check was chosen with 1,000 (YCB-V
# development split, training/README.md); 1,024 observed points against
# 3,000 vertices scored the turns a little better there, at twelve times
# the distance table.
SURFACE_POINTS = 1000


def read_ply_vertices(path):
    """Vertex positions [n, 3] (file units) of a PLY model, ASCII or binary
    little-endian, with float x, y, z first."""
    with open(path, "rb") as f:
        header = []
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header without end_header")
            header.append(line.decode("ascii", "replace").strip())
            if header[-1] == "end_header":
                break
        fmt = next((h.split()[1] for h in header if h.startswith("format ")), None)
        count = next((int(h.split()[2]) for h in header if h.startswith("element vertex ")), None)
        if count is None:
            raise ValueError(f"{path}: PLY header has no `element vertex`")
        start = header.index(next(h for h in header if h.startswith("element vertex ")))
        props = []
        for h in header[start + 1 :]:
            if not h.startswith("property "):
                break
            props.append(h.split())
        if [p[-1] for p in props[:3]] != ["x", "y", "z"]:
            raise ValueError(f"{path}: vertex properties start {[p[-1] for p in props[:3]]}, expected x, y, z")
        if fmt == "ascii":
            rows = [f.readline().split() for _ in range(count)]
            return np.array([[float(v) for v in row[:3]] for row in rows])
        if fmt != "binary_little_endian":
            raise ValueError(f"{path}: PLY format {fmt!r}, expected ascii or binary_little_endian")
        sizes = {"float": "<f4", "float32": "<f4", "double": "<f8", "uchar": "u1", "uint8": "u1", "char": "i1",
                 "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4", "int32": "<i4", "uint32": "<u4"}
        dtype = np.dtype([(p[-1], sizes[p[1]]) for p in props])
        data = np.frombuffer(f.read(dtype.itemsize * count), dtype=dtype)
        return np.stack([data["x"], data["y"], data["z"]], -1).astype(np.float64)


def farthest_point_order(points, count, start=0):
    """Indices of `count` points [N, 3] in farthest-point order from
    `start`: every prefix is an even subsample (the set abstraction's
    centres are a prefix; the check reads prefixes too)."""
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = start
    distance = np.full(points.shape[0], np.inf)
    for i in range(1, count):
        distance = np.minimum(distance, ((points - points[chosen[i - 1]]) ** 2).sum(-1))
        chosen[i] = int(distance.argmax())
    return chosen


def surface_points(models_dir, object_ids, count=SURFACE_POINTS):
    """[objects, count, 3] float32 metres: each object's `obj_XXXXXX.ply`
    vertices (millimetres, as BOP ships them), thinned to `count`. The
    vertices' extent is checked against `models_info.json`'s diameter, so a
    mesh in metres is an error here instead of a silently wrong check."""
    models_dir = Path(models_dir)
    info_path = models_dir / "models_info.json"
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"{info_path}: {e} (the models directory needs its models_info.json)")
    out = []
    for obj_id in object_ids:
        path = models_dir / f"obj_{obj_id:06d}.ply"
        if not path.exists():
            raise SystemExit(f"{path}: missing (object {obj_id} of the model)")
        vertices = read_ply_vertices(path)
        entry = info.get(str(obj_id))
        if entry is None:
            raise SystemExit(f"{info_path}: no entry for object {obj_id}")
        extent = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        diameter = float(entry["diameter"])
        if not 0.5 * diameter <= extent <= 1.5 * diameter:
            raise SystemExit(
                f"{path}: the vertices span {extent:.4g} units but models_info.json gives a diameter of "
                f"{diameter:.4g} mm; expected the mesh in millimetres")
        chosen = vertices[farthest_point_order(vertices, min(count, len(vertices)))] / 1000.0
        if len(chosen) < count:
            chosen = chosen[np.arange(count) % len(chosen)]
        out.append(chosen)
    return torch.from_numpy(np.stack(out)).float()


# A turn within this angle of a shape symmetry is that symmetry (the turns
# are at least 90 degrees apart).
TWIN_TOLERANCE_DEG = 5.0


def twin_turns(models_dir, object_ids, turns):
    """[objects, turns] bool: turn k of `turns` [K, 3, 3] is within
    TWIN_TOLERANCE_DEG of a symmetry of the object's shape in the models
    directory's `models_info_shape.json` (discrete ones, each combined with
    the continuous ones at 1-degree steps). All false where the file is
    missing (no shape symmetries were searched for) or lists no entry."""
    path = Path(models_dir) / "models_info_shape.json"
    out = torch.zeros(len(object_ids), turns.shape[0], dtype=torch.bool)
    if not path.exists():
        return out
    try:
        table = symmetries(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"{path}: {e} (expected BOP models_info entries with symmetries)")
    for i, obj_id in enumerate(object_ids):
        rotations = torch.stack([r for r, _ in table.get(int(obj_id), [(torch.eye(3), None)])])
        angles = se3.geodesic_angle(turns[:, None].expand(-1, len(rotations), 3, 3).reshape(-1, 3, 3),
                                    rotations[None].expand(len(turns), -1, 3, 3).reshape(-1, 3, 3))
        out[i] = torch.rad2deg(angles).reshape(len(turns), -1).amin(1) < TWIN_TOLERANCE_DEG
    return out
