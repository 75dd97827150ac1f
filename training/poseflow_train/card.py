"""Writes a model card (MODEL_CARD.md) and its learning-curve figure next to
an exported model, from measured files only: the training log, the
checkpoint, the training shards, the held-out evaluation of the exported
ONNX files (`poseflow_train.evaluate --model ... > eval.json`) and the Rust
latency benchmark (`poseflow bench model --json > bench.json`).

    python -m poseflow_train.card --config configs/lmo.json --model ../models/poseflow-lmo10 \\
        --eval eval.json --bench bench.json
"""

import argparse
import json
import math
from pathlib import Path

import torch

from .data import Shard
from .train import load_config


def instances(result):
    """"N object instances", naming those the ingest could not observe
    (counted as misses by `evaluate`)."""
    missed = result.get("unobserved", 0)
    total = result["observations"] + missed
    return f"{total} object instances" + (f" ({missed} not observed by the ingest: misses)" if missed else "")


def learning_curve(log_paths):
    """Validation entries of the runs' logs in order; an earlier run's
    entries count up to where the next run's log starts (a run continued
    from its checkpoint repeats nothing)."""
    runs = [[json.loads(line) for line in Path(p).read_text().splitlines() if line.strip()] for p in log_paths]
    curve = []
    for k, entries in enumerate(runs):
        later = [e["train_s"] for run in runs[k + 1:] for e in run[:1]]
        end = min(later, default=math.inf)
        for entry in entries:
            if "validation" not in entry or entry["train_s"] >= end:
                continue
            # A run resumed from an older checkpoint logs those steps again:
            # the later lines replace the earlier ones.
            while curve and curve[-1]["step"] >= entry["step"]:
                curve.pop()
            curve.append(entry)
    return curve


def plot(curve, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hours = [e["train_s"] / 3600 for e in curve]
    fig, (acc_ax, err_ax) = plt.subplots(1, 2, figsize=(10, 3.6))
    for key, label in [("acc_10deg_5cm", "10°5cm"), ("acc_5deg_5cm", "5°5cm")]:
        acc_ax.plot(hours, [e["validation"][key] for e in curve], marker="o", label=label)
    acc_ax.set_xlabel("training time (h, 2 CPU cores)")
    acc_ax.set_ylabel("per-sample accuracy (%)")
    acc_ax.legend()
    acc_ax.grid(alpha=0.3)
    err_ax.plot(hours, [e["validation"]["median_rot_deg"] for e in curve], marker="o", color="tab:red")
    err_ax.set_xlabel("training time (h, 2 CPU cores)")
    err_ax.set_ylabel("median rotation error (°)")
    err_ax.set_yscale("log")
    err_ax.grid(alpha=0.3)
    fig.suptitle("Validation during training (64 held-out observations, N = 50, K = 5)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def parameter_count(saved):
    return sum(v.numel() for part in ("encoder", "velocity") for v in saved[part].values() if v.is_floating_point())


def contract_of(model_dir):
    import onnx

    encoder = onnx.load(str(Path(model_dir) / "encoder.onnx"), load_external_data=False)
    return next(p.value for p in encoder.metadata_props if p.key == "contract")


def files_section(model_dir, saved, int8_eval=None):
    """The Files section: the ONNX files with their sizes, the INT8 ones
    (`poseflow_train.quantize`) with their held-out accuracy when measured."""
    model_dir = Path(model_dir)
    sizes = {f.name: f.stat().st_size for f in sorted(model_dir.glob("*.onnx"))}
    full = {n: v for n, v in sizes.items() if ".int8." not in n}
    int8 = {n: v for n, v in sizes.items() if ".int8." in n}
    text = f"""{files_section(out, saved)}## Architecture (paper, "Method")

- Image stream: a ViT trained from scratch on the {cfg.image_size}×{cfg.image_size} RGB crop,
  {cfg.patch_grid}×{cfg.patch_grid} patch tokens, {cfg.image_depth} blocks, width {cfg.width}, {cfg.heads} heads;
  tokens outside the object mask are masked in cross-attention.
- Point stream: PointNet++ set abstraction on the {cfg.point_count} centred points
  ({cfg.sa1_centres} then {cfg.sa2_centres} centres, {cfg.neighbours} neighbours; centres are prefixes of the
  ingest stage's farthest-point order), projected to width {cfg.width}.
- One object token (object identity as conditioning), ids {cfg.object_ids}.
- Velocity network: {cfg.dit_depth} DiT* blocks over a rotation and a translation pose
  token, adaLN on {cfg.fourier_features} Fourier features of t, masked cross-attention to the
  condition tokens; heads predict the clean pose (6D rotation, translation)
  and the velocities on the paper's path are derived from it:
  ω = log(R_tᵀR̂₁)/(1−t), v = (p̂₁ − p_t)/(1−t) (1−t ≥ {cfg.min_remaining}).
- Translations in metres relative to the observed points' mean, scaled by
  {cfg.translation_scale} m inside the network; initial translations N(0, {cfg.translation_noise_std} m).
- Coarse pose token: object-frame coordinates predicted for the first
  {cfg.correspondence_points} points (PointNet segmentation network), aligned to the observed
  points in closed form (Horn); the heads predict the clean pose as a
  correction of it.
- Refiner: {cfg.refine_iterations} iterations that map the observed points into the object
  frame by the current coarse pose, predict corrected object-frame
  coordinates (PointNet, residual) and align them again (Horn); the last
  pose is the coarse pose token (0 iterations: no refiner).
- PointNet++'s "group all" level adds one global point token; a pooled
  summary of the condition joins the adaLN conditioning
  (global_condition = {cfg.global_condition}).

## Data

`training/make-data`: `poseflow render` scenes of all ten objects on a
textured support plane with clutter primitives, random lights, the depth
noise model, camera on the view hemisphere (0.35–1.5 m); occlusion low /
medium / high by chunk; `poseflow observe` turns them into the ingest
stage's own observations. Training: {len(shards)} shards, {train_observations:,} observations
(seed 1, scenes 0–{20 * rendered_chunks - 1}). Held out: `test` split, seed 2, scenes 1000–1009,
medium occlusion, never trained on. {args.data_note}

## Training

{state['step']:,} steps, {state['train_s'] / 3600:.2f} h of training on 2 CPU cores (PyTorch,
`torch.set_num_threads(2)`), batch {config.get('batch')} observations × {config.get('samples_per_observation')} flow samples,
AdamW lr {learning_rate_text(config)}, loss λ·ℓ_pos + ℓ_rot with λ = {config.get('lambda_pos')} ("{config.get('loss', 'velocity')}"),
{last_run_text(config)} (see `training/README.md` for why). {args.history}
Hours are cumulative training time,
measured inside the training loop; part of it ran while the same two cores
built and tested the Rust workspace, so it overstates the CPU time spent.
During the warm-up the velocity network is untrained and its zero-initialised
corrections leave every sample at the coarse pose, so the flow's rows equal
the coarse pose's there.

![learning curve](learning-curve.png)

{table(curve_rows, ["step", "hours", "10°5cm %", "5°5cm %", "median rot °", "median trans cm", "coarse pose 10°5cm %"])}

## Held-out accuracy (the exported ONNX files through ONNX Runtime)

`python -m poseflow_train.evaluate --model {args.model} --shard {' '.join(evaluation['shard'])}`:
{instances(evaluation)} (visible fraction ≥ {evaluation['min_visib_fract']}),
N = {evaluation['samples']} samples from uniform rotations, K = {evaluation['steps']} Euler steps, no selection;
accuracy averaged over individual samples, with the minimum error over each
object's symmetries (`models_info.json`; continuous ones in 1° steps).

| | 10°5cm % | 5°5cm % | 10°2cm % | median rot ° | median trans cm |
|---|---|---|---|---|---|
| all | {evaluation['acc_10deg_5cm']} | {evaluation['acc_5deg_5cm']} | {evaluation['acc_10deg_2cm']} | {evaluation['median_rot_deg']} | {evaluation['median_trans_cm']} |
| the encoder's coarse pose alone (one per instance) | {coarse['acc_10deg_5cm']} | {coarse['acc_5deg_5cm']} | {coarse['acc_10deg_2cm']} | {coarse['median_rot_deg']} | {coarse['median_trans_cm']} |
{other_rows}
{args.eval_note}

{table(object_rows, ["object", "symmetric", "instances", "10°5cm %", "5°5cm %", "median rot °", "median trans cm"])}

{robustness_section(args.robustness, args.robustness_compare, args.robustness_compare_label, args.robustness_note)}
{Path(args.ambiguity).read_text() if args.ambiguity else ""}
## Latency (2 CPU cores, ONNX Runtime {bench['threads']} intra-op threads)

`poseflow bench model --model {bench['model']} --json`:
encoder per observation {timing(bench['encoder'])};
velocity for a batch of {bench['samples']} samples {timing(bench['velocity'])}.
"""
    (out / "MODEL_CARD.md").write_text(text)
    print(f"wrote {out / 'MODEL_CARD.md'} and {out / 'learning-curve.png'}")


if __name__ == "__main__":
    main()
