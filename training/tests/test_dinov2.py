import pytest
import torch

from poseflow_train import dinov2
from poseflow_train.model import Encoder, ModelConfig


def official_layout_checkpoint(path):
    """A random state dict with the names and shapes of Meta's
    dinov2_vits14_pretrain.pth."""
    module = dinov2.DinoV2Small("", grid=16)
    state = {k: torch.randn_like(v) * 0.02 for k, v in module.state_dict().items() if k != "grid_pos"}
    assert state["pos_embed"].shape == (1, 1370, 384)
    assert "blocks.11.ls2.gamma" in state and "blocks.0.attn.qkv.weight" in state
    torch.save(state, path)
    return state


def test_a_checkpoint_in_the_released_layout_loads_frozen_and_gives_patch_tokens(tmp_path):
    state = official_layout_checkpoint(tmp_path / "dinov2_vits14_pretrain.pth")
    cfg = ModelConfig(image_size=224, patch_grid=16, width=64, image_encoder="dinov2",
                      dinov2_checkpoint=str(tmp_path / "dinov2_vits14_pretrain.pth"), object_ids=[1, 5])
    encoder = Encoder(cfg)
    assert torch.equal(encoder.image.blocks[3].attn.qkv.weight, state["blocks.3.attn.qkv.weight"])
    assert not any(p.requires_grad for p in encoder.image.parameters())
    encoder.train()
    assert not encoder.image.training
    condition, mask = encoder(torch.randn(2, 3, 224, 224), torch.ones(2, 256), torch.randn(2, 1024, 3) * 0.03,
                              torch.tensor([0, 1]))
    tokens = 256 + cfg.sa2_centres + 3  # image, local point, global point, object, coarse pose
    assert condition.shape == (2, tokens, 64) and mask.shape == (2, tokens)


def test_wrong_sizes_and_files_are_named(tmp_path):
    with pytest.raises(SystemExit, match="14 x patch_grid"):
        ModelConfig(image_size=128, patch_grid=8, image_encoder="dinov2")
    with pytest.raises(SystemExit, match="does not exist"):
        Encoder(ModelConfig(image_size=224, patch_grid=16, image_encoder="dinov2", dinov2_checkpoint=str(tmp_path / "x.pth")))
    torch.save({"something": torch.zeros(1)}, tmp_path / "other.pth")
    with pytest.raises(SystemExit, match="not a DINOv2 ViT-S/14 checkpoint"):
        Encoder(ModelConfig(image_size=224, patch_grid=16, image_encoder="dinov2", dinov2_checkpoint=str(tmp_path / "other.pth")))
