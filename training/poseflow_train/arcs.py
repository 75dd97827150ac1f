"""Hidden-part arcs: for every observation of an object with a part that
can hide (the YCB-V mug's handle), the turns about the object's body axis
that keep the part out of sight. Each such turn of the true pose explains
the view as well as the truth does, so training draws its flow targets
from all of them (`hidden_arcs` in a config) instead of teaching the one
the renderer happened to pick.

    python -m poseflow_train.arcs data/lmo10/train_c*.obs

writes `<shard>.arcs.npz` beside each shard: `turns` [records, BINS] bool
(all false where the part is in view or the object has no part),
`obj_id`, `turn_axis` and `bin_deg`. A turn is judged from the rendered
depth image: the part's model points, turned, are projected with the
camera; a point is seen when it lies in the image, where depth was
measured, and not behind the measured surface by more than `tolerance`
(so the object's own body and other objects hide it, the background does
not). The part is hidden when at most `hidden_pixels` (scaled from
640 x 480 to the image's area, as `shared/scene/src/part.rs` counts them
for `poseflow render --mug-handle`) distinct pixels see it.

Convention: object frame as in the BOP models (metres here), camera frame
x right, y down, z forward; a turn by phi about `turn_axis` (through the
object origin) is the pose R @ exp(phi * axis), t unchanged.
"""

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from . import se3
from .data import Shard
from .surfaces import read_ply_vertices

BINS = 36

# The YCB-V mug (`025_mug`, BOP id 14): body a cylinder about object z
# through the origin; handle the points with x > 5 cm.
MUG = {"obj_id": 14, "part_axis": (1.0, 0.0, 0.0), "beyond_m": 0.05, "turn_axis": (0.0, 0.0, 1.0)}


def turn(axis, phi):
    """Rotation matrix (numpy, float64) of angle phi (radians) about `axis`."""
    a = torch.tensor(axis, dtype=torch.float64)
    return se3.so3_exp(a / a.norm() * phi).numpy()


def seen_pixels(part_points, rotation, translation, depth, intrinsics, tolerance):
    """Distinct pixels at which the camera would see any of `part_points`
    (object frame, metres) of an object at (rotation, translation), given
    the measured `depth` (metres, 0 = no measurement) and intrinsics
    (fx, fy, cx, cy)."""
    camera = part_points @ rotation.T + translation
    fx, fy, cx, cy = intrinsics
    z = camera[:, 2]
    front = z > 1e-6
    u = np.floor(fx * camera[front, 0] / z[front] + cx).astype(np.int64)
    v = np.floor(fy * camera[front, 1] / z[front] + cy).astype(np.int64)
    z = z[front]
    h, w = depth.shape
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[inside], v[inside], z[inside]
    d = depth[v, u]
    seen = (d > 0) & (z < d + tolerance)
    return len(np.unique(v[seen] * w + u[seen]))


def hidden_turns(part_points, rotation, translation, depth, intrinsics, turn_axis, hidden_pixels, tolerance=0.01):
    """[BINS] bool: the turns k * 360/BINS degrees about `turn_axis` that
    keep the part hidden; all false when the part is seen at the pose
    itself (then the view shows where it is)."""
    limit = hidden_pixels * depth.size / (640 * 480)
    out = np.zeros(BINS, dtype=bool)
    for k in range(BINS):
        r = rotation @ turn(turn_axis, 2 * math.pi * k / BINS)
        out[k] = seen_pixels(part_points, r, translation, depth, intrinsics, tolerance) <= limit
        if k == 0 and not out[0]:
            return np.zeros(BINS, dtype=bool)
    return out


def shard_arcs(shard, part=MUG, hidden_pixels=10.0):
    """`turns` [records, BINS] of one shard (see the module doc)."""
    # The dataset is where its models_info.json was found.
    models = shard.models_info.parent
    root = models.parent
    points = read_ply_vertices(models / f"obj_{part['obj_id']:06d}.ply") / 1000.0
    points = points[points @ np.asarray(part["part_axis"]) > part["beyond_m"]]
    split = root / shard.info["split"]
    cameras = {}
    turns = np.zeros((len(shard), BINS), dtype=bool)
    ids = shard.records["ids"]
    for i in np.nonzero(ids[:, 0] == part["obj_id"])[0]:
        scene, image = int(ids[i, 1]), int(ids[i, 2])
        if scene not in cameras:
            cameras[scene] = json.loads((split / f"{scene:06d}" / "scene_camera.json").read_text())
        camera = cameras[scene][str(image)]
        depth_path = split / f"{scene:06d}" / "depth" / f"{image:06d}.png"
        depth = np.asarray(Image.open(depth_path), dtype=np.float64) * camera.get("depth_scale", 1.0) / 1000.0
        k = camera["cam_K"]
        record = shard.records[i]
        rotation = record["rotation"].reshape(3, 3).astype(np.float64)
        translation = record["translation"].astype(np.float64)
        turns[i] = hidden_turns(points, rotation, translation, depth, (k[0], k[4], k[2], k[5]), part["turn_axis"],
                                hidden_pixels)
    return turns


def arcs_path(shard_path):
    return Path(shard_path).with_suffix(".arcs.npz")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("shards", nargs="+", help="observation shards (.obs) of a dataset rendered by `poseflow render`")
    args = parser.parse_args()
    for path in args.shards:
        shard = Shard(path)
        turns = shard_arcs(shard)
        np.savez(arcs_path(path), turns=turns, obj_id=MUG["obj_id"], turn_axis=np.array(MUG["turn_axis"]),
                 bin_deg=360.0 / BINS)
        part_rows = shard.records["ids"][:, 0] == MUG["obj_id"]
        hidden = turns.any(1)
        print(f"{path}: {part_rows.sum()} observations of object {MUG['obj_id']}, {hidden.sum()} with the part hidden, "
              f"median arc {np.median(turns[hidden].sum(1)) * 360 / BINS if hidden.any() else 0:.0f} deg", flush=True)


if __name__ == "__main__":
    main()
