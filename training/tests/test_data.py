"""The shard reader's choice of symmetry file (data.SYMMETRY_FILES)."""

import json

import numpy as np
import pytest

from poseflow_train.data import MAGIC, Shard


def one_record_shard(folder):
    """A shard of one zero record beside a models folder, as
    training/make-data lays them out."""
    # Image 4 px, 2x2 tokens, 2 points: 16 + 36 + 12 + 12 + 16 + 16 + 4 + 4
    # bytes of ids to visibility, then 4 + 48 + 24 of tokens, image, points.
    info = {"dataset": str(folder / "elsewhere"), "image_size": 4, "patch_grid": 2, "point_count": 2,
            "record_bytes": 192}
    path = folder / "train.obs"
    path.write_bytes(MAGIC + b"\n" + json.dumps(info).encode() + b"\n" + bytes(192))
    return path


def test_a_shard_reads_the_shape_symmetries_when_asked_and_names_the_missing_file(tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "models_info.json").write_text("{}")
    path = one_record_shard(tmp_path)
    assert Shard(path).models_info.name == "models_info.json"
    with pytest.raises(ValueError, match="--shape-symmetries"):
        Shard(path, "shape")
    (tmp_path / "models" / "models_info_shape.json").write_text("{}")
    assert Shard(path, "shape").models_info.name == "models_info_shape.json"
    assert len(Shard(path, "shape")) == 1
    with pytest.raises(SystemExit, match="'texture'"):
        Shard(path, "texture")
    assert np.all(Shard(path).records["visib_fract"] == 0)
