//! The exported fixture model (`models/test-tiny`) through ONNX Runtime
//! gives the outputs PyTorch gave on the stored inputs, within 1e-4; broken
//! model directories are rejected with the file and what was expected.

mod common;

use std::path::PathBuf;

use common::{max_difference, model_dir, parity, parity_of};
use poseflow_inference::parity::{OutputDrift, ParityVectors, output_drift};
use poseflow_inference::{Condition, EncoderInput, GraspFlowModel, PoseFlowModel, Precision};

#[test]
fn onnx_runtime_matches_pytorch_on_the_stored_vectors() {
    let mut model = PoseFlowModel::load(&model_dir(), 1).unwrap();
    assert_eq!((model.info.image_size, model.info.patch_grid, model.info.point_count), (112, 8, 1024));
    assert_eq!(model.info.object_ids, [1, 5, 6, 8, 9, 10, 11, 12]);
    let v = parity();
    let condition = model.encode(&v["image"], &v["token_mask"], &v["points"], v["object_index"][0] as usize).unwrap();
    assert!(max_difference(&condition.tokens, &v["condition"]) < 1e-4);
    assert_eq!(condition.mask, v["condition_mask"]);
    // The velocity net on the stored condition (not the recomputed one), so
    // each network is checked on its own inputs.
    let stored = Condition {
        tokens: v["condition"].clone(),
        mask: v["condition_mask"].clone(),
        cross_kv: Vec::new(),
        serial: 0,
    };
    let out = model.velocity(&stored, &v["rotation"], &v["translation"], &v["t"]).unwrap();
    assert!(max_difference(&out.rotation, &v["v_rot"]) < 1e-4, "{:?}", out.rotation);
    assert!(max_difference(&out.translation, &v["v_pos"]) < 1e-4);
    // Dynamic batch: 50 samples at once, each as it is alone.
    let rotations: Vec<f32> = v["rotation"].iter().copied().cycle().take(50 * 9).collect();
    let translations: Vec<f32> = v["translation"].iter().copied().cycle().take(50 * 3).collect();
    let t: Vec<f32> = v["t"].iter().copied().cycle().take(50).collect();
    let batch = model.velocity(&stored, &rotations, &translations, &t).unwrap();
    assert!(max_difference(&batch.rotation[45 * 3..], &v["v_rot"]) < 1e-4);
}

/// Every model shipped in `models/` (the default one included) reproduces
/// its own stored vectors.
#[test]
fn every_shipped_model_reproduces_its_parity_vectors() {
    let models = model_dir().parent().unwrap().to_path_buf();
    let mut checked = Vec::new();
    for entry in std::fs::read_dir(&models).unwrap() {
        let dir = entry.unwrap().path();
        if !dir.join("parity.json").is_file() {
            continue;
        }
        if dir.join("grasp_encoder.onnx").is_file() {
            check_grasp_flow(&dir);
            checked.push(dir.file_name().unwrap().to_string_lossy().into_owned());
            continue;
        }
        check_pose_flow(&dir);
        checked.push(dir.file_name().unwrap().to_string_lossy().into_owned());
    }
    for shipped in ["test-tiny", "poseflow-lmo10", "grasp-flow"] {
        assert!(checked.contains(&shipped.to_string()), "{checked:?}");
    }
}

/// A PoseFlow model directory reproduces its stored vectors (B stored
/// observations of G samples each), encoded and sampled as one batch and
/// one observation at a time; its INT8 files, when it has them, stay near.
fn check_pose_flow(dir: &std::path::Path) {
    let v = parity_of(dir);
    let mut model = PoseFlowModel::load(dir, 1).unwrap();
    let b = v["object_index"].len();
    let g = v["t"].len() / b;
    let part = |name: &str, i: usize| {
        let values = &v[name];
        let per = values.len() / b;
        &values[i * per..(i + 1) * per]
    };
    let inputs: Vec<EncoderInput> = (0..b)
        .map(|i| EncoderInput {
            image: part("image", i),
            token_mask: part("token_mask", i),
            points: part("points", i),
            object_index: part("object_index", i)[0] as usize,
        })
        .collect();
    let conditions = model.encode_batch(&inputs).unwrap();
    let tokens: Vec<f32> = conditions.iter().flat_map(|c| c.tokens.iter().copied()).collect();
    assert!(max_difference(&tokens, &v["condition"]) < 1e-4, "{}", dir.display());
    // The velocity network on the stored condition where the contract has no
    // cached keys and values (each network on its own inputs), else on the
    // encoder's.
    let stored: Vec<Condition> = (0..b)
        .map(|i| Condition {
            tokens: part("condition", i).to_vec(),
            mask: part("condition_mask", i).to_vec(),
            cross_kv: conditions[i].cross_kv.clone(),
            serial: 0,
        })
        .collect();
    let all: Vec<&Condition> = stored.iter().collect();
    let batch = model.velocity_batch(&all, &v["rotation"], &v["translation"], &v["t"]).unwrap();
    assert!(max_difference(&batch.rotation, &v["v_rot"]) < 1e-4, "{}", dir.display());
    assert!(max_difference(&batch.translation, &v["v_pos"]) < 1e-4, "{}", dir.display());
    // One observation at a time gives what the batch gave.
    for (i, input) in inputs.iter().enumerate() {
        let alone = model.encode_batch(std::slice::from_ref(input)).unwrap().pop().unwrap();
        assert!(max_difference(&alone.tokens, &conditions[i].tokens) < 1e-5, "{}", dir.display());
        assert!(max_difference(&alone.cross_kv, &conditions[i].cross_kv) < 1e-5, "{}", dir.display());
        let samples = i * g..(i + 1) * g;
        let out = model
            .velocity(
                &stored[i],
                &v["rotation"][9 * samples.start..9 * samples.end],
                &v["translation"][3 * samples.start..3 * samples.end],
                &v["t"][samples.clone()],
            )
            .unwrap();
        assert!(max_difference(&out.rotation, &batch.rotation[3 * samples.start..3 * samples.end]) < 1e-5);
        assert!(max_difference(&out.translation, &batch.translation[3 * samples.start..3 * samples.end]) < 1e-5);
    }
    if dir.join(Precision::Int8.files()[0]).is_file() {
        // Dynamic quantisation with 7-bit weights moves outputs by a few
        // per cent of their range on every x86 CPU; full 8-bit weights
        // overflowed ONNX Runtime's u8 × s8 sums on CPUs without VNNI and
        // moved them by 9–20 %.
        let mut int8 = PoseFlowModel::load_as(dir, 1, Precision::Int8).unwrap();
        let drift = output_drift(&mut int8, &ParityVectors::read(dir).unwrap().unwrap()).unwrap();
        assert!(drift.within(&OutputDrift::INT8_LIMITS), "{}: {drift:?}", dir.display());
    }
}

/// A grasp flow model directory reproduces its stored vectors, and a
/// batch of several clouds gives each cloud's grasps what it gives alone.
fn check_grasp_flow(dir: &std::path::Path) {
    let mut model = GraspFlowModel::load(dir, 1).unwrap();
    let v = parity_of(dir);
    let condition = model.encode(&v["points"]).unwrap();
    assert!(max_difference(&condition, &v["condition"]) < 1e-4, "{}", dir.display());
    let out = model.velocity(&v["condition"], &v["rotation"], &v["translation"], &v["t"]).unwrap();
    assert!(max_difference(&out.rotation, &v["v_rot"]) < 1e-4, "{}", dir.display());
    assert!(max_difference(&out.translation, &v["v_pos"]) < 1e-4, "{}", dir.display());
    // The stored inputs are two clouds with three grasps each: the second
    // cloud alone gives its three grasps the same velocities.
    let per_cloud = v["condition"].len() / 2;
    let alone = model
        .velocity(&v["condition"][per_cloud..], &v["rotation"][27..], &v["translation"][9..], &v["t"][3..])
        .unwrap();
    assert!(max_difference(&alone.rotation, &v["v_rot"][9..]) < 1e-4, "{}", dir.display());
    let err = model.velocity(&v["condition"], &v["rotation"][..45], &v["translation"][..15], &v["t"][..5]).unwrap_err();
    assert!(err.to_string().contains("B × G grasps"), "{err}");
}

#[test]
fn broken_model_directories_are_named() {
    let err = PoseFlowModel::load(&PathBuf::from("/nonexistent-model"), 1).unwrap_err().to_string();
    assert!(err.contains("/nonexistent-model/encoder.onnx") && err.contains("no such file"), "{err}");
    // The velocity net where the encoder should be: wrong inputs.
    let dir = std::env::temp_dir().join(format!("poseflow-inference-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(model_dir().join("velocity.onnx"), dir.join("encoder.onnx")).unwrap();
    std::fs::copy(model_dir().join("velocity.onnx"), dir.join("velocity.onnx")).unwrap();
    let err = PoseFlowModel::load(&dir, 1).unwrap_err().to_string();
    assert!(err.contains("encoder.onnx"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
