"""The detector's identifier: which object of the set (or none) one
segmented region is, from a crop around it.

The segmentation network labels every pixel, but its receptive field is a
fraction of an object, and on the development renders most of the objects
it misses are found whole and labelled as *another* object (an egg box as
the can, the glue as the driller). This network sees the whole region at a
fixed size beside its depth relief and its metric size, the way a second
stage of a two-stage detector does, and the detector stage relabels each
region with its answer (services/detector/src/identify.rs).

Its input, built the same way here and in the stage, on the frame's
"grid": every other pixel, cell (x, y) being frame pixel (2x + 1, 2y + 1),
so the detect data's `.detect2.npz` arrays are that grid:

- the crop is a square of `side = CONTEXT · max(box rows, box columns) + 2`
  cells centred on the region's box; CROP × CROP samples, sample i at cell
  floor(centre − side/2 + (i + ½)·side/CROP) (outside the grid: zeros);
- channels: R, G, B / 255; depth relative to the region's median depth
  z₀, (z − z₀)/RELIEF_M clamped to ±1 (0 without depth); 1 where depth was
  measured; 1 on the region's cells; the crop's side in metres
  (side · 2 · z₀ / fx) / SIZE_M everywhere.

Output: N × (1 + objects) probabilities, class 0 being "none of them".

    python -m poseflow_train.identify regions --data data/detect-lmo10 --detector ../target/detector-fine
    python -m poseflow_train.identify train --data data/detect-lmo10 --out checkpoints/identify-lmo10 --max-minutes 40
    python -m poseflow_train.identify export --checkpoint checkpoints/identify-lmo10 --data data/detect-lmo10 --out ../models/detector-lmo10
"""

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from poseflow_train.detector import add_export_command, block, conv, descend, export_onnx, learning_rate, read_split, write_entry

CROP = 48
CONTEXT = 1.25
RELIEF_M = 0.15
SIZE_M = 0.3
CHANNELS = 7
GRID_DOWN = 2
# A region this small (grid cells) is not identified: the stage drops it
# anyway (64 frame pixels).
MIN_CELLS = 16
FORMAT = "poseflow-identify/1"


def components(labels):
    """Same-label 4-connected regions of N × H × W labels (0 = background):
    an int64 array of region ids (−1 on background); an id is the flat index
    of one of its cells."""
    n, h, w = labels.shape
    size = n * h * w
    big = np.int64(size)
    ids = np.where(labels > 0, np.arange(size, dtype=np.int64).reshape(n, h, w), big)
    while True:
        m = ids.copy()
        for axis in (1, 2):
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            a[axis], b[axis] = slice(1, None), slice(None, -1)
            a, b = tuple(a), tuple(b)
            same = (labels[a] == labels[b]) & (labels[a] > 0)
            m[a] = np.where(same, np.minimum(m[a], ids[b]), m[a])
            m[b] = np.where(same, np.minimum(m[b], ids[a]), m[b])
        flat = m.reshape(-1)
        fg = flat < big
        for _ in range(4):  # pointer jumping: follow each cell's id to that cell's id
            flat[fg] = flat[flat[fg]]
        if np.array_equal(m, ids):
            break
        ids = m
    return np.where(ids < big, ids, -1)


def crop_input(rgb, depth_mm, region, fx, box=None):
    """One region's CHANNELS × CROP × CROP input. `rgb` H × W × 3 uint8,
    `depth_mm` H × W, `region` H × W bool, all on the grid; `box` (x0, y0,
    x1, y1) inclusive, default the region's bounds."""
    h, w = region.shape
    if box is None:
        ys, xs = np.nonzero(region)
        box = (xs.min(), ys.min(), xs.max(), ys.max())
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1 + 1) / 2.0, (y0 + y1 + 1) / 2.0
    side = CONTEXT * max(x1 - x0 + 1, y1 - y0 + 1) + 2.0
    steps = (np.arange(CROP) + 0.5) * side / CROP
    gx = np.floor(cx - side / 2.0 + steps).astype(np.int64)
    gy = np.floor(cy - side / 2.0 + steps).astype(np.int64)
    inside = ((gy >= 0) & (gy < h))[:, None] & ((gx >= 0) & (gx < w))[None, :]
    yy, xx = np.clip(gy, 0, h - 1)[:, None], np.clip(gx, 0, w - 1)[None, :]
    z = depth_mm.astype(np.float32) / 1000.0
    measured = z[region]
    measured = np.sort(measured[measured > 0])
    z0 = float(measured[(len(measured) - 1) // 2]) if len(measured) else 0.0
    out = np.zeros((CHANNELS, CROP, CROP), np.float32)
    out[0:3] = rgb[yy, xx].transpose(2, 0, 1).astype(np.float32) / 255.0
    zc = z[yy, xx]
    valid = (zc > 0) & (z0 > 0)
    out[3] = np.where(valid, np.clip((zc - z0) / RELIEF_M, -1.0, 1.0), 0.0)
    out[4] = zc > 0
    out[5] = region[yy, xx]
    out[6] = side * GRID_DOWN * z0 / fx / SIZE_M
    out[:6] *= inside
    return out


def regions(args):
    """The segmentation network's regions on every training image and the
    test split: each region's image, class and grid cells, and the class the
    annotation gives most of its cells (0 where background is most)."""
    import onnxruntime

    data = Path(args.data)
    meta = json.loads((Path(args.detector) / "detector.json").read_text())
    if meta["input"]["down"] != GRID_DOWN:
        raise SystemExit(f"{args.detector}: a network on the {GRID_DOWN}-pixel grid is needed, not down {meta['input']['down']}")
    weights = np.asarray(meta["class_weights"], np.float32)
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = args.threads
    session = onnxruntime.InferenceSession(str(Path(args.detector) / "detector.onnx"), options, providers=["CPUExecutionProvider"])
    splits = sorted(p.name for p in data.iterdir() if p.is_dir() and p.name.startswith("train_")) + ["test"]
    from poseflow_train.detector import to_input

    for split in splits:
        out = data / f"{split}.regions.npz"
        if out.exists():
            continue
        rgb, depth_mm, truth = read_split(data, split, meta["object_ids"], GRID_DOWN)
        predicted = np.zeros_like(truth)
        for i in range(0, len(rgb), 8):
            p = session.run(None, {"rgbd": to_input(rgb[i : i + 8], depth_mm[i : i + 8]).numpy()})[0]
            predicted[i : i + 8] = (p / weights[None, :, None, None]).argmax(1)
        ids = components(predicted)
        flat_ids, flat_truth, flat_pred = ids.reshape(-1), truth.reshape(-1), predicted.reshape(-1)
        order = np.argsort(flat_ids, kind="stable")
        order = order[flat_ids[order] >= 0]
        starts = np.flatnonzero(np.r_[True, flat_ids[order][1:] != flat_ids[order][:-1]])
        image, cls, majority, offsets, cells = [], [], [], [0], []
        plane = truth.shape[1] * truth.shape[2]
        for k, s in enumerate(starts):
            e = starts[k + 1] if k + 1 < len(starts) else len(order)
            member = order[s:e]
            if len(member) < MIN_CELLS:
                continue
            counts = np.bincount(flat_truth[member], minlength=len(meta["object_ids"]) + 1)
            image.append(member[0] // plane)
            cls.append(flat_pred[member[0]])
            majority.append(counts.argmax())
            cells.append(member % plane)
            offsets.append(offsets[-1] + len(member))
        np.savez(
            out,
            image=np.asarray(image, np.int32),
            predicted=np.asarray(cls, np.uint8),
            majority=np.asarray(majority, np.uint8),
            offsets=np.asarray(offsets, np.int64),
            cells=np.concatenate(cells).astype(np.int32) if cells else np.zeros(0, np.int32),
        )
        wrong = sum(1 for c, m in zip(cls, majority) if c != m)
        print(f"{split}: {len(image)} regions, {wrong} whose label is not the annotation's majority", flush=True)


class Identifier(nn.Module):
    """48 → 24 → 12 → 6 cells, pooled, then a linear layer."""

    def __init__(self, classes, width=24):
        super().__init__()
        w = [width, 2 * width, 4 * width]
        self.body = nn.Sequential(conv(CHANNELS, w[0], 3, 2), block(w[0], w[1], 2), block(w[1], w[2], 2), conv(w[2], 2 * w[2]))
        self.head = nn.Linear(2 * w[2], classes)

    def forward(self, x):
        return self.head(self.body(x).mean(dim=(2, 3)))


def grown(region, by):
    """The region dilated (by > 0) or eroded (by < 0) by |by| cells (square)."""
    out = region
    for _ in range(abs(by)):
        p = np.pad(out, 1, constant_values=(by < 0))
        stack = [p[1 + dy : 1 + dy + out.shape[0], 1 + dx : 1 + dx + out.shape[1]] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        out = np.logical_or.reduce(stack) if by > 0 else np.logical_and.reduce(stack)
    return out


class Examples:
    """Training or validation examples: annotated regions (each object of an
    image, jittered like a segmentation's) and the segmentation network's
    regions labelled by the annotation's majority (the false alarms are the
    'none' examples)."""

    def __init__(self, data, splits, object_ids, fx):
        parts = [read_split(data, s, object_ids, GRID_DOWN) for s in splits]
        self.rgb, self.depth_mm, self.truth = (np.concatenate([p[i] for p in parts]) for i in range(3))
        self.fx = fx
        self.classes = len(object_ids) + 1
        image, majority, cells = [], [], []
        base = 0
        for s, p in zip(splits, parts):
            with np.load(Path(data) / f"{s}.regions.npz") as r:
                r = {key: r[key] for key in ("image", "majority", "offsets", "cells")}
            image += [base + int(i) for i in r["image"]]
            majority += [int(m) for m in r["majority"]]
            cells += np.split(r["cells"], r["offsets"][1:-1])
            base += len(p[0])
        self.network = (np.asarray(image), np.asarray(majority), cells)
        # Annotated regions: (image, class) with enough cells.
        present = []
        for i, t in enumerate(self.truth):
            counts = np.bincount(t.reshape(-1), minlength=self.classes)
            present += [(i, c) for c in range(1, self.classes) if counts[c] >= MIN_CELLS]
        self.annotated = np.asarray(present)

    def one(self, rng, jitter):
        """An input and its class."""
        h, w = self.truth.shape[1:]
        if rng.random() < 0.5:
            i, c = self.annotated[rng.integers(len(self.annotated))]
            region = self.truth[i] == c
            if jitter:
                region = grown(region, int(rng.integers(-1, 2)))
                if rng.random() < 0.3:  # a straight cut through the region, as a detector's fragment
                    ys, xs = np.nonzero(region)
                    if len(ys):
                        angle = rng.uniform(0, 2 * math.pi)
                        d = np.cos(angle) * (np.arange(w)[None, :] - xs.mean()) + np.sin(angle) * (np.arange(h)[:, None] - ys.mean())
                        region = region & (d < rng.uniform(-0.2, 1.0) * d[region].std())
                if region.sum() < MIN_CELLS:
                    region = self.truth[i] == c
        else:
            images, majority, cells = self.network
            k = rng.integers(len(images))
            i, c = images[k], majority[k]
            region = np.zeros(h * w, bool)
            region[cells[k]] = True
            region = region.reshape(h, w)
        ys, xs = np.nonzero(region)
        box = [xs.min(), ys.min(), xs.max(), ys.max()]
        if jitter:  # a box a little off the region's, both ways
            span = max(box[2] - box[0], box[3] - box[1]) + 1
            box = [b + int(round(rng.normal(0, 0.05) * span)) for b in box]
            box = [min(box[0], box[2]), min(box[1], box[3]), max(box[0], box[2]), max(box[1], box[3])]
        rgb = self.rgb[i]
        if jitter:
            gain = rng.uniform(0.7, 1.3, size=3)
            rgb = np.clip(rgb.astype(np.float32) * gain + rng.uniform(-20, 20), 0, 255).astype(np.uint8)
        x = crop_input(rgb, self.depth_mm[i], region, self.fx, box)
        if jitter and rng.random() < 0.5:
            x = x[:, :, ::-1].copy()
        return x, int(c)

    def batch(self, n, rng, jitter):
        xs, ys = zip(*(self.one(rng, jitter) for _ in range(n)))
        return torch.as_tensor(np.stack(xs)), torch.as_tensor(ys, dtype=torch.long)


def fx_of(data):
    return float(json.loads((Path(data) / "camera.json").read_text())["fx"])


def train(args):
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info = json.loads((Path(args.data) / "models" / "models_info.json").read_text())
    object_ids = sorted(int(k) for k in info)
    (out / "identify.json").write_text(json.dumps({"object_ids": object_ids, "width": args.width}, indent=1))
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    fx = fx_of(args.data)
    splits = sorted(p.name for p in Path(args.data).iterdir() if p.is_dir() and p.name.startswith("train_"))
    examples = Examples(args.data, splits, object_ids, fx)
    validation = Examples(args.data, ["test"], object_ids, fx)
    val_rng = np.random.default_rng(12345)
    val_x, val_y = validation.batch(1024, val_rng, jitter=False)
    model = Identifier(len(object_ids) + 1, args.width)
    optimiser = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    step, elapsed = 0, 0.0
    checkpoint = out / "identify.pt"
    if checkpoint.exists():
        state = torch.load(checkpoint, weights_only=False)
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        step, elapsed = state["step"], state["elapsed_s"]
        print(f"resumed at step {step} after {elapsed / 60:.1f} min", flush=True)
    rng = np.random.default_rng(step)
    started, saved = time.time() - elapsed, time.time()
    log = open(out / "identify-log.jsonl", "a")
    print(
        f"{len(examples.annotated)} annotated and {len(examples.network[0])} network regions; "
        f"{sum(p.numel() for p in model.parameters())} parameters",
        flush=True,
    )
    while (time.time() - started) < 60 * args.max_minutes + elapsed:
        model.train()
        rate = learning_rate(args.lr, time.time() - started, 60 * args.lr_decay_minutes)
        for group in optimiser.param_groups:
            group["lr"] = rate
        x, y = examples.batch(args.batch, rng, jitter=True)
        loss = F.cross_entropy(model(x), y)
        descend(optimiser, loss)
        step += 1
        if step % 50 == 0:
            entry = {"step": step, "train_s": round(time.time() - started, 1), "loss": loss.item(), "lr": rate}
            if step % 250 == 0:
                model.eval()
                with torch.no_grad():
                    predicted = model(val_x).argmax(1)
                model.train()
                entry["validation"] = {
                    "accuracy": round(float((predicted == val_y).float().mean()), 4),
                    "objects_accuracy": round(float((predicted == val_y)[val_y > 0].float().mean()), 4),
                }
            write_entry(log, entry)
        if time.time() - saved > args.checkpoint_s:
            torch.save({"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step, "elapsed_s": time.time() - started}, checkpoint)
            saved = time.time()
    torch.save({"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step, "elapsed_s": time.time() - started}, checkpoint)


class Exported(nn.Module):
    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, crops):
        return torch.softmax(self.model(crops), dim=1)


def export(args):
    source = Path(args.checkpoint)
    config = json.loads((source / "identify.json").read_text())
    model = Identifier(len(config["object_ids"]) + 1, config["width"])
    state = torch.load(source / "identify.pt", weights_only=False)
    model.load_state_dict(state["model"])
    model.eval()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    exported = Exported(model).eval()
    export_onnx(exported, torch.zeros(1, CHANNELS, CROP, CROP), out / "identify.onnx", "crops")
    meta = {
        "format": FORMAT,
        "object_ids": config["object_ids"],
        "crop": CROP,
        "context": CONTEXT,
        "relief_m": RELIEF_M,
        "size_m": SIZE_M,
        "grid_down": GRID_DOWN,
        "training": {"step": state["step"], "train_minutes": round(state["elapsed_s"] / 60, 1)},
    }
    (out / "identify.json").write_text(json.dumps(meta, indent=1) + "\n")
    write_parity(out, args.data, config["object_ids"], exported)
    print(f"exported step {state['step']} to {out}")


def write_parity(out, data, object_ids, exported):
    """`identify-parity.bin`: the first validation image on the grid (rows,
    columns as u32; RGB u8, depth mm u16 LE, annotated labels u8), then each
    annotated region of at least MIN_CELLS cells in raster order of its
    first cell: its probabilities through the exported network (u32 count,
    then count × classes f32 LE)."""
    import onnxruntime

    rgb, depth_mm, truth = (a[0] for a in read_split(data, "test", object_ids, GRID_DOWN))
    ids = components(truth[None])[0]
    firsts = sorted(i for i in np.unique(ids) if i >= 0 and (ids == i).sum() >= MIN_CELLS)
    crops = np.stack([crop_input(rgb, depth_mm, ids == i, fx_of(data)) for i in firsts])
    session = onnxruntime.InferenceSession(str(out / "identify.onnx"), providers=["CPUExecutionProvider"])
    probabilities = session.run(None, {"crops": crops})[0]
    with torch.no_grad():
        reference = exported(torch.as_tensor(crops)).numpy()
    with open(out / "identify-parity.bin", "wb") as f:
        f.write(np.asarray(truth.shape, "<u4").tobytes())
        f.write(rgb.astype(np.uint8).tobytes())
        f.write(depth_mm.astype("<u2").tobytes())
        f.write(truth.astype(np.uint8).tobytes())
        f.write(np.asarray([len(firsts)], "<u4").tobytes())
        f.write(probabilities.astype("<f4").tobytes())
    answers = probabilities.argmax(1)
    own = [int(truth.reshape(-1)[i]) for i in firsts]
    print(f"parity: {len(firsts)} regions, {sum(int(a == o) for a, o in zip(answers, own))} identified as annotated; "
          f"max |onnx - torch| = {np.abs(probabilities - reference).max():.2e}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("regions")
    r.add_argument("--data", required=True)
    r.add_argument("--detector", required=True, help="an exported segmentation network on the 2-pixel grid (arch fine)")
    r.add_argument("--threads", type=int, default=2)
    t = sub.add_parser("train")
    t.add_argument("--data", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--width", type=int, default=24)
    t.add_argument("--batch", type=int, default=64)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--lr-decay-minutes", type=float, default=40)
    t.add_argument("--max-minutes", type=float, default=40)
    t.add_argument("--checkpoint-s", type=float, default=300)
    t.add_argument("--threads", type=int, default=2)
    add_export_command(sub)
    args = ap.parse_args()
    {"regions": regions, "train": train, "export": export}[args.command](args)


if __name__ == "__main__":
    main()
