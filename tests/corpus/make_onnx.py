#!/usr/bin/env python3
"""Builds tests/corpus/onnx: tiny PoseFlow model directories whose networks
break the ONNX contract (services/inference/src/model.rs) in one place each.
Needs the `onnx` package only (not PyTorch):

    python3 -m venv /tmp/onnxgen && /tmp/onnxgen/bin/pip install onnx==1.17.0
    /tmp/onnxgen/bin/python tests/corpus/make_onnx.py tests/corpus/onnx

The graphs compute nothing useful (constants and Identity nodes): the
inference stage must reject them at load, before any inference.
"""
import json
import sys
from pathlib import Path

import onnx
from onnx import TensorProto, helper

F, I = TensorProto.FLOAT, TensorProto.INT64
TOKENS, WIDTH = 4, 8
METADATA = {
    "contract": "poseflow-onnx/1", "image_size": 112, "patch_grid": 8, "point_count": 1024, "width": WIDTH,
    "normalisation_mean": [0.485, 0.456, 0.406], "normalisation_std": [0.229, 0.224, 0.225],
    "translation_noise_std": 0.05, "object_ids": [1], "translation_scale": 0.1,
}


def model(inputs, outputs, nodes, name):
    graph = helper.make_graph(nodes, name, inputs, outputs)
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    for key, value in METADATA.items():
        entry = m.metadata_props.add()
        entry.key, entry.value = key, json.dumps(value)
    onnx.checker.check_model(m)
    return m


def constant(name, shape):
    values = helper.make_tensor(name + "_value", F, shape, [0.0] * int(__import__("math").prod(shape)))
    return helper.make_node("Constant", [], [name], value=values)


def encoder(image_size):
    inputs = [
        helper.make_tensor_value_info("image", F, ["B", 3, image_size, image_size]),
        helper.make_tensor_value_info("token_mask", F, ["B", 64]),
        helper.make_tensor_value_info("points", F, ["B", 1024, 3]),
        helper.make_tensor_value_info("object_index", I, ["B"]),
    ]
    outputs = [
        helper.make_tensor_value_info("condition", F, ["B", "T", WIDTH]),
        helper.make_tensor_value_info("condition_mask", F, ["B", "T"]),
    ]
    nodes = [constant("condition", [1, TOKENS, WIDTH]), constant("condition_mask", [1, TOKENS])]
    return model(inputs, outputs, nodes, "encoder")


def velocity(rotation_shape):
    inputs = [
        helper.make_tensor_value_info("condition", F, [1, TOKENS, WIDTH]),
        helper.make_tensor_value_info("condition_mask", F, [1, TOKENS]),
        helper.make_tensor_value_info("rotation", F, rotation_shape),
        helper.make_tensor_value_info("translation", F, ["M", 3]),
        helper.make_tensor_value_info("t", F, ["M"]),
    ]
    outputs = [
        helper.make_tensor_value_info("v_rot", F, ["M", 3]),
        helper.make_tensor_value_info("v_pos", F, ["M", 3]),
    ]
    nodes = [helper.make_node("Identity", ["translation"], ["v_rot"]),
             helper.make_node("Identity", ["translation"], ["v_pos"])]
    return model(inputs, outputs, nodes, "velocity")


def main(target):
    target = Path(target)
    cases = {
        # S = 64 in the graph, 112 in the metadata.
        "encoder-image-size": (encoder(64), velocity(["M", 3, 3])),
        # Rotations as quaternions instead of 3x3 matrices.
        "velocity-rotation-shape": (encoder(112), velocity(["M", 4])),
    }
    for name, (enc, vel) in cases.items():
        (target / name).mkdir(parents=True, exist_ok=True)
        onnx.save(enc, target / name / "encoder.onnx")
        onnx.save(vel, target / name / "velocity.onnx")


if __name__ == "__main__":
    main(*sys.argv[1:])
