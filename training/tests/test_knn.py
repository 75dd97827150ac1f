"""The point stream's neighbour search ranks by |p|^2 - 2 q.p (a matrix
product) instead of the explicit squared distance: the same neighbours."""

import torch

from poseflow_train.model import knn


def test_knn_finds_the_nearest_points_by_explicit_distance():
    g = torch.Generator().manual_seed(3)
    # Centred clouds in the point stream's units (metres / 0.05): a few units across.
    points = torch.randn(4, 512, 3, generator=g) * 2.0
    queries = points[:, :128]
    found = knn(queries, points, 16)
    d2 = (queries[:, :, None, :] - points[:, None, :, :]).pow(2).sum(-1)
    expected = d2.topk(16, dim=-1, largest=False).indices
    assert torch.equal(found.sort(-1).values, expected.sort(-1).values)
    # Each query's own point is its nearest.
    assert torch.equal(found[:, :, 0], torch.arange(128).expand(4, 128))
