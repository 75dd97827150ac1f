"""How an exported model's per-sample accuracy moves when frames look less
like the renders it was trained on: what a real RGB-D sensor and a real
segmentation add (colour cast and exposure, image noise, a mask bleeding
over the object's outline or falling short of it, depth holes, extra depth
noise, a depth scale error). Each variant is a perturbed copy of a BOP
split (rgb/, depth/, mask_visib/), turned into observations by the ingest
stage's own code (`poseflow observe`, so its outlier filtering takes part)
and scored like `evaluate` (N samples, K steps, no selection).

    python -m poseflow_train.robustness --model ../models/poseflow-lmo10 \\
        --dataset data/lmo10 --split heldout3 --out /tmp/robustness
"""

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
from PIL import Image

from .data import Observations
from .evaluate import unobserved, accuracy, add_model_arguments, load_model


def colour_gains(gains):
    """Per-channel gains on the colour image (white balance / exposure)."""
    return {"rgb": lambda rgb, rng: np.clip(rgb * np.asarray(gains), 0, 255)}


def image_noise(sigma):
    """Additive Gaussian noise of `sigma` (in units of full scale)."""
    return {"rgb": lambda rgb, rng: np.clip(rgb + 255.0 * sigma * rng.standard_normal(rgb.shape), 0, 255)}


def grey():
    """Colour removed (luma in every channel)."""
    return {"rgb": lambda rgb, rng: np.repeat((rgb @ np.array([0.299, 0.587, 0.114]))[..., None], 3, axis=2)}


def mask_grown(pixels):
    """Every visible mask dilated (> 0) or eroded (< 0) by `pixels` (a
    square neighbourhood): a detector's mask too wide, so pixels of the
    table or the object behind join the object's, or too narrow."""
    return {"mask": lambda mask, depth, rng: dilate(mask, pixels) if pixels > 0 else ~dilate(~mask, -pixels)}


def depth_hole(share):
    """No depth on the `share` of each object's visible pixels nearest to a
    random one of them (a dark or specular patch), as sensors report it: 0."""

    def hole(mask, depth, rng):
        ys, xs = np.nonzero(mask)
        if len(ys) == 0:
            return depth
        k = rng.integers(len(ys))
        order = np.argsort((ys - ys[k]) ** 2 + (xs - xs[k]) ** 2)[: int(share * len(ys))]
        holed = depth.copy()
        holed[ys[order], xs[order]] = 0
        return holed

    return {"depth_per_mask": hole}


def depth_noise(sigma_mm):
    """Extra Gaussian noise of `sigma_mm` on every valid depth pixel."""

    def noise(depth, scale_mm, rng):
        valid = depth > 0
        noisy = depth + valid * rng.standard_normal(depth.shape) * (sigma_mm / scale_mm)
        return np.where(valid, np.maximum(noisy, 1), 0)

    return {"depth": noise}


def depth_shift(pixels):
    """The depth image moved `pixels` to the right of the colour image and
    the masks (depth registered off the colour camera): along one side of
    each object the mask sees the background's depth, along the other the
    object's depth spills past the mask."""

    def shift(depth, scale_mm, rng):
        moved = np.zeros_like(depth)
        moved[:, pixels:] = depth[:, :-pixels]
        return moved

    return {"depth": shift}


def depth_scale(factor):
    """Every depth multiplied by `factor` (a miscalibrated sensor)."""
    return {"depth": lambda depth, scale_mm, rng: depth * factor}


VARIANTS = {
    "none": {},
    "warm cast (gains 1.2, 1.0, 0.8)": colour_gains((1.2, 1.0, 0.8)),
    "cool cast (gains 0.8, 1.0, 1.2)": colour_gains((0.8, 1.0, 1.2)),
    "darker (gain 0.6)": colour_gains((0.6, 0.6, 0.6)),
    "brighter (gain 1.4)": colour_gains((1.4, 1.4, 1.4)),
    "image noise (sigma 0.05)": image_noise(0.05),
    "grey image": grey(),
    "masks 1 px wider": mask_grown(1),
    "masks 3 px wider": mask_grown(3),
    "masks 6 px wider": mask_grown(6),
    "masks 3 px narrower": mask_grown(-3),
    "depth hole on 20 % of each object": depth_hole(0.2),
    "depth noise +3 mm": depth_noise(3.0),
    "depth scale x1.01": depth_scale(1.01),
    "depth 2 px right of the colour image": depth_shift(2),
}


# `poseflow render --sensor realistic` effects (shared/scene/src/sensor.rs),
# rendered one at a time for `--sensor-effects`.
SENSOR_EFFECTS = ["depth-noise", "quantisation", "flying-pixels", "shadow", "dark", "grazing", "specular",
                  "misregistration", "exposure", "white-balance", "gamma", "defocus", "motion-blur", "shot-noise",
                  "read-noise", "vignetting", "jpeg"]


def sensor_variants():
    """name -> `poseflow render` sensor arguments: the exact render, each
    realistic effect alone, and all of them."""
    variants = {"sensor: none (exact render)": ["--sensor", "clean"]}
    for effect in SENSOR_EFFECTS:
        others = ",".join(e for e in SENSOR_EFFECTS if e != effect)
        variants[f"sensor: {effect} only"] = ["--sensor", "realistic", "--without", others]
    variants["sensor: all realistic effects"] = ["--sensor", "realistic"]
    return variants


def dilate(mask, pixels):
    """Binary dilation by a (2·pixels+1)² square, as a max over shifts."""
    out = mask.copy()
    h, w = mask.shape
    for dy in range(-pixels, pixels + 1):
        for dx in range(-pixels, pixels + 1):
            out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] |= \
                mask[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return out


def write_variant(dataset, split, out, variant, seed):
    """A dataset root at `out` whose `split` is `dataset`'s with `variant`
    applied; untouched files are linked, not copied."""
    dataset, out = Path(dataset).resolve(), Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    os.symlink(dataset / "models", out / "models")
    shutil.copy(dataset / "camera.json", out / "camera.json")
    rng = np.random.default_rng(seed)
    for scene in sorted((dataset / split).iterdir()):
        target = out / split / scene.name
        for folder in ("rgb", "depth", "mask_visib"):
            (target / folder).mkdir(parents=True)
        for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
            shutil.copy(scene / name, target / name)
        cameras = json.loads((scene / "scene_camera.json").read_text())
        for image in sorted((scene / "rgb").iterdir()):
            write_image(scene, target, image.stem, cameras[str(int(image.stem))]["depth_scale"], variant, rng)


def write_image(scene, target, stem, scale_mm, variant, rng):
    """One image's rgb, depth and visible masks through the variant."""
    masks = sorted((scene / "mask_visib").glob(f"{stem}_*.png"))
    grown = {}
    for path in masks:
        mask = np.asarray(Image.open(path)) > 0
        if "mask" in variant:
            mask = variant["mask"](mask, None, rng)
            Image.fromarray(mask.astype(np.uint8) * 255).save(target / "mask_visib" / path.name)
        else:
            os.symlink(path.resolve(), target / "mask_visib" / path.name)
        grown[path.name] = mask
    rgb_path, depth_path = scene / "rgb" / f"{stem}.png", scene / "depth" / f"{stem}.png"
    if "rgb" in variant:
        rgb = np.asarray(Image.open(rgb_path).convert("RGB")).astype(np.float64)
        Image.fromarray(np.round(variant["rgb"](rgb, rng)).astype(np.uint8)).save(target / "rgb" / rgb_path.name)
    else:
        os.symlink(rgb_path.resolve(), target / "rgb" / rgb_path.name)
    if "depth" in variant or "depth_per_mask" in variant:
        depth = np.asarray(Image.open(depth_path)).astype(np.float64)
        if "depth" in variant:
            depth = variant["depth"](depth, scale_mm, rng)
        for mask in grown.values():
            if "depth_per_mask" in variant:
                depth = variant["depth_per_mask"](mask, depth, rng)
        Image.fromarray(np.clip(np.round(depth), 0, 65535).astype(np.uint16)).save(target / "depth" / depth_path.name)
    else:
        os.symlink(depth_path.resolve(), target / "depth" / depth_path.name)


def observe(poseflow, root, split, shard, image_size, patch_grid, config):
    """The split's observations, made by the ingest stage's own code."""
    settings = ["--config", config] if config else []
    subprocess.run([poseflow, "observe", "--dataset", str(root), "--split", split, "--out", str(shard),
                    "--image-size", str(image_size), "--patch-grid", str(patch_grid), *settings],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def main():
    import argparse

    parser = argparse.ArgumentParser(description="Per-sample accuracy of an exported model on perturbed copies of a BOP split.")
    add_model_arguments(parser)
    parser.add_argument("--dataset", required=True, help="BOP dataset root (models/, camera.json, the split)")
    parser.add_argument("--split", required=True, help="split folder (not named test*: that reads test targets)")
    parser.add_argument("--out", required=True, help="scratch folder for the perturbed copies and their shards")
    parser.add_argument("--only", nargs="+", choices=[*VARIANTS, *sensor_variants()],
                        help="these variants only (with --sensor-effects, of its renders: \"sensor: ...\")")
    parser.add_argument("--poseflow", default="../target/release/poseflow")
    parser.add_argument("--ingest-config", help="ingest parameters (TOML, as config/ingest.toml) for `poseflow observe`")
    parser.add_argument("--sensor-effects", metavar="RENDER_ARGS",
                        help="instead of perturbing --split, render it again once per sensor effect with these "
                             "`poseflow render` arguments (the split's models, seed, scenes, camera; not --out, "
                             "--split or --sensor), e.g. \"--models ../objects/ycbv/models --seed 4 --first-scene "
                             "3000 --scenes 10 --frames-per-scene 5 --camera ycbv --textured\"")
    args = parser.parse_args()
    model, cfg = load_model(args)
    meta = model.encoder_session.get_modelmeta().custom_metadata_map
    rows = {}
    sensors = sensor_variants() if args.sensor_effects else {}
    names = args.only or list(sensors if args.sensor_effects else VARIANTS)
    wrong = [name for name in names if name not in (sensors if args.sensor_effects else VARIANTS)]
    if wrong:
        parser.error(f"--only {wrong[0]!r}: " + ("not a --sensor-effects render" if args.sensor_effects else
                                                 "a --sensor-effects render; add --sensor-effects"))
    for number, name in enumerate(names):
        root = Path(args.out) / f"variant{number:02d}"
        if args.sensor_effects:
            shutil.rmtree(root, ignore_errors=True)
            subprocess.run([args.poseflow, "render", *args.sensor_effects.split(), "--out", str(root), "--split",
                            args.split, *sensors[name]], check=True, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
        else:
            write_variant(args.dataset, args.split, root, VARIANTS[name], args.seed)
        shard = root / f"{args.split}.obs"
        observe(args.poseflow, root, args.split, shard, meta["image_size"], meta["patch_grid"], args.ingest_config)
        observations = Observations([shard], model.object_ids, symmetries=args.symmetries)
        result = accuracy(model.encoder, model.velocity, observations, cfg, len(observations), args.samples,
                          args.steps, args.seed, unobserved(observations, 0.1))
        result.pop("per_object")
        rows[name] = result
        print(f"{name}: {result['observations']} observations, per-sample 10deg5cm {result['acc_10deg_5cm']} %, "
              f"coarse pose {result['coarse']['acc_10deg_5cm']} %", flush=True)
    print(json.dumps({"model": args.model, "dataset": args.dataset, "split": args.split, "symmetries": args.symmetries,
                      "variants": rows}))


if __name__ == "__main__":
    main()
