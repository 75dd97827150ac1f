"""The detector network: a small RGB-D U-Net that labels each pixel with
the object seen there (or background), trained on the renders of
`training/make-data-detect`. Instances are the connected regions of each
label; the detector stage turns them into Frame detections.

Input ("rgbd", float32, N×5×H×W at H×W = 120×160, a 640×480 frame
downsampled 4×): RGB / 255, depth in metres / 2 (0 = no measurement), and
the measured-depth mask. Output ("logits", N×(1+K)×H×W): class 0 is
background, class k the k-th id of `object_ids`.

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

HEIGHT, WIDTH, DOWN = 120, 160, 4
DEPTH_SCALE_M = 2.0


def read_split(root, split, object_ids, cache=True):
    """Every image of a BOP split as (rgbd float32 5×H×W, labels uint8 H×W);
    cached next to the split as a .npz."""
    split_dir = Path(root) / split
    cached = Path(root) / f"{split}.detect.npz"
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
            rgbs.append(downsample(rgb))
            depths.append(np.round(downsample(depth_mm)).clip(0, 65535).astype(np.uint16))
            labels.append(label[DOWN // 2 :: DOWN, DOWN // 2 :: DOWN])
    rgb, depth_mm, labels = np.stack(rgbs), np.stack(depths), np.stack(labels)
    if cache:
        np.savez(cached, rgb=rgb, depth_mm=depth_mm, labels=labels)
    return rgb, depth_mm, labels


def downsample(image):
    """Every DOWN-th pixel (the centre one of each DOWN×DOWN block): what
    the detector stage does, so depth edges stay sharp."""
    return image[DOWN // 2 :: DOWN, DOWN // 2 :: DOWN]


def to_input(rgb, depth_mm):
    """uint8 N×H×W×3 and depth in mm N×H×W → float32 N×5×H×W."""
    rgb = torch.as_tensor(rgb, dtype=torch.float32).permute(0, 3, 1, 2) / 255.0
    depth = torch.as_tensor(depth_mm.astype(np.float32)).unsqueeze(1) / (1000.0 * DEPTH_SCALE_M)
    return torch.cat([rgb, depth, (depth > 0).float()], dim=1)


def block(cin, cout, stride=1):
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


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
        x = skips.pop()
        for stage in self.dec:
            skip = skips.pop()
            x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = stage(torch.cat([x, skip], dim=1))
        return self.head(x)


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
    config = {"object_ids": object_ids, "width": args.width, "height": HEIGHT, "width_px": WIDTH, "down": DOWN}
    (out / "detector.json").write_text(json.dumps(config, indent=1))
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    splits = sorted(p.name for p in Path(args.data).iterdir() if p.is_dir() and p.name.startswith("train_"))
    parts = [read_split(args.data, s, object_ids) for s in splits]
    rgb, depth_mm, labels = (np.concatenate([p[i] for p in parts]) for i in range(3))
    val = read_split(args.data, "test", object_ids)
    model = Detector(1 + len(object_ids), args.width)
    optimiser = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    step, elapsed = 0, 0.0
    checkpoint = out / "detector.pt"
    if checkpoint.exists():
        state = torch.load(checkpoint, map_location="cpu")
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        step, elapsed = state["step"], state["elapsed_s"]
        print(f"resumed at step {step} after {elapsed / 60:.1f} min", flush=True)
    weights = torch.tensor(class_weights(len(object_ids)))
    rng = np.random.default_rng(step)
    started, saved = time.time() - elapsed, time.time()
    log = open(out / "detector-log.jsonl", "a")
    print(f"{len(rgb)} training and {len(val[0])} validation images; {sum(p.numel() for p in model.parameters())} parameters", flush=True)
    while args.max_minutes is None or (time.time() - started) < 60 * args.max_minutes + elapsed:
        if args.steps and step >= args.steps:
            break
        model.train()
        for group in optimiser.param_groups:
            group["lr"] = learning_rate(args.lr, step, args.lr_decay_steps)
        batch = rng.choice(len(rgb), size=args.batch, replace=False)
        b_rgb, b_depth, b_labels = augment(rgb[batch], depth_mm[batch], labels[batch], rng)
        logits = model(to_input(b_rgb, b_depth))
        loss = F.cross_entropy(logits, torch.as_tensor(b_labels, dtype=torch.long), weight=weights)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        step += 1
        if step % 50 == 0:
            entry = {"step": step, "train_s": round(time.time() - started, 1), "loss": loss.item()}
            if step % 500 == 0:
                entry["validation"] = evaluate_arrays(model, *val, object_ids)
            print(entry, flush=True)
            log.write(json.dumps(entry) + "\n")
            log.flush()
        if time.time() - saved > args.checkpoint_s:
            save(model, optimiser, step, time.time() - started, checkpoint)
            saved = time.time()
    save(model, optimiser, step, time.time() - started, checkpoint)


def learning_rate(base, step, decay_steps):
    """Constant without `decay_steps`; else a cosine from `base` down to 5 %
    of it at `decay_steps`, held there after."""
    if not decay_steps:
        return base
    progress = min(step / decay_steps, 1.0)
    return base * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * progress)))


def save(model, optimiser, step, elapsed, path):
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step, "elapsed_s": elapsed}, tmp)
    tmp.replace(path)


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
        return torch.softmax(self.model(rgbd), dim=1)


def export(args):
    source = Path(args.checkpoint)
    config = json.loads((source / "detector.json").read_text())
    model = Detector(1 + len(config["object_ids"]), config["width"])
    state = torch.load(source / "detector.pt", map_location="cpu")
    model.load_state_dict(state["model"])
    model.eval()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    exported = Exported(model).eval()
    example = torch.zeros(1, 5, HEIGHT, WIDTH)
    torch.onnx.export(
        exported,
        (example,),
        out / "detector.onnx",
        input_names=["rgbd"],
        output_names=["probabilities"],
        dynamic_axes={"rgbd": {0: "n"}, "probabilities": {0: "n"}},
        opset_version=17,
        dynamo=False,
    )
    meta = {
        "format": "poseflow-detector/1",
        "object_ids": config["object_ids"],
        "input": {"height": HEIGHT, "width": WIDTH, "down": DOWN, "depth_scale_m": DEPTH_SCALE_M},
        "class_weights": class_weights(len(config["object_ids"])),
        "training": {"step": state["step"], "train_minutes": round(state["elapsed_s"] / 60, 1)},
    }
    (out / "detector.json").write_text(json.dumps(meta, indent=1) + "\n")
    # Parity: the first validation image through the exported network.
    import onnxruntime

    rgb, depth_mm, truth = read_split(args.data, "test", config["object_ids"])
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


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("--data", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--width", type=int, default=16)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--lr", type=float, default=2e-3)
    t.add_argument("--lr-decay-steps", type=int, default=0, help="cosine decay to 5 %% of --lr at this step (0: constant)")
    t.add_argument("--steps", type=int, default=0)
    t.add_argument("--max-minutes", type=float)
    t.add_argument("--checkpoint-s", type=float, default=300)
    t.add_argument("--threads", type=int, default=2)
    e = sub.add_parser("export")
    e.add_argument("--checkpoint", required=True)
    e.add_argument("--data", required=True)
    e.add_argument("--out", required=True)
    args = ap.parse_args()
    if args.command == "train":
        train(args)
    else:
        export(args)


if __name__ == "__main__":
    main()
