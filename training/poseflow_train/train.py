"""Flow-matching training with checkpoints and resume, on a GPU when there
is one (`training_device`), else on the CPU.

    python -m poseflow_train.train --config training/configs/lmo.json

Every `checkpoint_s` seconds of training (and when stopped by SIGTERM or
Ctrl-C) the model, optimiser, step,
cumulative training time and random state go to `<out>/checkpoint.pt`
(written atomically); a later run with the same config continues from it.
`<out>/log.jsonl` gets one line per `log_every` steps (loss) and one per
validation (per-sample accuracy on a held-out shard after K Euler steps
from N uniform samples), so the learning curve is accuracy against
cumulative training time.
"""

import argparse
import contextlib
import glob
import json
import math
import os
import signal
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from . import se3
from .data import Observations, category_models_info
from .evaluate import rollout, symmetries, validate
from .model import SIZE_REFERENCE_M, Encoder, ModelConfig, VelocityNet, read_hint


class LossModule(torch.nn.Module):
    """The trained modules as one module whose forward is a step's loss
    computation (a closure over them), so that DistributedDataParallel sees
    every parameter the step uses."""

    def __init__(self, modules):
        super().__init__()
        self.parts = torch.nn.ModuleDict(modules)

    def forward(self, compute):
        return compute()


def training_device(requested="auto"):
    """The device a process trains on: `requested` ("auto", "cpu", "cuda" or
    a torch device string); "auto" is the process's own GPU (LOCAL_RANK, as
    `torchrun` sets it) when PyTorch sees one, else the CPU."""
    if requested == "auto":
        requested = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(requested)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit(f"config: device {requested!r}, but PyTorch sees no GPU (torch.cuda.is_available())")
        if device.index is None:
            device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def moved(value, device):
    """`value` (a tensor, or a dict, list or tuple of them) on `device`."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return {k: moved(v, device) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(moved(v, device) for v in value)
    return value


class Replicas:
    """Data-parallel training through PyTorch's own launcher. Under
    `torchrun` (WORLD_SIZE > 1) every process trains a replica on batches of
    its own (so the global batch is `batch` x processes), DistributedData-
    Parallel averages the gradients (over NCCL between GPUs, gloo between
    CPU processes), and rank 0 alone logs, validates and writes the
    checkpoint, in the same format as a single process. Alone, nothing
    changes."""

    def __init__(self, device):
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.device = device
        self.ddp = None
        if self.world > 1:
            if device.type == "cuda":
                torch.cuda.set_device(device)
            dist.init_process_group(self.backend)

    @property
    def backend(self):
        return "nccl" if self.device.type == "cuda" else "gloo"

    @property
    def main(self):
        return self.rank == 0

    def wrap(self, modules):
        """Replicas start from rank 0's weights (DDP broadcasts them)."""
        if self.world > 1:
            on_gpu = [self.device] if self.device.type == "cuda" else None
            self.ddp = DistributedDataParallel(LossModule(modules), device_ids=on_gpu, find_unused_parameters=True)

    def loss(self, compute):
        """`compute()` (the step's loss and its parts), through DDP when
        distributed so that backward averages the gradients."""
        return self.ddp(compute) if self.ddp is not None else compute()

    def seed(self, seed):
        """Rank r > 0 draws its own batches: seeds apart from rank 0's."""
        return seed if self.rank == 0 else [seed, self.rank]

    def any(self, flag):
        """True on every process if `flag` is true on any (a stop request)."""
        if self.world == 1:
            return flag
        value = torch.tensor([float(flag)], device=self.device)
        dist.all_reduce(value, op=dist.ReduceOp.MAX)
        return bool(value.item())

    def barrier(self):
        if self.world > 1:
            dist.barrier()

    def close(self):
        if self.world > 1:
            dist.destroy_process_group()


def shard_paths(patterns, key):
    """Shard files named by paths or glob patterns, in sorted order."""
    paths = []
    for pattern in patterns:
        found = sorted(glob.glob(pattern))
        if not found:
            raise SystemExit(f"config: {key}: {pattern!r} matches no file (render them with training/make-data)")
        paths.extend(found)
    return paths


def load_config(path):
    config = json.loads(Path(path).read_text())
    config["model"] = ModelConfig(**config.get("model", {}))
    for key in ("train", "val"):
        config[key] = shard_paths(config[key], key)
    return config


def equivalent_targets(batch, samples, table, generator, turns=None):
    """Per flow sample, a target drawn uniformly from the poses that explain
    the observation as well as its ground truth does: the truth times one of
    its object's symmetries (`table`: R [n_obj, K, 3, 3], t [n_obj, K, 3],
    count [n_obj] of real entries) and, where `turns` ([B, bins] bool, from
    `poseflow_train.arcs`) marks turns about object z that keep a part
    hidden, turned by one of them (uniform within its bin). A render shows
    one of these poses; teaching that one would teach the network to guess
    it. Returns (r1 [B*samples, 3, 3], p1 [B*samples, 3])."""
    r = batch["rotation"].repeat_interleave(samples, 0)
    p = batch["translation"].repeat_interleave(samples, 0)
    m = r.shape[0]
    if turns is not None:
        turns = turns.repeat_interleave(samples, 0)
        bins = turns.shape[1]
        hidden = turns.any(1)
        # A uniform bin among the allowed ones, then uniform within it.
        weights = torch.where(hidden[:, None], turns.float(), torch.ones_like(turns, dtype=torch.float32))
        k = torch.multinomial(weights.cpu(), 1, generator=generator)[:, 0].float()
        phi = ((k + torch.rand(m, generator=generator) - 0.5) * (2 * math.pi / bins)).to(r.device)
        phi = torch.where(hidden.to(r.device), phi, torch.zeros_like(phi))
        r = r @ se3.so3_exp(phi[:, None] * torch.tensor([0.0, 0.0, 1.0], device=r.device))
    sym_r, sym_t, count = table
    obj = batch["object_index"].repeat_interleave(samples, 0)
    # The generator draws on the CPU (its state is the checkpoint's on any device).
    k = (torch.rand(m, generator=generator).to(count.device) * count[obj]).long().clamp_max(sym_r.shape[1] - 1)
    s_r, s_t = sym_r[obj, k], sym_t[obj, k]
    return r @ s_r, (r @ s_t[..., None])[..., 0] + p


def targets_of(observations, indices, batch, samples, table, generator):
    """`equivalent_targets` of a batch when the config asks for them
    (`table` given), else None (the ground truth)."""
    if table is None:
        return None
    turns = observations.hidden_turns(indices) if observations.arcs is not None else None
    return equivalent_targets(batch, samples, table, generator, turns)


def flow_batch(batch, cfg, samples, steps, generator, hint=None, hint_paths=0.0, targets=None):
    """Per observation, `samples` draws of (t, R0, p0) on the path to the
    ground truth (or at `targets`, per sample, see `equivalent_targets`):
    the poses at t and the target velocities. Half of the
    times sit exactly where a K-step sampler evaluates (0, 1/K, ...), half
    anywhere in [0, (K - 1)/K].

    `hint_paths`: the share of draws whose path ends at the encoder's coarse
    pose `hint` (R [B,3,3], p [B,3]) instead of the truth, the target still
    being the truth. At inference the late states lie near the network's own
    prediction, not near the truth; trained only on paths to the truth the
    network learns to trust a late state and keeps a wrong one (measured:
    one step from the coarse pose at t = 0.8 made it worse, 18.8 -> 16.4 %
    10deg5cm). These draws teach it to correct such a state."""
    b = batch["rotation"].shape[0]
    m = b * samples
    if targets is None:
        r1 = batch["rotation"].repeat_interleave(samples, 0)
        p1 = batch["translation"].repeat_interleave(samples, 0)
    else:
        r1, p1 = targets
    device = r1.device
    r0 = se3.uniform_rotation((m,), generator=generator).to(device)
    p0 = (torch.randn(m, 3, generator=generator) * cfg.translation_noise_std).to(device)
    grid = torch.randint(0, steps, (m,), generator=generator).float() / steps
    anywhere = torch.rand(m, generator=generator) * (steps - 1) / steps
    t = torch.where(torch.rand(m, generator=generator) < 0.5, grid, anywhere).to(device)
    r_end, p_end = r1, p1
    if hint is not None and hint_paths > 0.0:
        to_hint = (torch.rand(m, generator=generator) < hint_paths).to(device)
        hint_r = hint[0].detach().to(device).repeat_interleave(samples, 0)
        hint_p = hint[1].detach().to(device).repeat_interleave(samples, 0)
        r_end = torch.where(to_hint[:, None, None], hint_r, r1)
        p_end = torch.where(to_hint[:, None], hint_p, p1)
    r_t, p_t = se3.interpolate(r0, p0, r_end, p_end, t)
    v_rot, v_pos = se3.target_velocity(r_t, p_t, r1, p1, t)
    return {"r_t": r_t, "p_t": p_t, "t": t, "v_rot": v_rot, "v_pos": v_pos, "r1": r1, "p1": p1}


def draw_weights(obj_ids, oversample):
    """Draw probabilities of the training observations: an observation of
    object `o` is drawn `oversample[str(o)]` times as often as one of an
    object not listed (views the data holds few of, such as a mug with its
    handle out of sight, otherwise barely reach the loss). None when
    nothing is oversampled, so the draws stay those of uniform sampling."""
    if not oversample:
        return None
    factors = {}
    for key, factor in oversample.items():
        if not str(key).isdigit() or not isinstance(factor, (int, float)) or factor <= 0:
            raise SystemExit(f"config: oversample {{{key!r}: {factor!r}}}: expected an object id and a positive factor")
        if int(key) not in set(obj_ids.tolist()):
            raise SystemExit(f"config: oversample names object {key}, which no training observation shows")
        factors[int(key)] = float(factor)
    weights = np.array([factors.get(int(o), 1.0) for o in obj_ids])
    return weights / weights.sum()


def draw(rng, count, size, weights):
    """`size` observation indices, uniform or by `weights`."""
    if weights is None:
        return rng.integers(0, count, size)
    return rng.choice(count, size, p=weights)


def flow_losses(config, cfg, velocity, condition, mask, flow):
    """(l_rot, l_pos) of one batch. `loss` "velocity" (the default): squared
    errors of the predicted velocities against the paper's targets, weighted
    per `loss_weighting`. "clean-pose": the same network's clean pose against
    the ground truth, chordal ||R1_hat - R1||_F^2 and squared translation
    error; since the velocities are derived from the clean pose, both are
    zero exactly when the velocity errors are."""
    s = cfg.translation_scale
    if config.get("loss", "velocity") == "clean-pose":
        r1_hat, p1_hat = velocity.clean_pose(condition, mask, flow["r_t"], flow["p_t"], flow["t"])
        loss_rot = (r1_hat - flow["r1"]).pow(2).sum((-1, -2)).mean()
        return loss_rot, ((p1_hat - flow["p1"]) / s).pow(2).sum(-1).mean()
    if config.get("loss", "velocity") != "velocity":
        raise SystemExit(f"config: loss {config['loss']!r}, expected \"velocity\" or \"clean-pose\"")
    pred_rot, pred_pos = velocity(condition, mask, flow["r_t"], flow["p_t"], flow["t"])
    weight = loss_weight(config.get("loss_weighting", "endpoint"), flow["t"], cfg)
    loss_rot = (weight * (pred_rot - flow["v_rot"]).pow(2).sum(-1)).mean()
    return loss_rot, (weight * ((pred_pos - flow["v_pos"]) / s).pow(2).sum(-1)).mean()


def energy_score(r, p, target_r, target_p, cfg, lambda_pos):
    """Mean over observations of the energy score of samples (r [B, N, 3, 3],
    p [B, N, 3] metres) against draws from the poses the view allows
    (target_r [B, T, 3, 3], target_p [B, T, 3]):
    E|X - Y| - E|X - X'| / 2 with |.| the Euclidean distance of
    (R flattened, sqrt(lambda_pos) p / translation_scale), the metric of
    the clean-pose loss. A proper scoring rule: its expectation is least
    when the samples are distributed as the targets, so unlike the
    per-sample flow loss (least at the posterior mean) it rewards samples
    that spread over every pose and penalises ones that pile up on one."""
    def embed(rotation, translation):
        return torch.cat([rotation.flatten(-2), math.sqrt(lambda_pos) * translation / cfg.translation_scale], -1)

    def distances(a, b):
        # The epsilon keeps the gradient finite where a sample meets itself.
        return ((a[:, :, None] - b[:, None]).pow(2).sum(-1) + 1e-8).sqrt()

    x, y = embed(r, p), embed(target_r, target_p)
    n = x.shape[1]
    spread = distances(x, x).sum((1, 2)) / (n * (n - 1))
    return (distances(x, y).mean((1, 2)) - 0.5 * spread).mean()


def rollout_energy(config, cfg, velocity, train, cache, weights, target_table, rng, generator, steps):
    """`rollout_energy` {"weight", "observations", "samples"}: the energy
    score of what the K-step sampler makes of `samples` noise draws, on
    `observations` observations drawn afresh, against as many equivalent
    targets each. The flow loss trains each step to land on the mean of
    what the current sample could still become, and K = 5 such steps
    narrow a wide distribution even with an exact field
    (docs/distributions.md); this trains the K-step map itself to end on
    draws. Backpropagates through all K steps."""
    settings = config["rollout_energy"]
    count, samples = settings.get("observations", 16), settings.get("samples", 32)
    indices = np.sort(draw(rng, len(train), count, weights))
    device = next(velocity.parameters()).device
    batch = moved(train.poses(indices), device)
    condition, mask = (torch.from_numpy(np.asarray(c[indices])).to(device) for c in cache)
    targets = targets_of(train, indices, batch, samples, target_table, generator)
    if targets is None:
        targets = (batch["rotation"].repeat_interleave(samples, 0), batch["translation"].repeat_interleave(samples, 0))
    r, p = rollout(velocity, condition, mask, cfg, samples, steps, generator)
    target_r, target_p = targets[0].reshape(count, samples, 3, 3), targets[1].reshape(count, samples, 3)
    return energy_score(r, p, target_r, target_p, cfg, config.get("lambda_pos", 10.0))


def loss_weight(kind, t, cfg):
    """Per-sample weight of the squared velocity errors. "velocity": 1, the
    plain flow-matching loss, dominated by late t where the targets grow as
    1/(1 - t). "endpoint": (1 - t)^2, which turns the velocity error into
    the clean-pose error in the tangent space at the current pose, so every
    t counts alike and the hard early times (where the pose comes from the
    observation alone) are not drowned out. Same targets either way."""
    if kind == "velocity":
        return torch.ones_like(t)
    if kind == "endpoint":
        return (1.0 - t).clamp_min(cfg.min_remaining).pow(2)
    raise SystemExit(f"config: loss_weighting {kind!r}, expected \"endpoint\" or \"velocity\"")


def symmetry_table(models_info, object_ids, continuous_steps, counts=False):
    """Per object index, K symmetry transforms (R [n_obj, K, 3, 3], t [n_obj,
    K, 3] metres), identity first, padded by repetition: what the
    correspondence loss minimises over. With `counts`, also each object's
    number of real entries ([n_obj]), for uniform draws."""
    table = symmetries(models_info, continuous_steps)
    lists = [table.get(obj, [(torch.eye(3), torch.zeros(3))]) for obj in object_ids]
    k = max(len(entries) for entries in lists)
    rotations = torch.stack([torch.stack([entries[i % len(entries)][0] for i in range(k)]) for entries in lists])
    translations = torch.stack([torch.stack([entries[i % len(entries)][1] for i in range(k)]) for entries in lists])
    if counts:
        return rotations, translations, torch.tensor([len(entries) for entries in lists])
    return rotations, translations


def correspondence_loss(coordinates, batch, table, cfg):
    """Mean L1 distance (in translation_scale units) between the predicted
    and the true model-frame coordinates of the observed points, under the
    closest symmetric version of the ground truth."""
    sym_r, sym_t = (x[batch["object_index"]] for x in table)
    r = batch["rotation"][:, None] @ sym_r
    t = (batch["rotation"][:, None] @ sym_t[..., None])[..., 0] + batch["translation"][:, None]
    observed = batch["points"][:, None, : coordinates.shape[1]]
    truth = (observed - t[:, :, None]) @ r  # rows: R^T (x - t)
    error = (coordinates[:, None] - truth).abs().sum(-1).mean(-1) / cfg.translation_scale
    return error.amin(1).mean()


def perturbed(rotation, translation, max_deg, max_cm, generator):
    """Each pose turned by a uniform angle up to `max_deg` about a uniform
    axis and moved by up to `max_cm` in a uniform direction."""
    b = rotation.shape[0]
    axis = torch.randn(b, 3, generator=generator).to(rotation.device)
    angle = (torch.rand(b, 1, generator=generator) * math.radians(max_deg)).to(rotation.device)
    shift = torch.randn(b, 3, generator=generator).to(rotation.device)
    length = (torch.rand(b, 1, generator=generator) * max_cm / 100.0).to(rotation.device)
    turned = rotation @ se3.so3_exp(axis / axis.norm(dim=-1, keepdim=True) * angle)
    return turned, translation + shift / shift.norm(dim=-1, keepdim=True) * length


def correspondence_losses(encoder, batch, table, cfg, config, generator):
    """Mean correspondence loss of the first coordinates and of each
    refinement. The refiner starts half the time from the first pose (what
    it meets at inference) and half from the truth perturbed by up to
    `refine_perturbation` [degrees, cm] (a wider basin than the first
    pose's errors alone would teach)."""
    coordinates, rotation, translation = encoder.first_pose(batch["points"], batch["object_index"])
    losses = [correspondence_loss(coordinates, batch, table, cfg)]
    if cfg.refine_iterations > 0:
        max_deg, max_cm = config.get("refine_perturbation", [40.0, 2.0])
        r, p = perturbed(batch["rotation"], batch["translation"], max_deg, max_cm, generator)
        from_first = (torch.rand(r.shape[0], generator=generator) < 0.5).to(r.device)
        rotation = torch.where(from_first[:, None, None], rotation, r)
        translation = torch.where(from_first[:, None], translation, p)
        refined, _, _ = encoder.refine(batch["points"], batch["object_index"], rotation, translation)
        losses += [correspondence_loss(c, batch, table, cfg) for c in refined]
    loss = sum(losses) / len(losses)
    if cfg.size_head:
        loss = loss + config.get("size_weight", 1.0) * size_loss(encoder, batch)
    return loss


def size_loss(encoder, batch):
    """Mean L1 distance of the log box extents, from the coarse pose the
    encoder itself reaches (what the size head meets at inference)."""
    _, rotation, translation = encoder.coarse_pose(batch["points"], batch["object_index"])
    predicted = encoder.size(batch["points"], batch["object_index"], rotation, translation)
    return (predicted - (batch["size"] / SIZE_REFERENCE_M).log()).abs().mean()


def learning_rate(config, state):
    """`lr`, or with `lr_decay` {"over_s", "final"} a cosine from `lr` to
    `final` over the run's first `over_s` seconds of training (counted from
    `init_from`'s time for a grown model), then `final`: a time budget, not
    a step count, is what a CPU run has. `lr_decay.from_s` starts the
    cosine at that much training time instead (a warm restart of a run
    that trained at `lr` until then)."""
    lr = config.get("lr", 3e-4)
    decay = config.get("lr_decay")
    if not decay:
        return lr
    start = decay.get("from_s", state.get("initialised_at_s", 0.0))
    done = (state["train_s"] - start) / decay["over_s"]
    return decay["final"] + (lr - decay["final"]) * 0.5 * (1.0 + math.cos(math.pi * min(max(done, 0.0), 1.0)))


def condition_cache(encoder, observations, path, source, device, batch=64):
    """Every observation's condition tokens and mask under a frozen encoder
    ([n, T, D] and [n, T] float32, memory-mapped): computed once and stored
    at `path`.condition.npy / .mask.npy beside `path`.json, which names the
    encoder's checkpoint and the shards, so a cache of another encoder or
    other data is refused rather than silently reused."""
    path = Path(path)
    key = {"encoder": str(source), "shards": [str(s.path) for s in observations.shards], "count": len(observations)}
    files = [path.with_suffix(".condition.npy"), path.with_suffix(".mask.npy")]
    described = path.with_suffix(".json")
    if described.exists():
        if json.loads(described.read_text()) != key:
            raise SystemExit(f"{described}: a condition cache of another encoder or other shards ({described.read_text()}); "
                             "delete it or name another condition_cache")
        return [np.load(f, mmap_mode="r") for f in files]
    path.parent.mkdir(parents=True, exist_ok=True)
    encoder.eval()
    arrays = None
    started = time.monotonic()
    with torch.no_grad():
        for start in range(0, len(observations), batch):
            b = moved(observations.batch(range(start, min(start + batch, len(observations)))), device)
            condition, mask = encoder(b["image"], b["token_mask"], b["points"], b["object_index"])
            if arrays is None:
                arrays = [np.lib.format.open_memmap(f.with_suffix(".tmp.npy"), mode="w+", dtype=np.float32,
                                                    shape=(len(observations), *x.shape[1:]))
                          for f, x in zip(files, (condition, mask))]
            arrays[0][start:start + len(condition)] = condition.cpu().numpy()
            arrays[1][start:start + len(condition)] = mask.cpu().numpy()
            if start // batch % 50 == 0:
                print(f"condition cache: {start + len(condition)} of {len(observations)} "
                      f"({time.monotonic() - started:.0f} s)", flush=True)
    for array, f in zip(arrays, files):
        array.flush()
        os.replace(f.with_suffix(".tmp.npy"), f)
    described.write_text(json.dumps(key))
    return [np.load(f, mmap_mode="r") for f in files]


class WeightAverage:
    """An exponential moving average of the modules' weights (config
    `"ema": decay`), updated after every optimiser step:
    shadow <- decay * shadow + (1 - decay) * weights. At a constant learning
    rate neighbouring steps of one run differ a lot (the YCB-V run: 39.4 and
    46.3 % per sample 150 steps apart), and the average of the last ~1 /
    (1 - decay) steps is steadier; validation scores it, and the portable
    weights (hence exports) hold it. Non-float entries are copied."""

    def __init__(self, modules, decay, saved=None):
        if not 0.0 < decay < 1.0:
            raise SystemExit(f"config: ema {decay!r}: expected a decay between 0 and 1 (say 0.999)")
        self.decay = decay
        self.shadow = {name: {k: v.detach().clone() for k, v in module.state_dict().items()}
                       for name, module in modules.items()}
        if saved is not None:
            for name, weights in self.shadow.items():
                for k, v in weights.items():
                    v.copy_(saved[name][k])

    @torch.no_grad()
    def update(self, modules):
        for name, module in modules.items():
            for k, v in module.state_dict().items():
                shadow = self.shadow[name][k]
                if v.is_floating_point():
                    shadow.lerp_(v, 1.0 - self.decay)
                else:
                    shadow.copy_(v)

    @contextlib.contextmanager
    def applied(self, modules):
        """The modules hold the average inside the block, their own weights
        again after it."""
        own = {name: {k: v.detach().clone() for k, v in module.state_dict().items()} for name, module in modules.items()}
        for name, module in modules.items():
            module.load_state_dict(self.shadow[name])
        try:
            yield
        finally:
            for name, module in modules.items():
                module.load_state_dict(own[name])


def model_weights(saved):
    """{"encoder": ..., "velocity": ...}: the weights a checkpoint's model
    is made of, its average where the run kept one (`WeightAverage`). A
    run's portable weights already are the average."""
    return saved.get("ema", saved)


def save_checkpoint(path, modules, optimiser, state, generator, rng, cfg, average=None):
    """Everything a later run needs to continue, written atomically; and
    beside it `weights.pt`, the portable resume point small enough for git
    (half-precision weights, step, time and random state, no optimiser).
    With a weight average the checkpoint holds it beside the weights, and
    the portable weights are the average (`"averaged": true`): a run resumed
    from them starts from the model it would export."""
    # On the CPU whatever the device trained on: one format, resumable anywhere.
    saved = {name: moved(module.state_dict(), "cpu") for name, module in modules.items()}
    saved.update({"optimiser": moved(optimiser.state_dict(), "cpu"), "state": state, "generator": generator.get_state(),
                  "rng": rng.bit_generator.state, "model_config": cfg.to_dict()})
    if average is not None:
        saved["ema"] = moved(average.shadow, "cpu")
    tmp = path.with_suffix(".tmp")
    torch.save(saved, tmp)
    os.replace(tmp, path)
    weights = model_weights(saved)
    portable = {name: {k: v.half() if v.is_floating_point() else v for k, v in weights[name].items()}
                for name in modules}
    portable.update({k: saved[k] for k in ("state", "generator", "rng", "model_config")})
    if average is not None:
        portable["averaged"] = True
    tmp = path.with_name("weights.tmp")
    torch.save(portable, tmp)
    os.replace(tmp, path.with_name(PORTABLE))


# A run's portable resume point beside its checkpoint (`save_checkpoint`).
PORTABLE = "weights.pt"


def resume_point(checkpoint):
    """`checkpoint`, or where it is missing (another machine) the portable
    weights beside it when they exist: what a run resumes from."""
    portable = checkpoint.with_name(PORTABLE)
    return portable if not checkpoint.exists() and portable.exists() else checkpoint


def step(config, state, optimiser, params, loss):
    """One optimiser step at the scheduled learning rate."""
    for group in optimiser.param_groups:
        group["lr"] = learning_rate(config, state)
    optimiser.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, config.get("clip", 1.0))
    optimiser.step()
    state["step"] += 1


def finish_step(config, state, started, log, loss, parts, encoder, velocity, val, cfg, steps,
                checkpoint, modules, optimiser, generator, rng, marks, average=None):
    """Counts the step's time; updates the weight average; logs (the loss
    and its `parts`, name -> tensor), validates (the average, when kept) and
    checkpoints when due (`marks` holds the training time of the last
    validation and checkpoint). `log` is None on replicas other than rank
    0, which only count time."""
    state["train_s"] += time.monotonic() - started
    if log is None:
        return
    if average is not None:
        average.update(modules)
    if state["step"] % config.get("log_every", 20) == 0:
        entry = {"step": state["step"], "train_s": round(state["train_s"], 1), "lr": learning_rate(config, state), "loss": loss.item(),
                 **{name: value.item() for name, value in parts.items()}}
        log.write(json.dumps(entry) + "\n")
        log.flush()
        print(entry, flush=True)
    if state["train_s"] - marks["validation"] >= config.get("validate_s", 900):
        marks["validation"] = state["train_s"]
        count = config.get("val_observations", 64)
        entry = {"step": state["step"], "train_s": round(state["train_s"], 1)}
        with average.applied(modules) if average is not None else contextlib.nullcontext():
            entry["validation"] = validate(encoder, velocity, val["val"], cfg, count, 50, steps, seed=1)
            for name, observations in val.items():
                if name != "val":
                    entry[f"validation_{name}"] = validate(encoder, velocity, observations, cfg, count, 50, steps, seed=1)
        log.write(json.dumps(entry) + "\n")
        log.flush()
        print(entry, flush=True)
    if state["train_s"] - marks["checkpoint"] >= config.get("checkpoint_s", 300):
        marks["checkpoint"] = state["train_s"]
        save_checkpoint(checkpoint, modules, optimiser, state, generator, rng, cfg, average)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", required=True)
    parser.add_argument("--max-minutes", type=float, help="stop after this much training time in this run")
    parser.add_argument("--replica-weights", help="(tests) each process writes its final weights to DIR/rank<r>.pt")
    parser.add_argument("--device", help="auto (a GPU when PyTorch sees one, else the CPU), cpu, cuda or cuda:N; "
                                         "overrides the config's \"device\" (default auto)")
    args = parser.parse_args()
    config = load_config(args.config)
    device = training_device(args.device or config.get("device", "auto"))
    replicas = Replicas(device)
    cfg = config["model"]
    out = Path(config["out"])
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(config.get("threads", 2))
    equivalent = config.get("equivalent_targets", False)
    if config.get("hidden_arcs") and not equivalent:
        raise SystemExit("config: hidden_arcs needs equivalent_targets")
    categories = cfg.size_head
    # "shape": targets, loss and validation up to the one-coloured shapes'
    # symmetries, the ambiguity renders without the print really have.
    symmetries = config.get("symmetries", "models-info")
    train = Observations(config["train"], cfg.object_ids, config.get("min_visib_fract", 0.1), config.get("hidden_arcs", False),
                         categories, symmetries)
    # `validate_also` {name: [shards]}: more held-out sets scored at each
    # validation (say, views where the mug's handle is hidden), logged as
    # `validation_<name>`.
    val = {"val": Observations(config["val"], cfg.object_ids, config.get("min_visib_fract", 0.1), categories=categories,
                               symmetries=symmetries)}
    for name, patterns in config.get("validate_also", {}).items():
        val[name] = Observations(shard_paths(patterns, f"validate_also.{name}"), cfg.object_ids,
                                 config.get("min_visib_fract", 0.1), categories=categories, symmetries=symmetries)
    for key in ("image_size", "patch_grid", "point_count"):
        if train.info[key] != getattr(cfg, key):
            raise SystemExit(f"{config['train'][0]}: {key} {train.info[key]}, the model config says {getattr(cfg, key)}")
    # On the device before the optimiser is made and any state is loaded
    # (load_state_dict copies into the parameters where they are).
    encoder, velocity = Encoder(cfg).to(device), VelocityNet(cfg).to(device)
    modules = {"encoder": encoder, "velocity": velocity}
    # A category model's symmetries are its categories' (object index =
    # category), an instance model's its objects'.
    symmetry_source = category_models_info(cfg.object_ids) if categories else train.models_info
    table = moved(symmetry_table(symmetry_source, cfg.object_ids, config.get("loss_continuous_steps", 36)), device)
    # Flow targets drawn from every equivalent pose: continuous symmetries
    # at 1-degree steps.
    target_table = moved(symmetry_table(symmetry_source, cfg.object_ids, 360, counts=True), device) if equivalent else None
    # `frozen_encoder`: the encoder (from `init_from`) is fixed and its
    # conditions are computed once (`condition_cache`), so a step costs the
    # velocity network alone and can afford many more flow samples.
    frozen = config.get("frozen_encoder", False)
    if frozen:
        if not (config.get("init_from") and config.get("condition_cache")):
            raise SystemExit("config: frozen_encoder needs init_from (the encoder) and condition_cache (a path)")
        encoder.requires_grad_(False)
    if config.get("rollout_energy"):
        if not frozen:
            raise SystemExit("config: rollout_energy needs frozen_encoder (it rolls the sampler out on cached conditions)")
        settings = config["rollout_energy"]
        if not (isinstance(settings.get("samples", 32), int) and settings.get("samples", 32) >= 2
                and isinstance(settings.get("observations", 16), int) and settings.get("observations", 16) >= 1):
            raise SystemExit(f"config: rollout_energy {settings!r}: expected \"samples\" >= 2 (the score compares "
                             "samples with each other) and \"observations\" >= 1")
    # A frozen DINOv2 image encoder has no trainable parameters.
    params = [p for m in modules.values() for p in m.parameters() if p.requires_grad]
    optimiser = torch.optim.AdamW(params, lr=config.get("lr", 3e-4), weight_decay=config.get("weight_decay", 1e-4))
    state = {"step": 0, "train_s": 0.0}
    checkpoint = out / "checkpoint.pt"
    generator = torch.Generator().manual_seed(config.get("seed", 0) + 7919 * replicas.rank)
    rng = np.random.default_rng(replicas.seed(config.get("seed", 0)))
    resume_from = resume_point(checkpoint)
    resumed = resume_from.exists()
    saved_average = None
    if resumed:
        # The full checkpoint, or on another machine the portable weights
        # committed with the run (a fresh optimiser, which AdamW rebuilds
        # within a few hundred steps).
        saved = torch.load(resume_from, weights_only=False, map_location="cpu")
        for name, module in modules.items():
            module.load_state_dict({k: v.to(module.state_dict()[k].dtype) for k, v in saved[name].items()})
        saved_average = saved.get("ema")
        if "optimiser" in saved:
            optimiser.load_state_dict(saved["optimiser"])
        else:
            print(f"{resume_from}: half-precision weights, a fresh optimiser", flush=True)
        state = saved["state"]
        if replicas.main:
            generator.set_state(saved["generator"])
            rng.bit_generator.state = saved["rng"]
        else:
            # The checkpoint holds rank 0's streams; the others start anew
            # from where the run stands.
            generator.manual_seed(config.get("seed", 0) + 7919 * replicas.rank + state["step"])
            rng = np.random.default_rng([config.get("seed", 0), replicas.rank, state["step"]])
        print(f"resumed at step {state['step']} after {state['train_s'] / 60:.1f} min of training", flush=True)
    elif config.get("init_from"):
        # A new run continuing an earlier one with a grown model: its weights
        # (modules it lacks start fresh), step and training time (so the
        # learning curve stays cumulative); a fresh optimiser.
        saved = torch.load(config["init_from"], weights_only=False, map_location="cpu")
        for name, module in modules.items():
            # A tensor whose shape changed (the object tokens of another
            # object set) starts fresh like a missing one.
            own = module.state_dict()
            source_weights = model_weights(saved)[name]
            reshaped = [k for k, v in source_weights.items() if k in own and own[k].shape != v.shape]
            weights = {k: v for k, v in source_weights.items() if k not in reshaped}
            if reshaped:
                print(f"init_from: {name}: {', '.join(reshaped)} changed shape and start fresh", flush=True)
            missing, unexpected = module.load_state_dict(weights, strict=False)
            if unexpected:
                raise SystemExit(f"config: init_from {config['init_from']}: {name} has no {unexpected[0]!r}")
            missing = [k for k in missing if k not in reshaped]
            if missing:
                print(f"init_from: {name}: {len(missing)} new tensors ({missing[0]}, ...) start fresh", flush=True)
        state = dict(saved["state"], initialised_at_s=saved["state"]["train_s"])
        if config.get("reset_heads"):
            # The heads' outputs mean something else in the new model (e.g.
            # `relative_pose`): start from the coarse pose again.
            for head in (velocity.rotation_head, velocity.translation_head):
                torch.nn.init.zeros_(head.weight)
                torch.nn.init.zeros_(head.bias)
        print(f"initialised from {config['init_from']} (step {state['step']}, {state['train_s'] / 60:.1f} min)", flush=True)
    if config.get("encoder_from") and not resumed:
        # The frozen encoder of another checkpoint (the one a condition
        # cache was built with), over whatever init_from held; a resumed run
        # has it in its own checkpoint, so encoder_from may be gone.
        encoder.load_state_dict(torch.load(config["encoder_from"], weights_only=False, map_location="cpu")["encoder"])
    source = config.get("encoder_from") or config.get("init_from")
    cache = None
    if frozen:
        # Rank 0 writes the cache; the others read it once it is there.
        if replicas.main:
            cache = condition_cache(encoder, train, config["condition_cache"], source, device)
        replicas.barrier()
        if not replicas.main:
            cache = condition_cache(encoder, train, config["condition_cache"], source, device)
    replicas.wrap(modules)
    log = open(out / "log.jsonl", "a") if replicas.main else None
    # Rank 0 alone keeps the average: it alone validates and checkpoints. A
    # run without one (or resumed from portable weights, which are the
    # average) starts it at the current weights.
    average = WeightAverage(modules, config["ema"], saved_average) if config.get("ema") and replicas.main else None
    batch_size, samples, steps = config.get("batch", 16), config.get("samples_per_observation", 16), config.get("steps", 5)
    lam = config.get("lambda_pos", 10.0)
    run_started = time.monotonic()
    marks = {"checkpoint": state["train_s"], "validation": state["train_s"]}
    weights = draw_weights(train.obj_ids(), config.get("oversample", {}))
    print(f"{len(train)} training and {len(val['val'])} validation observations, training on {device}", flush=True)
    # SIGTERM / SIGINT end the run after the current step, with a checkpoint.
    stop = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda number, frame: stop.append(number))
    while state["step"] < config.get("max_steps", 10**9):
        time_up = args.max_minutes is not None and time.monotonic() - run_started > 60 * args.max_minutes
        if replicas.any(bool(stop) or time_up):
            break
        started = time.monotonic()
        if cache is not None:
            indices = np.sort(draw(rng, len(train), batch_size, weights))
            batch = moved(train.poses(indices), device)
            condition, mask = (torch.from_numpy(np.asarray(c[indices])).to(device) for c in cache)
            targets = targets_of(train, indices, batch, samples, target_table, generator)
            flow = flow_batch(batch, cfg, samples, steps, generator, read_hint(condition, cfg), config.get("hint_paths", 0.0),
                              targets)

            def cached_loss():
                loss_rot, loss_pos = flow_losses(config, cfg, velocity, condition, mask, flow)
                loss = lam * loss_pos + loss_rot
                parts = {"loss_rot": loss_rot, "loss_pos": loss_pos}
                if config.get("rollout_energy"):
                    parts["loss_energy"] = rollout_energy(config, cfg, velocity, train, cache, weights, target_table, rng,
                                                          generator, steps)
                    loss = loss + config["rollout_energy"].get("weight", 1.0) * parts["loss_energy"]
                return loss, parts

            loss, parts = replicas.loss(cached_loss)
            step(config, state, optimiser, params, loss)
            finish_step(config, state, started, log, loss, parts, encoder, velocity, val, cfg, steps,
                        checkpoint, modules, optimiser, generator, rng, marks, average)
            continue
        indices = draw(rng, len(train), batch_size, weights)
        batch = moved(train.batch(indices), device)
        # Warm-ups: the correspondence network (and refiner) alone, many
        # times faster per observation than the whole model: for the first
        # `correspondence_warmup_s` of training, and for the first
        # `refine_warmup_s` after `init_from` (a refiner added to a trained
        # model gives the velocity network a useful coarse pose only once
        # it has learnt something).
        refine_warmup_end = state.get("initialised_at_s", 0.0) + config.get("refine_warmup_s", 0)
        warming_up = state["train_s"] < max(config.get("correspondence_warmup_s", 0), refine_warmup_end)

        def whole_loss():
            if warming_up:
                more = moved(train.batch(draw(rng, len(train), batch_size + config.get("correspondence_extra_batch", 0),
                                                    weights)), device)
                loss_corr = correspondence_losses(encoder, more, table, cfg, config, generator)
                loss_rot = loss_pos = torch.zeros((), device=device)
            else:
                condition, mask, coordinates = encoder.encode(batch["image"], batch["token_mask"], batch["points"],
                                                              batch["object_index"])
                targets = targets_of(train, indices, batch, samples, target_table, generator)
                flow = flow_batch(batch, cfg, samples, steps, generator, read_hint(condition, cfg),
                                  config.get("hint_paths", 0.0), targets)
                loss_rot, loss_pos = flow_losses(config, cfg, velocity, condition, mask, flow)
                loss_corr = sum(correspondence_loss(c, batch, table, cfg) for c in coordinates) / len(coordinates)
            extra = config.get("correspondence_extra_batch", 0)
            if extra and not warming_up:
                # The correspondences are the slow part to learn and cheap to
                # train alone: each step also trains them on more observations.
                more = moved(train.batch(draw(rng, len(train), extra, weights)), device)
                loss_more = correspondence_losses(encoder, more, table, cfg, config, generator)
                loss_corr = (batch_size * loss_corr + extra * loss_more) / (batch_size + extra)
            loss = lam * loss_pos + loss_rot + config.get("correspondence", 1.0) * loss_corr
            return loss, {"loss_rot": loss_rot, "loss_pos": loss_pos, "loss_corr": loss_corr}

        loss, parts = replicas.loss(whole_loss)
        step(config, state, optimiser, params, loss)
        finish_step(config, state, started, log, loss, parts, encoder, velocity, val, cfg, steps, checkpoint, modules,
                    optimiser, generator, rng, marks, average)
    if replicas.main:
        save_checkpoint(checkpoint, modules, optimiser, state, generator, rng, cfg, average)
    if args.replica_weights:
        Path(args.replica_weights).mkdir(parents=True, exist_ok=True)
        torch.save({name: moved(module.state_dict(), "cpu") for name, module in modules.items()},
                   Path(args.replica_weights) / f"rank{replicas.rank}.pt")
    replicas.close()
    print(f"stopped at step {state['step']} after {state['train_s'] / 60:.1f} min of training", flush=True)


if __name__ == "__main__":
    main()
