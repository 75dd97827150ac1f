//! Criterion benchmarks of the ingest stage's point-cloud kernels at the
//! default sizes: statistical outlier removal (16 neighbours) on the 4096
//! points a mask is thinned to, then farthest-point sampling to 1024.
//! `cargo bench -p poseflow-ingest`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Vector3};
use poseflow_geometry::sampling::seeded_rng;
use poseflow_ingest::{OutlierFilter, remove_outliers, sample_fixed};
use rand::Rng;

/// What a depth camera sees of a 10 cm ball 70 cm away: its front half,
/// one point per pixel ray (a regular grid in the image), 1 mm depth noise,
/// 2 % stray points behind it (mask bleed onto the background).
fn observed_ball() -> Vec<Point3<f32>> {
    let mut rng = seeded_rng(4);
    let centre = Vector3::new(0.0f32, 0.0, 0.7);
    let side = 64;
    let mut points = Vec::with_capacity(side * side);
    for row in 0..side {
        for col in 0..side {
            let (u, v) = ((col as f32 + 0.5) / side as f32 * 2.0 - 1.0, (row as f32 + 0.5) / side as f32 * 2.0 - 1.0);
            if u * u + v * v > 1.0 {
                continue;
            }
            let depth = centre.z - 0.05 * (1.0 - u * u - v * v).sqrt() + rng.random_range(-0.001..0.001);
            let stray = if rng.random_bool(0.02) { rng.random_range(0.05..0.3) } else { 0.0 };
            points.push(Point3::new(0.05 * u, 0.05 * v, depth + stray));
        }
    }
    points
}

fn point_cloud(c: &mut Criterion) {
    let cloud = observed_ball();
    c.bench_function(&format!("statistical_outliers/{}_points_16_neighbours", cloud.len()), |b| {
        b.iter(|| remove_outliers(black_box(cloud.clone()), &OutlierFilter::default()))
    });
    let kept = remove_outliers(cloud, &OutlierFilter::default());
    c.bench_function(&format!("sample_fixed/{}_to_1024_points", kept.len()), |b| {
        b.iter(|| sample_fixed(black_box(&kept), 1024, &mut seeded_rng(0)))
    });
}

criterion_group!(benches, point_cloud);
criterion_main!(benches);
