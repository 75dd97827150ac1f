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

from .data import SYMMETRY_FILES, Shard
from .train import load_config, resume_point

# The default model's descriptions; another model's card passes its own
# (--intro, --data-text).
LMO_INTRO = ("The default PoseFlow network of this project: the encoder and velocity\n"
             "networks of SE(3)-PoseFlow, trained from scratch on a 2-core CPU on renders\n"
             "of ten objects")
LMO_DATA = ("`training/make-data`: `poseflow render` scenes of all ten objects on a\n"
            "textured support plane with clutter primitives, random lights, the depth\n"
            "noise model, camera on the view hemisphere (0.35–1.5 m); occlusion low /\n"
            "medium / high by chunk")


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


def trained_run(config):
    """The run directory of a config and its checkpoint (on the CPU): the
    full one, or on a machine without it the portable weights the run
    resumes from (`train.resume_point`), which hold the same state and
    model config."""
    run = Path(config["out"])
    return run, torch.load(resume_point(run / "checkpoint.pt"), weights_only=False, map_location="cpu")


def parameter_count(saved):
    return sum(v.numel() for part in ("encoder", "velocity") for v in saved[part].values() if v.is_floating_point())


def encoder_metadata(model_dir):
    """The exported encoder's metadata, {key: text}."""
    import onnx

    encoder = onnx.load(str(Path(model_dir) / "encoder.onnx"), load_external_data=False)
    return {p.key: p.value for p in encoder.metadata_props}


def contract_of(model_dir):
    return encoder_metadata(model_dir)["contract"]


def verification_text(model_dir):
    """The Architecture bullet of an encoder exported with `--verify-coarse`
    (empty without it)."""
    meta = encoder_metadata(model_dir).get("coarse_verification")
    if meta is None:
        return ""
    meta = json.loads(meta)
    return f"""- Coarse pose check (`export --verify-coarse`, inference only): the coarse
  pose and its other {meta['turns'] - 1} turns of the cube's rotation group about the
  object's centre each get one refiner pass and are scored by the observed
  points' distance to {meta['surface_points']:,} points of the object's mesh; the best is
  refined again and becomes the coarse pose token.
"""


def files_section(model_dir, saved, int8_eval=None):
    """The Files section: the ONNX files with their sizes, the INT8 ones
    (`poseflow_train.quantize`) with their held-out accuracy when measured."""
    model_dir = Path(model_dir)
    sizes = {f.name: f.stat().st_size for f in sorted(model_dir.glob("*.onnx"))}
    full = {n: v for n, v in sizes.items() if ".int8." not in n}
    int8 = {n: v for n, v in sizes.items() if ".int8." in n}
    text = f"""## Files

{table([(name, f"{size / 1e6:.2f} MB") for name, size in sizes.items()], ["file", "size"])}

FP32 {sum(full.values()) / 1e6:.2f} MB; {parameter_count(saved):,} parameters.
`parity.bin`/`parity.json`: stored inputs and PyTorch outputs, which ONNX
Runtime reproduces within 1e-4 (checked at export and by the Rust tests).
"""
    if int8:
        text += f"""
`encoder.int8.onnx` and `velocity.int8.onnx` ({sum(int8.values()) / 1e6:.2f} MB): the same networks
after ONNX Runtime's dynamic quantisation of their matrix products (weights
INT8 in 7 bits, activations quantised per run; `python -m poseflow_train.quantize`;
why 7 bits: [docs/network.md](../../docs/network.md#int8-on-every-x86-cpu)),
served by the inference stage with `precision = "int8"`.
"""
    for e in int8_eval or []:
        text += (f"Their per-sample 10°5cm on `{' '.join(e['shard'])}`: {e['acc_10deg_5cm']} % "
                 f"(5°5cm {e['acc_5deg_5cm']} %, median rotation error {e['median_rot_deg']}°).\n")
    return text + "\n"


def rewrite_files(args):
    """The card with its Files section and contract replaced: for a model
    exported or quantised again from the same checkpoint."""
    import re

    # The checkpoint only (no training shards needed).
    out = json.loads(Path(args.config).read_text())["out"]
    saved = torch.load(Path(out) / "checkpoint.pt", weights_only=False, map_location="cpu")
    path = Path(args.model) / "MODEL_CARD.md"
    text = path.read_text()
    start, end = text.index("## Files"), text.index("## Architecture")
    int8_eval = [json.loads(Path(p).read_text()) for p in args.int8_eval]
    text = text[:start] + files_section(args.model, saved, int8_eval) + text[end:]
    text = re.sub(r"the ONNX contract `poseflow-onnx/\d+`", f"the ONNX contract `{contract_of(args.model)}`", text, count=1)
    path.write_text(text)
    print(f"wrote the Files section of {path}")


def table(rows, header):
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def learning_rate_text(config):
    """The learning rate and its schedule, as the card states it."""
    decay = config.get("lr_decay")
    if not decay:
        return f"{config.get('lr')}"
    return f"{config.get('lr')} cosine-decayed to {decay['final']} over {decay['over_s'] / 60:.0f} minutes (`lr_decay`)"


def last_run_text(config):
    """What the last run trained besides the flow loss, as the card states it."""
    if not config.get("frozen_encoder"):
        parts = [f"plus the correspondence loss with weight {config.get('correspondence', 1.0)}"]
        if config.get("correspondence_warmup_s"):
            parts[0] += (f"; the first {config['correspondence_warmup_s'] / 60:.0f} minutes train the correspondence "
                         "network alone")
    else:
        parts = [f"the encoder frozen (`{config.get('encoder_from') or config['init_from']}`) and the velocity network "
                 "trained on its cached conditions"]
    if config.get("equivalent_targets"):
        parts.append("each flow target drawn from the poses equivalent to the truth (symmetries"
                     + (", hidden-handle turns" if config.get("hidden_arcs") else "") + ")")
    if config.get("rollout_energy"):
        energy = config["rollout_energy"]
        parts.append(f"plus {energy.get('weight', 1.0)} × the energy score of the {config.get('steps')}-step sampler's "
                     f"output ({energy.get('observations', 16)} observations × {energy.get('samples', 32)} samples) "
                     "against those targets")
    return "; ".join(parts)


def robustness_section(path, compare_path, compare_label, note):
    """The robustness table: per variant the per-sample and coarse-pose
    accuracy, and another run's per-sample 10°5cm when given."""
    if not path:
        return ""
    result = json.loads(Path(path).read_text())
    compare = json.loads(Path(compare_path).read_text())["variants"] if compare_path else {}
    header = ["frames", "instances", "10°5cm %", "5°5cm %", "coarse pose 10°5cm %"]
    if compare:
        header.append(compare_label)
    rows = [
        (name, r["observations"], r["acc_10deg_5cm"], r["acc_5deg_5cm"], r["coarse"]["acc_10deg_5cm"],
         *([compare[name]["acc_10deg_5cm"] if name in compare else "–"] if compare else []))
        for name, r in result["variants"].items()
    ]
    return f"""## Robustness: frames less like the renders

`python -m poseflow_train.robustness --model {result['model']} --dataset {result['dataset']} --split {result['split']}`:
perturbed copies of a held-out split (what a real sensor and a real
segmentation add), each turned into observations by the ingest stage's own
code (`poseflow observe`, default parameters) and scored as above (N = 50,
K = 5, per sample, no selection).

{table(rows, header)}

{note}

"""


def rewrite_robustness(args):
    """The card with its Robustness section replaced (or put before the
    Latency section): for robustness runs made after the rest of the card."""
    if not args.robustness:
        raise SystemExit("--robustness-only needs --robustness")
    path = Path(args.model) / "MODEL_CARD.md"
    text = path.read_text()
    start = text.find("## Robustness")
    latency = text.index("## Latency")
    before = text[:start] if start >= 0 else text[:latency]
    section = robustness_section(args.robustness, args.robustness_compare, args.robustness_compare_label,
                                 args.robustness_note)
    path.write_text(before + section + text[latency:])
    print(f"wrote the Robustness section of {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config")
    parser.add_argument("--model", required=True)
    parser.add_argument("--eval")
    parser.add_argument("--bench")
    parser.add_argument("--files-only", action="store_true",
                        help="only (re)write the card's Files section and contract (needs --config; the rest stays)")
    parser.add_argument("--int8-eval", nargs="*", default=[],
                        help="`evaluate --precision int8` outputs, for the Files section")
    parser.add_argument("--robustness-only", action="store_true",
                        help="only (re)write the card's Robustness section from --robustness (the rest stays)")
    parser.add_argument("--also-eval", nargs="*", default=[],
                        help="evaluate outputs on further held-out shards (e.g. one never used during training)")
    parser.add_argument("--earlier-logs", nargs="*", default=[],
                        help="log.jsonl of the runs this one continues, oldest first (for the learning curve)")
    parser.add_argument("--eval-note", default="", help="Markdown after the held-out table")
    parser.add_argument("--robustness", help="`poseflow_train.robustness` output for this model")
    parser.add_argument("--robustness-compare", help="another `robustness` output (e.g. other ingest settings), as a column")
    parser.add_argument("--robustness-compare-label", default="compared 10°5cm %", help="that column's heading")
    parser.add_argument("--robustness-note", default="", help="Markdown after the robustness table")
    parser.add_argument("--data-note", default="", help="Markdown at the end of the Data section")
    parser.add_argument("--ambiguity", help="the Ambiguity section as `evaluation/results_page.py --ambiguity-only` wrote "
                                            "it (Markdown, included as it is)")
    parser.add_argument("--history", default="",
                        help="Markdown describing how the runs followed each other, for the Training section")
    parser.add_argument("--intro", default=LMO_INTRO, help="what the model is, the card's first sentence up to "
                                                           "\"exported to the ONNX contract\"")
    parser.add_argument("--data-text", default=LMO_DATA,
                        help="how the training renders were made, the Data section's first sentence")
    args = parser.parse_args()
    if args.robustness_only:
        return rewrite_robustness(args)
    if args.files_only:
        return rewrite_files(args)
    missing = [flag for flag in ("config", "eval", "bench") if getattr(args, flag) is None]
    if missing:
        parser.error(f"--{missing[0]} is required (unless --robustness-only)")
    config = load_config(args.config)
    cfg = config["model"]
    out = Path(args.model)
    run, saved = trained_run(config)
    state = saved["state"]
    curve = learning_curve([*args.earlier_logs, run / "log.jsonl"])
    plot(curve, out / "learning-curve.png")
    evaluation = json.loads(Path(args.eval).read_text())
    coarse = evaluation["coarse"]
    bench = json.loads(Path(args.bench).read_text())
    shards = [Shard(p) for p in config["train"]]
    train_observations = sum(len(s) for s in shards)
    rendered_chunks = len({(s.info["dataset"], s.info["split"]) for s in shards})
    symmetries = evaluation.get("symmetries", "models-info")
    val_shard = Shard(config["val"][0], symmetries)
    info = json.loads(val_shard.models_info.read_text())

    curve_rows = [
        (e["step"], f"{e['train_s'] / 3600:.2f}", e["validation"]["acc_10deg_5cm"], e["validation"]["acc_5deg_5cm"],
         e["validation"]["median_rot_deg"], e["validation"]["median_trans_cm"],
         e["validation"].get("coarse", {}).get("acc_10deg_5cm", "–"))
        for e in curve
    ]
    object_rows = [
        (obj, "yes" if info.get(obj, {}).get("symmetries_discrete") or info.get(obj, {}).get("symmetries_continuous")
         else "no", r["observations"] + r.get("unobserved", 0), r["acc_10deg_5cm"], r["acc_5deg_5cm"], r["median_rot_deg"], r["median_trans_cm"])
        for obj, r in evaluation["per_object"].items()
    ]
    others = [json.loads(Path(p).read_text()) for p in args.also_eval]
    other_rows = "".join(
        f"| all, `{' '.join(e['shard'])}` ({instances(e)}) | {e['acc_10deg_5cm']} | {e['acc_5deg_5cm']} | "
        f"{e['acc_10deg_2cm']} | {e['median_rot_deg']} | {e['median_trans_cm']} |\n"
        f"| its coarse pose | {e['coarse']['acc_10deg_5cm']} | {e['coarse']['acc_5deg_5cm']} | "
        f"{e['coarse']['acc_10deg_2cm']} | {e['coarse']['median_rot_deg']} | {e['coarse']['median_trans_cm']} |\n"
        for e in others)
    timing = lambda t: f"{t['p50_ms']:.1f} ms p50, {t['p99_ms']:.1f} ms p99 (mean {t['mean_ms']:.1f})"  # noqa: E731
    time_grid = evaluation.get("time_grid", "uniform")
    grid_flag = "" if time_grid == "uniform" else f" --time-grid {time_grid}"
    grid_text = "" if time_grid == "uniform" else (
        f" on the {time_grid} time grid (the sampler stage's `time_grid = \"{time_grid}\"`, docs/distributions.md)")
    text = f"""# Model card: {out.name}

{args.intro}, exported to the ONNX contract `{contract_of(out)}` that the
inference stage serves (`services/inference`). Generated by
`training/poseflow_train/card.py` from the training log, the checkpoint and
the measurements below; nothing in it is typed by hand.

{files_section(out, saved)}## Architecture (paper, "Method")

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
{verification_text(out)}- PointNet++'s "group all" level adds one global point token; a pooled
  summary of the condition joins the adaLN conditioning
  (global_condition = {cfg.global_condition}).

## Data

{args.data_text}; `poseflow observe` turns them into the ingest
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

`python -m poseflow_train.evaluate --model {args.model} --shard {' '.join(evaluation['shard'])}{grid_flag}`:
{instances(evaluation)} (visible fraction ≥ {evaluation['min_visib_fract']}),
N = {evaluation['samples']} samples from uniform rotations, K = {evaluation['steps']} Euler steps{grid_text}, no selection;
accuracy averaged over individual samples, with the minimum error over each
object's symmetries (`{SYMMETRY_FILES[symmetries]}`; continuous ones in 1° steps).

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

`poseflow bench model --model {bench['model']} --precision {bench.get('precision', 'fp32')} --json`:
encoder per observation {timing(bench['encoder'])};
velocity for a batch of {bench['samples']} samples {timing(bench['velocity'])}.
"""
    (out / "MODEL_CARD.md").write_text(text)
    print(f"wrote {out / 'MODEL_CARD.md'} and {out / 'learning-curve.png'}")


if __name__ == "__main__":
    main()
