"""The model card generator's inputs."""

import torch

from poseflow_train.card import trained_run


def test_a_run_without_its_checkpoint_is_read_from_its_portable_weights(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    torch.save({"state": {"step": 7, "train_s": 1.0}, "encoder": {}, "velocity": {}}, run / "weights.pt")
    directory, saved = trained_run({"out": str(run)})
    assert directory == run and saved["state"]["step"] == 7
    # The full checkpoint, where there is one, is what the card describes.
    torch.save({"state": {"step": 9, "train_s": 2.0}, "encoder": {}, "velocity": {}}, run / "checkpoint.pt")
    assert trained_run({"out": str(run)})[1]["state"]["step"] == 9
