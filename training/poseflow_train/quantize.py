"""Writes the INT8 files of an exported model directory: ONNX Runtime's
dynamic quantisation (weights INT8, activations quantised per run) of the
matrix products of `encoder.onnx` and `velocity.onnx`.

    python -m poseflow_train.quantize --model ../models/poseflow-lmo10

writes `encoder.int8.onnx` and `velocity.int8.onnx` beside the FP32 files
(same inputs, outputs and metadata, so the same contract), and prints how
far their outputs move on the stored parity inputs. The inference stage
serves them with `precision = "int8"`; their accuracy is measured with
`python -m poseflow_train.evaluate --precision int8`.
"""

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
from onnxruntime.quantization import QuantType, quantize_dynamic
from onnxruntime.quantization.shape_inference import quant_pre_process

NETWORKS = ("encoder", "velocity")


def quantise(source, target):
    with tempfile.TemporaryDirectory() as scratch:
        prepared = Path(scratch) / "prepared.onnx"
        quant_pre_process(str(source), str(prepared), skip_symbolic_shape=True)
        # Weights in 7 bits (reduce_range): x86 CPUs without VNNI multiply u8
        # activations by s8 weights in a 16-bit pairwise sum that saturates
        # for full-range weights (the encoder's outputs moved by 0.68 on an
        # AVX2-only CPU, 0.05 with 7 bits; docs/network.md). ONNX Runtime's
        # own remedy, a session option that rewrites the weights as u8, fails
        # to load these graphs in 1.32.
        quantize_dynamic(str(prepared), str(target), weight_type=QuantType.QInt8, reduce_range=True,
                         op_types_to_quantize=["MatMul", "Gemm"])
    # The metadata (contract, sizes, object ids) as the FP32 file has it.
    original, quantised = onnx.load(str(source)), onnx.load(str(target))
    del quantised.metadata_props[:]
    for entry in original.metadata_props:
        quantised.metadata_props.add(key=entry.key, value=entry.value)
    quantised.metadata_props.add(key="precision", value="int8")
    onnx.save(quantised, str(target))


def parity_inputs(model_dir):
    index = json.loads((model_dir / "parity.json").read_text())
    blob = (model_dir / "parity.bin").read_bytes()
    arrays = {}
    for name, entry in index.items():
        dtype = "<i8" if entry["dtype"] == "i64" else "<f4"
        count = int(np.prod(entry["shape"]))
        arrays[name] = np.frombuffer(blob, dtype, count, entry["offset"]).reshape(entry["shape"]).copy()
    return arrays


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="an exported model directory (poseflow_train.export)")
    args = parser.parse_args()
    model_dir = Path(args.model)
    moved = {}
    stored = parity_inputs(model_dir)
    for network in NETWORKS:
        source, target = model_dir / f"{network}.onnx", model_dir / f"{network}.int8.onnx"
        quantise(source, target)
        sessions = [onnxruntime.InferenceSession(str(path)) for path in (source, target)]
        if network == "encoder" and len(sessions[0].get_outputs()) > 2:
            encoded = sessions[0].run(None, {i.name: stored[i.name] for i in sessions[0].get_inputs()})
            # poseflow-onnx/2: the velocity network's cached keys and values
            # are not stored.
            stored["cross_kv"] = encoded[2]
        feed = {i.name: stored[i.name] for i in sessions[0].get_inputs()}
        full, quantised = (session.run(None, feed) for session in sessions)
        moved[network] = {output.name: float(np.abs(a - b).max())
                          for output, a, b in zip(sessions[0].get_outputs(), full, quantised)}
    sizes = {f.name: f.stat().st_size for f in sorted(model_dir.glob("*.int8.onnx"))}
    print(json.dumps({"model": str(model_dir), "sizes": sizes, "max_abs_difference_on_parity_inputs": moved}))


if __name__ == "__main__":
    main()
