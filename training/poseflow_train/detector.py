"""The detector network: a small RGB-D U-Net that labels each pixel with
the object seen there (or background), trained on the renders of
`training/make-data-detect`. Instances are the connected regions of each
label; the detector stage turns them into Frame detections.

Input ("rgbd", float32, N×5×H×W): RGB / 255, depth in metres / 2 (0 = no
measurement), and the measured-depth mask, each pixel the centre one of a
`down` × `down` block of the frame. Output ("logits", N×(1+K)×H×W): class
0 is background, class k the k-th id of `object_ids`. Two architectures
(`--arch`, kept in the checkpoint's detector.json):

- `fine` (default): a 240×320 input (`down` 2, a 640×480 frame halved), a
  stride-2 stem into a U-Net body at 120×160, and a head at 240×320 that
  joins the body's features with features of the full input: small and
  far objects keep twice the pixels for about the same time per frame;
- `unet`: the first network, everything at 120×160 (`down` 4).

    python -m poseflow_train.detector train --data data/detect-lmo10 --out checkpoints/detect-lmo10 [--max-minutes M]
    python -m poseflow_train.detector export --checkpoint checkpoints/detect-lmo10 --data data/detect-lmo10 --out ../models/detector-lmo10

The export writes `detector.onnx` (input "rgbd", output "probabilities":
the softmax over the classes), `detector.json` (object ids, input size,
downsampling, depth scale, the loss's class weights) and `parity.bin`: one
validation image's input (uint8 RGB, uint16 depth in mm), its true labels
(uint8), and the exported network's labels (uint8) and their probabilities
(float32), both with the class weights divided out, which the Rust stage
must reproduce.
Evaluation (AP50, mask IoU) runs through the stage: `poseflow eval --detect`.

Training checkpoints (weights, optimiser, step, elapsed seconds) every
`--checkpoint-s` and resumes from the last checkpoint.
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
from PIL import Image

# The `unet` architecture's input; `fine` takes twice the rows and columns.
HEIGHT, WIDTH, DOWN = 120, 160, 4
DEPTH_SCALE_M = 2.0
ARCHITECTURES = ("fine", "unet")


def input_size(arch):
    """(height, width, down) of an architecture's input, for a 640×480 frame."""
    return (HEIGHT, WIDTH, DOWN) if arch == "unet" else (2 * HEIGHT, 2 * WIDTH, DOWN // 2)


def read_split(root, split, object_ids, down=DOWN, cache=True):
    """Every image of a BOP split as (rgb uint8 N×H×W×3, depth mm uint16
    N×H×W, labels uint8 N×H×W), every `down`-th pixel; cached next to the
    split as a .npz."""
    split_dir = Path(root) / split
    cached = Path(root) / (f"{split}.detect.npz" if down == DOWN else f"{split}.detect{down}.npz")
    if cache and cached.exists():
        data = np.load(cached)
        return data["rgb"], data["depth_mm"], data["labels"]
    class_of = {obj: k + 1 for k, obj in enumerate(object_ids)}
    rgbs, depths, labels = [], [], []
    for scene in sorted(p for p in split_dir.iterdir() if p.is_dir()):
        cameras = json.loads((scene / "scene_camera.json").read_text())
        gts = json.loads((scene / "scene_gt.json").read_text())
        for im in sorted(cameras, key=int):
            rgb = np.asarray(Image.open(scene / "rgb" / f"{int(im):06d}.png").convert("RGB"))
            raw = np.asarray(Image.open(scene / "depth" / f"{int(im):06d}.png")).astype(np.float32)
            depth_mm = raw * float(cameras[im]["depth_scale"])
            label = np.zeros(rgb.shape[:2], np.uint8)
            for k, gt in enumerate(gts[im]):
                mask = scene / "mask_visib" / f"{int(im):06d}_{k:06d}.png"
                if gt["obj_id"] in class_of and mask.exists():
                    label[np.asarray(Image.open(mask)) > 0] = class_of[gt["obj_id"]]
            rgbs.append(downsample(rgb, down))
            depths.append(np.round(downsample(depth_mm, down)).clip(0, 65535).astype(np.uint16))
            labels.append(downsample(label, down))
    rgb, depth_mm, labels = np.stack(rgbs), np.stack(depths), np.stack(labels)
    if cache:
        np.savez(cached, rgb=rgb, depth_mm=depth_mm, labels=labels)
    return rgb, depth_mm, labels


def downsample(image, down=DOWN):
    """Every `down`-th pixel (the centre one of each down×down block): what
    the detector stage does, so depth edges stay sharp."""
    return image[down // 2 :: down, down // 2 :: down]


def to_input(rgb, depth_mm):
    """uint8 N×H×W×3 and depth in mm N×H×W → float32 N×5×H×W."""
    rgb = torch.as_tensor(rgb, dtype=torch.float32).permute(0, 3, 1, 2) / 255.0
    depth = torch.as_tensor(depth_mm.astype(np.float32)).unsqueeze(1) / (1000.0 * DEPTH_SCALE_M)
    return torch.cat([rgb, depth, (depth > 0).float()], dim=1)


def conv(cin, cout, kernel=3, stride=1):
    return nn.Sequential(
        nn.Conv2d(cin, cout, kernel, stride=stride, padding=kernel // 2, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


def block(cin, cout, stride=1):
    return nn.Sequential(conv(cin, cout, 3, stride), conv(cout, cout))


def decode(stages, skips, x):
    """The U-Net's way up: each stage takes the level below, upsampled to
    its skip's size, beside that skip."""
    for stage in stages:
        skip = skips.pop()
        x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
        x = stage(torch.cat([x, skip], dim=1))
    return x


class Detector(nn.Module):
    """A four-level U-Net, 120×160 in and out."""

    def __init__(self, classes, width=16):
        super().__init__()
        w = [width, 2 * width, 4 * width, 8 * width]
        self.enc = nn.ModuleList([block(5, w[0]), block(w[0], w[1], 2), block(w[1], w[2], 2), block(w[2], w[3], 2)])
        self.dec = nn.ModuleList([block(w[3] + w[2], w[2]), block(w[2] + w[1], w[1]), block(w[1] + w[0], w[0])])
        self.head = nn.Conv2d(w[0], classes, 1)

    def forward(self, x):
        skips = []
        for stage in self.enc:
            x = stage(x)
            skips.append(x)
        return self.head(decode(self.dec, skips, skips.pop()))


class FineDetector(nn.Module):
    """Input and output at twice the body's resolution. A stride-2 stem
    feeds a four-level U-Net body (one more block at the two coarsest
    levels, where convolutions are cheap; decoders reduce their inputs by
    a 1×1 convolution first), and the head joins the body's upsampled
    features with a few of the full input's own, so outlines and small
    objects are labelled at the input's resolution. About the `unet`'s
    time per frame at 4× its input pixels (1 ONNX Runtime thread)."""

    def __init__(self, classes, width=16, fine=8):
        super().__init__()
        w = [width, 2 * width, 4 * width, 8 * width]
        self.stem = conv(5, w[0], 3, 2)
        self.enc = nn.ModuleList(
            [
                conv(w[0], w[0]),
                block(w[0], w[1], 2),
                nn.Sequential(block(w[1], w[2], 2), block(w[2], w[2])),
                nn.Sequential(block(w[2], w[3], 2), block(w[3], w[3])),
            ]
        )
        self.dec = nn.ModuleList(
            [nn.Sequential(conv(w[k + 1] + w[k], w[k], 1), conv(w[k], w[k])) for k in (2, 1, 0)]
        )
        self.fine = conv(5, fine)
        self.head = nn.Sequential(conv(w[0] + fine, w[0], 1), nn.Conv2d(w[0], classes, 1))

    def forward(self, x):
        full = x
        x = self.stem(x)
        skips = []
        for stage in self.enc:
            x = stage(x)
            skips.append(x)
        x = decode(self.dec, skips, skips.pop())
        x = F.interpolate(x, size=full.shape[-2:], mode="nearest")
        return self.head(torch.cat([x, self.fine(full)], dim=1))


def build(arch, classes, width):
    return FineDetector(classes, width) if arch == "fine" else Detector(classes, width)


def random_crops(rgb, depth_mm, labels, size, rng):
    """The same random `size` (rows, columns) window of each image; the
    network is convolutional, so it trains on windows and runs on frames."""
    rows, cols = min(size[0], rgb.shape[1]), min(size[1], rgb.shape[2])
    out = [], [], []
    for i in range(len(rgb)):
        y, x = rng.integers(0, rgb.shape[1] - rows + 1), rng.integers(0, rgb.shape[2] - cols + 1)
        for part, array in zip(out, (rgb, depth_mm, labels)):
            part.append(array[i, y : y + rows, x : x + cols])
    return tuple(np.stack(part) for part in out)


def augment(rgb, depth_mm, labels, rng):
    """Horizontal flips and colour jitter per image (the renders already
    carry the sensor effects)."""
    rgb, depth_mm, labels = rgb.copy(), depth_mm.copy(), labels.copy()
    for i in range(len(rgb)):
        if rng.random() < 0.5:
            rgb[i], depth_mm[i], labels[i] = rgb[i, :, ::-1], depth_mm[i, :, ::-1], labels[i, :, ::-1]
        gain = rng.uniform(0.7, 1.3, size=3)
        rgb[i] = np.clip(rgb[i].astype(np.float32) * gain + rng.uniform(-20, 20), 0, 255).astype(np.uint8)
    return rgb, depth_mm, labels


def train(args):
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    info = json.loads((Path(args.data) / "models" / "models_info.json").read_text())
    object_ids = sorted(int(k) for k in info)
    height, width_px, down = input_size(args.arch)
    config_path = out / "detector.json"
    if config_path.exists():  # a resumed run keeps the architecture it started with
        config = json.loads(config_path.read_text())
        if config.get("arch", "unet") != args.arch or config["width"] != args.width:
            raise SystemExit(f"{config_path}: the run was started with {config}, not --arch {args.arch} --width {args.width}")
    config = {"object_ids": object_ids, "arch": args.arch, "width": args.width, "height": height, "width_px": width_px, "down": down}
    config_path.write_text(json.dumps(config, indent=1))
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    splits = sorted(p.name for p in Path(args.data).iterdir() if p.is_dir() and p.name.startswith("train_"))
    parts = [read_split(args.data, s, object_ids, down) for s in splits]
    rgb, depth_mm, labels = (np.concatenate([p[i] for p in parts]) for i in range(3))
    val = read_split(args.data, "test", object_ids, down)
    model = build(args.arch, 1 + len(object_ids), args.width)
    optimiser = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    step, elapsed = 0, 0.0
    checkpoint = out / "detector.pt"
    if checkpoint.exists() or (out / PORTABLE).exists():
        state = load_state(out)
        model.load_state_dict(state["model"])
        if "optimiser" in state:
            optimiser.load_state_dict(state["optimiser"])
        step, elapsed = state["step"], state["elapsed_s"]
        print(
            f"resumed at step {step} after {elapsed / 60:.1f} min"
            + ("" if "optimiser" in state else f" from {PORTABLE} (the optimiser starts afresh)"),
            flush=True,
        )
    weights = torch.tensor(class_weights(len(object_ids)))
    rng = np.random.default_rng(step)
    started, saved = time.time() - elapsed, time.time()
    log = open(out / "detector-log.jsonl", "a")
    print(f"{len(rgb)} training and {len(val[0])} validation images; {sum(p.numel() for p in model.parameters())} parameters", flush=True)
    while args.max_minutes is None or (time.time() - started) < 60 * args.max_minutes + elapsed:
        if args.steps and step >= args.steps:
            break
        model.train()
        if args.lr_decay_minutes:
            # By training time, so a run that shares the cores still ends decayed.
            rate = learning_rate(args.lr, time.time() - started, 60 * args.lr_decay_minutes)
        else:
            rate = learning_rate(args.lr, step, args.lr_decay_steps)
        for group in optimiser.param_groups:
            group["lr"] = rate
        batch = rng.choice(len(rgb), size=args.batch, replace=False)
        b_rgb, b_depth, b_labels = augment(rgb[batch], depth_mm[batch], labels[batch], rng)
        if args.crop:
            b_rgb, b_depth, b_labels = random_crops(b_rgb, b_depth, b_labels, args.crop, rng)
        logits = model(to_input(b_rgb, b_depth))
        loss = F.cross_entropy(logits, torch.as_tensor(b_labels, dtype=torch.long), weight=weights)
        descend(optimiser, loss)
        step += 1
        if step % 50 == 0:
            entry = {"step": step, "train_s": round(time.time() - started, 1), "loss": loss.item(), "lr": rate}
            if step % 500 == 0:
                entry["validation"] = evaluate_arrays(model, *val, object_ids)
            write_entry(log, entry)
        if time.time() - saved > args.checkpoint_s:
            save(model, optimiser, step, time.time() - started, checkpoint)
            saved = time.time()
    save(model, optimiser, step, time.time() - started, checkpoint)


def descend(optimiser, loss):
    """One optimiser step on `loss`."""
    optimiser.zero_grad()
    loss.backward()
    optimiser.step()


def write_entry(log, entry):
    """One training-log entry, printed and appended to the open log."""
    print(entry, flush=True)
    log.write(json.dumps(entry) + "\n")
    log.flush()


def learning_rate(base, step, decay_steps):
    """Constant without `decay_steps`; else a cosine from `base` down to 5 %
    of it at `decay_steps`, held there after (steps, or seconds of training)."""
    if not decay_steps:
        return base
    progress = min(step / decay_steps, 1.0)
    return base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * progress)))


# Beside `detector.pt`: the weights alone in half precision, small enough
# for git, so a run (or the shipped network) can be trained on from another
# machine; the optimiser's moments are not kept.
PORTABLE = "weights.pt"


def save(model, optimiser, step, elapsed, path):
    state = {"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step, "elapsed_s": elapsed}
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    write_portable(state, path.with_name(PORTABLE))


def write_portable(state, path):
    half = {k: v.half() if v.is_floating_point() else v for k, v in state["model"].items()}
    tmp = path.with_suffix(".tmp")
    torch.save({"model": half, "step": state["step"], "elapsed_s": state["elapsed_s"]}, tmp)
    tmp.replace(path)


def load_state(directory):
    """`detector.pt` of a run's directory, or where it is missing (another
    machine) its portable weights, in single precision."""
    directory = Path(directory)
    checkpoint = directory / "detector.pt"
    if checkpoint.exists():
        return torch.load(checkpoint, map_location="cpu")
    state = torch.load(directory / PORTABLE, map_location="cpu")
    state["model"] = {k: v.float() if v.is_floating_point() else v for k, v in state["model"].items()}
    return state


# Background dominates the pixels: the loss weighs the objects up. The
# network then predicts each class as if it were its weight times as likely,
# so the labels are taken from the probabilities divided by the weights
# (`class_weights` in detector.json; the stage does the same).
BACKGROUND_WEIGHT = 0.2


def class_weights(objects):
    return [BACKGROUND_WEIGHT] + [1.0] * objects


def labels_of(probabilities, weights):
    """The label of each pixel: N×C×H×W probabilities → N×H×W."""
    return (probabilities / np.asarray(weights, np.float32)[None, :, None, None]).argmax(1)


def evaluate_arrays(model, rgb, depth_mm, labels, object_ids):
    """Per-pixel mask IoU per object (the union over the split) and their
    mean, with the stage's labels (the class weights divided out; logs
    before step 8,617 used the plain argmax)."""
    model.eval()
    predicted = []
    weights = class_weights(len(object_ids))
    with torch.no_grad():
        for i in range(0, len(rgb), 16):
            logits = model(to_input(rgb[i : i + 16], depth_mm[i : i + 16]))
            predicted.append(labels_of(torch.softmax(logits, dim=1).numpy(), weights))
    predicted = np.concatenate(predicted)
    ious = {}
    for k, obj in enumerate(object_ids, start=1):
        truth, guess = labels == k, predicted == k
        union = (truth | guess).sum()
        if truth.sum() > 0:
            ious[str(obj)] = round(float((truth & guess).sum() / max(union, 1)), 4)
    return {"mean_iou": round(float(np.mean(list(ious.values()))), 4), "iou": ious}


class Exported(nn.Module):
    """The network as the stage runs it: probabilities, not logits."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, rgbd):
        # The softmax written out: ONNX Runtime's Softmax over the channel
        # axis of an N×C×H×W tensor took 8.6 of the `fine` network's 24 ms
        # (1 thread), these element-wise operations about 1.7.
        logits = self.model(rgbd)
        e = torch.exp(logits - logits.amax(dim=1, keepdim=True))
        return e / e.sum(dim=1, keepdim=True)


def export_onnx(module, example, path, input_name):
    """`module` to ONNX at `path`: one input, output `probabilities`, the
    batch dimension dynamic (the stage's contracts)."""
    torch.onnx.export(
        module,
        (example,),
        path,
        input_names=[input_name],
        output_names=["probabilities"],
        dynamic_axes={input_name: {0: "n"}, "probabilities": {0: "n"}},
        opset_version=17,
        dynamo=False,
    )


def export(args):
    source = Path(args.checkpoint)
    config = json.loads((source / "detector.json").read_text())
    arch = config.get("arch", "unet")
    height, width_px, down = input_size(arch)
    model = build(arch, 1 + len(config["object_ids"]), config["width"])
    state = load_state(source)
    model.load_state_dict(state["model"])
    model.eval()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    exported = Exported(model).eval()
    export_onnx(exported, torch.zeros(1, 5, height, width_px), out / "detector.onnx", "rgbd")
    meta = {
        "format": "poseflow-detector/1",
        "object_ids": config["object_ids"],
        "input": {"height": height, "width": width_px, "down": down, "depth_scale_m": DEPTH_SCALE_M},
        "architecture": arch,
        "class_weights": class_weights(len(config["object_ids"])),
        "training": {"step": state["step"], "train_minutes": round(state["elapsed_s"] / 60, 1)},
    }
    (out / "detector.json").write_text(json.dumps(meta, indent=1) + "\n")
    # Parity: the first validation image through the exported network.
    import onnxruntime

    rgb, depth_mm, truth = read_split(args.data, "test", config["object_ids"], down)
    session = onnxruntime.InferenceSession(str(out / "detector.onnx"), providers=["CPUExecutionProvider"])
    probabilities = session.run(None, {"rgbd": to_input(rgb[:1], depth_mm[:1]).numpy()})[0][0]
    weights = class_weights(len(config["object_ids"]))
    labels = labels_of(probabilities[None], weights)[0].astype(np.uint8)
    with open(out / "parity.bin", "wb") as f:
        f.write(rgb[0].astype(np.uint8).tobytes())
        f.write(depth_mm[0].astype("<u2").tobytes())
        f.write(truth[0].astype(np.uint8).tobytes())
        f.write(labels.tobytes())
        weighted = probabilities / np.asarray(weights, np.float32)[:, None, None]
        f.write((weighted.max(0) / weighted.sum(0)).astype("<f4").tobytes())
    with torch.no_grad():
        reference = exported(to_input(rgb[:1], depth_mm[:1]))[0].numpy()
    print(f"exported step {state['step']} to {out}: max |onnx - torch| = {np.abs(probabilities - reference).max():.2e}")
    log = [json.loads(line) for line in (source / "detector-log.jsonl").read_text().splitlines() if line.strip()]
    (out / "detector-log.jsonl").write_text("".join(json.dumps(e) + "\n" for e in log))
    plot_curve([e for e in log if "validation" in e], out / "learning-curve.png")


def plot_curve(curve, path):
    """Validation mean mask IoU (per pixel, union over the split) against
    training time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hours = [e["train_s"] / 3600 for e in curve]
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(hours, [100 * e["validation"]["mean_iou"] for e in curve], marker="o")
    ax.set_xlabel("training time (h, 2 CPU cores, shared with other work)")
    ax.set_ylabel("validation mean mask IoU (%)")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    fig.suptitle("Detector: 50 held-out validation renders (split test, seed 22)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def add_export_command(sub):
    """The `export` sub-command: a checkpoint directory, the data (for the
    parity file) and the model directory to write."""
    e = sub.add_parser("export")
    e.add_argument("--checkpoint", required=True)
    e.add_argument("--data", required=True)
    e.add_argument("--out", required=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("--data", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--arch", choices=ARCHITECTURES, default="fine", help="fine: 240×320 input and output (default); unet: 120×160")
    t.add_argument("--width", type=int, default=16)
    t.add_argument("--crop", type=int, nargs=2, metavar=("ROWS", "COLS"), help="train on random windows of this size (input pixels)")
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--lr-decay-steps", type=int, default=0, help="cosine decay to 5 %% of --lr at this step (0: constant)")
    t.add_argument("--lr-decay-minutes", type=float, default=0, help="the same decay over this much training time instead of steps")
    t.add_argument("--steps", type=int, default=0)
    t.add_argument("--max-minutes", type=float)
    t.add_argument("--checkpoint-s", type=float, default=300)
    t.add_argument("--threads", type=int, default=2)
    add_export_command(sub)
    args = ap.parse_args()
    if args.command == "train":
        train(args)
    else:
        export(args)


if __name__ == "__main__":
    main()
