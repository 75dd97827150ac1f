"""The grasp flow (paper, "Robotic Grasping"; EquiGraspFlow's role): flow
matching on SE(3) grasp poses conditioned on an object's zero-mean point
cloud, with the pose flow's path, velocities and Euler sampler (`se3`).

The grasp stage (services/grasp) evaluates it once per pose hypothesis on
that hypothesis' model cloud and averages the velocities (the paper's mean
field): grasps valid under every plausible pose win.

Data: `poseflow grasp-data` (antipodal, collision-checked grasps per object
and the object's surface cloud, object frame). Each training example turns
one object by a uniform random rotation (the hypothesis' orientation in the
camera frame) and centres its cloud; the grasps turn and shift with it. No
network here is equivariant: the rotations are learnt from this
augmentation.

Grasp frame: origin midway between the fingertips, z the approach, x the
closing direction (services/grasp/src/gripper.rs). A parallel-jaw grasp
turned half a turn about its approach axis is the same grasp: the accuracy
measure below counts both.

    python -m poseflow_train.grasp train --config configs/grasp.json [--max-minutes M]
    python -m poseflow_train.grasp export --checkpoint checkpoints/grasp/checkpoint.pt --out ../models/grasp-flow
    python -m poseflow_train.grasp card --config configs/grasp.json --checkpoint checkpoints/grasp/checkpoint.pt --model ../models/grasp-flow
"""

import argparse
import glob
import json
import math
import os
import signal
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from . import se3
from .model import DiTBlock, PointEncoder, fourier
from .surfaces import farthest_point_order

CONTRACT = "poseflow-grasp-onnx/1"
HALF_TURN_Z = torch.diag(torch.tensor([-1.0, -1.0, 1.0]))


@dataclass
class GraspConfig:
    point_count: int = 512
    group_points: int = 512
    sa1_centres: int = 64
    sa2_centres: int = 16
    neighbours: int = 16
    width: int = 96
    heads: int = 4
    dit_depth: int = 3
    fourier_features: int = 16
    # Metres per internal translation unit.
    translation_scale: float = 0.05
    # Initial grasp positions: N(0, std^2) per axis about the cloud's mean, metres.
    translation_noise_std: float = 0.08
    min_remaining: float = 0.05

    def to_dict(self):
        return asdict(self)


def part_weights(rotation, translation, contact_depth, part):
    """Draw weights of an object's grasps (R [G,3,3], t [G,3], object
    frame): `part` {"axis": [x, y, z], "beyond": metres, "factor": f}
    weighs the grasps whose contact point (the middle of the finger pads,
    `contact_depth` behind the fingertips) lies beyond the plane
    axis · x = beyond by f, the others by 1; no part, all 1. Antipodal
    proposals land on a part in proportion to its surface, so a mug's
    handle holds 3 % of its grasps and a flow trained on them barely
    proposes one; a task that wants the handle needs them proposed."""
    weights = torch.ones(rotation.shape[0])
    if part is None:
        return weights
    try:
        axis, beyond, factor = torch.tensor(part["axis"], dtype=torch.float32), float(part["beyond"]), float(part["factor"])
    except (KeyError, TypeError, ValueError) as error:
        raise SystemExit(f"config: oversample_parts entry {part!r}: expected {{\"axis\": [x, y, z], \"beyond\": m, "
                         f"\"factor\": f}} ({error})") from error
    if axis.shape != (3,) or not axis.norm() > 0 or not factor > 0:
        raise SystemExit(f"config: oversample_parts entry {part!r}: expected a non-zero 3-vector axis and a positive factor")
    contact = rotation[:, :, 2] * -contact_depth + translation
    on_part = contact @ (axis / axis.norm()) > beyond
    return torch.where(on_part, torch.tensor(factor), weights)


class GraspData:
    """Every grasps_*.json of a directory: per object its grasps (object
    frame, R [G,3,3], t [G,3]) and a few farthest-point ordered clouds
    (rotation does not change that order, so they are made once)."""

    def __init__(self, directory, point_count, orders=8, seed=0, oversample_parts=None):
        paths = sorted(glob.glob(str(Path(directory) / "grasps_*.json")))
        if not paths:
            raise SystemExit(f"{directory}: no grasps_NNNNNN.json (make them with `poseflow grasp-data`)")
        rng = np.random.default_rng(seed)
        self.objects = []
        for path in paths:
            data = json.loads(Path(path).read_text())
            grasps = torch.tensor(data["grasps"], dtype=torch.float32)
            cloud = np.asarray(data["cloud"], dtype=np.float32)
            if len(grasps) == 0:
                continue
            if cloud.shape[0] < point_count:
                raise SystemExit(f"{path}: {cloud.shape[0]} cloud points, the model takes {point_count}")
            clouds = []
            for _ in range(orders):
                subset = cloud[rng.choice(cloud.shape[0], min(cloud.shape[0], 2 * point_count), replace=False)]
                clouds.append(subset[farthest_point_order(subset, point_count, int(rng.integers(subset.shape[0])))])
            rotation, translation = grasps[:, :9].reshape(-1, 3, 3), grasps[:, 9:]
            self.objects.append({
                "obj_id": data["obj_id"], "rotation": rotation, "translation": translation,
                "clouds": torch.tensor(np.stack(clouds)), "gripper": data["gripper"],
                "weights": part_weights(rotation, translation, data["gripper"]["contact_depth"],
                                        (oversample_parts or {}).get(str(data["obj_id"]))),
            })

        unknown = set(oversample_parts or {}) - {str(o["obj_id"]) for o in self.objects}
        if unknown:
            raise SystemExit(f"config: oversample_parts names objects {sorted(unknown)}, which {directory} has no grasps of")

    def draw(self, count, generator):
        """`count` examples: object index [B], turn [B,3,3], the turned and
        centred clouds [B,P,3] and the means subtracted [B,3]."""
        index = torch.randint(0, len(self.objects), (count,), generator=generator)
        turn = se3.uniform_rotation((count,), generator=generator)
        clouds = []
        for b, i in enumerate(index.tolist()):
            orders = self.objects[i]["clouds"]
            clouds.append(orders[torch.randint(0, len(orders), (1,), generator=generator).item()] @ turn[b].T)
        clouds = torch.stack(clouds)
        mean = clouds.mean(1)
        return index, turn, clouds - mean[:, None, :], mean

    def grasps(self, i, turn, mean, pick=None):
        """Object i's grasps (all, or those at `pick`) in an example's frame."""
        obj = self.objects[i]
        r, t = obj["rotation"], obj["translation"]
        if pick is not None:
            r, t = r[pick], t[pick]
        return turn @ r, t @ turn.T - mean

    def batch(self, count, grasps_per_object, generator):
        """Clouds [B,P,3] and G of each object's grasps in the same frame:
        R [B,G,3,3], p [B,G,3]."""
        index, turn, clouds, mean = self.draw(count, generator)
        rotations, translations = [], []
        for b, i in enumerate(index.tolist()):
            pick = torch.multinomial(self.objects[i]["weights"], grasps_per_object, replacement=True, generator=generator)
            r, p = self.grasps(i, turn[b], mean[b], pick)
            rotations.append(r)
            translations.append(p)
        return clouds, torch.stack(rotations), torch.stack(translations)


class GraspEncoder(nn.Module):
    """Zero-mean cloud [B,P,3] (metres) -> condition tokens [B,T,D]."""

    def __init__(self, cfg):
        super().__init__()
        self.points = PointEncoder(cfg)
        self.norm = nn.LayerNorm(cfg.width)

    def forward(self, points):
        return self.norm(self.points(points))


class GraspVelocity(nn.Module):
    """(condition [B,T,D], grasps at time t: R [B*G,3,3], p [B*G,3],
    t [B*G]) -> (v_rot body frame, v_pos m per unit t). The G grasps of one
    cloud follow each other. The heads predict the clean grasp (6D
    rotation, position); the velocities are derived on the paper's path,
    as in the pose flow."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.rotation_in, self.translation_in = nn.Linear(9, w), nn.Linear(3, w)
        self.kind = nn.Parameter(torch.randn(2, w) * 0.02)
        self.time = nn.Sequential(nn.Linear(2 * cfg.fourier_features, w), nn.SiLU(), nn.Linear(w, w))
        self.summary = nn.Sequential(nn.Linear(w, w), nn.SiLU(), nn.Linear(w, w))
        self.blocks = nn.ModuleList([DiTBlock(w, cfg.heads) for _ in range(cfg.dit_depth)])
        self.final_norm = nn.LayerNorm(w, elementwise_affine=False)
        self.final_modulation = nn.Linear(w, 2 * w)
        self.rotation_head, self.translation_head = nn.Linear(w, 6), nn.Linear(w, 3)

    def clean_grasp(self, condition, rotation, translation, t):
        scale = self.cfg.translation_scale
        x = torch.stack(
            [self.rotation_in(rotation.reshape(-1, 9)) + self.kind[0], self.translation_in(translation / scale) + self.kind[1]],
            1,
        )
        bc = condition.shape[0]
        c = self.time(fourier(t, self.cfg.fourier_features))
        c = (c.reshape(bc, -1, c.shape[-1]) + self.summary(condition.mean(1))[:, None, :]).reshape(-1, c.shape[-1])
        for block in self.blocks:
            x = block(x, c, condition, None)
        shift, scl = self.final_modulation(nn.functional.silu(c))[:, None, :].chunk(2, -1)
        x = self.final_norm(x) * (1 + scl) + shift
        # A correction of the current grasp in its own frame, so a late,
        # nearly clean state needs only a small one.
        r1 = rotation @ se3.rotation_from_6d(torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]) + self.rotation_head(x[:, 0]))
        return r1, translation + self.translation_head(x[:, 1]) * scale

    def forward(self, condition, rotation, translation, t):
        r1, p1 = self.clean_grasp(condition, rotation, translation, t)
        remaining = (1.0 - t).clamp_min(self.cfg.min_remaining)[:, None]
        return se3.so3_log(rotation.transpose(-1, -2) @ r1) / remaining, (p1 - translation) / remaining


def sample(encoder, velocity, clouds, grasps, steps, generator, mean_field=False):
    """G grasps per cloud [B,P,3] after K Euler steps from noise: R [B,G,3,3],
    p [B,G,3]. With `mean_field` the B clouds are hypotheses of one object
    and one set of G grasps follows the mean of their velocities."""
    cfg = velocity.cfg
    b = clouds.shape[0]
    chains = 1 if mean_field else b
    r = se3.uniform_rotation((chains, grasps), generator=generator)
    p = torch.randn(chains, grasps, 3, generator=generator) * cfg.translation_noise_std
    with torch.no_grad():
        condition = encoder(clouds)
        for k in range(steps):
            t = torch.full((b * grasps,), k / steps)
            rr, pp = (r.expand(b, -1, -1, -1), p.expand(b, -1, -1)) if mean_field else (r, p)
            v_rot, v_pos = velocity(condition, rr.reshape(-1, 3, 3), pp.reshape(-1, 3), t)
            v_rot, v_pos = v_rot.reshape(b, grasps, 3), v_pos.reshape(b, grasps, 3)
            if mean_field:
                v_rot, v_pos = v_rot.mean(0, keepdim=True), v_pos.mean(0, keepdim=True)
            r, p = se3.euler_step(r, p, v_rot, v_pos, 1.0 / steps)
    return r, p


def near_a_grasp(r, p, truth_r, truth_p, max_deg=20.0, max_m=0.02):
    """Per sampled grasp [G]: is it within `max_deg` and `max_m` of one of
    the true grasps [T] (or of its half turn about the approach axis)?"""
    close = (p[:, None, :] - truth_p[None, :, :]).norm(dim=-1) <= max_m
    angle = torch.minimum(
        se3.geodesic_angle(r[:, None], truth_r[None]), se3.geodesic_angle(r[:, None], (truth_r @ HALF_TURN_Z)[None])
    )
    return (close & (angle <= math.radians(max_deg))).any(1)


def validate(encoder, velocity, data, count, grasps, steps, seed):
    """Share of sampled grasps near a true grasp, over `count` fixed random
    turns of the objects; a cheap learning-curve figure (the grasp stage's
    check on the mesh is the real test)."""
    generator = torch.Generator().manual_seed(seed)
    index, turn, clouds, mean = data.draw(count, generator)
    encoder.eval(), velocity.eval()
    try:
        r, p = sample(encoder, velocity, clouds, grasps, steps, generator)
    finally:
        encoder.train(), velocity.train()
    per_object = {}
    for b, i in enumerate(index.tolist()):
        hit = near_a_grasp(r[b], p[b], *data.grasps(i, turn[b], mean[b])).float().mean().item()
        per_object.setdefault(data.objects[i]["obj_id"], []).append(hit)
    hits = [h for v in per_object.values() for h in v]
    return {"examples": count, "grasps": grasps, "steps": steps, "near_a_grasp": round(100 * float(np.mean(hits)), 2),
            "per_object": {k: round(100 * float(np.mean(v)), 2) for k, v in sorted(per_object.items())}}


def save_checkpoint(path, encoder, velocity, optimiser, state, generator, cfg, gripper):
    saved = {"encoder": encoder.state_dict(), "velocity": velocity.state_dict(), "optimiser": optimiser.state_dict(),
             "state": state, "generator": generator.get_state(), "model_config": cfg.to_dict(), "gripper": gripper}
    tmp = path.with_suffix(".tmp")
    torch.save(saved, tmp)
    os.replace(tmp, path)


def train(config_path, max_minutes):
    """Trains to `max_steps` or until stopped; checkpoints every
    `checkpoint_s` seconds of training and on SIGTERM / Ctrl-C, and
    continues from `<out>/checkpoint.pt`."""
    config = json.loads(Path(config_path).read_text())
    cfg = GraspConfig(**config.get("model", {}))
    out = Path(config["out"])
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(config.get("threads", 2))
    data = GraspData(config["data"], cfg.point_count, seed=config.get("seed", 0),
                     oversample_parts=config.get("oversample_parts"))
    encoder, velocity = GraspEncoder(cfg), GraspVelocity(cfg)
    params = [*encoder.parameters(), *velocity.parameters()]
    optimiser = torch.optim.AdamW(params, lr=config.get("lr", 3e-4), weight_decay=1e-4)
    generator = torch.Generator().manual_seed(config.get("seed", 0))
    state = {"step": 0, "train_s": 0.0}
    checkpoint = out / "checkpoint.pt"
    if checkpoint.exists():
        saved = torch.load(checkpoint, weights_only=False)
        encoder.load_state_dict(saved["encoder"])
        velocity.load_state_dict(saved["velocity"])
        optimiser.load_state_dict(saved["optimiser"])
        state = saved["state"]
        generator.set_state(saved["generator"])
        print(f"resumed at step {state['step']} after {state['train_s'] / 60:.1f} min", flush=True)
    elif config.get("init_from"):
        # Continuing another run with other data: its weights, step and
        # training time (the curve stays cumulative), a fresh optimiser.
        saved = torch.load(config["init_from"], weights_only=False)
        encoder.load_state_dict(saved["encoder"])
        velocity.load_state_dict(saved["velocity"])
        state = dict(saved["state"])
        print(f"initialised from {config['init_from']} (step {state['step']}, {state['train_s'] / 60:.1f} min)", flush=True)
    print(f"{len(data.objects)} objects, {sum(len(o['rotation']) for o in data.objects)} grasps", flush=True)
    log = open(out / "log.jsonl", "a")
    stop = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda number, frame: stop.append(number))
    started_run = time.monotonic()
    last_checkpoint = last_validation = state["train_s"]
    batch, per_object, lam = config.get("batch", 16), config.get("grasps_per_object", 16), config.get("lambda_pos", 10.0)
    while state["step"] < config.get("max_steps", 10**9) and not stop:
        if max_minutes is not None and time.monotonic() - started_run > 60 * max_minutes:
            break
        started = time.monotonic()
        clouds, r1, p1 = data.batch(batch, per_object, generator)
        r1, p1 = r1.reshape(-1, 3, 3), p1.reshape(-1, 3)
        m = r1.shape[0]
        r0 = se3.uniform_rotation((m,), generator=generator)
        p0 = torch.randn(m, 3, generator=generator) * cfg.translation_noise_std
        t = torch.rand(m, generator=generator) * (1.0 - cfg.min_remaining)
        r_t, p_t = se3.interpolate(r0, p0, r1, p1, t)
        r_hat, p_hat = velocity.clean_grasp(encoder(clouds), r_t, p_t, t)
        # The clean grasp against the nearer of the true grasp and its half
        # turn about the approach axis (the same grasp).
        loss_rot = torch.minimum((r_hat - r1).pow(2).sum((-1, -2)), (r_hat - r1 @ HALF_TURN_Z).pow(2).sum((-1, -2))).mean()
        loss_pos = ((p_hat - p1) / cfg.translation_scale).pow(2).sum(-1).mean()
        loss = loss_rot + lam * loss_pos
        optimiser.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimiser.step()
        state["step"] += 1
        state["train_s"] += time.monotonic() - started
        if state["step"] % config.get("log_every", 50) == 0:
            entry = {"step": state["step"], "train_s": round(state["train_s"], 1), "loss": loss.item(),
                     "loss_rot": loss_rot.item(), "loss_pos": loss_pos.item()}
            log.write(json.dumps(entry) + "\n")
            log.flush()
            print(entry, flush=True)
        if state["train_s"] - last_validation >= config.get("validate_s", 600):
            last_validation = state["train_s"]
            entry = {"step": state["step"], "train_s": round(state["train_s"], 1),
                     "validation": validate(encoder, velocity, data, 32, 32, config.get("steps", 10), seed=1)}
            log.write(json.dumps(entry) + "\n")
            log.flush()
            print(entry, flush=True)
        if state["train_s"] - last_checkpoint >= config.get("checkpoint_s", 300):
            last_checkpoint = state["train_s"]
            save_checkpoint(checkpoint, encoder, velocity, optimiser, state, generator, cfg, data.objects[0]["gripper"])
    save_checkpoint(checkpoint, encoder, velocity, optimiser, state, generator, cfg, data.objects[0]["gripper"])
    print(f"stopped at step {state['step']} after {state['train_s'] / 60:.1f} min", flush=True)


def export_model(checkpoint, out, training_data):
    """grasp_encoder.onnx: points [B,P,3] f32 (zero mean, metres) ->
    condition [B,T,D]; grasp_velocity.onnx: condition [B,T,D], rotation
    [B*G,3,3], translation [B*G,3] (metres, relative to the cloud's mean),
    t [B*G] -> v_rot [B*G,3] (body frame), v_pos [B*G,3]; the G grasps of
    each cloud in a row. Metadata: the contract, sizes, scales, the gripper
    the data was checked with. Parity vectors for the Rust test."""
    import onnxruntime

    from .export import export, write_parity

    saved = torch.load(checkpoint, weights_only=False)
    cfg = GraspConfig(**saved["model_config"])
    encoder, velocity = GraspEncoder(cfg).eval(), GraspVelocity(cfg).eval()
    encoder.load_state_dict(saved["encoder"])
    velocity.load_state_dict(saved["velocity"])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    values = {"contract": CONTRACT, "point_count": cfg.point_count, "width": cfg.width,
              "translation_scale": cfg.translation_scale, "translation_noise_std": cfg.translation_noise_std,
              "gripper": saved.get("gripper", {}), "training_data": training_data,
              "training_steps": saved["state"]["step"], "training_minutes": round(saved["state"]["train_s"] / 60, 1)}
    meta = {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()}
    g = torch.Generator().manual_seed(0)
    points = torch.randn(2, cfg.point_count, 3, generator=g) * 0.03
    points = points - points.mean(1, keepdim=True)
    export(encoder, (points,), ["points"], ["condition"], {"points": {0: "clouds"}, "condition": {0: "clouds"}},
           out / "grasp_encoder.onnx", meta)
    with torch.no_grad():
        condition = encoder(points)
    m = 6
    rotation = se3.uniform_rotation((m,), generator=g)
    translation = torch.randn(m, 3, generator=g) * cfg.translation_noise_std
    t = torch.tensor([0.0, 0.2, 0.4, 0.5, 0.7, 0.9])
    inputs = (condition, rotation, translation, t)
    samples = {0: "grasps"}
    export(velocity, inputs, ["condition", "rotation", "translation", "t"], ["v_rot", "v_pos"],
           {"condition": {0: "clouds"}, "rotation": samples, "translation": samples, "t": samples, "v_rot": samples,
            "v_pos": samples}, out / "grasp_velocity.onnx", meta)
    with torch.no_grad():
        v_rot, v_pos = velocity(*inputs)
    got = onnxruntime.InferenceSession(str(out / "grasp_encoder.onnx")).run(None, {"points": points.numpy()})
    assert np.abs(got[0] - condition.numpy()).max() < 1e-4, "grasp encoder parity"
    names = ["condition", "rotation", "translation", "t"]
    got = onnxruntime.InferenceSession(str(out / "grasp_velocity.onnx")).run(
        None, {k: v.numpy() for k, v in zip(names, inputs)})
    assert np.abs(got[0] - v_rot.numpy()).max() < 1e-4 and np.abs(got[1] - v_pos.numpy()).max() < 1e-4, "grasp velocity parity"
    write_parity(out, {"points": points, "condition": condition, "rotation": rotation, "translation": translation, "t": t,
                       "v_rot": v_rot, "v_pos": v_pos})
    print(json.dumps({"out": str(out), "sizes": {f.name: f.stat().st_size for f in out.glob("*.onnx")}, "parity": "ok"}))


def card(config_path, checkpoint, model_dir, data_dir, note):
    """models/<grasp model>/MODEL_CARD.md from the checkpoint, its log, the
    data and latencies measured here through ONNX Runtime."""
    import onnxruntime

    config = json.loads(Path(config_path).read_text())
    checkpoint, model_dir = Path(checkpoint), Path(model_dir)
    saved = torch.load(checkpoint, weights_only=False)
    cfg = GraspConfig(**saved["model_config"])
    state = saved["state"]
    parameters = sum(v.numel() for key in ("encoder", "velocity") for v in saved[key].values())
    log = [json.loads(line) for line in (checkpoint.parent / "log.jsonl").read_text().splitlines() if line.strip()]
    curve = [(e["step"], e["train_s"] / 60, e["validation"]["near_a_grasp"]) for e in log if "validation" in e]
    sets = [json.loads(Path(p).read_text()) for p in sorted(glob.glob(str(Path(data_dir) / "grasps_*.json")))]
    sizes = {f.name: f.stat().st_size for f in sorted(model_dir.glob("*.onnx"))}
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = 1
    encoder = onnxruntime.InferenceSession(str(model_dir / "grasp_encoder.onnx"), options)
    velocity = onnxruntime.InferenceSession(str(model_dir / "grasp_velocity.onnx"), options)
    clouds, grasps = 8, 32
    points = (np.random.default_rng(0).standard_normal((clouds, cfg.point_count, 3)) * 0.03).astype(np.float32)
    condition = encoder.run(None, {"points": points})[0]
    inputs = {"condition": condition, "rotation": se3.uniform_rotation((clouds * grasps,)).numpy(),
              "translation": np.zeros((clouds * grasps, 3), np.float32), "t": np.full(clouds * grasps, 0.5, np.float32)}

    def median_ms(run, repeats=30):
        times = []
        for _ in range(repeats):
            started = time.perf_counter()
            run()
            times.append(1000 * (time.perf_counter() - started))
        return float(np.median(times))

    encode_ms = median_ms(lambda: encoder.run(None, {"points": points}))
    velocity_ms = median_ms(lambda: velocity.run(None, inputs))
    rows = "\n".join(f"| {step} | {minutes:.1f} | {near} |" for step, minutes, near in curve)
    data_rows = "\n".join(
        f"| {d['obj_id']} | {len(d['grasps']):,} | {d['proposals']:,} | {100 * len(d['grasps']) / max(d['proposals'], 1):.1f} |"
        for d in sets)
    gripper = sets[0]["gripper"] if sets else {}
    text = f"""# Model card: {model_dir.name}

The grasp flow of the grasp stage (`services/grasp`): flow matching on
SE(3) grasp poses conditioned on an object's zero-mean point cloud, the
role EquiGraspFlow plays in the paper (its weights cannot be downloaded
here). The stage evaluates it once per pose hypothesis and averages the
velocities (the paper's mean field). Generated by
`python -m poseflow_train.grasp card`; nothing in it is typed by hand.

## Files

| file | size |
|---|---|
""" + "\n".join(f"| {name} | {size / 1e6:.2f} MB |" for name, size in sizes.items()) + f"""

{parameters:,} parameters. Contract `{CONTRACT}` (`grasp_encoder.onnx`:
points [B,{cfg.point_count},3] → condition [B,T,{cfg.width}]; `grasp_velocity.onnx`: condition,
rotation [B·G,3,3], translation [B·G,3], t [B·G] → v_rot, v_pos).
`parity.bin`/`parity.json`: stored inputs and PyTorch outputs, reproduced
by ONNX Runtime within 1e-4 (at export and by the Rust tests).

## Architecture

- Condition: PointNet++ set abstraction on {cfg.point_count} points of the centred cloud
  ({cfg.sa1_centres} then {cfg.sa2_centres} centres, {cfg.neighbours} neighbours, farthest-point order) and a
  global token, width {cfg.width}.
- Velocity: {cfg.dit_depth} DiT* blocks over a rotation and a position token, adaLN on
  Fourier features of t plus a pooled summary of the condition,
  cross-attention to the condition tokens; heads predict the clean grasp
  as a correction of the current one; velocities on the paper's path,
  ω = log(R_tᵀR̂₁)/(1−t), v = (p̂₁ − p_t)/(1−t).
- Initial grasps: uniform rotations, positions N(0, {cfg.translation_noise_std} m) about the
  cloud's mean; positions scaled by {cfg.translation_scale} m inside the network.
- Not equivariant: rotations are learnt from every example turned by a
  uniform random rotation. A grasp and its half turn about the approach
  axis are the same grasp: the loss takes the nearer of the two.

## Data

`poseflow grasp-data` (run by `training/make-data`): per object,
antipodal proposals (a surface point, a closing direction inside its
friction cone, the point where that ray leaves the object, a random
approach about the closing axis), each kept only when
`check_grasp` (services/grasp) says it holds: the open gripper clear of
the mesh, both contact normals inside the friction cone. Gripper:
`{json.dumps(gripper)}` (metres; Franka-Panda-like).

| object | grasps | proposals | kept % |
|---|---|---|---|
{data_rows}

## Training

{state['step']:,} steps, {state['train_s'] / 60:.1f} min of training on {config.get('threads', 1)} CPU thread(s) of the
2-core VM (how the runs shared it: the note below), batch {config.get('batch', 16)} objects × {config.get('grasps_per_object', 16)} grasps, AdamW lr {config.get('lr', 3e-4)}. Validation (every 10 min): share of
32 grasps sampled with 10 Euler steps for 32 fixed random turns of the
objects that lie within 2 cm and 20° of a data grasp — a cheap
learning-curve figure; the grasp stage's mesh check is the real test
(`poseflow sim grasp`, docs/results.md).

| step | minutes | near a data grasp % |
|---|---|---|
{rows}

{note}

## Latency (2-core VM, ONNX Runtime, 1 intra-op thread)

Median of 30 runs: encoder for {clouds} clouds {encode_ms:.1f} ms; velocity for {clouds} clouds ×
{grasps} grasps {velocity_ms:.1f} ms (one Euler step of the grasp stage's default
mean field: 8 hypotheses × 32 grasps).
"""
    (model_dir / "MODEL_CARD.md").write_text(text)
    print(f"wrote {model_dir / 'MODEL_CARD.md'}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    train_args = commands.add_parser("train")
    train_args.add_argument("--config", required=True)
    train_args.add_argument("--max-minutes", type=float)
    export_args = commands.add_parser("export")
    export_args.add_argument("--checkpoint", required=True)
    export_args.add_argument("--out", required=True)
    export_args.add_argument("--training-data", default="", help="a line for the metadata: what the model was trained on")
    card_args = commands.add_parser("card")
    card_args.add_argument("--config", required=True)
    card_args.add_argument("--checkpoint", required=True)
    card_args.add_argument("--model", required=True, help="the exported model directory")
    card_args.add_argument("--data", default="data/grasps")
    card_args.add_argument("--note", default="", help="Markdown after the learning curve")
    args = parser.parse_args()
    if args.command == "train":
        train(args.config, args.max_minutes)
    elif args.command == "export":
        export_model(args.checkpoint, args.out, args.training_data)
    else:
        card(args.config, args.checkpoint, args.model, args.data, args.note)


if __name__ == "__main__":
    main()
