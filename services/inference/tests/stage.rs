//! The inference stage in-process: encoder once per observation, velocity
//! requests answered from the cached condition in the contract's layout and
//! frame, every failure answered with a status.

mod common;

use std::collections::BTreeMap;

use common::{max_difference, model_dir, parity, parity_of};
use poseflow_contracts::{Header, MessageHeader, ObservationHeader, VelocityRequest, VelocitySegment, status};
use poseflow_inference::stage::{InferenceParams, InferenceStage};
use poseflow_inference::{PoseFlowModel, Precision};
use poseflow_runtime::{EmitError, Emitter, Input, Transform};

fn stage(cache: usize) -> InferenceStage {
    InferenceStage::with_model(PoseFlowModel::load(&model_dir(), 1).unwrap(), cache)
}

/// The stored observation as an Observation message whose points are
/// divided by `point_scale`.
fn observation(v: &BTreeMap<String, Vec<f32>>, object_id: u32, point_scale: f32) -> (ObservationHeader, Vec<f32>) {
    let header = ObservationHeader {
        header: Header::new(7, object_id),
        centroid: [0.1, -0.05, 0.8],
        point_scale,
        crop: [100.0, 80.0, 212.0, 192.0],
        image_size: 112,
        patch_grid: 8,
        point_count: 1024,
        valid_point_count: 1024,
        ..ObservationHeader::default()
    };
    let points = v["points"].iter().map(|x| x / point_scale);
    let payload: Vec<f32> = v["image"].iter().chain(&v["token_mask"]).copied().chain(points).collect();
    header.check_payload(&payload).unwrap();
    (header, payload)
}

/// The first of the stored observations (its image, token mask and
/// points), with every stored pose.
fn first_observation(v: &BTreeMap<String, Vec<f32>>) -> BTreeMap<String, Vec<f32>> {
    let observations = v["object_index"].len();
    ["image", "token_mask", "points"]
        .iter()
        .map(|&name| (name.to_string(), v[name][..v[name].len() / observations].to_vec()))
        .chain(["rotation", "translation"].iter().map(|&name| (name.to_string(), v[name].clone())))
        .collect()
}

/// The stored poses as a request payload (R row-major, t), translations
/// divided by `point_scale`.
fn poses(v: &BTreeMap<String, Vec<f32>>, point_scale: f32) -> Vec<f32> {
    v["rotation"]
        .chunks_exact(9)
        .zip(v["translation"].chunks_exact(3))
        .flat_map(|(r, t)| r.iter().copied().chain(t.iter().map(|x| x / point_scale)))
        .collect()
}

fn request(condition_id: u64, sample_count: u32, t: f32) -> VelocityRequest {
    VelocityRequest {
        step_index: 1,
        step_count: 5,
        ..VelocityRequest::single(Header::new(7, 1), condition_id, 3, sample_count, t)
    }
}

/// Observations that arrived together are encoded in one run, and one
/// request of several segments (observations at other scales, sample
/// counts and flow times) is answered as each segment is alone, under both
/// contracts (the fixture is `poseflow-onnx/1`, the default model `/2`).
#[test]
fn held_observations_and_segmented_requests_match_one_by_one() {
    let default_model = model_dir().parent().unwrap().join("poseflow-lmo10");
    for dir in [model_dir(), default_model] {
        let first = first_observation(&parity_of(&dir));
        let mut together = InferenceStage::with_model(PoseFlowModel::load(&dir, 1).unwrap(), 8);
        let mut alone = InferenceStage::with_model(PoseFlowModel::load(&dir, 1).unwrap(), 8);
        let scales = [1.0, 0.5];
        let mut handles = Vec::new();
        for &scale in &scales {
            let (header, payload) = observation(&first, 5, scale);
            together.hold(&header, &payload).unwrap();
            handles.push(alone.encode(&header, &payload).unwrap());
        }
        assert_eq!(together.held(), 2);
        let held = together.encode_held().unwrap();
        assert_eq!(together.held(), 0);
        // Segments of 5 and 3 samples at different flow times.
        let counts = [5usize, 3];
        let times = [0.2f32, 0.8];
        let mut joint = VelocityRequest { header: Header::new(7, 5), ..Default::default() };
        let mut payload = Vec::new();
        let mut expected = Vec::new();
        for (k, handle) in held.iter().enumerate() {
            joint.push(VelocitySegment {
                condition_id: handle.condition_id,
                sample_count: counts[k] as u32,
                t: times[k],
            });
            let part = &poses(&first, scales[k])[..counts[k] * 12];
            payload.extend_from_slice(part);
            let mut out = vec![0.0; counts[k] * 6];
            alone.velocities(&request(handles[k].condition_id, counts[k] as u32, times[k]), part, &mut out).unwrap();
            expected.extend(out);
        }
        joint.check_payload(&payload).unwrap();
        let mut out = vec![0.0; expected.len()];
        together.velocities(&joint, &payload, &mut out).unwrap();
        assert!(max_difference(&out, &expected) < 1e-4, "{}", dir.display());
        // A segment whose condition is unknown fails the whole request.
        joint.segments[1].condition_id ^= 1 << 40;
        assert_eq!(together.velocities(&joint, &payload, &mut out), Err(status::UNKNOWN_CONDITION));
    }
}

/// The handles the stage emits.
#[derive(Default)]
struct Handles(Vec<poseflow_contracts::ConditionHandle>);

impl Emitter<poseflow_contracts::ConditionHandle> for Handles {
    fn emit(
        &mut self,
        header: poseflow_contracts::ConditionHandle,
        _: usize,
        _: &mut dyn FnMut(&mut [f32]),
    ) -> Result<(), EmitError> {
        self.0.push(header);
        Ok(())
    }
}

/// `encode = "on-request"`: the handles go out as the Observations come,
/// with nothing encoded; a request encodes the observations it names (in
/// one run) and answers what encoding on arrival answers; one never asked
/// for is never encoded. A category model cannot defer (its handle carries
/// the encoder's size).
#[test]
fn observations_encoded_on_request_give_the_velocities_of_encoding_on_arrival() {
    let dir = model_dir().parent().unwrap().join("poseflow-lmo10");
    let first = first_observation(&parity_of(&dir));
    let params = |encode: &str| {
        let json = serde_json::json!({"model": dir, "precision": "fp32", "threads": 1, "encode": encode});
        InferenceParams::from_json(&json).unwrap()
    };
    let mut lazy = InferenceStage::new(&params("on-request")).unwrap();
    let mut eager = InferenceStage::new(&params("on-arrival")).unwrap();
    let (mut lazy_handles, mut eager_handles) = (Handles::default(), Handles::default());
    let scales = [1.0, 0.5, 0.8];
    for (k, &scale) in scales.iter().enumerate() {
        let (mut header, payload) = observation(&first, 5, scale);
        if k + 1 < scales.len() {
            header.header.flags |= poseflow_contracts::flags::MORE_IN_FRAME;
        }
        lazy.process(Input { header: &header, payload: &payload }, &mut lazy_handles).unwrap();
        assert_eq!(lazy_handles.0.len(), k + 1, "a handle per observation at once");
        eager.process(Input { header: &header, payload: &payload }, &mut eager_handles).unwrap();
    }
    assert_eq!((lazy.encoder_inputs(), eager.encoder_inputs()), (0, 3));
    let strip = |h: &poseflow_contracts::ConditionHandle| poseflow_contracts::ConditionHandle { condition_id: 0, ..*h };
    let lazy_fields: Vec<_> = lazy_handles.0.iter().map(strip).collect();
    assert_eq!(lazy_fields, eager_handles.0.iter().map(strip).collect::<Vec<_>>());

    // One request naming the first and third observations.
    let answer = |stage: &mut InferenceStage, handles: &Handles| {
        let mut joint = VelocityRequest { header: Header::new(7, 5), ..Default::default() };
        let mut payload = Vec::new();
        for k in [0, 2] {
            joint.push(VelocitySegment { condition_id: handles.0[k].condition_id, sample_count: 4, t: 0.3 });
            payload.extend_from_slice(&poses(&first, scales[k])[..4 * 12]);
        }
        let mut out = vec![0.0; 8 * 6];
        stage.velocities(&joint, &payload, &mut out).unwrap();
        out
    };
    let (from_lazy, from_eager) = (answer(&mut lazy, &lazy_handles), answer(&mut eager, &eager_handles));
    assert!(max_difference(&from_lazy, &from_eager) < 1e-5);
    assert_eq!(lazy.encoder_inputs(), 2, "the second observation was never asked for");
    // Asked again: already encoded.
    answer(&mut lazy, &lazy_handles);
    assert_eq!(lazy.encoder_inputs(), 2);

    let category = serde_json::json!({"model": model_dir().parent().unwrap().join("test-tiny-cat"), "precision": "fp32", "threads": 1, "encode": "on-request"});
    let error = InferenceStage::new(&InferenceParams::from_json(&category).unwrap()).unwrap_err().to_string();
    assert!(error.contains("`encode`") && error.contains("category-level"), "{error}");
    let error = InferenceParams::from_json(&serde_json::json!({"encode": "later"})).unwrap_err().to_string();
    assert!(error.contains("later") && error.contains("on-request"), "{error}");
}

#[test]
fn velocities_come_from_the_cached_condition_as_v_then_omega() {
    let v = parity();
    let obj = 5; // object index 1 of the fixture's [1, 5, 6, ...]
    let mut stage = stage(4);
    let (header, payload) = observation(&v, obj, 1.0);
    let handle = stage.encode(&header, &payload).unwrap();
    assert_eq!((handle.image_tokens, handle.point_tokens, handle.model_width), (64, 33, 64));
    assert_eq!(handle.active_image_tokens as usize, v["token_mask"].iter().filter(|&&m| m > 0.5).count());
    assert_eq!((handle.centroid, handle.point_scale), (header.centroid, 1.0));

    let n = v["t"].len();
    let t = 0.4f32;
    let mut out = vec![0.0; n * 6];
    stage.velocities(&request(handle.condition_id, n as u32, t), &poses(&v, 1.0), &mut out).unwrap();

    let mut reference = PoseFlowModel::load(&model_dir(), 1).unwrap();
    let condition = reference.encode(&v["image"], &v["token_mask"], &v["points"], 1).unwrap();
    let expected = reference.velocity(&condition, &v["rotation"], &v["translation"], &vec![t; n]).unwrap();
    let v_pos: Vec<f32> = out.chunks_exact(6).flat_map(|o| o[..3].to_vec()).collect();
    let omega: Vec<f32> = out.chunks_exact(6).flat_map(|o| o[3..].to_vec()).collect();
    assert!(max_difference(&v_pos, &expected.translation) < 1e-5);
    assert!(max_difference(&omega, &expected.rotation) < 1e-5);

    // The same observation in units of 0.5 m: velocities scale, ω does not.
    let (scaled_header, scaled_payload) = observation(&v, obj, 0.5);
    let scaled = stage.encode(&scaled_header, &scaled_payload).unwrap();
    assert_ne!(scaled.condition_id, handle.condition_id);
    let mut scaled_out = vec![0.0; n * 6];
    stage.velocities(&request(scaled.condition_id, n as u32, t), &poses(&v, 0.5), &mut scaled_out).unwrap();
    let rescaled: Vec<f32> =
        scaled_out.chunks_exact(6).flat_map(|o| [o[0] * 0.5, o[1] * 0.5, o[2] * 0.5, o[3], o[4], o[5]]).collect();
    assert!(max_difference(&rescaled, &out) < 1e-4);
}

#[test]
fn an_evicted_or_foreign_condition_is_unknown_and_bad_poses_are_invalid() {
    let v = parity();
    let mut stage = stage(1);
    let (header, payload) = observation(&v, 1, 1.0);
    let first = stage.encode(&header, &payload).unwrap();
    let second = stage.encode(&header, &payload).unwrap();
    let n = v["t"].len();
    let mut out = vec![0.0; n * 6];
    let mut ask = |id, poses: &[f32]| stage.velocities(&request(id, n as u32, 0.2), poses, &mut out);
    assert_eq!(ask(first.condition_id, &poses(&v, 1.0)), Err(status::UNKNOWN_CONDITION));
    assert_eq!(ask(second.condition_id ^ (1 << 40), &poses(&v, 1.0)), Err(status::UNKNOWN_CONDITION));
    assert_eq!(ask(second.condition_id, &poses(&v, 1.0)), Ok(()));
    let mut broken = poses(&v, 1.0);
    broken[4] = f32::NAN;
    assert_eq!(ask(second.condition_id, &broken), Err(status::INVALID_REQUEST));
}

#[test]
fn observations_the_model_cannot_take_are_rejected_with_the_reason() {
    let v = parity();
    let mut stage = stage(2);
    let (header, payload) = observation(&v, 2, 1.0);
    let err = stage.encode(&header, &payload).unwrap_err().to_string();
    assert!(err.contains("frame 7") && err.contains("object 2 is not one the model knows"), "{err}");

    let (mut header, _) = observation(&v, 1, 1.0);
    header.image_size = 224;
    header.patch_grid = 16;
    let payload = vec![0.0; header.payload_len().unwrap()];
    let err = stage.encode(&header, &payload).unwrap_err().to_string();
    assert!(err.contains("image_size 224") && err.contains("expects 112"), "{err}");
}

/// INT8 files whose outputs drift from the stored FP32 ones (here the
/// YCB-V model's INT8 networks beside the default model's FP32 ones and
/// parity vectors: the same contract, other weights) are not served; the
/// stage serves the FP32 networks. The default model's own INT8 files are
/// served.
#[test]
fn int8_networks_that_drift_from_fp32_are_replaced_by_fp32() {
    let models = model_dir().parent().unwrap().to_path_buf();
    let params = |dir: &std::path::Path| {
        InferenceParams::from_json(&serde_json::json!({ "model": dir, "precision": "int8", "threads": 1 })).unwrap()
    };
    let stage = InferenceStage::new(&params(&models.join("poseflow-lmo10"))).unwrap();
    assert_eq!(stage.precision(), Precision::Int8);

    let mixed = std::env::temp_dir().join(format!("poseflow-int8-drift-{}", std::process::id()));
    std::fs::create_dir_all(&mixed).unwrap();
    for file in ["encoder.onnx", "velocity.onnx", "parity.json", "parity.bin"] {
        std::fs::copy(models.join("poseflow-lmo10").join(file), mixed.join(file)).unwrap();
    }
    for file in Precision::Int8.files() {
        std::fs::copy(models.join("poseflow-ycbv").join(file), mixed.join(file)).unwrap();
    }
    let stage = InferenceStage::new(&params(&mixed));
    std::fs::remove_dir_all(&mixed).unwrap();
    assert_eq!(stage.unwrap().precision(), Precision::Fp32);
}

#[test]
fn parameters_name_the_key_that_is_wrong() {
    let params = InferenceParams::from_json(&serde_json::json!({ "model": "models/x" })).unwrap();
    assert_eq!((params.threads, params.cache, params.batch), (2, 8, 8));
    let err = InferenceParams::from_json(&serde_json::json!({ "batch": 0 })).unwrap_err().to_string();
    assert!(err.contains("`batch`") && err.contains("1 to 64"), "{err}");
    let err = InferenceParams::from_json(&serde_json::json!({ "precision": "fp16" })).unwrap_err().to_string();
    assert!(err.contains("fp16") && err.contains("fp32") && err.contains("int8"), "{err}");
    let err = InferenceParams::from_json(&serde_json::json!({ "threads": 0 })).unwrap_err().to_string();
    assert!(err.contains("`threads`") && err.contains("1 to 64"), "{err}");
    let err = InferenceParams::from_json(&serde_json::json!({ "modle": "x" })).unwrap_err().to_string();
    assert!(err.contains("modle"), "{err}");
}

/// A category-level model (`models/test-tiny-cat`, an untrained contract
/// fixture): object ids reach it through the `classes` file (or as
/// category codes), and each Condition carries the category and the size
/// the encoder put in its last token.
#[test]
fn a_category_model_takes_classes_and_hands_on_its_category_and_size() {
    let dir = model_dir().parent().unwrap().join("test-tiny-cat");
    let v = parity_of(&dir);
    let first = first_observation(&v);
    let scratch = std::env::temp_dir().join(format!("poseflow-classes-{}", std::process::id()));
    std::fs::create_dir_all(&scratch).unwrap();
    let classes = scratch.join("categories.json");
    // The fixture's first stored observation is object index 0: code 1, bottle.
    std::fs::write(&classes, r#"{"17": {"category": "bottle", "seed": 3}, "18": {"category": "mug"}}"#).unwrap();
    let params = |classes: Option<&std::path::Path>| {
        let mut json = serde_json::json!({"model": dir, "precision": "fp32", "threads": 1});
        if let Some(path) = classes {
            json["classes"] = serde_json::json!(path);
        }
        InferenceParams::from_json(&json).unwrap()
    };
    let mut stage = InferenceStage::new(&params(Some(&classes))).unwrap();
    let (header, payload) = observation(&first, 17, 1.0);
    let handle = stage.encode(&header, &payload).unwrap();
    assert_eq!(handle.category.code, 1);
    // The size is the stored condition's last token, values 12..15, times the
    // translation scale (0.05 m).
    let (tokens, width) = (handle.image_tokens + handle.point_tokens, handle.model_width);
    let last = (tokens as usize - 1) * width as usize;
    let expected: Vec<f32> = v["condition"][last + 12..last + 15].iter().map(|x| x * 0.05).collect();
    assert!(max_difference(&handle.category.size, &expected) < 1e-5, "{:?} vs {expected:?}", handle.category.size);
    assert!(handle.category.size.iter().all(|s| *s > 0.0));
    // An object the file does not list is refused by name.
    let (unlisted, payload_unlisted) = observation(&first, 19, 1.0);
    let error = stage.encode(&unlisted, &payload_unlisted).unwrap_err().to_string();
    assert!(error.contains("object 19 has no category"), "{error}");

    // Without `classes`, object ids are category codes.
    let mut direct = InferenceStage::new(&params(None)).unwrap();
    let (bottle, payload_bottle) = observation(&first, 1, 1.0);
    assert_eq!(direct.encode(&bottle, &payload_bottle).unwrap().category, handle.category);
    let error = direct.encode(&unlisted, &payload_unlisted).unwrap_err().to_string();
    assert!(error.contains("category codes") && error.contains("classes"), "{error}");

    // A category the model lacks, and `classes` for an instance-level model.
    std::fs::write(&classes, r#"{"17": {"category": "laptop"}}"#).unwrap();
    let error = InferenceStage::new(&params(Some(&classes))).unwrap_err().to_string();
    assert!(error.contains("object 17") && error.contains("\"laptop\""), "{error}");
    let instance = serde_json::json!({"model": model_dir(), "precision": "fp32", "threads": 1, "classes": classes});
    let error = InferenceStage::new(&InferenceParams::from_json(&instance).unwrap()).unwrap_err().to_string();
    assert!(error.contains("instance-level"), "{error}");
    std::fs::remove_dir_all(&scratch).unwrap();
}
