//! Criterion benchmarks of the default model's networks (INT8, 2 threads),
//! one by one and batched as the inference stage batches the objects of a
//! frame: eight observations encoded in eight runs or in one, and their
//! 8 × 50 samples' velocities in eight runs or in one.
//! `cargo bench -p poseflow-bench --bench networks` (needs ONNX Runtime:
//! `deploy/setup`).

use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use poseflow_bench::NetworkWorkload;
use poseflow_inference::{PoseFlowModel, Precision};

const OBJECTS: usize = 8;
const SAMPLES: usize = 50;

fn networks(c: &mut Criterion) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/poseflow-lmo10");
    let mut model = PoseFlowModel::load_as(&dir, 2, Precision::Int8).expect("the default model and ONNX Runtime");
    let one = NetworkWorkload::new(&model, 1, SAMPLES);
    let all = NetworkWorkload::new(&model, OBJECTS, SAMPLES);
    let (one_input, all_inputs) = (one.inputs(), all.inputs());
    let single = model.encode_batch(&one_input).unwrap();
    let batched = model.encode_batch(&all_inputs).unwrap();
    let (single, batched): (Vec<_>, Vec<_>) = (single.iter().collect(), batched.iter().collect());
    let mut group = c.benchmark_group(format!("{OBJECTS}_observations"));
    group.sample_size(20);
    group.bench_function("encoder/one_by_one", |b| {
        b.iter(|| (0..OBJECTS).for_each(|_| drop(model.encode_batch(&one_input).unwrap())))
    });
    group.bench_function("encoder/batched", |b| b.iter(|| model.encode_batch(&all_inputs).unwrap()));
    group.bench_function(format!("velocity_{SAMPLES}_samples_each/one_by_one"), |b| {
        b.iter(|| (0..OBJECTS).for_each(|_| one.velocities(&mut model, &single).unwrap()))
    });
    group.bench_function(format!("velocity_{SAMPLES}_samples_each/batched"), |b| {
        b.iter(|| all.velocities(&mut model, &batched).unwrap())
    });
    group.finish();
}

criterion_group!(benches, networks);
criterion_main!(benches);
