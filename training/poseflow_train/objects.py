"""Writes `objects.json` beside an exported model: the BOP ids it was
trained on and each object's diameter (mm) from the training data's
`models_info.json`. `poseflow eval` compares it with the models directory it
is given, so that a model of one object set is not run on another set's
objects that happen to share ids (LM-O's 1 is the ape, YCB-V's 1 the master
chef can).

    python -m poseflow_train.objects --model ../models/poseflow-lmo10 \\
        --models-info ../objects/lmo/models_info.json ../objects/ycbv/mug-bowl/models_info.json
"""

import argparse
import json
from pathlib import Path

import onnx


def objects_entry(object_ids, models_info_paths):
    """{"object_ids": [...], "diameters_mm": [...]} from the first file that
    lists each id."""
    infos = [json.loads(Path(p).read_text()) for p in models_info_paths]
    diameters = []
    for obj_id in object_ids:
        found = next((info[str(obj_id)] for info in infos if str(obj_id) in info), None)
        if found is None:
            raise SystemExit(f"object {obj_id}: in none of {[str(p) for p in models_info_paths]}")
        diameters.append(round(float(found["diameter"]), 3))
    return {"object_ids": list(object_ids), "diameters_mm": diameters}


def write_objects(model_dir, object_ids, models_info_paths):
    path = Path(model_dir) / "objects.json"
    path.write_text(json.dumps(objects_entry(object_ids, models_info_paths), indent=1) + "\n")
    return path


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="model directory with encoder.onnx")
    parser.add_argument("--models-info", nargs="+", required=True, help="the training data's models_info.json files")
    args = parser.parse_args()
    encoder = onnx.load(str(Path(args.model) / "encoder.onnx"), load_external_data=False)
    meta = {p.key: p.value for p in encoder.metadata_props}
    print(write_objects(args.model, json.loads(meta["object_ids"]), args.models_info))


if __name__ == "__main__":
    main()
