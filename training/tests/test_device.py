"""Training on a GPU: the device a process picks, and every tensor a step
makes following the model's device. No GPU here, so the step's pieces run
on PyTorch's `meta` device under a mode that fails any operation given
tensors on two devices (CUDA refuses those too; meta alone lets a matrix
product through)."""

import math

import pytest
import torch
from torch.utils._pytree import tree_flatten

from poseflow_train import se3
from poseflow_train.evaluate import on_cpu, rollout
from poseflow_train.model import Encoder, ModelConfig, VelocityNet
from poseflow_train.train import (Replicas, correspondence_losses, equivalent_targets, flow_batch, flow_losses,
                                  moved, training_device)

META = torch.device("meta")


class OneDevice(torch.overrides.TorchFunctionMode):
    """Fails an operation whose tensor arguments (beyond 0-d scalars, which
    CUDA accepts from the CPU) sit on more than one device."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if name in ("to", "copy_") or name.startswith("_"):
            # Moving or copying between devices is what they are for (and
            # the underscored ones are PyTorch's own plumbing of `.to`).
            return func(*args, **kwargs)
        tensors = [x for x in tree_flatten((args, kwargs))[0] if isinstance(x, torch.Tensor) and x.dim() > 0]
        devices = {x.device for x in tensors}
        assert len(devices) <= 1, f"{name or func} on {sorted(map(str, devices))}"
        return func(*args, **kwargs)


def tiny_config():
    return ModelConfig(object_ids=[1, 2], image_size=32, patch_grid=4, point_count=128, width=32, image_depth=1,
                       dit_depth=1, group_points=64, correspondence_points=32, refine_iterations=1,
                       relative_pose=True)


def meta_batch(b=2, n=128):
    g = torch.Generator().manual_seed(0)
    batch = {"rotation": se3.uniform_rotation((b,), generator=g), "translation": torch.randn(b, 3, generator=g) * 0.02,
             "points": torch.randn(b, n, 3, generator=g) * 0.03, "object_index": torch.tensor([0, 1])[:b],
             "image": torch.zeros(b, 3, 32, 32), "token_mask": torch.ones(b, 16)}
    return moved(batch, META)


def test_auto_trains_on_the_cpu_without_a_gpu_and_on_the_local_gpu_with_one(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert training_device("auto") == torch.device("cpu")
    with pytest.raises(SystemExit, match="no GPU"):
        training_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert training_device("auto") == torch.device("cuda", 1)
    assert training_device("cuda:0") == torch.device("cuda", 0)
    assert training_device("cpu") == torch.device("cpu")


def test_replicas_average_over_nccl_between_gpus_and_gloo_between_cpus(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert Replicas(torch.device("cpu")).backend == "gloo"
    assert Replicas(torch.device("cuda", 0)).backend == "nccl"


def test_the_device_check_catches_a_matrix_product_across_devices():
    with OneDevice(), pytest.raises(AssertionError, match="cpu"):
        torch.zeros(3, 3) @ torch.zeros(3, 3, device=META)


def test_a_steps_tensors_follow_the_models_device():
    with OneDevice():
        a_step_on_meta()


def a_step_on_meta():
    cfg = tiny_config()
    encoder, velocity = Encoder(cfg).to(META), VelocityNet(cfg).to(META)
    batch = meta_batch()
    generator = torch.Generator().manual_seed(1)
    condition, mask, coordinates = encoder.encode(batch["image"], batch["token_mask"], batch["points"],
                                                  batch["object_index"])
    # Equivalent targets over a symmetry table and hidden-part turns.
    table = moved((torch.eye(3).expand(2, 2, 3, 3).clone(), torch.zeros(2, 2, 3), torch.tensor([1, 2])), META)
    turns = torch.tensor([[True, False, True, False], [False, False, False, False]])
    targets = equivalent_targets(batch, 4, table, generator, turns)
    assert targets[0].device == META and targets[1].device == META
    # Flow draws, half of them ending at the coarse pose.
    hint = (batch["rotation"], batch["translation"])
    flow = flow_batch(batch, cfg, 4, 5, generator, hint, 0.5, targets)
    assert all(v.device == META for v in flow.values())
    loss_rot, loss_pos = flow_losses({"loss": "clean-pose"}, cfg, velocity, condition.repeat_interleave(4, 0),
                                     mask.repeat_interleave(4, 0), flow)
    loss_rot.backward(retain_graph=True)
    # The correspondence losses with the refiner started from perturbed truths.
    sym = moved((torch.eye(3)[None, None].expand(2, 1, 3, 3), torch.zeros(2, 1, 3)), META)
    loss = correspondence_losses(encoder, batch, sym, cfg, {"refine_perturbation": [40.0, 2.0]}, generator)
    assert loss.device == META
    # The sampler's rollout (the energy score trains through it).
    r, p = rollout(velocity, condition, mask, cfg, 3, 2, generator)
    assert r.shape == (2, 3, 3, 3) and r.device == META and p.device == META
    assert math.isfinite(cfg.translation_scale)


def test_validation_scores_a_model_on_another_device_with_cpu_tensors():
    cfg = tiny_config()
    velocity = VelocityNet(cfg)
    seen = []

    class Elsewhere(torch.nn.Module):
        """A stand-in module whose parameters sit on the meta device."""

        def __init__(self):
            super().__init__()
            self.weight = torch.nn.Parameter(torch.zeros(1, device=META))

        def forward(self, *inputs):
            seen.extend(x.device for x in inputs)
            return tuple(x * self.weight for x in inputs[:2])

    call = on_cpu(Elsewhere())
    with pytest.raises(NotImplementedError):
        # Its outputs come back to the CPU (meta tensors have no data to copy).
        call(torch.ones(2), torch.ones(2))
    assert seen == [META, META]
    assert on_cpu(velocity) is velocity
