"""A frozen DINOv2 ViT-S/14 image encoder loaded from a local checkpoint
(the paper's image stream), for users who have the weights: nothing is
downloaded. The module layout and parameter names follow Meta's released
`dinov2_vits14_pretrain.pth` (embedding 384, 12 blocks, 6 heads, patch 14,
LayerScale, positional embeddings for a 37 x 37 grid), so that file loads
with `strict=True`.

The positional embeddings are resampled once, at load, to the crop's patch
grid (bicubic, as DINOv2 does), so the exported graph has no resampling.
"""

import math
from pathlib import Path

import torch
from torch import nn

EMBED, DEPTH, HEADS, PATCH, TRAINED_GRID = 384, 12, 6, 14, 37


class LayerScale(nn.Module):
    def __init__(self, width):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(width))

    def forward(self, x):
        return x * self.gamma


class SelfAttention(nn.Module):
    def __init__(self, width, heads):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)

    def forward(self, x):
        b, n, d = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        scores = (q @ k.transpose(-1, -2)) / math.sqrt(d // self.heads)
        return self.proj((scores.softmax(-1) @ v).transpose(1, 2).reshape(b, n, d))


class Mlp(nn.Module):
    def __init__(self, width):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(width, 4 * width), nn.Linear(4 * width, width)

    def forward(self, x):
        return self.fc2(nn.functional.gelu(self.fc1(x)))


class DinoBlock(nn.Module):
    def __init__(self, width, heads):
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(width, eps=1e-6), nn.LayerNorm(width, eps=1e-6)
        self.attn, self.mlp = SelfAttention(width, heads), Mlp(width)
        self.ls1, self.ls2 = LayerScale(width), LayerScale(width)

    def forward(self, x):
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class PatchEmbed(nn.Module):
    def __init__(self):
        super().__init__()
        self.proj = nn.Conv2d(3, EMBED, PATCH, stride=PATCH)


class DinoV2Small(nn.Module):
    """Image [B, 3, 14 g, 14 g] (ImageNet-normalised) -> patch tokens
    [B, g * g, 384], frozen."""

    width = EMBED

    def __init__(self, checkpoint, grid):
        super().__init__()
        self.patch_embed = PatchEmbed()
        self.cls_token = nn.Parameter(torch.zeros(1, 1, EMBED))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + TRAINED_GRID**2, EMBED))
        self.mask_token = nn.Parameter(torch.zeros(1, EMBED))
        self.blocks = nn.ModuleList([DinoBlock(EMBED, HEADS) for _ in range(DEPTH)])
        self.norm = nn.LayerNorm(EMBED, eps=1e-6)
        if checkpoint:
            path = Path(checkpoint)
            if not path.is_file():
                raise SystemExit(
                    f"model.dinov2_checkpoint: {path} does not exist (expected Meta's dinov2_vits14_pretrain.pth)"
                )
            state = torch.load(path, map_location="cpu", weights_only=True)
            missing, unexpected = self.load_state_dict(state, strict=False)
            if missing or unexpected:
                raise SystemExit(
                    f"{path}: not a DINOv2 ViT-S/14 checkpoint (missing {missing[:4]}, unexpected {unexpected[:4]})"
                )
        for parameter in self.parameters():
            parameter.requires_grad_(False)
        self.register_buffer("grid_pos", self.resampled_positions(grid))

    def resampled_positions(self, grid):
        table = self.pos_embed[0, 1:].reshape(1, TRAINED_GRID, TRAINED_GRID, EMBED).permute(0, 3, 1, 2)
        table = nn.functional.interpolate(table, size=(grid, grid), mode="bicubic", align_corners=False)
        return table.permute(0, 2, 3, 1).reshape(1, grid * grid, EMBED).detach().clone()

    def train(self, mode=True):
        # Frozen: always in inference mode.
        return super().train(False)

    def forward(self, image):
        x = self.patch_embed.proj(image).flatten(2).transpose(1, 2) + self.grid_pos
        cls = self.cls_token + self.pos_embed[:, :1]
        x = torch.cat([cls.expand(x.shape[0], -1, -1), x], 1)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)[:, 1:]
