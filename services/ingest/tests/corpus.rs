//! The bad-input corpus (`tests/corpus/ingest`, built by
//! `tests/corpus/make_ingest_corpus.py`): every kind of broken input gets an
//! error naming the file or frame, the object and what was expected, and
//! the frames after it are still read.

use std::path::PathBuf;

use poseflow_geometry::sampling::seeded_rng;
use poseflow_ingest::sources::{BopFrames, FrameSource, Masks};
use poseflow_ingest::{IngestParams, check_frame, prepare};

fn corpus() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/corpus/ingest"))
}

/// What became of each frame: the observations made, or the errors.
fn outcomes() -> Vec<(usize, Vec<String>)> {
    let mut frames = BopFrames::open(&corpus(), "test", &[], None, Masks::GroundTruth).unwrap();
    let params = IngestParams { image_size: 56, patch_grid: 4, point_count: 64, ..IngestParams::default() };
    let mut outcomes = Vec::new();
    while let Some(loaded) = frames.next_frame() {
        let loaded = match loaded {
            Ok(loaded) => loaded,
            Err(err) => {
                outcomes.push((0, vec![err.to_string()]));
                continue;
            }
        };
        let mut errors: Vec<String> = loaded.skipped.iter().map(ToString::to_string).collect();
        if let Err(err) = check_frame(&loaded.frame) {
            outcomes.push((0, vec![err.to_string()]));
            continue;
        }
        let mut observed = 0;
        for object in &loaded.objects {
            match prepare(&loaded.frame, object, &params, &mut seeded_rng(0)) {
                Ok(_) => observed += 1,
                Err(err) => errors.push(err.to_string()),
            }
        }
        outcomes.push((observed, errors));
    }
    outcomes
}

fn assert_mentions(errors: &[String], parts: &[&str]) {
    assert!(errors.iter().any(|e| parts.iter().all(|p| e.contains(p))), "no error with {parts:?} in {errors:#?}");
}

#[test]
fn every_bad_input_is_named_and_the_stream_goes_on() {
    let outcomes = outcomes();
    assert_eq!(outcomes.len(), 9, "8 images of scene 0 and 1 of scene 1: {outcomes:#?}");
    assert_eq!(outcomes[0], (3, vec![]), "the good image");
    assert_mentions(&outcomes[1].1, &["rgb/000001.png", "cannot read"]);
    assert_mentions(&outcomes[2].1, &["rgb/000002.png"]);
    assert_mentions(&outcomes[3].1, &["depth/000003.png", "expected a 16-bit single-channel depth PNG", "L8"]);
    assert_mentions(&outcomes[4].1, &["image 4", "depth image is 80×60, expected the camera's 160×120"]);
    let masks = &outcomes[5].1;
    assert_eq!(outcomes[5].0, 0);
    assert_mentions(masks, &["image 5, object 1 (instance 0)", "mask has 0 pixels, expected at least 16"]);
    assert_mentions(masks, &["object 10 (instance 1)", "mask has 3 pixels, expected at least 16"]);
    assert_mentions(masks, &["object 11 (instance 2)", "mask_visib/000005_000002.png"]);
    assert_eq!(outcomes[6].0, 0);
    assert_mentions(&outcomes[6].1, &["image 6, object 1", "0 of 387 mask pixels have a valid depth"]);
    assert_mentions(&outcomes[7].1, &["scene_camera.json: image 7", "missing field `cam_K`"]);
    assert_mentions(&outcomes[8].1, &["000001/scene_camera.json", "line"]);
}
