"""The PoseFlow network (paper, "Method"): image patch tokens and
PointNet++ point tokens projected to one width, DiT* blocks over a rotation
and a translation pose token with adaLN conditioning on Fourier features of
t (and the object), masked cross-attention to the condition tokens, heads
for the two velocities.

The heads predict the clean pose (a 6D rotation R1_hat and p1_hat) and the
velocities are derived from it on the paper's path,
w = log(R_t^T R1_hat) / (1 - t), v = (p1_hat - p_t) / (1 - t): on a CPU
budget this learns rotation far faster than regressing velocities directly
(../shared/DESIGN.md, "Training on a CPU"); the exported velocity contract is
the same either way.

Beyond the paper, for the CPU budget: the encoder also predicts, for each of
the first `correspondence_points` observed points, where it lies on the
object (object-frame coordinates, trained densely against the ground truth,
NOCS-style), aligns those to the observed points (Horn's closed form) and
appends the resulting coarse pose as a last condition token. The velocity
network predicts the clean pose as a correction of that coarse pose. A
refiner then maps the observed points into the object frame under the
current coarse pose and predicts their corrected coordinates, aligned again
by Horn, `refine_iterations` times: a learned ICP whose input is already
pose-normalised, so it learns local corrections instead of global
orientation (measured: held-out 10deg5cm of the coarse pose 26 -> 69 % after
3 iterations, refiner trained alone for 25 minutes). Dense
per-point supervision teaches orientation an order of magnitude faster than
a rotation read from a global feature (measured: 10-object held-out rotation
error below 10 degrees for 8.6 % of observations after 4 minutes, against
0.5 % for a regressed rotation from the same points).

Units: points and translations in metres (centred on the observed points'
mean); internally translations are divided by `translation_scale`.
"""

import itertools
import math
from dataclasses import asdict, dataclass, field

import torch
from torch import nn

from . import se3
from .dinov2 import DinoV2Small


@dataclass
class ModelConfig:
    image_size: int = 112
    patch_grid: int = 8
    point_count: int = 1024
    width: int = 128
    heads: int = 4
    image_depth: int = 4
    dit_depth: int = 4
    # The first-level grouping searches only this prefix of the points (the
    # ingest stage's farthest-point order makes it an even subsample): the
    # k-NN search dominates the encoder's cost on a CPU.
    group_points: int = 1024
    sa1_centres: int = 128
    sa2_centres: int = 32
    neighbours: int = 16
    fourier_features: int = 16
    # Metres per internal translation unit.
    translation_scale: float = 0.05
    # The flow's initial translations: N(0, std^2) per axis, metres.
    translation_noise_std: float = 0.05
    # Smallest 1 - t used when deriving velocities (the sampler never goes
    # past t = (K - 1) / K).
    min_remaining: float = 0.05
    object_ids: list = field(default_factory=lambda: [1])
    # "scratch": a small ViT trained with the rest (the CPU default);
    # "dinov2": a frozen DINOv2 ViT-S/14 from `dinov2_checkpoint` (Meta's
    # dinov2_vits14_pretrain.pth; image_size must be 14 * patch_grid).
    image_encoder: str = "scratch"
    dinov2_checkpoint: str = ""
    # Add a pooled summary of the condition tokens to the adaLN conditioning
    # (as DiT adds its class embedding to the time embedding), beside the
    # cross-attention: every block is then modulated by the observation.
    global_condition: bool = True
    # Points whose object-frame coordinates the encoder predicts (a prefix of
    # the farthest-point order) for the coarse pose token.
    correspondence_points: int = 256
    # Refinement iterations of the coarse pose (0: none, as models trained
    # before the refiner existed).
    refine_iterations: int = 0
    # The velocity network sees each sample's pose relative to the coarse
    # pose (R_c^T R_t, p_t - p_c) and predicts the clean pose as R_c Delta,
    # a correction in the object frame. An ambiguity is then one fixed
    # function of the relative pose for every view (a hidden mug handle:
    # keep the sample's turn about the mug's axis; a symmetric object: its
    # nearest twin), where a correction of the coarse pose's 6D columns in
    # the camera frame has to relearn it per orientation, and in practice
    # collapses every sample onto the coarse pose. False: the first models.
    relative_pose: bool = False
    # A category-level model (`object_ids` are category codes) also predicts
    # the object's size, its box extents in the canonical frame, from the
    # observed points under the coarse pose (`SizeHead`), and carries it in
    # the coarse pose token (`hint_token`).
    size_head: bool = False

    def __post_init__(self):
        if self.image_encoder not in ("scratch", "dinov2"):
            raise SystemExit(f"model.image_encoder: {self.image_encoder!r}, expected \"scratch\" or \"dinov2\"")
        if self.image_encoder == "dinov2" and self.image_size != 14 * self.patch_grid:
            raise SystemExit(
                f"model.image_size {self.image_size}: DINOv2 takes 14-pixel patches, so 14 x patch_grid "
                f"= {14 * self.patch_grid}"
            )

    def to_dict(self):
        return asdict(self)


class Attention(nn.Module):
    """Multi-head attention written out (exports to plain ONNX ops).

    `x` [Bc * G, N, D] attends to `context` [Bc, T, D]: the G queries of a
    group share one context (the samples of one observation share its
    condition), whose keys and values are computed once. `mask` [Bc, T]:
    1 = attend, 0 = ignore. `kv` [Bc, T, 2 D]: the context's keys and
    values when already computed (`context_kv`), as the exported velocity
    network receives them once per observation."""

    def __init__(self, width, heads):
        super().__init__()
        self.heads = heads
        self.scale = 1.0 / math.sqrt(width // heads)
        self.q = nn.Linear(width, width)
        self.kv = nn.Linear(width, 2 * width)
        self.out = nn.Linear(width, width)

    def context_kv(self, context):
        return self.kv(context)

    def forward(self, x, context, mask=None, kv=None):
        bx, n, d = x.shape
        bc, tk = context.shape[0], context.shape[1]
        h, dh = self.heads, d // self.heads
        q = self.q(x).reshape(bc, -1, n, h, dh).permute(0, 1, 3, 2, 4)
        kv = (self.kv(context) if kv is None else kv).reshape(bc, tk, 2, h, dh).permute(2, 0, 3, 1, 4)
        k, v = kv[0][:, None], kv[1][:, None]
        scores = (q @ k.transpose(-1, -2)) * self.scale
        if mask is not None:
            scores = scores + (1.0 - mask[:, None, None, None, :]) * -1e4
        out = (scores.softmax(-1) @ v).permute(0, 1, 3, 2, 4).reshape(bx, n, d)
        return self.out(out)


def mlp(width, hidden):
    return nn.Sequential(nn.Linear(width, hidden), nn.GELU(), nn.Linear(hidden, width))


class Block(nn.Module):
    """Pre-norm transformer block (self-attention + MLP)."""

    def __init__(self, width, heads):
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.attn = Attention(width, heads)
        self.mlp = mlp(width, 4 * width)

    def forward(self, x):
        y = self.norm1(x)
        x = x + self.attn(y, y)
        return x + self.mlp(self.norm2(x))


class ImageEncoder(nn.Module):
    """A small ViT from scratch: P x P patch tokens of an S x S crop."""

    def __init__(self, cfg):
        super().__init__()
        patch = cfg.image_size // cfg.patch_grid
        self.embed = nn.Conv2d(3, cfg.width, patch, stride=patch)
        self.position = nn.Parameter(torch.randn(1, cfg.patch_grid**2, cfg.width) * 0.02)
        self.blocks = nn.ModuleList([Block(cfg.width, cfg.heads) for _ in range(cfg.image_depth)])
        self.norm = nn.LayerNorm(cfg.width)

    def forward(self, image):
        x = self.embed(image).flatten(2).transpose(1, 2) + self.position
        for block in self.blocks:
            x = block(x)
        return self.norm(x)


def gather(values, index):
    """values [B, N, C], index [B, M, K] -> [B, M, K, C]."""
    b, m, k = index.shape
    flat = index.reshape(b, m * k, 1).expand(-1, -1, values.shape[-1])
    return torch.gather(values, 1, flat).reshape(b, m, k, values.shape[-1])


def knn(queries, points, k):
    """Indices [B, M, k] of the k nearest `points` to each query, ranked by
    |p|^2 - 2 q.p: the squared distance less the query's own |q|^2, which
    does not change a query's ranking. One matrix product instead of a
    [B, M, N, 3] difference tensor, which dominated the point stream's
    cost in ONNX Runtime."""
    rank = points.pow(2).sum(-1)[:, None, :] - 2.0 * (queries @ points.transpose(1, 2))
    return rank.topk(k, dim=-1, largest=False).indices


class SetAbstraction(nn.Module):
    """PointNet++ set abstraction: centres (the first M points: the ingest
    stage's farthest-point order makes every prefix a farthest-point
    sample), k-nearest grouping, a shared MLP on [relative xyz, features],
    max pooling."""

    def __init__(self, centres, neighbours, in_features, out_features):
        super().__init__()
        self.centres, self.neighbours = centres, neighbours
        self.mlp = nn.Sequential(
            nn.Linear(3 + in_features, out_features // 2),
            nn.GELU(),
            nn.Linear(out_features // 2, out_features),
            nn.GELU(),
            nn.Linear(out_features, out_features),
        )

    def forward(self, xyz, features):
        centres = xyz[:, : self.centres]
        index = knn(centres, xyz, self.neighbours)
        relative = gather(xyz, index) - centres[:, :, None, :]
        grouped = relative if features is None else torch.cat([relative, gather(features, index)], -1)
        return centres, self.mlp(grouped).amax(2)


class PointEncoder(nn.Module):
    def __init__(self, cfg):
        super().__init__()
        self.scale = cfg.translation_scale
        self.group_points = cfg.group_points
        self.sa1 = SetAbstraction(cfg.sa1_centres, cfg.neighbours, 0, cfg.width // 2)
        self.sa2 = SetAbstraction(cfg.sa2_centres, cfg.neighbours, cfg.width // 2, cfg.width)
        self.position = nn.Sequential(nn.Linear(3, cfg.width), nn.GELU(), nn.Linear(cfg.width, cfg.width))
        # PointNet++'s last level, "group all": one token for the whole cloud.
        self.sa3 = nn.Sequential(
            nn.Linear(3 + cfg.width, cfg.width), nn.GELU(), nn.Linear(cfg.width, 2 * cfg.width), nn.GELU(),
            nn.Linear(2 * cfg.width, cfg.width),
        )

    def forward(self, points):
        """[B, N, 3] -> [B, sa2_centres + 1, D]: local tokens, then the global one."""
        xyz = points[:, : self.group_points] / self.scale
        centres, features = self.sa1(xyz, None)
        centres, features = self.sa2(centres, features)
        whole = self.sa3(torch.cat([centres, features], -1)).amax(1, keepdim=True)
        return torch.cat([features + self.position(centres), whole], 1)


def split_first(mlp, local, shared):
    """`mlp(cat([local, shared expanded over the points], -1))` with the
    first layer's product split in two: the shared part ([B, 1, C]: the
    object embedding, the cloud's pooled feature) is multiplied once per
    cloud instead of once per point. Same function, same parameters."""
    first = mlp[0]
    k = local.shape[-1]
    hidden = local @ first.weight[:, :k].T + (shared @ first.weight[:, k:].T + first.bias)
    return mlp[1:](hidden)


class Correspondences(nn.Module):
    """Object-frame coordinates of observed points: a PointNet segmentation
    network (per-point features, the cloud's max-pooled feature, the
    object's embedding) over the first `correspondence_points` centred
    points. Returns [B, n, 3] in metres (model frame)."""

    def __init__(self, cfg):
        super().__init__()
        self.count, self.scale = cfg.correspondence_points, cfg.translation_scale
        self.objects = nn.Embedding(len(cfg.object_ids), 64)
        self.local = nn.Sequential(nn.Linear(3, 64), nn.LayerNorm(64), nn.GELU(), nn.Linear(64, 128), nn.LayerNorm(128), nn.GELU())
        self.whole = nn.Sequential(nn.Linear(128 + 64, 256), nn.LayerNorm(256), nn.GELU(), nn.Linear(256, 512))
        self.head = nn.Sequential(
            nn.Linear(128 + 512 + 64, 256), nn.LayerNorm(256), nn.GELU(), nn.Linear(256, 128), nn.GELU(), nn.Linear(128, 3)
        )

    def forward(self, points, object_index):
        x = points[:, : self.count] / self.scale
        o = self.objects(object_index)[:, None, :]
        local = self.local(x)
        whole = split_first(self.whole, local, o).amax(1, keepdim=True)
        return split_first(self.head, local, torch.cat([whole, o], -1)) * self.scale


class Refiner(nn.Module):
    """One refinement of a coarse pose (R, p): the observed points mapped
    into the object frame by it, R^T (x - p), through a PointNet like
    `Correspondences` (with a third local layer), which predicts a residual
    to the object-frame coordinates; Horn aligns the result again. The head
    starts at zero, so an untrained refiner returns the pose it is given."""

    def __init__(self, cfg):
        super().__init__()
        self.count, self.scale = cfg.correspondence_points, cfg.translation_scale
        self.objects = nn.Embedding(len(cfg.object_ids), 64)
        self.local = nn.Sequential(
            nn.Linear(3, 64), nn.LayerNorm(64), nn.GELU(), nn.Linear(64, 128), nn.LayerNorm(128), nn.GELU(),
            nn.Linear(128, 128), nn.LayerNorm(128), nn.GELU(),
        )
        self.whole = nn.Sequential(nn.Linear(128 + 64, 256), nn.LayerNorm(256), nn.GELU(), nn.Linear(256, 512))
        self.head = nn.Sequential(
            nn.Linear(128 + 512 + 64, 256), nn.LayerNorm(256), nn.GELU(), nn.Linear(256, 128), nn.GELU(), nn.Linear(128, 3)
        )
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def forward(self, points, object_index, rotation, translation):
        """(coordinates [B, n, 3] metres, R [B,3,3], p [B,3]): the corrected
        object-frame coordinates of the first n points and their alignment."""
        observed = points[:, : self.count]
        # Rows R^T (x - p), in translation_scale units.
        canonical = ((observed - translation[:, None]) @ rotation) / self.scale
        o = self.objects(object_index)[:, None, :]
        local = self.local(canonical)
        whole = split_first(self.whole, local, o).amax(1, keepdim=True)
        coordinates = (canonical + split_first(self.head, local, torch.cat([whole, o], -1))) * self.scale
        rotation, translation = se3.align(coordinates, observed)
        return coordinates, rotation, translation


class SizeHead(nn.Module):
    """The object's size (box extents along its canonical x, y, z, metres)
    from the observed points mapped into the object frame by the coarse
    pose and the category's embedding: a PointNet regressing log extents
    about 10 cm. Returns log(size / 0.1 m) [B, 3]."""

    def __init__(self, cfg):
        super().__init__()
        self.count, self.scale = cfg.correspondence_points, cfg.translation_scale
        self.objects = nn.Embedding(len(cfg.object_ids), 64)
        self.local = nn.Sequential(nn.Linear(3, 64), nn.LayerNorm(64), nn.GELU(), nn.Linear(64, 128), nn.LayerNorm(128), nn.GELU())
        self.whole = nn.Sequential(nn.Linear(128 + 64, 256), nn.LayerNorm(256), nn.GELU(), nn.Linear(256, 256))
        self.head = nn.Sequential(nn.Linear(256 + 64, 128), nn.GELU(), nn.Linear(128, 3))

    def forward(self, points, object_index, rotation, translation):
        canonical = ((points[:, : self.count] - translation[:, None]) @ rotation) / self.scale
        o = self.objects(object_index)[:, None, :]
        whole = split_first(self.whole, self.local(canonical), o).amax(1)
        return self.head(torch.cat([whole, o[:, 0]], -1))


# Reference of `SizeHead`'s log extents, metres.
SIZE_REFERENCE_M = 0.1

# Layout of the coarse pose token (the last condition token): R row-major,
# then p / translation_scale, then (models with `size_head`) the size /
# translation_scale, then zeros. The velocity network's pose input reads the
# first HINT_VALUES.
HINT_VALUES = 12
SIZE_VALUES = slice(12, 15)


def hint_token(rotation, translation, cfg, size=None):
    b = rotation.shape[0]
    parts = [rotation.reshape(b, 9), translation / cfg.translation_scale]
    if size is not None:
        parts.append(size / cfg.translation_scale)
    values = torch.cat(parts, -1)
    return torch.cat([values, torch.zeros(b, cfg.width - values.shape[1], dtype=values.dtype, device=values.device)], -1)[:, None, :]


def read_size(condition, cfg):
    """The size [Bc, 3] metres a `size_head` model put in its last token."""
    return condition[:, -1, SIZE_VALUES] * cfg.translation_scale


def read_hint(condition, cfg):
    """(R [Bc,3,3], p [Bc,3] metres) from the last condition token."""
    values = condition[:, -1, :HINT_VALUES]
    return values[:, :9].reshape(-1, 3, 3), values[:, 9:] * cfg.translation_scale


def cube_turns(dtype=torch.float32):
    """[24, 3, 3]: the proper rotations that permute and flip the object's
    axes (the cube's rotation group), the identity first."""
    turns = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = torch.zeros(3, 3, dtype=dtype)
            for row, (col, sign) in enumerate(zip(perm, signs)):
                m[row, col] = sign
            if torch.det(m) > 0:
                turns.append(m)
    return torch.stack(sorted(turns, key=lambda m: -float(torch.trace(m))))


# Coarse pose verification (`Encoder.verify_coarse`). Each turned candidate
# gets one refiner pass over the first VERIFY_POINTS observed points (a
# prefix of the farthest-point order, so spread over the object), and is
# scored by the mean distance of the first VERIFY_SCORE_POINTS to the
# object's surface, truncated at VERIFY_TRUNCATION_M so that background
# points and occluders count as one fixed miss instead of dominating.
VERIFY_POINTS = 64
VERIFY_SCORE_POINTS = 256
VERIFY_TRUNCATION_M = 0.01


def surface_distance(points, rotation, translation, surface):
    """[M]: mean over the points [M, n, 3] (camera axes, metres) of the
    distance to the nearest surface point [M, s, 3] (object frame) under
    the poses (R [M,3,3], p [M,3]), each truncated at VERIFY_TRUNCATION_M.
    Squared distances by one product (|a|^2 + |b|^2 - 2 a.b), which exports
    to ONNX where `cdist` does not."""
    local = (points - translation[:, None]) @ rotation
    squared = local.pow(2).sum(-1, keepdim=True) + surface.pow(2).sum(-1)[:, None, :] - 2.0 * local @ surface.transpose(1, 2)
    nearest = squared.amin(-1).clamp_min(0.0).sqrt()
    return nearest.clamp(max=VERIFY_TRUNCATION_M).mean(-1)


class Encoder(nn.Module):
    """Observation -> condition tokens [B, T, D] and their mask [B, T]:
    P*P image tokens (masked by the token mask), point tokens, one object
    token, the coarse pose token."""

    def __init__(self, cfg):
        super().__init__()
        if cfg.image_encoder == "dinov2":
            self.image = DinoV2Small(cfg.dinov2_checkpoint, cfg.patch_grid)
        else:
            self.image = ImageEncoder(cfg)
        image_width = self.image.width if cfg.image_encoder == "dinov2" else cfg.width
        self.points = PointEncoder(cfg)
        self.image_proj, self.point_proj = nn.Linear(image_width, cfg.width), nn.Linear(cfg.width, cfg.width)
        self.kind = nn.Parameter(torch.randn(3, cfg.width) * 0.02)
        self.objects = nn.Embedding(len(cfg.object_ids), cfg.width)
        self.correspondences = Correspondences(cfg)
        if cfg.refine_iterations > 0:
            self.refiner = Refiner(cfg)
        if cfg.size_head:
            self.size = SizeHead(cfg)
        self.cfg = cfg
        # Object surfaces for `verify_coarse` ([objects, s, 3] metres, object
        # frame), set at export by `set_surfaces`; None: no verification (as
        # in training). Buffers that checkpoints do not carry.
        for name in ("surfaces", "turns", "twins"):
            self.register_buffer(name, None, persistent=False)

    def set_surfaces(self, surfaces, twins=None):
        """Turns on the coarse pose's verification with these surface points
        ([objects, s, 3] metres, in `object_ids` order). `twins` [objects,
        24] bool marks the turns (`cube_turns`) that are symmetries of an
        object's shape: the mesh cannot tell those apart, the network may
        (a real box's print), so they are never preferred to its pose."""
        if self.cfg.refine_iterations == 0:
            raise SystemExit("coarse pose verification needs a model with a refiner (model.refine_iterations > 0)")
        if surfaces.shape[0] != len(self.cfg.object_ids):
            raise SystemExit(f"surfaces for {surfaces.shape[0]} objects, the model has {len(self.cfg.object_ids)}")
        self.surfaces = surfaces
        self.turns = cube_turns(surfaces.dtype)
        if twins is None:
            twins = torch.zeros(surfaces.shape[0], self.turns.shape[0], dtype=torch.bool)
        # The identity is every shape's symmetry, and it is the network's pose.
        self.twins = twins.clone()
        self.twins[:, 0] = False

    def verify_coarse(self, points, object_index, rotation, translation):
        """The coarse pose or one of its 24 turns about the object's centre
        (`cube_turns`), whichever puts the observed points nearest the
        object's surface after one refiner pass, then refined as the coarse
        pose is. A learned correspondence can land on a half or quarter turn
        of the truth when a shape is nearly symmetric (a bottle, a block, a
        banana); geometry the network has not weighed tells them apart.
        Beyond the paper; inference only (`set_surfaces`)."""
        b, k = points.shape[0], self.turns.shape[0]
        surface = self.surfaces[object_index]
        centre = surface.mean(1)
        turned = rotation[:, None] @ self.turns[None]
        # The centre stays where the pose put it: p + (R - R S) c.
        shifted = translation[:, None] + ((rotation[:, None] - turned) @ centre[:, None, :, None])[..., 0]

        def per_candidate(x):
            return x[:, None].expand(b, k, *x.shape[1:]).reshape(b * k, *x.shape[1:])

        _, candidates_r, candidates_p = self.refiner(
            per_candidate(points[:, :VERIFY_POINTS]), per_candidate(object_index),
            turned.reshape(b * k, 3, 3), shifted.reshape(b * k, 3))
        score = surface_distance(per_candidate(points[:, :VERIFY_SCORE_POINTS]), candidates_r, candidates_p,
                                 per_candidate(surface)).reshape(b, k)
        # A truncated distance is at most VERIFY_TRUNCATION_M: a twin's score
        # above it loses to every other turn.
        best = torch.where(self.twins[object_index], score + 2 * VERIFY_TRUNCATION_M, score).argmin(1)
        chosen_r = candidates_r.reshape(b, k, 3, 3).gather(1, best[:, None, None, None].expand(b, 1, 3, 3))[:, 0]
        chosen_p = candidates_p.reshape(b, k, 3).gather(1, best[:, None, None].expand(b, 1, 3))[:, 0]
        # The coarse pose itself when it wins, not its one-pass refinement
        # on fewer points.
        kept = (best == 0)[:, None]
        rotation = torch.where(kept[..., None], rotation, chosen_r)
        translation = torch.where(kept, translation, chosen_p)
        return self.refine(points, object_index, rotation, translation)[1:]

    def first_pose(self, points, object_index):
        """(model-frame coordinates [B, n, 3], R [B,3,3], p [B,3]): the
        predicted coordinates aligned to the observed points. The pose is
        not trained through (the coordinates have their own loss)."""
        coordinates = self.correspondences(points, object_index)
        observed = points[:, : coordinates.shape[1]]
        rotation, translation = se3.align(coordinates.detach(), observed)
        return coordinates, rotation, translation

    def refine(self, points, object_index, rotation, translation):
        """The refiner's iterations from (R, p): a list of each iteration's
        coordinates, and the final pose. Poses are detached between
        iterations (each iteration's coordinates have their own loss)."""
        steps = []
        for _ in range(self.cfg.refine_iterations):
            coordinates, rotation, translation = self.refiner(points, object_index, rotation.detach(), translation.detach())
            steps.append(coordinates)
        return steps, rotation.detach(), translation.detach()

    def coarse_pose(self, points, object_index):
        """(every set of predicted coordinates, R, p): the first pose and
        its refinements; the pose is an input of the velocity network."""
        coordinates, rotation, translation = self.first_pose(points, object_index)
        refined, rotation, translation = self.refine(points, object_index, rotation, translation)
        if self.surfaces is not None:
            rotation, translation = self.verify_coarse(points, object_index, rotation, translation)
        return [coordinates, *refined], rotation, translation

    def encode(self, image, token_mask, points, object_index):
        """(condition, condition_mask, every set of predicted model-frame
        coordinates: the first, then one per refinement)."""
        image_tokens = self.image_proj(self.image(image)) + self.kind[0]
        point_tokens = self.point_proj(self.points(points)) + self.kind[1]
        object_token = (self.objects(object_index) + self.kind[2])[:, None, :]
        coordinates, rotation, translation = self.coarse_pose(points, object_index)
        size = None
        if self.cfg.size_head:
            size = SIZE_REFERENCE_M * self.size(points, object_index, rotation, translation).exp()
        hint = hint_token(rotation, translation, self.cfg, size)
        condition = torch.cat([image_tokens, point_tokens, object_token, hint], 1)
        ones = torch.ones(points.shape[0], point_tokens.shape[1] + 2, dtype=token_mask.dtype, device=token_mask.device)
        return condition, torch.cat([token_mask, ones], 1), coordinates

    def forward(self, image, token_mask, points, object_index):
        condition, mask, _ = self.encode(image, token_mask, points, object_index)
        return condition, mask


def fourier(t, count):
    """[M] -> [M, 2 count] sin/cos features of t at log-spaced frequencies."""
    freqs = torch.exp(torch.linspace(0.0, math.log(1000.0), count, device=t.device, dtype=t.dtype))
    angles = t[:, None] * freqs[None, :] * 2 * math.pi / 10.0
    return torch.cat([angles.sin(), angles.cos()], -1)


class DiTBlock(nn.Module):
    """DiT* block: adaLN-modulated self-attention over the pose tokens,
    masked cross-attention to the condition, MLP; zero-initialised gates."""

    def __init__(self, width, heads):
        super().__init__()
        self.norms = nn.ModuleList([nn.LayerNorm(width, elementwise_affine=False) for _ in range(3)])
        self.self_attn, self.cross_attn = Attention(width, heads), Attention(width, heads)
        self.mlp = mlp(width, 4 * width)
        self.modulation = nn.Linear(width, 9 * width)
        nn.init.zeros_(self.modulation.weight)
        nn.init.zeros_(self.modulation.bias)

    def forward(self, x, c, condition, condition_mask, cross_kv=None):
        shift = self.modulation(nn.functional.silu(c))[:, None, :].chunk(9, -1)

        def modulated(i, y):
            return self.norms[i](y) * (1 + shift[3 * i + 1]) + shift[3 * i]

        y = modulated(0, x)
        x = x + shift[2] * self.self_attn(y, y)
        x = x + shift[5] * self.cross_attn(modulated(1, x), condition, condition_mask, cross_kv)
        return x + shift[8] * self.mlp(modulated(2, x))


class VelocityNet(nn.Module):
    """(condition, poses at time t) -> (v_rot body-frame rad/s, v_pos m/s)."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.rotation_in, self.translation_in = nn.Linear(9, w), nn.Linear(3, w)
        self.kind = nn.Parameter(torch.randn(2, w) * 0.02)
        self.time = nn.Sequential(nn.Linear(2 * cfg.fourier_features, w), nn.SiLU(), nn.Linear(w, w))
        if cfg.global_condition:
            self.summary = nn.Sequential(nn.LayerNorm(w), nn.Linear(w, w), nn.SiLU(), nn.Linear(w, w))
        self.hint = nn.Sequential(nn.Linear(HINT_VALUES, w), nn.SiLU(), nn.Linear(w, w))
        self.blocks = nn.ModuleList([DiTBlock(w, cfg.heads) for _ in range(cfg.dit_depth)])
        self.final_norm = nn.LayerNorm(w, elementwise_affine=False)
        self.final_modulation = nn.Linear(w, 2 * w)
        self.rotation_head, self.translation_head = nn.Linear(w, 6), nn.Linear(w, 3)
        # Start from the coarse pose: the heads predict corrections of it.
        for head in (self.rotation_head, self.translation_head):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)

    def cross_kv(self, condition):
        """[B, L, T, 2 D]: the keys and values of every block's
        cross-attention over the condition tokens. They depend on the
        observation only, so inference computes them once per observation
        instead of at every Euler step."""
        return torch.stack([block.cross_attn.context_kv(condition) for block in self.blocks], 1)

    def clean_pose(self, condition, condition_mask, rotation, translation, t, cross_kv=None):
        """The predicted clean pose (R1_hat, p1_hat in metres)."""
        scale = self.cfg.translation_scale
        bc = condition.shape[0]
        hint_r, hint_p = read_hint(condition, self.cfg)
        if self.cfg.relative_pose:
            per_sample = rotation.shape[0] // bc
            base_r = hint_r[:, None].expand(bc, per_sample, 3, 3).reshape(-1, 3, 3)
            base_p = hint_p[:, None, :].expand(bc, per_sample, 3).reshape(-1, 3)
            rotation, translation = base_r.transpose(-1, -2) @ rotation, translation - base_p
        x = torch.stack(
            [self.rotation_in(rotation.reshape(-1, 9)) + self.kind[0], self.translation_in(translation / scale) + self.kind[1]],
            1,
        )
        c = self.time(fourier(t, self.cfg.fourier_features))
        # Per-observation conditioning, shared by its samples (grouped as in
        # `Attention`): the coarse pose and the masked mean of the tokens.
        per_observation = self.hint(condition[:, -1, :HINT_VALUES])
        if self.cfg.global_condition:
            weights = condition_mask[:, :, None]
            pooled = (condition * weights).sum(1) / weights.sum(1).clamp_min(1.0)
            per_observation = per_observation + self.summary(pooled)
        c = (c.reshape(bc, -1, c.shape[-1]) + per_observation[:, None, :]).reshape(-1, c.shape[-1])
        samples = rotation.shape[0] // bc
        for i, block in enumerate(self.blocks):
            x = block(x, c, condition, condition_mask, None if cross_kv is None else cross_kv[:, i])
        shift, scl = self.final_modulation(nn.functional.silu(c))[:, None, :].chunk(2, -1)
        x = self.final_norm(x) * (1 + scl) + shift
        # Corrections of the coarse pose, not of (R_t, p_t): at small t the
        # current pose is noise, and a correction of it would have to undo a
        # random rotation, which an MLP learns slowly (a run with
        # corrections of R_t stayed at chance for 11,000 steps).
        base_p = hint_p[:, None, :].expand(bc, samples, 3).reshape(-1, 3)
        p1 = base_p + self.translation_head(x[:, 1]) * scale
        if self.cfg.relative_pose:
            base_r = hint_r[:, None].expand(bc, samples, 3, 3).reshape(-1, 3, 3)
            identity_6d = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], dtype=x.dtype, device=x.device)
            return base_r @ se3.rotation_from_6d(identity_6d + self.rotation_head(x[:, 0])), p1
        base_6d = torch.cat([hint_r[:, :, 0], hint_r[:, :, 1]], -1)[:, None, :].expand(bc, samples, 6).reshape(-1, 6)
        return se3.rotation_from_6d(base_6d + self.rotation_head(x[:, 0])), p1

    def forward(self, condition, condition_mask, rotation, translation, t, cross_kv=None):
        r1, p1 = self.clean_pose(condition, condition_mask, rotation, translation, t, cross_kv)
        remaining = (1.0 - t).clamp_min(self.cfg.min_remaining)[:, None]
        return se3.so3_log(rotation.transpose(-1, -2) @ r1) / remaining, (p1 - translation) / remaining
