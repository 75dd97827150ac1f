"""Training shards written by `poseflow observe` (layout:
services/ingest/src/shard.rs): the ingest stage's own observations with
their ground truth, memory-mapped."""

import json
from pathlib import Path

import numpy as np
import torch

MAGIC = b"POSEFLOW-OBS v1"

# Which file of the dataset's models directory gives the objects'
# symmetries: the real, printed objects' as BOP records them, or the
# one-coloured shapes' (`poseflow import-model --shape-symmetries`), up to
# which renders without the print are ambiguous.
SYMMETRY_FILES = {"models-info": "models_info.json", "shape": "models_info_shape.json"}


class Shard:
    def __init__(self, path, symmetries="models-info"):
        if symmetries not in SYMMETRY_FILES:
            raise SystemExit(f"symmetries {symmetries!r}: expected one of {sorted(SYMMETRY_FILES)}")
        self.symmetry_file = SYMMETRY_FILES[symmetries]
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
        """The dataset's models_info.json (or its shape twin, see
        `SYMMETRY_FILES`): where the shard says the dataset is (relative to
        where `poseflow observe` ran), or the shard's own folder (where
        training/make-data puts it)."""
        for root in (Path(self.info["dataset"]), self.path.parent):
            candidate = root / "models" / self.symmetry_file
            if candidate.is_file():
                return candidate
        raise ValueError(
            f"{self.path}: no models/{self.symmetry_file} under {self.info['dataset']!r} or {str(self.path.parent)!r} "
            "(needed for the objects' symmetries"
            + ("; `poseflow import-model --shape-symmetries` writes it)" if self.symmetry_file != "models_info.json" else ")")
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


# Category codes of a category-level model's `object_ids`: REAL275's (NOCS)
# class ids, so a detector trained on its classes names them alike.
CATEGORY_IDS = {"bottle": 1, "bowl": 2, "camera": 3, "can": 4, "laptop": 5, "mug": 6}
# The categories whose shapes (and colours) every turn about their y axis
# leaves unchanged (`shared/scene/src/category.rs`).
SYMMETRIC_ABOUT_Y = ("bottle", "bowl", "can")


def category_models_info(object_ids):
    """A models_info-like dict {category code: entry} giving each category
    the symmetry its generated instances share: continuous about y for
    bottles, bowls and cans, none for mugs (a hidden handle is an ambiguity
    of the view, not of the shape)."""
    names = {code: name for name, code in CATEGORY_IDS.items()}
    unknown = [code for code in object_ids if code not in names]
    if unknown:
        raise SystemExit(f"model.object_ids: {unknown[0]} is no category code; expected one of {sorted(names)} "
                         f"({', '.join(f'{c} {n}' for n, c in sorted(CATEGORY_IDS.items(), key=lambda x: x[1]))})")
    axis = [{"axis": [0, 1, 0], "offset": [0, 0, 0]}]
    return {str(code): {"symmetries_continuous": axis} if names[code] in SYMMETRIC_ABOUT_Y else {} for code in object_ids}


def read_categories(shard):
    """{obj_id: (category code, size [3] metres)} from the categories.json
    beside the shard's models_info.json (`poseflow generate-objects`)."""
    path = Path(shard.models_info).with_name("categories.json")
    if not path.is_file():
        raise SystemExit(f"{shard.path}: no {path} (a category model trains on `poseflow generate-objects` libraries)")
    out = {}
    for key, entry in json.loads(path.read_text()).items():
        if entry["category"] not in CATEGORY_IDS:
            raise SystemExit(f"{path}: object {key}: category {entry['category']!r}, expected one of {sorted(CATEGORY_IDS)}")
        out[int(key)] = (CATEGORY_IDS[entry["category"]], np.asarray(entry["size_mm"], dtype=np.float32) / 1000.0)
    return out


class Observations:
    """Several shards as one indexable set, filtered by visibility and
    object, yielding torch batches. With `categories`, `object_ids` are
    category codes (`CATEGORY_IDS`) and each observation's object index is
    its instance's category (from each shard's categories.json); batches
    then also hold the instance's `size` (box extents, metres).
    `symmetries` names the symmetry file (`SYMMETRY_FILES`)."""

    def __init__(self, paths, object_ids, min_visib_fract=0.1, hidden_arcs=False, categories=False,
                 symmetries="models-info"):
        self.shards = [Shard(p, symmetries) for p in paths]
        # Per shard, {obj_id: (category code, size)} of a category model.
        self.categories = [read_categories(shard) for shard in self.shards] if categories else None
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
            ids = self.model_ids(k, shard.records["ids"][:, 0])
            keep = (shard.records["visib_fract"] >= min_visib_fract) & np.isin(ids, list(self.object_index))
            self.index.extend((k, int(i)) for i in np.nonzero(keep)[0])
        norm = first["normalisation"]
        self.mean = torch.tensor(norm["mean"]).reshape(1, 3, 1, 1)
        self.std = torch.tensor(norm["std"]).reshape(1, 3, 1, 1)

    def model_ids(self, k, obj_ids):
        """The ids the model knows the objects of shard `k` by: their own,
        or their category's code."""
        if self.categories is None:
            return np.asarray(obj_ids)
        table = self.categories[k]
        missing = [int(o) for o in obj_ids if int(o) not in table]
        if missing:
            raise SystemExit(f"{self.shards[k].path}: object {missing[0]} has no entry in its categories.json")
        return np.array([table[int(o)][0] for o in obj_ids], dtype=np.int64)

    def __len__(self):
        return len(self.index)

    def rows(self, indices):
        """(shard index, record) of each position."""
        return [(k, self.shards[k].records[i]) for k, i in (self.index[j] for j in indices)]

    def identities(self, rows):
        """`object_index`, `obj_id` and, for a category model, `size`."""
        obj = np.stack([r["ids"] for _, r in rows])[:, 0].astype(np.int64)
        keys = [int(self.model_ids(k, [r["ids"][0]])[0]) for k, r in rows]
        out = {"object_index": torch.tensor([self.object_index[key] for key in keys]), "obj_id": torch.from_numpy(obj)}
        if self.categories is not None:
            out["size"] = torch.from_numpy(np.stack([self.categories[k][int(r["ids"][0])][1] for k, r in rows]))
        return out

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
        tagged = self.rows(indices)
        rows = [r for _, r in tagged]
        centroid = torch.from_numpy(np.stack([r["centroid"] for r in rows]))
        return {
            **self.identities(tagged),
            "rotation": torch.from_numpy(np.stack([r["rotation"] for r in rows])).reshape(-1, 3, 3),
            "translation": torch.from_numpy(np.stack([r["translation"] for r in rows])) - centroid,
        }

    def batch(self, indices):
        """A dict of tensors for the given positions in this set."""
        tagged = self.rows(indices)
        rows = [r for _, r in tagged]
        s, n = self.info["image_size"], self.info["point_count"]
        image = torch.from_numpy(np.stack([r["image"] for r in rows]).astype(np.float32)).reshape(-1, 3, s, s)
        centroid = torch.from_numpy(np.stack([r["centroid"] for r in rows]))
        return {
            "image": (image / 255.0 - self.mean) / self.std,
            "token_mask": torch.from_numpy(np.stack([r["token_mask"] for r in rows]).astype(np.float32)),
            "points": torch.from_numpy(np.stack([r["points"] for r in rows])).reshape(-1, n, 3),
            **self.identities(tagged),
            "rotation": torch.from_numpy(np.stack([r["rotation"] for r in rows])).reshape(-1, 3, 3),
            # The pose's translation relative to the observed points' mean.
            "translation": torch.from_numpy(np.stack([r["translation"] for r in rows])) - centroid,
        }
