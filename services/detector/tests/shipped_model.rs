//! The shipped detector (models/detector-lmo10) through this crate: the
//! same labels as the exporting Python run on its stored validation image,
//! and labels that match that image's truth (an untrained network fails).

use std::path::Path;

use poseflow_detector::{ImageView, SegmentationNetwork};
use poseflow_geometry::metrics::Pinhole;

struct Parity {
    rgb: Vec<f32>,
    depth: Vec<f32>,
    truth: Vec<u8>,
    labels: Vec<u8>,
    confidence: Vec<f32>,
}

fn model_dir() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/detector-lmo10")
}

fn read_parity(pixels: usize) -> Parity {
    let bytes = std::fs::read(model_dir().join("parity.bin")).expect("parity.bin is shipped with the model");
    assert_eq!(bytes.len(), pixels * (3 + 2 + 1 + 1 + 4), "parity.bin size");
    let (rgb, rest) = bytes.split_at(3 * pixels);
    let (depth, rest) = rest.split_at(2 * pixels);
    let (truth, rest) = rest.split_at(pixels);
    let (labels, confidence) = rest.split_at(pixels);
    Parity {
        rgb: rgb.iter().map(|&v| f32::from(v)).collect(),
        depth: depth.chunks_exact(2).map(|b| f32::from(u16::from_le_bytes([b[0], b[1]])) / 1000.0).collect(),
        truth: truth.to_vec(),
        labels: labels.to_vec(),
        confidence: confidence.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
    }
}

#[test]
fn the_shipped_detector_reproduces_its_export_and_finds_the_objects() {
    let mut network = SegmentationNetwork::load(&model_dir(), 1).expect("the shipped detector loads");
    let spec = network.meta().input;
    let pixels = spec.width * spec.height;
    let parity = read_parity(pixels);
    // The stored image is already at the network's size: sampling is the identity.
    // The network does not use the intrinsics.
    let camera = Pinhole { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0 };
    let image = ImageView { rgb: &parity.rgb, depth: &parity.depth, width: spec.width, height: spec.height, camera };
    let map = network.segment(&image).expect("the network runs");
    let agree = map.labels.iter().zip(&parity.labels).filter(|(a, b)| a == b).count();
    assert!(agree as f64 >= 0.995 * pixels as f64, "labels agree on {agree} of {pixels} pixels");
    for ((a, b), (p, q)) in map.labels.iter().zip(&parity.labels).zip(map.confidence.iter().zip(&parity.confidence)) {
        if a == b {
            assert!((p - q).abs() < 1e-3, "probability {p} against {q}");
        }
    }
    // Against the truth: the mean IoU over the classes in the image.
    let classes: std::collections::BTreeSet<u8> = parity.truth.iter().copied().filter(|&c| c > 0).collect();
    assert!(!classes.is_empty());
    let iou = |c: u8| {
        let both = map.labels.iter().zip(&parity.truth).filter(|&(&l, &t)| l == c && t == c).count();
        let either = map.labels.iter().zip(&parity.truth).filter(|&(&l, &t)| l == c || t == c).count();
        both as f64 / either as f64
    };
    let mean = classes.iter().map(|&c| iou(c)).sum::<f64>() / classes.len() as f64;
    assert!(mean > 0.4, "mean IoU {mean:.3} over classes {classes:?}");
}
