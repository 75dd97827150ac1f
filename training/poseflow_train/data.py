"""Training shards written by `poseflow observe` (layout:
services/ingest/src/shard.rs): the ingest stage's own observations with
their ground truth, memory-mapped."""

import json
from pathlib import Path

import numpy as np
import torch

MAGIC = b"POSEFLOW-OBS v1"


class Shard:
    def __init__(self, path):
        self.path = Path(path)
        with open(self.path, "rb") as f:
            magic = f.readline().rstrip(b"\n")
            if magic != MAGIC:
                raise ValueError(f"{self.path}: not a PoseFlow observation shard (first line {magic[:40]!r})")
            self.info = json.loads(f.readline())
            offset = f.tell()
        s, p, n = self.info["image_size"], self.info["patch_grid"], self.info["point_count"]
        self.dtype = np.dtype(
            [
                ("ids", "<u4", 4),
                ("rotation", "<f4", 9),
                ("translation", "<f4", 3),
                ("centroid", "<f4", 3),
                ("crop", "<f4", 4),
                ("intrinsics", "<f4", 4),
                ("valid_points", "<u4"),
                ("visib_fract", "<f4"),
                ("token_mask", "u1", p * p),
                ("image", "u1", 3 * s * s),
                ("points", "<f4", 3 * n),
            ]
        )
        if self.dtype.itemsize != self.info["record_bytes"]:
            raise ValueError(f"{self.path}: records of {self.info['record_bytes']} bytes, expected {self.dtype.itemsize}")
        size = self.path.stat().st_size - offset
        if size % self.dtype.itemsize:
            raise ValueError(f"{self.path}: {size} bytes of records is not a whole number of records")
        self.models_info = self.find_models_info()
        self.records = np.memmap(self.path, dtype=self.dtype, mode="r", offset=offset, shape=(size // self.dtype.itemsize,))

    def find_models_info(self):
        """The dataset's models_info.json: where the shard says the dataset
        is (relative to where `poseflow observe` ran), or the shard's own
        folder (where training/make-data puts it)."""
        for root in (Path(self.info["dataset"]), self.path.parent):
            candidate = root / "models" / "models_info.json"
            if candidate.is_file():
                return candidate
        raise ValueError(
            f"{self.path}: no models/models_info.json under {self.info['dataset']!r} or {str(self.path.parent)!r} "
            "(needed for the objects' symmetries)"
        )

    def __len__(self):
        return len(self.records)


def load_arcs(shard):
    """The hidden-part turns written beside a shard by `poseflow_train.arcs`."""
    path = shard.path.with_suffix(".arcs.npz")
    if not path.is_file():
        raise SystemExit(f"{path}: missing; write it with `python -m poseflow_train.arcs {shard.path}` (hidden_arcs)")
    saved = np.load(path)
    turns = saved["turns"]
    if tuple(saved["turn_axis"]) != (0.0, 0.0, 1.0):
        raise SystemExit(f"{path}: turns about {tuple(saved['turn_axis'])}; training draws them about object z")
    if len(turns) != len(shard):
        raise SystemExit(f"{path}: {len(turns)} rows for {len(shard)} observations; write it again")
    return turns


class Observations:
    """Several shards as one indexable set, filtered by visibility and
    object, yielding torch batches."""

    def __init__(self, paths, object_ids, min_visib_fract=0.1, hidden_arcs=False):
        self.shards = [Shard(p) for p in paths]
        # Per shard, the turns that keep a part hidden ([records, bins]
        # bool, `poseflow_train.arcs`), when asked for.
        self.arcs = [load_arcs(shard) for shard in self.shards] if hidden_arcs else None
        first = self.shards[0].info
        for shard in self.shards[1:]:
            for key in ("image_size", "patch_grid", "point_count"):
                if shard.info[key] != first[key]:
                    raise ValueError(f"{shard.path}: {key} {shard.info[key]} differs from {first[key]}")
        self.info = first
        self.models_info = self.shards[0].models_info
        self.object_index = {obj: i for i, obj in enumerate(object_ids)}
        self.index = []
        for k, shard in enumerate(self.shards):
            ids = shard.records["ids"][:, 0]
            keep = (shard.records["visib_fract"] >= min_visib_fract) & np.isin(ids, list(self.object_index))
            self.index.extend((k, int(i)) for i in np.nonzero(keep)[0])
        norm = first["normalisation"]
        self.mean = torch.tensor(norm["mean"]).reshape(1, 3, 1, 1)
        self.std = torch.tensor(norm["std"]).reshape(1, 3, 1, 1)

    def __len__(self):
        return len(self.index)

    def obj_ids(self):
        """The object id of every observation, in index order."""
        return np.array([int(self.shards[k].records["ids"][i, 0]) for k, i in self.index], dtype=np.int64)

    def hidden_turns(self, indices):
        """[B, bins] bool: the turns (`poseflow_train.arcs`) that keep the
        observation's part hidden; all false where none does."""
        return torch.from_numpy(np.stack([self.arcs[k][i] for k, i in (self.index[j] for j in indices)]))

    def poses(self, indices):
        """The ground truth alone (what training on cached conditions needs):
        `rotation`, `translation` (relative to the observed points' mean),
        `object_index` and `obj_id` of the given positions."""
        rows = [self.shards[k].records[i] for k, i in (self.index[j] for j in indices)]
        ids = np.stack([r["ids"] for r in rows])
        centroid = torch.from_numpy(np.stack([r["centroid"] for r in rows]))
        return {
            "object_index": torch.tensor([self.object_index[int(o)] for o in ids[:, 0]]),
            "obj_id": torch.from_numpy(ids[:, 0].astype(np.int64)),
            "rotation": torch.from_numpy(np.stack([r["rotation"] for r in rows])).reshape(-1, 3, 3),
            "translation": torch.from_numpy(np.stack([r["translation"] for r in rows])) - centroid,
        }

    def batch(self, indices):
        """A dict of tensors for the given positions in this set."""
        rows = [self.shards[k].records[i] for k, i in (self.index[j] for j in indices)]
        s, n = self.info["image_size"], self.info["point_count"]
        image = torch.from_numpy(np.stack([r["image"] for r in rows]).astype(np.float32)).reshape(-1, 3, s, s)
        ids = np.stack([r["ids"] for r in rows])
        centroid = torch.from_numpy(np.stack([r["centroid"] for r in rows]))
        return {
            "image": (image / 255.0 - self.mean) / self.std,
            "token_mask": torch.from_numpy(np.stack([r["token_mask"] for r in rows]).astype(np.float32)),
            "points": torch.from_numpy(np.stack([r["points"] for r in rows])).reshape(-1, n, 3),
            "object_index": torch.tensor([self.object_index[int(o)] for o in ids[:, 0]]),
            "obj_id": torch.from_numpy(ids[:, 0].astype(np.int64)),
            "rotation": torch.from_numpy(np.stack([r["rotation"] for r in rows])).reshape(-1, 3, 3),
            # The pose's translation relative to the observed points' mean.
            "translation": torch.from_numpy(np.stack([r["translation"] for r in rows])) - centroid,
        }
