//! The bad-input corpus (tests/corpus): every file is read by the parser a
//! stage would use. Files listed in tests/corpus/expected.toml must fail with
//! an error holding every listed fragment (what and where); the others are
//! valid inputs (also the fuzzers' seeds) and must load.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use poseflow_contracts::{MessageHeader, MessageVisitor, VelocityRequest, VelocityResponse, visit_message};
use poseflow_geometry::SymmetrySet;
use poseflow_geometry::models_info::ModelsInfo;
use poseflow_scene::bop::{ByImage, CameraEntry, GtEntry, read_json};

/// Reads one corpus entry as a stage would; the error as text.
type Reader = fn(&Path) -> Result<(), String>;

fn corpus() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/corpus"))
}

/// The mesh loader of the model library.
fn mesh(path: &Path) -> Result<(), String> {
    poseflow_scene::load_mesh(path, 1.0).map(|_| ()).map_err(|e| e.to_string())
}

/// The BOP JSON readers of the frame source and the model library, chosen
/// by file name (`scene_camera*`, `scene_gt*`, `models_info*`).
fn bop_json(path: &Path) -> Result<(), String> {
    let name = path.file_name().unwrap().to_string_lossy();
    let text = |e: poseflow_scene::SceneError| e.to_string();
    if name.starts_with("scene_camera") {
        let cameras: ByImage<CameraEntry> = read_json(path).map_err(text)?;
        for (&im_id, entry) in &cameras {
            entry.camera(640, 480, path, im_id).map_err(text)?;
            entry.camera_from_world(path, im_id).map_err(text)?;
        }
    } else if name.starts_with("scene_gt") {
        let truths: ByImage<Vec<GtEntry>> = read_json(path).map_err(text)?;
        for (&im_id, entries) in &truths {
            for (instance, entry) in entries.iter().enumerate() {
                entry.pose(path, im_id, instance).map_err(text)?;
            }
        }
    } else if name.starts_with("models_info") {
        let info = ModelsInfo::from_path(path).map_err(|e| e.to_string())?;
        for model in info.objects.values() {
            SymmetrySet::from_model_info(model, 0.2);
        }
    } else {
        panic!("{}: name it scene_camera*, scene_gt* or models_info*", path.display());
    }
    Ok(())
}

fn graph(path: &Path) -> Result<(), String> {
    poseflow_graph::load(path, &[]).map(|_| ()).map_err(|e| e.to_string())
}

/// A received message, as tests/corpus/make_messages.py lays it out: the
/// type's index, header bytes, f32 payload.
fn message(path: &Path) -> Result<(), String> {
    struct Check<'a>(&'a [u8]);
    impl Check<'_> {
        fn check<H: MessageHeader>(self) -> Result<(), String> {
            let size = std::mem::size_of::<H>();
            let header = self
                .0
                .get(..size)
                .and_then(poseflow_contracts::header_from_bytes::<H>)
                .ok_or_else(|| format!("{}: header of {} bytes, expected {size}", H::NAME, self.0.len()))?;
            let payload: Vec<f32> =
                self.0[size..].chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
            header.check_payload(&payload).map_err(|e| e.to_string())
        }
    }
    impl MessageVisitor for Check<'_> {
        type Output = Result<(), String>;
        fn visit<H: MessageHeader + Send + 'static>(self) -> Self::Output {
            self.check::<H>()
        }
    }
    let bytes = std::fs::read(path).unwrap();
    let (&kind, rest) = bytes.split_first().expect("a type byte");
    let names = poseflow_graph::PUBLISH_SUBSCRIBE_MESSAGES;
    match usize::from(kind) {
        i if i < names.len() => visit_message(names[i], Check(rest)).unwrap(),
        i if i == names.len() => Check(rest).check::<VelocityRequest>(),
        _ => Check(rest).check::<VelocityResponse>(),
    }
}

/// A model directory, as the inference stage loads it.
fn onnx_model(dir: &Path) -> Result<(), String> {
    poseflow_inference::PoseFlowModel::load(dir, 1).map(|_| ()).map_err(|e| e.to_string())
}

#[test]
fn every_bad_input_is_named_and_every_good_one_loads() {
    let text = std::fs::read_to_string(corpus().join("expected.toml")).unwrap();
    let mut expected: BTreeMap<String, Vec<String>> = toml::from_str::<toml::Table>(&text)
        .unwrap()
        .remove("errors")
        .and_then(|errors| errors.try_into().ok())
        .expect("an [errors] table of file = [fragments]");
    let readers: [(&str, Reader); 5] =
        [("models", mesh), ("bop", bop_json), ("graphs", graph), ("messages", message), ("onnx", onnx_model)];
    let mut failures = Vec::new();
    let mut checked = 0;
    for (dir, read) in readers {
        let mut entries: Vec<PathBuf> =
            std::fs::read_dir(corpus().join(dir)).unwrap().map(|e| e.unwrap().path()).collect();
        entries.sort();
        for path in entries {
            let key = format!("{dir}/{}", path.file_name().unwrap().to_string_lossy());
            checked += 1;
            match (read(&path), expected.remove(&key)) {
                (Ok(()), None) => {}
                (Ok(()), Some(_)) => failures.push(format!("{key}: loaded, expected an error")),
                (Err(err), None) => failures.push(format!("{key}: unexpected error: {err}")),
                (Err(err), Some(fragments)) => {
                    let missing: Vec<_> = fragments.iter().filter(|f| !err.contains(f.as_str())).collect();
                    if !missing.is_empty() {
                        failures.push(format!("{key}: error lacks {missing:?}: {err}"));
                    }
                }
            }
        }
    }
    failures.extend(expected.keys().map(|key| format!("{key}: listed but not in the corpus")));
    assert!(failures.is_empty(), "{} of {checked} corpus entries:\n{}", failures.len(), failures.join("\n"));
    assert!(checked >= 40, "{checked}");
}
