//! Seeded random draws that start the flow (Haar-uniform rotations and
//! translation noise) and farthest-point subsampling of point clouds.

use nalgebra::{Point3, Quaternion, Rotation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::Pose;

/// The generator used everywhere a draw must be reproducible: ChaCha8, whose
/// stream for a given seed is fixed across platforms and crate releases.
pub type SeededRng = ChaCha8Rng;

pub fn seeded_rng(seed: u64) -> SeededRng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// A rotation drawn from the Haar (uniform) measure on SO(3), by Shoemake's
/// uniform unit quaternion.
pub fn uniform_rotation<R: Rng + ?Sized>(rng: &mut R) -> Rotation3<f64> {
    let u1: f64 = rng.random();
    let u2: f64 = rng.random::<f64>() * std::f64::consts::TAU;
    let u3: f64 = rng.random::<f64>() * std::f64::consts::TAU;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    UnitQuaternion::from_quaternion(Quaternion::new(b * u3.cos(), a * u2.sin(), a * u2.cos(), b * u3.sin()))
        .to_rotation_matrix()
}

/// The distribution of the flow's initial translation `p₀`, in the same
/// (centred, metric) frame as the target translation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TranslationNoise {
    /// Independent `N(0, σ²)` per axis; `std_dev` σ in metres.
    Gaussian { std_dev: f64 },
    /// Uniform in the cube `[−h, h]³`; `half_extent` h in metres.
    UniformBox { half_extent: f64 },
}

impl TranslationNoise {
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> Vector3<f64> {
        match *self {
            Self::Gaussian { std_dev } => Vector3::from_fn(|_, _| {
                let z: f64 = StandardNormal.sample(rng);
                z * std_dev
            }),
            Self::UniformBox { half_extent } => Vector3::from_fn(|_, _| rng.random_range(-1.0..=1.0) * half_extent),
        }
    }
}

/// The seed of one observation's draws (pose samples, grasps): the same
/// (seed, frame, object) gives the same draws in every process and in
/// every order.
pub fn sample_seed(seed: u64, frame_id: u64, object_id: u32) -> u64 {
    let mut z = seed ^ frame_id.rotate_left(17) ^ u64::from(object_id).rotate_left(47);
    // splitmix64 finaliser.
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// An initial flow sample `(R₀, p₀)`: Haar-uniform rotation, translation from
/// `noise`.
pub fn initial_pose<R: Rng + ?Sized>(rng: &mut R, noise: &TranslationNoise) -> Pose {
    let rotation = uniform_rotation(rng);
    Pose::new(rotation, noise.sample(rng))
}

/// Lanes of the farthest-point scan: independent running maxima the
/// compiler keeps in one vector register.
const LANES: usize = 8;

/// Points per block of the farthest-point scan. The points are scanned in
/// Morton (Z-curve) order, so each block of consecutive points is compact
/// in space; a block whose box is farther from the newest pick than the
/// block's own farthest point is skipped whole, since none of its distances
/// can shrink. After the first picks most blocks are skipped.
const BLOCK: usize = 64;

/// Relative margin on a block's box distance before it is skipped, far
/// above the rounding of a squared distance (a few units in the last
/// place): a skipped block is one whose distances an update would leave
/// exactly as they are.
const SKIP_MARGIN: f32 = 1e-5;

/// One block of the farthest-point scan: a run of points in Morton order.
struct Block {
    range: std::ops::Range<usize>,
    min: [f32; 3],
    max: [f32; 3],
    /// The block's largest distance.
    farthest: f32,
}

impl Block {
    /// A lower bound on the squared distance from `p` to any point of the
    /// block.
    fn distance_bound(&self, p: [f32; 3]) -> f32 {
        let gap = |k: usize| (self.min[k] - p[k]).max(p[k] - self.max[k]).max(0.0);
        let (x, y, z) = (gap(0), gap(1), gap(2));
        x * x + y * y + z * z
    }
}

/// Lowers each `distance` to the squared distance to `last` if closer and
/// returns the index of the largest (the first, on ties) and its value.
/// Branch-free per lane so the loop vectorises; one pass over the arrays.
/// Not inlined: inlined into the block loop it compiled to scalar code
/// (1.7× slower, `cargo bench -p poseflow-ingest`).
#[inline(never)]
fn update_and_find_farthest(
    distance: &mut [f32],
    (xs, ys, zs): (&[f32], &[f32], &[f32]),
    last: [f32; 3],
) -> (usize, f32) {
    let [lx, ly, lz] = last;
    let mut best = [f32::NEG_INFINITY; LANES];
    let mut best_index = [0u32; LANES];
    let full = distance.len() / LANES * LANES;
    let lanes = distance[..full]
        .chunks_exact_mut(LANES)
        .zip(xs.chunks_exact(LANES).zip(ys.chunks_exact(LANES)).zip(zs.chunks_exact(LANES)));
    for (chunk, (base, ((x, y), z))) in lanes.enumerate().map(|(c, (d, xyz))| (d, (c * LANES, xyz))) {
        for l in 0..LANES {
            let (dx, dy, dz) = (x[l] - lx, y[l] - ly, z[l] - lz);
            let d = chunk[l].min(dx * dx + dy * dy + dz * dz);
            chunk[l] = d;
            let farther = d > best[l];
            best[l] = if farther { d } else { best[l] };
            best_index[l] = if farther { (base + l) as u32 } else { best_index[l] };
        }
    }
    let mut farthest = (usize::MAX, f32::NEG_INFINITY);
    for l in 0..LANES {
        let (i, d) = (best_index[l] as usize, best[l]);
        if d > farthest.1 || (d == farthest.1 && i < farthest.0) {
            farthest = (i, d);
        }
    }
    for i in full..distance.len() {
        let (dx, dy, dz) = (xs[i] - lx, ys[i] - ly, zs[i] - lz);
        distance[i] = distance[i].min(dx * dx + dy * dy + dz * dz);
        if distance[i] > farthest.1 {
            farthest = (i, distance[i]);
        }
    }
    farthest
}

/// The axis-aligned box `(min, max)` of points given as `[x, y, z]`.
fn bounding_box(points: impl IntoIterator<Item = [f32; 3]>) -> ([f32; 3], [f32; 3]) {
    points.into_iter().fold(([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]), |(min, max), p| {
        ([0, 1, 2].map(|k| min[k].min(p[k])), [0, 1, 2].map(|k| max[k].max(p[k])))
    })
}

/// Input indices in Morton (Z-curve) order of the points' cells on a
/// 1024-per-axis grid over their box.
fn morton_order(points: &[Point3<f32>]) -> Vec<u32> {
    let (min, max) = bounding_box(points.iter().map(|p| [p.x, p.y, p.z]));
    let cell = |p: &Point3<f32>, k: usize| {
        let extent = max[k] - min[k];
        let unit = if extent > 0.0 { (p[k] - min[k]) / extent } else { 0.0 };
        // `as` saturates and maps NaN to 0: any coordinate has a cell.
        (unit * 1023.0) as u32
    };
    // The 10 bits of a cell index, two zero bits between each (room for
    // the other two axes' bits).
    let spread = |v: u32| {
        let mut x = u64::from(v & 0x3ff);
        x = (x | (x << 16)) & 0x0300_00ff;
        x = (x | (x << 8)) & 0x0300_f00f;
        x = (x | (x << 4)) & 0x030c_30c3;
        (x | (x << 2)) & 0x0924_9249
    };
    let mut keyed: Vec<(u64, u32)> = points
        .iter()
        .enumerate()
        .map(|(i, p)| (spread(cell(p, 0)) | spread(cell(p, 1)) << 1 | spread(cell(p, 2)) << 2, i as u32))
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, i)| i).collect()
}

/// Indices of `count` points chosen by farthest-point sampling, starting
/// from the first point: each next point is the one farthest from those
/// chosen (the lowest index among equally far ones). `count` must not
/// exceed `points.len()`.
pub fn farthest_point_indices(points: &[Point3<f32>], count: usize) -> Vec<usize> {
    let mut chosen = Vec::with_capacity(count);
    if points.is_empty() || count == 0 {
        return chosen;
    }
    let input = morton_order(points);
    // Coordinates as separate arrays so the distance update vectorises.
    let coordinate = |k: usize| input.iter().map(|&i| points[i as usize][k]).collect::<Vec<f32>>();
    let (xs, ys, zs) = (coordinate(0), coordinate(1), coordinate(2));
    let mut blocks: Vec<Block> = (0..points.len())
        .step_by(BLOCK)
        .map(|first| {
            let range = first..(first + BLOCK).min(points.len());
            let (min, max) = bounding_box(range.clone().map(|i| [xs[i], ys[i], zs[i]]));
            Block { range, min, max, farthest: f32::INFINITY }
        })
        .collect();
    let mut distance = vec![f32::INFINITY; points.len()];
    let mut next = input.iter().position(|&i| i == 0).unwrap_or(0);
    for _ in 0..count {
        chosen.push(input[next] as usize);
        let last = [xs[next], ys[next], zs[next]];
        let mut farthest = f32::NEG_INFINITY;
        for block in &mut blocks {
            if block.distance_bound(last) * (1.0 - SKIP_MARGIN) <= block.farthest {
                let r = block.range.clone();
                let arrays = (&xs[r.clone()], &ys[r.clone()], &zs[r.clone()]);
                block.farthest = update_and_find_farthest(&mut distance[r], arrays, last).1;
            }
            farthest = farthest.max(block.farthest);
        }
        // Of the points that far (almost always one), the lowest input index.
        let tied = blocks.iter().filter(|b| b.farthest == farthest).flat_map(|b| b.range.clone());
        next = tied.filter(|&at| distance[at] == farthest).min_by_key(|&at| input[at]).unwrap_or(next);
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3;

    #[test]
    fn rotation_angles_follow_the_haar_density() {
        // Under Haar measure the angle has density (1 − cos θ)/π on [0, π],
        // mean π/2 + 2/π ≈ 2.2074. Uniform axis-angle would give π/2.
        let mut rng = seeded_rng(7);
        let n = 20_000;
        let mut mean_angle = 0.0;
        let mut mean_matrix = nalgebra::Matrix3::zeros();
        for _ in 0..n {
            let r = uniform_rotation(&mut rng);
            mean_angle += so3::log(&r).norm() / n as f64;
            mean_matrix += r.matrix() / n as f64;
        }
        let expected = std::f64::consts::FRAC_PI_2 + 2.0 / std::f64::consts::PI;
        assert!((mean_angle - expected).abs() < 0.02, "mean angle {mean_angle}");
        // E[R] = 0 under Haar measure; each entry has σ = 1/√(3n) ≈ 0.004.
        assert!(mean_matrix.abs().max() < 0.03, "{mean_matrix}");
    }

    #[test]
    fn same_seed_same_draws() {
        let noise = TranslationNoise::Gaussian { std_dev: 0.1 };
        let a = initial_pose(&mut seeded_rng(3), &noise);
        let b = initial_pose(&mut seeded_rng(3), &noise);
        assert_eq!(a, b);
    }

    #[test]
    fn noise_has_the_requested_scale() {
        let mut rng = seeded_rng(11);
        let n = 20_000;
        let gaussian = TranslationNoise::Gaussian { std_dev: 0.2 };
        let var: f64 = (0..n).map(|_| gaussian.sample(&mut rng).x.powi(2)).sum::<f64>() / n as f64;
        assert!((var.sqrt() - 0.2).abs() < 0.005, "std {}", var.sqrt());

        let cube = TranslationNoise::UniformBox { half_extent: 0.5 };
        let samples: Vec<_> = (0..n).map(|_| cube.sample(&mut rng)).collect();
        assert!(samples.iter().all(|p| p.amax() <= 0.5));
        // Uniform on [−h, h] has variance h²/3.
        let var: f64 = samples.iter().map(|p| p.y * p.y).sum::<f64>() / n as f64;
        assert!((var - 0.25 / 3.0).abs() < 0.003, "var {var}");
    }

    #[test]
    fn farthest_point_sampling_spreads_out() {
        // Two clusters far apart: the second pick is in the other cluster.
        let mut points: Vec<Point3<f32>> = (0..50).map(|i| Point3::new(i as f32 * 1e-4, 0.0, 0.0)).collect();
        points.extend((0..50).map(|i| Point3::new(1.0 + i as f32 * 1e-4, 0.0, 0.0)));
        let picks = farthest_point_indices(&points, 2);
        assert_eq!(picks, [0, 99]);
        // From the centre of a square: then the corners (ties go to the
        // lowest index), each once.
        let square = [[0.5, 0.5], [0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]].map(|[x, y]| Point3::new(x, y, 0.0));
        assert_eq!(farthest_point_indices(&square, 5), [0, 1, 2, 3, 4]);
    }

    /// The textbook two-pass loop the lane-wise scan replaces.
    fn farthest_point_reference(points: &[Point3<f32>], count: usize) -> Vec<usize> {
        let mut distance = vec![f32::INFINITY; points.len()];
        let mut chosen = Vec::new();
        let mut next = 0;
        for _ in 0..count {
            chosen.push(next);
            for (d, p) in distance.iter_mut().zip(points) {
                *d = d.min((p - points[next]).norm_squared());
            }
            next = (0..points.len()).fold(0, |best, i| if distance[i] > distance[best] { i } else { best });
        }
        chosen
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 10_000, ..Default::default() })]

        /// Any cloud size (lanes full, partial, none), duplicates and ties
        /// included: the same picks in the same order as the reference.
        #[test]
        fn farthest_point_sampling_matches_the_reference(
            coordinates in proptest::collection::vec((0u8..6, 0u8..6, 0u8..3), 1..60),
            count in 1usize..20,
        ) {
            let points: Vec<Point3<f32>> =
                coordinates.iter().map(|&(x, y, z)| Point3::new(f32::from(x), f32::from(y), f32::from(z) * 0.5)).collect();
            let count = count.min(points.len());
            proptest::prop_assert_eq!(farthest_point_indices(&points, count), farthest_point_reference(&points, count));
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 500, ..Default::default() })]

        /// Clouds of many blocks, on a coarse grid (ties between blocks) or
        /// not, in random or in scan order (compact blocks, most skipped):
        /// the same picks.
        #[test]
        fn farthest_point_sampling_over_many_blocks_matches_the_reference(
            mut coordinates in proptest::collection::vec((0u16..40, 0u16..40, 0u16..40), 1..700),
            grid in proptest::bool::ANY,
            scan_order in proptest::bool::ANY,
            count in 1usize..120,
        ) {
            if scan_order {
                coordinates.sort_unstable_by_key(|&(x, y, z)| (y, x, z));
            }
            let scale = if grid { 1.0 } else { 0.013_7 };
            let points: Vec<Point3<f32>> = coordinates
                .iter()
                .map(|&(x, y, z)| Point3::new(f32::from(x), f32::from(y), f32::from(z) * 0.5) * scale)
                .collect();
            let count = count.min(points.len());
            proptest::prop_assert_eq!(farthest_point_indices(&points, count), farthest_point_reference(&points, count));
        }
    }
}
