//! Criterion benchmarks of the per-frame geometry kernels: the sampler's
//! batched Euler step, the selector's Karcher statistics and the ingest
//! stage's farthest-point sampling, at the default sizes (N = 50 samples,
//! 20 % of them kept, 4096 → 1024 points). `cargo bench -p poseflow-geometry`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};
use poseflow_geometry::flow::euler_step;
use poseflow_geometry::mean::karcher_mean_poses;
use poseflow_geometry::sampling::{TranslationNoise, farthest_point_indices, initial_pose, seeded_rng};
use poseflow_geometry::{KarcherOptions, Pose, PoseStatistics, Velocity, so3};
use rand::Rng;

const SAMPLES: usize = 50;

fn uniform_poses(count: usize) -> Vec<Pose> {
    let mut rng = seeded_rng(7);
    let noise = TranslationNoise::Gaussian { std_dev: 0.05 };
    (0..count).map(|_| initial_pose(&mut rng, &noise)).collect()
}

/// Poses within ~10° and 1 cm of one pose: what a converged flow keeps.
fn concentrated_poses(count: usize) -> Vec<Pose> {
    let mut rng = seeded_rng(11);
    let centre = Pose::new(so3::exp(&Vector3::new(0.3, -1.2, 0.7)), Vector3::new(0.05, -0.02, 0.8));
    (0..count)
        .map(|_| {
            let turn = Vector3::from_fn(|_, _| rng.random_range(-0.1..0.1));
            let shift = Vector3::from_fn(|_, _| rng.random_range(-0.01..0.01));
            Pose::new(centre.rotation * so3::exp(&turn), centre.translation + shift)
        })
        .collect()
}

fn euler(c: &mut Criterion) {
    let start = uniform_poses(SAMPLES);
    let mut rng = seeded_rng(3);
    let velocities: Vec<Velocity> = (0..SAMPLES)
        .map(|_| Velocity {
            linear: Vector3::from_fn(|_, _| rng.random_range(-0.2..0.2)),
            angular: Vector3::from_fn(|_, _| rng.random_range(-3.0..3.0)),
        })
        .collect();
    let mut poses = start.clone();
    c.bench_function("euler_step/50_poses", |b| {
        b.iter(|| {
            poses.copy_from_slice(&start);
            euler_step(black_box(&mut poses), black_box(&velocities), 0.2).expect("equal lengths");
        })
    });
}

fn karcher(c: &mut Criterion) {
    let options = KarcherOptions::default();
    let all = concentrated_poses(SAMPLES);
    let kept = &all[..SAMPLES / 5];
    c.bench_function("karcher_mean/50_poses", |b| {
        b.iter(|| karcher_mean_poses(black_box(&all), None, &options).expect("non-empty"))
    });
    c.bench_function("pose_statistics/10_kept_poses", |b| {
        b.iter(|| PoseStatistics::compute(black_box(kept), None, &options).expect("non-empty"))
    });
}

fn farthest_points(c: &mut Criterion) {
    // A noisy 10 cm sphere cap as an observed surface.
    let mut rng = seeded_rng(5);
    let cloud: Vec<Point3<f32>> = (0..4096)
        .map(|_| {
            let direction = Vector3::<f32>::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
            Point3::from(direction * 0.1 + Vector3::from_fn(|_, _| rng.random_range(-0.002..0.002)))
        })
        .collect();
    c.bench_function("farthest_point_sampling/4096_to_1024", |b| {
        b.iter(|| farthest_point_indices(black_box(&cloud), 1024))
    });
}

criterion_group!(benches, euler, karcher, farthest_points);
criterion_main!(benches);
