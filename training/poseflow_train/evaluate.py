"""Sampling poses with the trained flow and scoring them: per-sample
n-degree m-cm accuracy (the paper's "None" selection), with the minimum
error over an object's discrete symmetries (models_info.json)."""

import json
import math
from pathlib import Path

import torch

from . import se3
from .model import read_hint


# Continuous symmetries are discretised in steps of 1 degree (the rotation
# error is then at most 0.5 degrees above the exact minimum).
CONTINUOUS_STEPS = 360


def symmetries(models_info, continuous_steps=CONTINUOUS_STEPS):
    """{obj_id: [(R [3,3], t [3] metres)]} with the identity first: the
    discrete symmetries, each combined with the discretised continuous ones
    (as the BOP toolkit does), from a models_info.json (a path, or its
    parsed dict)."""
    info = models_info if isinstance(models_info, dict) else json.loads(Path(models_info).read_text())
    out = {}
    for key, entry in info.items():
        discrete = [(torch.eye(3), torch.zeros(3))]
        for m in entry.get("symmetries_discrete", []):
            m = torch.tensor(m, dtype=torch.float32).reshape(4, 4)
            discrete.append((m[:3, :3], m[:3, 3] / 1000.0))
        continuous = [(torch.eye(3), torch.zeros(3))]
        for sym in entry.get("symmetries_continuous", []):
            axis = torch.tensor(sym["axis"], dtype=torch.float32)
            axis = axis / axis.norm()
            offset = torch.tensor(sym["offset"], dtype=torch.float32) / 1000.0
            for k in range(1, continuous_steps):
                r = se3.so3_exp(axis * (2 * math.pi * k / continuous_steps))
                continuous.append((r, offset - r @ offset))
        out[int(key)] = [(rd @ rc, rd @ tc + td) for rd, td in discrete for rc, tc in continuous]
    return out


@torch.no_grad()
def sample(encoder, velocity, batch, cfg, samples, steps, generator):
    """N samples per observation after K Euler steps from uniform rotations
    and Gaussian translations: ([B, N, 3, 3], [B, N, 3]), and the encoder's
    coarse poses ([B, 3, 3], [B, 3])."""
    condition, mask = encoder(batch["image"], batch["token_mask"], batch["points"], batch["object_index"])
    r, p = rollout(velocity, condition, mask, cfg, samples, steps, generator, getattr(cfg, "time_grid", "uniform"))
    return r, p, read_hint(condition, cfg)


TIME_GRIDS = ("uniform", "quadratic")


def flow_times(steps, time_grid="uniform"):
    """t_0 = 0 < ... < t_K = 1 of K Euler steps, as the sampler stage's
    `time_grid` (poseflow_geometry::flow::TimeGrid): uniform t_k = k/K,
    quadratic t_k = 1 - (1 - k/K)^2."""
    if time_grid == "uniform":
        return [k / steps for k in range(steps + 1)]
    if time_grid == "quadratic":
        return [1.0 - (1.0 - k / steps) ** 2 for k in range(steps + 1)]
    raise ValueError(f"time grid {time_grid!r}: expected one of {', '.join(TIME_GRIDS)}")


def euler_steps(steps, time_grid="uniform"):
    """(t_k, t_{k+1} - t_k) of each Euler step; the uniform grid's length is
    exactly 1/K, so that recorded results reproduce bit for bit."""
    times = flow_times(steps, time_grid)
    if time_grid == "uniform":
        return [(t, 1.0 / steps) for t in times[:-1]]
    return [(t, after - t) for t, after in zip(times, times[1:])]


def rollout(velocity, condition, mask, cfg, samples, steps, generator, time_grid="uniform"):
    """The sampler of the inference stage: `samples` uniform rotations and
    Gaussian translations per observation, carried by K Euler steps at the
    times of `euler_steps` ([B, N, 3, 3], [B, N, 3]). Differentiable, so
    training can score what K steps produce (`rollout_energy`)."""
    b = condition.shape[0]
    m = b * samples
    # Drawn on the generator's CPU, carried where the condition is.
    r = se3.uniform_rotation((m,), generator=generator).to(condition.device)
    p = (torch.randn(m, 3, generator=generator) * cfg.translation_noise_std).to(condition.device)
    for time, length in euler_steps(steps, time_grid):
        t = torch.full((m,), time, device=condition.device)
        v_rot, v_pos = velocity(condition, mask, r, p, t)
        r, p = se3.euler_step(r, p, v_rot, v_pos, length)
    return r.reshape(b, samples, 3, 3), p.reshape(b, samples, 3)


def errors(r, p, gt_r, gt_p, transforms):
    """Rotation (degrees) and translation (cm) errors of samples [N] against
    the closest symmetric version of the ground truth."""
    best_rot = torch.full((r.shape[0],), math.inf)
    best_trans = torch.full((r.shape[0],), math.inf)
    best_score = torch.full((r.shape[0],), math.inf)
    for s_r, s_t in transforms:
        sym_r, sym_p = gt_r @ s_r, gt_r @ s_t + gt_p
        rot = torch.rad2deg(se3.geodesic_angle(r, sym_r.expand_as(r)))
        trans = (p - sym_p).norm(dim=-1) * 100.0
        score = rot / 10.0 + trans / 5.0
        better = score < best_score
        best_rot, best_trans, best_score = (torch.where(better, a, b) for a, b in ((rot, best_rot), (trans, best_trans), (score, best_score)))
    return best_rot, best_trans


def summarise(rot, trans, misses, per_instance):
    """Accuracies (%) of the scored poses' errors (degrees, cm), with
    `misses` instances of `per_instance` poses each counted as failures;
    medians over the scored poses."""
    def acc(deg, cm):
        hits = ((rot < deg) & (trans < cm)).float().sum().item()
        return round(100.0 * hits / (rot.numel() + misses * per_instance), 2)

    return {
        "acc_5deg_5cm": acc(5, 5),
        "acc_10deg_5cm": acc(10, 5),
        "acc_10deg_2cm": acc(10, 2),
        "median_rot_deg": round(rot.median().item(), 2),
        "median_trans_cm": round(trans.median().item(), 2),
    }


def coverage(rots, transs, misses):
    """% of observations (one error tensor [N] each) with at least one
    sample within 10 degrees and 5 cm, `misses` counted as failures: does
    the distribution hold the truth, as `poseflow eval` measures it."""
    hits = sum(bool(((r < 10) & (t < 5)).any()) for r, t in zip(rots, transs))
    return round(100.0 * hits / max(len(rots) + misses, 1), 2)


def unobserved(observations, min_visib_fract):
    """{obj_id: instances} of the shards' BOP splits that are visible
    enough to be scored but have no observation: the ingest rejected them
    (too few valid depth points, say). They are misses, as in `poseflow
    eval`. The split folder is found where the shard says the dataset is, or
    beside the shard (training/make-data's layout)."""
    wanted = set(observations.object_index)
    missing = {}
    for shard in observations.shards:
        candidates = [Path(shard.info["dataset"]) / shard.info["split"], shard.path.parent / shard.info["split"]]
        split = next((c for c in candidates if c.is_dir()), None)
        if split is None:
            raise SystemExit(f"{shard.path}: its split folder is at none of {[str(c) for c in candidates]} "
                             "(needed to count the instances the ingest could not observe)")
        expected = {}
        for scene in sorted(p for p in split.iterdir() if (p / "scene_gt_info.json").is_file()):
            gts = json.loads((scene / "scene_gt.json").read_text())
            infos = json.loads((scene / "scene_gt_info.json").read_text())
            for im_id, entries in gts.items():
                for gt, info in zip(entries, infos[im_id]):
                    if gt["obj_id"] in wanted and info["visib_fract"] >= min_visib_fract:
                        expected[gt["obj_id"]] = expected.get(gt["obj_id"], 0) + 1
        records = shard.records
        keep = records["visib_fract"] >= min_visib_fract
        for obj, count in expected.items():
            observed = int(((records["ids"][:, 0] == obj) & keep).sum())
            if count > observed:
                missing[obj] = missing.get(obj, 0) + count - observed
    return missing


def accuracy(encoder, velocity, observations, cfg, count, samples, steps, seed, missed=None):
    """Per-sample accuracies over the first `count` observations, overall
    and per object. `encoder` and `velocity` are callables with the
    signatures of the PyTorch modules (or `OnnxPoseFlow`'s). `missed`
    ({obj_id: instances}, from `unobserved`) count as instances whose every
    sample failed; medians are over the observed ones."""
    missed = missed or {}
    if observations.categories is not None and missed:
        raise ValueError("accuracy: unobserved instances are counted per object, not per category")
    generator = torch.Generator().manual_seed(seed)
    transforms = symmetries(observations.models_info)
    count = min(count, len(observations))
    rots, transs, objects, coarse_rots, coarse_transs = [], [], [], [], []
    for start in range(0, count, 16):
        batch = observations.batch(range(start, min(start + 16, count)))
        r, p, (coarse_r, coarse_p) = sample(encoder, velocity, batch, cfg, samples, steps, generator)
        for i in range(r.shape[0]):
            obj = int(batch["obj_id"][i])
            sym = transforms.get(obj, [(torch.eye(3), torch.zeros(3))])
            rot, trans = errors(r[i], p[i], batch["rotation"][i], batch["translation"][i], sym)
            rots.append(rot)
            transs.append(trans)
            # A category model's figures are per category, not per instance.
            objects.append(int(batch["object_index"][i]) if observations.categories is not None else obj)
            rot, trans = errors(coarse_r[i:i + 1], coarse_p[i:i + 1], batch["rotation"][i], batch["translation"][i], sym)
            coarse_rots.append(rot)
            coarse_transs.append(trans)

    summary = summarise
    total_missed = sum(missed.values())
    result = {"observations": len(rots), "unobserved": total_missed, "samples": samples, "steps": steps,
              "time_grid": getattr(cfg, "time_grid", "uniform"),
              **summary(torch.cat(rots), torch.cat(transs), total_missed, samples)}
    # The encoder's coarse pose alone (one per observation), for comparison.
    result["coarse"] = summary(torch.cat(coarse_rots), torch.cat(coarse_transs), total_missed, 1)
    result["coverage_10deg_5cm"] = coverage(rots, transs, total_missed)
    names = {i: code for code, i in observations.object_index.items()} if observations.categories is not None else None
    result["per_object"] = {
        str(names[obj] if names else obj): {"observations": objects.count(obj), "unobserved": missed.get(obj, 0),
                   **summary(torch.cat([r for r, o in zip(rots, objects) if o == obj]),
                             torch.cat([t for t, o in zip(transs, objects) if o == obj]), missed.get(obj, 0), samples),
                   "coverage_10deg_5cm": coverage([r for r, o in zip(rots, objects) if o == obj],
                                                  [t for t, o in zip(transs, objects) if o == obj], missed.get(obj, 0))}
        for obj in sorted(set(objects))
    }
    return result


def on_cpu(module):
    """`module` as a callable taking and returning CPU tensors wherever its
    parameters are (a GPU during training): what `accuracy` scores."""
    device = next(module.parameters()).device
    if device.type == "cpu":
        return module
    return lambda *inputs: tuple(out.cpu() for out in module(*(x.to(device) for x in inputs)))


def validate(encoder, velocity, observations, cfg, count, samples, steps, seed):
    """`accuracy` of the modules in eval mode, during training."""
    encoder.eval()
    velocity.eval()
    try:
        return accuracy(on_cpu(encoder), on_cpu(velocity), observations, cfg, count, samples, steps, seed)
    finally:
        encoder.train()
        velocity.train()


class OnnxPoseFlow:
    """An exported model directory through ONNX Runtime, callable like the
    PyTorch modules, so the figures of a model card come from the files the
    inference stage serves. `precision` "int8" loads the quantised files
    (`encoder.int8.onnx`, `velocity.int8.onnx`, `poseflow_train.quantize`)."""

    def __init__(self, model_dir, threads, precision="fp32"):
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = threads
        model_dir = Path(model_dir)
        suffix = {"fp32": "", "int8": ".int8"}[precision]
        self.encoder_session = onnxruntime.InferenceSession(str(model_dir / f"encoder{suffix}.onnx"), options)
        self.velocity_session = onnxruntime.InferenceSession(str(model_dir / f"velocity{suffix}.onnx"), options)
        meta = self.encoder_session.get_modelmeta().custom_metadata_map
        self.contract = meta["contract"]
        self.object_ids = json.loads(meta["object_ids"])
        self.translation_noise_std = float(meta["translation_noise_std"])
        self.translation_scale = float(meta["translation_scale"])
        self.width = int(meta["width"])
        # poseflow-onnx/2: the cross-attention keys and values of the last
        # encoded batch, which the velocity calls that follow it read.
        self.cross_kv = None

    def encoder(self, image, token_mask, points, object_index):
        outputs = self.encoder_session.run(
            None, {"image": image.numpy(), "token_mask": token_mask.numpy(), "points": points.numpy(),
                   "object_index": object_index.numpy()})
        if self.contract != "poseflow-onnx/1":
            self.cross_kv = outputs[2]
        return torch.from_numpy(outputs[0]), torch.from_numpy(outputs[1])

    def velocity(self, condition, mask, r, p, t):
        """Samples are grouped by observation, in order. poseflow-onnx/2
        runs all observations at once on the last encoded batch's keys and
        values; poseflow-onnx/1 takes one observation per run."""
        if self.contract != "poseflow-onnx/1":
            assert self.cross_kv is not None and self.cross_kv.shape[0] == condition.shape[0], "encode first"
            w, v = self.velocity_session.run(
                None, {"condition": condition.numpy(), "condition_mask": mask.numpy(), "cross_kv": self.cross_kv,
                       "rotation": r.numpy(), "translation": p.numpy(), "t": t.numpy()})
            return torch.from_numpy(w), torch.from_numpy(v)
        b = condition.shape[0]
        n = r.shape[0] // b
        v_rot, v_pos = [], []
        for i in range(b):
            part = slice(i * n, (i + 1) * n)
            w, v = self.velocity_session.run(
                None, {"condition": condition[i:i + 1].numpy(), "condition_mask": mask[i:i + 1].numpy(),
                       "rotation": r[part].numpy(), "translation": p[part].numpy(), "t": t[part].numpy()})
            v_rot.append(torch.from_numpy(w))
            v_pos.append(torch.from_numpy(v))
        return torch.cat(v_rot), torch.cat(v_pos)


def add_model_arguments(parser):
    """The flags every scoring command shares: the exported model and how it
    samples (N, K, threads, seed)."""
    parser.add_argument("--model", required=True, help="directory with encoder.onnx and velocity.onnx")
    parser.add_argument("--samples", type=int, default=50)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--time-grid", choices=TIME_GRIDS, default="uniform",
                        help="where the Euler steps ask for the velocity (the sampler stage's time_grid)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--precision", choices=["fp32", "int8"], default="fp32",
                        help="int8: the quantised files (encoder.int8.onnx, velocity.int8.onnx)")
    parser.add_argument("--symmetries", choices=["models-info", "shape"], default="models-info",
                        help="score up to models_info.json's symmetries (the printed objects') or "
                             "models_info_shape.json's (the one-coloured shapes', as poseflow eval --symmetries)")


def load_model(args):
    """The exported model of `add_model_arguments`' flags and the sampling
    settings `accuracy` takes from its metadata."""
    from types import SimpleNamespace

    torch.set_num_threads(args.threads)
    model = OnnxPoseFlow(args.model, args.threads, args.precision)
    cfg = SimpleNamespace(translation_noise_std=model.translation_noise_std, translation_scale=model.translation_scale,
                          time_grid=args.time_grid)
    return model, cfg


def main():
    import argparse

    from .data import Observations

    parser = argparse.ArgumentParser(description="Per-sample accuracy of an exported model on a held-out shard.")
    add_model_arguments(parser)
    parser.add_argument("--shard", required=True, nargs="+")
    parser.add_argument("--count", type=int, default=10**9, help="first observations only")
    parser.add_argument("--min-visib-fract", type=float, default=0.1)
    args = parser.parse_args()
    model, cfg = load_model(args)
    observations = Observations(args.shard, model.object_ids, args.min_visib_fract, symmetries=args.symmetries)
    # A prefix of the observations (--count) is a quick look, not a figure
    # over the split: only the whole split counts its unobserved instances.
    missed = unobserved(observations, args.min_visib_fract) if args.count >= len(observations) else {}
    result = accuracy(model.encoder, model.velocity, observations, cfg, args.count, args.samples, args.steps, args.seed,
                      missed)
    result.update({"model": args.model, "shard": args.shard, "min_visib_fract": args.min_visib_fract,
                   "symmetries": args.symmetries})
    print(json.dumps(result))


if __name__ == "__main__":
    main()
