"""Exports a trained checkpoint to the ONNX contract the Rust inference
stage serves (services/inference), with parity vectors.

    python -m poseflow_train.export --checkpoint runs/lmo/checkpoint.pt --out ../models/lmo

writes `encoder.onnx`, `velocity.onnx` and `parity.bin` + `parity.json`
(fixed inputs and the PyTorch outputs, checked against ONNX Runtime here and
from Rust in CI).

Contract poseflow-onnx/2 (B observations, G samples each, M = B*G):

encoder.onnx:  image [B,3,S,S] f32 (normalised), token_mask [B,P*P] f32,
               points [B,N,3] f32 (centred, metres), object_index [B] i64
               -> condition [B,T,D] f32, condition_mask [B,T] f32,
                  cross_kv [B,L,T,2D] f32 (keys then values of each of the
                  L DiT blocks' cross-attention over the condition tokens)
velocity.onnx: condition [B,T,D], condition_mask [B,T], cross_kv [B,L,T,2D],
               rotation [M,3,3], translation [M,3] (metres, relative to the
               points' mean), t [M]; samples b*G .. (b+1)*G - 1 belong to
               observation b -> v_rot [M,3] (body frame), v_pos [M,3]
               (m per unit t)

poseflow-onnx/1 differed in two ways: the encoder had no cross_kv (the
velocity network computed the keys and values at every Euler step), and
the velocity network took one observation ([1,T,D]).
"""

import argparse
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import torch

from . import se3
from .data import CATEGORY_IDS
from .model import SIZE_VALUES, Encoder, ModelConfig, VelocityNet, cube_turns
from .objects import write_objects
from .surfaces import SURFACE_POINTS, farthest_point_order, surface_points, twin_turns
from .train import model_weights

CONTRACT = "poseflow-onnx/2"


class ExportedEncoder(torch.nn.Module):
    """encoder.onnx: the encoder, plus the keys and values of the velocity
    network's cross-attention over its condition, which depend on the
    observation only (computed once per observation, not per Euler step)."""

    def __init__(self, encoder, velocity):
        super().__init__()
        self.encoder, self.velocity = encoder, velocity

    def forward(self, image, token_mask, points, object_index):
        condition, mask = self.encoder(image, token_mask, points, object_index)
        return condition, mask, self.velocity.cross_kv(condition)


class ExportedVelocity(torch.nn.Module):
    """velocity.onnx: the velocity network on cached keys and values."""

    def __init__(self, velocity):
        super().__init__()
        self.velocity = velocity

    def forward(self, condition, condition_mask, cross_kv, rotation, translation, t):
        return self.velocity(condition, condition_mask, rotation, translation, t, cross_kv)


def surface_views(surfaces, count, generator):
    """[B, count, 3]: each object's surface points [B, s, 3] turned by a
    random rotation with 1 mm of noise (repeated where there are fewer than
    `count`), `count` of them in farthest-point order, centred, as the ingest stage hands
    points on. The parity inputs of an encoder that checks its coarse pose:
    on a random cloud every turn fits about as badly, so which one wins is
    a near tie that INT8 rounding may break, while on an object's surface
    one turn fits clearly best."""
    views = []
    for surface in surfaces:
        rotation = se3.uniform_rotation((1,), generator=generator)[0]
        total = max(count, len(surface))
        chosen = surface[torch.arange(total) % len(surface)] @ rotation.T
        chosen = chosen + torch.randn(total, 3, generator=generator) * 0.001
        chosen = chosen[torch.from_numpy(farthest_point_order(chosen.numpy(), count))]
        views.append(chosen - chosen.mean(0))
    return torch.stack(views)


def metadata(cfg, extra):
    values = {
        "contract": CONTRACT,
        "image_size": cfg.image_size,
        "patch_grid": cfg.patch_grid,
        "point_count": cfg.point_count,
        "width": cfg.width,
        "normalisation_mean": [0.485, 0.456, 0.406],
        "normalisation_std": [0.229, 0.224, 0.225],
        "translation_scale": cfg.translation_scale,
        "translation_noise_std": cfg.translation_noise_std,
        "object_ids": cfg.object_ids,
        "image_encoder": cfg.image_encoder,
        **extra,
    }
    if cfg.size_head:
        # A category-level model: its object ids are category codes, and its
        # size (extents / translation_scale) lies in the last condition token.
        names = {code: name for name, code in CATEGORY_IDS.items()}
        values["categories"] = {str(code): names[code] for code in cfg.object_ids}
        values["size_values"] = [SIZE_VALUES.start, SIZE_VALUES.stop]
    return {k: v if isinstance(v, str) else json.dumps(v) for k, v in values.items()}


def export(module, args, names, outputs, dynamic, path, meta):
    torch.onnx.export(
        module, args, str(path), input_names=names, output_names=outputs, dynamic_axes=dynamic,
        opset_version=17, dynamo=False,
    )
    model = onnx.load(str(path))
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(model, str(path))


def write_parity(out, tensors):
    """`parity.bin` (the tensors, little-endian, one after another) and
    `parity.json` (name -> shape, dtype, byte offset): what the Rust parity
    tests read."""
    index, blob, offset = {}, bytearray(), 0
    for name, value in tensors.items():
        array = value.numpy()
        kind = "i64" if array.dtype == np.int64 else "f32"
        data = array.astype("<i8" if kind == "i64" else "<f4").tobytes()
        index[name] = {"shape": list(array.shape), "dtype": kind, "offset": offset}
        blob += data
        offset += len(data)
    (out / "parity.bin").write_bytes(bytes(blob))
    (out / "parity.json").write_text(json.dumps(index, indent=1) + "\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--training-data", default="", help="a line for the metadata: what the model was trained on")
    parser.add_argument("--models-info", nargs="*", default=[],
                        help="the training data's models_info.json files: objects.json records each object's diameter")
    parser.add_argument("--verify-coarse", metavar="MODELS_DIR",
                        help="a BOP models directory (millimetres) with the model's objects: the encoder then checks "
                             "its coarse pose against the 24 turns of it and keeps the one whose refinement fits the "
                             "object's surface best (Encoder.verify_coarse); turns that are symmetries of the shape "
                             "(the directory's models_info_shape.json, if any) stay the network's call")
    args = parser.parse_args()
    saved = torch.load(args.checkpoint, weights_only=False)
    cfg = ModelConfig(**saved["model_config"])
    encoder, velocity = Encoder(cfg).eval(), VelocityNet(cfg).eval()
    # The run's weight average where it kept one (`train.WeightAverage`).
    weights = model_weights(saved)
    encoder.load_state_dict(weights["encoder"])
    velocity.load_state_dict(weights["velocity"])
    extra = {"training_data": args.training_data, "training_steps": saved["state"]["step"],
             "training_minutes": round(saved["state"]["train_s"] / 60, 1)}
    if args.verify_coarse:
        encoder.set_surfaces(surface_points(args.verify_coarse, cfg.object_ids),
                             twin_turns(args.verify_coarse, cfg.object_ids, cube_turns()))
        extra["coarse_verification"] = {"turns": 24, "surface_points": SURFACE_POINTS,
                                        "twins": int(encoder.twins.sum())}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = metadata(cfg, extra)

    g = torch.Generator().manual_seed(0)
    s, p, n = cfg.image_size, cfg.patch_grid, cfg.point_count
    image = torch.randn(2, 3, s, s, generator=g)
    token_mask = (torch.rand(2, p * p, generator=g) < 0.5).float()
    points = torch.randn(2, n, 3, generator=g) * 0.03
    object_index = torch.tensor([0, len(cfg.object_ids) - 1])
    if encoder.surfaces is not None:
        # Objects without shape symmetries where there are such: a twin turn
        # would leave even the coarse pose to a near tie.
        plain = (encoder.twins.sum(1) == 0).nonzero()[:, 0]
        if len(plain) > 0:
            object_index = plain[[0, -1]]
        points = surface_views(encoder.surfaces[object_index], n, g)
    encoder_inputs = ["image", "token_mask", "points", "object_index"]
    export(ExportedEncoder(encoder, velocity), (image, token_mask, points, object_index), encoder_inputs,
           ["condition", "condition_mask", "cross_kv"],
           {k: {0: "batch"} for k in encoder_inputs + ["condition", "condition_mask", "cross_kv"]},
           out / "encoder.onnx", meta)
    with torch.no_grad():
        condition, mask = encoder(image, token_mask, points, object_index)
        cross_kv = velocity.cross_kv(condition)
    # Two observations with 5 samples each, so the export traces the grouping.
    m = 5
    rotation = se3.uniform_rotation((2 * m,), generator=g)
    translation = torch.randn(2 * m, 3, generator=g) * cfg.translation_noise_std
    t = torch.tensor([0.0, 0.2, 0.4, 0.6, 0.8] * 2)
    velocity_inputs = ["condition", "condition_mask", "cross_kv", "rotation", "translation", "t"]
    vel_inputs = (condition, mask, cross_kv, rotation, translation, t)
    export(ExportedVelocity(velocity), vel_inputs, velocity_inputs, ["v_rot", "v_pos"],
           {"condition": {0: "observations"}, "condition_mask": {0: "observations"}, "cross_kv": {0: "observations"},
            "rotation": {0: "samples"}, "translation": {0: "samples"}, "t": {0: "samples"}, "v_rot": {0: "samples"},
            "v_pos": {0: "samples"}},
           out / "velocity.onnx", meta)
    with torch.no_grad():
        v_rot, v_pos = velocity(condition, mask, rotation, translation, t)

    # Parity: ONNX Runtime against PyTorch (which computes the keys and values
    # inside the velocity network, as in training), and the vectors for the
    # Rust tests: two observations, encoded and sampled together. The keys and
    # values (0.8 MB) are not stored: the Rust tests take the encoder's.
    tensors = {
        "image": image, "token_mask": token_mask, "points": points, "object_index": object_index,
        "condition": condition, "condition_mask": mask, "rotation": rotation,
        "translation": translation, "t": t, "v_rot": v_rot, "v_pos": v_pos,
    }
    enc_session = onnxruntime.InferenceSession(str(out / "encoder.onnx"))
    got = enc_session.run(None, {k: tensors[k].numpy() for k in encoder_inputs})
    assert np.abs(got[0] - tensors["condition"].numpy()).max() < 1e-4, "encoder parity"
    assert np.abs(got[2] - cross_kv.numpy()).max() < 1e-4, "encoder parity (cross_kv)"
    vel_session = onnxruntime.InferenceSession(str(out / "velocity.onnx"))
    got = vel_session.run(None, {**{k: tensors[k].numpy() for k in velocity_inputs if k != "cross_kv"},
                                 "cross_kv": cross_kv.numpy()})
    assert np.abs(got[0] - v_rot.numpy()).max() < 1e-4 and np.abs(got[1] - v_pos.numpy()).max() < 1e-4, "velocity parity"
    # One observation at a time, with another sample count: what the batch gave.
    alone = vel_session.run(None, {"condition": condition[1:].numpy(), "condition_mask": mask[1:].numpy(),
                                   "cross_kv": cross_kv[1:].numpy(), "rotation": rotation[m + 2:].numpy(),
                                   "translation": translation[m + 2:].numpy(), "t": t[m + 2:].numpy()})
    assert np.abs(alone[0] - v_rot[m + 2:].numpy()).max() < 1e-4, "velocity parity (one observation)"
    write_parity(out, tensors)
    if args.models_info:
        write_objects(out, cfg.object_ids, args.models_info)
    sizes = {f.name: f.stat().st_size for f in out.glob("*.onnx")}
    print(json.dumps({"out": str(out), "sizes": sizes, "parity": "ok"}))


if __name__ == "__main__":
    main()
