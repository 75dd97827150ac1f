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

/// `identify-parity.bin` (written by `poseflow_train.identify export`).
struct IdentifyParity {
    rows: usize,
    columns: usize,
    rgb: Vec<u8>,
    depth_mm: Vec<u16>,
    truth: Vec<u8>,
    probabilities: Vec<f32>,
}

fn read_identify_parity() -> IdentifyParity {
    let bytes = std::fs::read(model_dir().join("identify-parity.bin")).expect("identify-parity.bin is shipped");
    let u32_at = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
    let (rows, columns) = (u32_at(0), u32_at(4));
    let cells = rows * columns;
    let mut at = 8;
    let rgb = bytes[at..at + 3 * cells].to_vec();
    at += 3 * cells;
    let depth_mm = bytes[at..at + 2 * cells].chunks_exact(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect();
    at += 2 * cells;
    let truth = bytes[at..at + cells].to_vec();
    at += cells;
    let count = u32_at(at);
    at += 4;
    let probabilities: Vec<f32> =
        bytes[at..].chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    assert_eq!(probabilities.len() % count.max(1), 0, "identify-parity.bin size");
    IdentifyParity { rows, columns, rgb, depth_mm, truth, probabilities }
}

#[test]
fn the_shipped_identifier_reproduces_its_export_and_names_the_annotated_regions() {
    use poseflow_detector::{Identifier, LabelMap};
    let segmentation = SegmentationNetwork::load(&model_dir(), 1).expect("the shipped detector loads");
    let object_ids = segmentation.meta().object_ids.clone();
    let mut identifier = Identifier::load(&model_dir(), 1, &object_ids).expect("it loads").expect("it is shipped");
    let parity = read_identify_parity();
    let (rows, columns) = (parity.rows, parity.columns);
    // A frame twice the grid's size whose every 2 × 2 block is one grid cell.
    let (width, height) = (2 * columns, 2 * rows);
    let cell = |u: usize, v: usize| (v / 2) * columns + u / 2;
    let rgb: Vec<f32> = (0..width * height)
        .flat_map(|p| (0..3).map(move |c| (p, c)))
        .map(|(p, c)| f32::from(parity.rgb[3 * cell(p % width, p / width) + c]))
        .collect();
    let depth: Vec<f32> =
        (0..width * height).map(|p| f32::from(parity.depth_mm[cell(p % width, p / width)]) / 1000.0).collect();
    let camera = Pinhole { fx: 572.4114, fy: 573.57043, cx: 325.2611, cy: 242.04899 };
    let image = ImageView { rgb: &rgb, depth: &depth, width, height, camera };
    let mut map = LabelMap {
        width: columns,
        height: rows,
        labels: parity.truth.clone(),
        confidence: vec![1.0; rows * columns],
        depth: Vec::new(),
        instances: Vec::new(),
    };
    let done = identifier.relabel(&mut map, &image, 16, None).expect("the identifier runs");
    let classes = object_ids.len() + 1;
    assert_eq!(done.regions * classes, parity.probabilities.len(), "the same regions as the export");
    // Each region in raster order of its first cell, as the export wrote them.
    let mut firsts: Vec<usize> = Vec::new();
    let mut seen = vec![false; rows * columns];
    for start in 0..rows * columns {
        if parity.truth[start] == 0 || seen[start] {
            continue;
        }
        let mut stack = vec![start];
        let mut members = Vec::new();
        seen[start] = true;
        while let Some(i) = stack.pop() {
            members.push(i);
            let (x, y) = (i % columns, i / columns);
            let near = [
                (x > 0).then(|| i - 1),
                (x + 1 < columns).then(|| i + 1),
                (y > 0).then(|| i - columns),
                (y + 1 < rows).then(|| i + columns),
            ];
            for n in near.into_iter().flatten() {
                if !seen[n] && parity.truth[n] == parity.truth[start] {
                    seen[n] = true;
                    stack.push(n);
                }
            }
        }
        if members.len() >= 16 {
            firsts.push(start);
        }
    }
    let mut named = 0;
    for (k, &first) in firsts.iter().enumerate() {
        let p = &parity.probabilities[k * classes..(k + 1) * classes];
        // The most probable object (class 0, none of them, never labels).
        let (label, probability) =
            p.iter().enumerate().skip(1).fold((0, f32::NEG_INFINITY), |b, (c, &q)| if q > b.1 { (c, q) } else { b });
        let probability = probability / p.iter().sum::<f32>();
        assert_eq!(usize::from(map.labels[first]), label, "region at cell {first}: {p:?}");
        assert!((map.confidence[first] - probability).abs() < 1e-3, "{} against {probability}", map.confidence[first]);
        named += usize::from(label == usize::from(parity.truth[first]));
    }
    // Against the annotation: an untrained identifier names about one in
    // eleven regions right.
    assert!(named * 4 >= firsts.len() * 3, "{named} of {} regions named as annotated", firsts.len());
}

#[test]
fn a_frame_too_small_for_the_identifiers_grid_keeps_its_labels() {
    use poseflow_detector::{Identifier, LabelMap};
    let segmentation = SegmentationNetwork::load(&model_dir(), 1).expect("the shipped detector loads");
    let object_ids = segmentation.meta().object_ids.clone();
    let mut identifier = Identifier::load(&model_dir(), 1, &object_ids).expect("it loads").expect("it is shipped");
    let camera = Pinhole { fx: 500.0, fy: 500.0, cx: 0.5, cy: 0.5 };
    let (rgb, depth) = ([10.0, 20.0, 30.0], [1.0]);
    let image = ImageView { rgb: &rgb, depth: &depth, width: 1, height: 1, camera };
    let mut map = LabelMap {
        width: 1,
        height: 1,
        labels: vec![3],
        confidence: vec![0.9],
        depth: Vec::new(),
        instances: Vec::new(),
    };
    let done = identifier.relabel(&mut map, &image, 1, None).expect("no error");
    assert_eq!(done.regions, 0);
    assert_eq!((map.labels[0], map.confidence[0]), (3, 0.9));
}
