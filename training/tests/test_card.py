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


def test_the_architecture_names_the_coarse_pose_check_only_when_the_encoder_has_one(tmp_path):
    import json

    import onnx
    from onnx import helper

    from poseflow_train.card import verification_text

    def write(meta):
        graph = helper.make_graph([], "g", [], [])
        model = helper.make_model(graph)
        for key, value in meta.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(model, str(tmp_path / "encoder.onnx"))

    write({"contract": "poseflow-onnx/2"})
    assert verification_text(tmp_path) == ""
    write({"contract": "poseflow-onnx/2", "coarse_verification": json.dumps({"turns": 24, "surface_points": 1000})})
    text = verification_text(tmp_path)
    assert "other 23 turns" in text and "1,000 points" in text
