//! BOP-style pose error metrics over model points.
//!
//! `points` are model surface points in the object frame (metres; e.g. the
//! mesh vertices); poses are `camera_from_object` (metres). Errors are in
//! metres, [`mspd`] in pixels. Symmetric objects: [`mssd`] and [`mspd`]
//! take the minimum over the [`SymmetrySet`], as the BOP toolkit does;
//! [`add_s`] needs no symmetries (closest-point matching). [`vsd`] compares
//! depth images and so needs no symmetries either.

use nalgebra::Point3;

use crate::{Pose, SymmetrySet};

/// Pinhole intrinsics (pixels; OpenCV convention: camera frame x right,
/// y down, z forward; pixel u right, v down from the top-left corner).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Pinhole {
    fn project(&self, p: &Point3<f64>) -> [f64; 2] {
        [self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy]
    }

    /// The pixel a camera-frame point projects to; `None` behind the camera.
    pub fn pixel(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        (p.z > 1e-6).then(|| {
            let [u, v] = self.project(p);
            (u, v)
        })
    }
}

/// ADD: mean distance between each point under the estimate and under the
/// truth. 0 for no points.
pub fn add(points: &[Point3<f64>], estimate: &Pose, truth: &Pose) -> f64 {
    let sum: f64 = points.iter().map(|p| (estimate.transform_point(p) - truth.transform_point(p)).norm()).sum();
    sum / points.len().max(1) as f64
}

/// ADD-S: mean distance from each point under the estimate to the closest
/// point under the truth. Builds a [`NearestPoints`] index each call; to
/// score many poses of one object, build it once and call
/// [`NearestPoints::add_s`]. 0 for no points.
pub fn add_s(points: &[Point3<f64>], estimate: &Pose, truth: &Pose) -> f64 {
    NearestPoints::new(points).add_s(estimate, truth)
}

/// Exact nearest-neighbour distances to a fixed point set (object frame,
/// metres) through a uniform grid, so ADD-S over every vertex of a mesh
/// costs about a few dozen distance evaluations per point instead of n.
///
/// Cells are `cell` metres wide; indices of the points of each cell are
/// stored contiguously (compressed rows, x fastest).
#[derive(Debug, Clone)]
pub struct NearestPoints {
    points: Vec<Point3<f64>>,
    origin: Point3<f64>,
    cell: f64,
    dims: [i64; 3],
    /// `starts[c]..starts[c + 1]` indexes `order` for cell `c`.
    starts: Vec<u32>,
    order: Vec<u32>,
}

impl NearestPoints {
    /// Points per occupied cell aimed at on a surface (area ≈ extent²).
    const POINTS_PER_CELL: f64 = 3.0;
    /// Cells per axis at most, whatever the point count.
    const MAX_DIM: f64 = 128.0;

    pub fn new(points: &[Point3<f64>]) -> Self {
        let mut min = Point3::from([f64::INFINITY; 3]);
        let mut max = Point3::from([f64::NEG_INFINITY; 3]);
        for p in points {
            min = min.inf(p);
            max = max.sup(p);
        }
        let extent = if points.is_empty() { 0.0 } else { (max - min).max() };
        let surface_cell = extent * (Self::POINTS_PER_CELL / points.len().max(1) as f64).sqrt();
        let cell = surface_cell.max(extent / Self::MAX_DIM).max(1e-9);
        let dims: [i64; 3] = if points.is_empty() {
            [0; 3]
        } else {
            std::array::from_fn(|k| ((max[k] - min[k]) / cell).floor() as i64 + 1)
        };
        let mut index =
            Self { points: points.to_vec(), origin: min, cell, dims, starts: Vec::new(), order: Vec::new() };
        let cell_count = (dims[0] * dims[1] * dims[2]) as usize;
        let cells: Vec<usize> = points.iter().map(|p| index.flat(index.cell_of(p))).collect();
        let mut counts = vec![0u32; cell_count + 1];
        for &c in &cells {
            counts[c + 1] += 1;
        }
        for c in 0..cell_count {
            counts[c + 1] += counts[c];
        }
        let mut next = counts.clone();
        let mut order = vec![0u32; points.len()];
        for (i, &c) in cells.iter().enumerate() {
            order[next[c] as usize] = i as u32;
            next[c] += 1;
        }
        index.starts = counts;
        index.order = order;
        index
    }

    fn cell_of(&self, p: &Point3<f64>) -> [i64; 3] {
        std::array::from_fn(|k| ((p[k] - self.origin[k]) / self.cell).floor() as i64)
    }

    fn flat(&self, c: [i64; 3]) -> usize {
        (c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])) as usize
    }

    /// Distance from `query` to the nearest point; infinity for no points.
    pub fn nearest_distance(&self, query: &Point3<f64>) -> f64 {
        let exhaustive = || self.points.iter().map(|p| (p - query).norm_squared()).fold(f64::INFINITY, f64::min).sqrt();
        if self.points.is_empty() {
            return f64::INFINITY;
        }
        // Chebyshev distance in cells from the query's cell to the grid, in
        // floating point: a far query's cell index would overflow.
        let cells: [f64; 3] = std::array::from_fn(|k| ((query[k] - self.origin[k]) / self.cell).floor());
        let outside =
            (0..3).map(|k| (-cells[k]).max(cells[k] - (self.dims[k] - 1) as f64).max(0.0)).fold(0.0, f64::max);
        let largest_dim = self.dims.iter().copied().max().unwrap_or(0);
        if outside > largest_dim as f64 || query.iter().any(|v| !v.is_finite()) {
            return exhaustive();
        }
        let centre: [i64; 3] = cells.map(|c| c as i64);
        let outside = outside as i64;
        let mut best = f64::INFINITY;
        let mut ring = outside;
        loop {
            let lo: [i64; 3] = std::array::from_fn(|k| (centre[k] - ring).max(0));
            let hi: [i64; 3] = std::array::from_fn(|k| (centre[k] + ring).min(self.dims[k] - 1));
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let on_ring =
                            (x - centre[0]).abs().max((y - centre[1]).abs()).max((z - centre[2]).abs()) == ring;
                        if !on_ring {
                            continue;
                        }
                        let c = self.flat([x, y, z]);
                        for &i in &self.order[self.starts[c] as usize..self.starts[c + 1] as usize] {
                            best = best.min((self.points[i as usize] - query).norm_squared());
                        }
                    }
                }
            }
            // Every point in a farther ring is at least `ring` cells away.
            if best.sqrt() <= ring as f64 * self.cell || ring > outside + largest_dim {
                return best.sqrt();
            }
            ring += 1;
        }
    }

    /// ADD-S of the indexed points (see [`add_s`]): the nearest point is
    /// searched in the object frame, `truth⁻¹ · estimate · p`.
    pub fn add_s(&self, estimate: &Pose, truth: &Pose) -> f64 {
        if self.points.is_empty() {
            return 0.0;
        }
        let relative = truth.inverse() * *estimate;
        let sum: f64 = self.points.iter().map(|p| self.nearest_distance(&relative.transform_point(p))).sum();
        sum / self.points.len() as f64
    }
}

/// The largest per-point error of `distance` under `truth · S`, minimised
/// over the symmetries `S`.
fn min_over_symmetries(
    points: &[Point3<f64>],
    symmetries: &SymmetrySet,
    estimate: &Pose,
    truth: &Pose,
    distance: impl Fn(&Point3<f64>, &Pose) -> f64,
) -> f64 {
    // Twins nearest the estimate in rotation first: the first one's error
    // then cuts the others short after a few points, which matters for a
    // continuous symmetry's hundreds of twins (the minimum is the same).
    let mut twins: Vec<(f64, Pose)> = symmetries
        .equivalent_poses(truth)
        .map(|twin| (-(twin.rotation.transpose() * estimate.rotation).matrix().trace(), twin))
        .collect();
    twins.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut best = f64::INFINITY;
    for (_, twin) in twins {
        let mut largest = 0.0f64;
        for p in points {
            largest = largest.max(distance(p, &twin));
            // This twin can no longer be the minimum.
            if largest >= best {
                break;
            }
        }
        best = best.min(largest);
    }
    best
}

/// MSSD (BOP): the maximum 3D point distance, minimised over symmetries.
pub fn mssd(points: &[Point3<f64>], estimate: &Pose, truth: &Pose, symmetries: &SymmetrySet) -> f64 {
    min_over_symmetries(points, symmetries, estimate, truth, |p, twin| {
        (estimate.transform_point(p) - twin.transform_point(p)).norm()
    })
}

/// MSPD (BOP): the maximum 2D distance of the projected points (pixels),
/// minimised over symmetries.
pub fn mspd(points: &[Point3<f64>], estimate: &Pose, truth: &Pose, symmetries: &SymmetrySet, camera: &Pinhole) -> f64 {
    min_over_symmetries(points, symmetries, estimate, truth, |p, twin| {
        let (a, b) = (camera.project(&estimate.transform_point(p)), camera.project(&twin.transform_point(p)));
        (a[0] - b[0]).hypot(a[1] - b[1])
    })
}

/// Depth images of one camera for [`vsd`]: row-major, `width` pixels per
/// row, metres of camera-frame z, 0 = no measurement / no surface.
#[derive(Debug, Clone, Copy)]
pub struct DepthImages<'a> {
    pub pinhole: Pinhole,
    pub width: usize,
    /// The sensor's depth of the test image.
    pub test: &'a [f32],
    /// The object alone rendered at the estimate and at the truth.
    pub estimate: &'a [f32],
    pub truth: &'a [f32],
}

/// Visible Surface Discrepancy (BOP19; Hodaň et al.), one error in [0, 1]
/// per misalignment tolerance in `taus` (metres): over the pixels where the
/// object is visible under the estimate or the truth, the share that is not
/// visible under both with distances within τ. Visibility as the BOP toolkit's
/// "bop19" mode: the rendered surface is at most `delta` metres behind the
/// test depth, or the test has no measurement there; a pixel visible under
/// the truth counts as visible under the estimate wherever the estimate has
/// a surface. Distances are along the ray, not z. An empty union gives 1.
/// Images of different sizes give 1 (nothing can be compared).
pub fn vsd(images: &DepthImages<'_>, delta: f64, taus: &[f64]) -> Vec<f64> {
    let n = images.test.len();
    if images.estimate.len() != n || images.truth.len() != n || images.width == 0 {
        return vec![1.0; taus.len()];
    }
    let Pinhole { fx, fy, cx, cy } = images.pinhole;
    let visible = |model: f64, test: f64| model > 0.0 && (test == 0.0 || model - test <= delta);
    let (mut union, mut only_one) = (0usize, 0usize);
    let mut both: Vec<f64> = Vec::new();
    for i in 0..n {
        // Neither model surface here: not visible under either (most of
        // the image, so skip the ray before computing it).
        if images.estimate[i] <= 0.0 && images.truth[i] <= 0.0 {
            continue;
        }
        let (u, v) = ((i % images.width) as f64, (i / images.width) as f64);
        let ray = ((u - cx) / fx).hypot((v - cy) / fy).hypot(1.0);
        let [test, estimate, truth] = [images.test[i], images.estimate[i], images.truth[i]].map(|z| f64::from(z) * ray);
        let in_truth = visible(truth, test);
        let in_estimate = visible(estimate, test) || (in_truth && estimate > 0.0);
        match (in_truth, in_estimate) {
            (true, true) => both.push((estimate - truth).abs()),
            (false, false) => continue,
            _ => only_one += 1,
        }
        union += 1;
    }
    taus.iter()
        .map(|&tau| {
            if union == 0 {
                return 1.0;
            }
            let misaligned = both.iter().filter(|&&d| d >= tau).count();
            (misaligned + only_one) as f64 / union as f64
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};

    use super::*;
    use crate::models_info::ModelInfo;

    /// Points on a circle of radius `r` about the object's z axis.
    fn ring(r: f64, n: usize) -> Vec<Point3<f64>> {
        (0..n)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                Point3::new(r * a.cos(), r * a.sin(), 0.0)
            })
            .collect()
    }

    fn at_depth(rotation: Rotation3<f64>, x: f64) -> Pose {
        Pose::new(rotation, Vector3::new(x, 0.0, 0.5))
    }

    fn exhaustive_add_s(points: &[Point3<f64>], estimate: &Pose, truth: &Pose) -> f64 {
        let targets: Vec<Point3<f64>> = points.iter().map(|p| truth.transform_point(p)).collect();
        let sum: f64 = points
            .iter()
            .map(|p| {
                let q = estimate.transform_point(p);
                targets.iter().map(|t| (q - t).norm_squared()).fold(f64::INFINITY, f64::min).sqrt()
            })
            .sum();
        sum / points.len() as f64
    }

    #[test]
    fn the_nearest_point_grid_is_exact() {
        use rand::Rng;
        let mut rng = crate::sampling::seeded_rng(7);
        // A clustered cloud (a surface patch and a few strays) and queries
        // inside, near and far outside it.
        let mut points: Vec<Point3<f64>> = (0..800)
            .map(|_| {
                Point3::new(rng.random_range(-0.05..0.05), rng.random_range(-0.03..0.03), 0.002 * rng.random::<f64>())
            })
            .collect();
        points.extend((0..5).map(|_| Point3::new(rng.random_range(-0.1..0.1), 0.08, rng.random_range(-0.1..0.1))));
        let index = NearestPoints::new(&points);
        for scale in [0.01, 0.1, 1.0, 10.0] {
            for _ in 0..200 {
                let q = Point3::new(
                    scale * rng.random_range(-1.0..1.0),
                    scale * rng.random_range(-1.0..1.0),
                    scale * rng.random_range(-1.0..1.0),
                );
                let exact = points.iter().map(|p| (p - q).norm()).fold(f64::INFINITY, f64::min);
                assert_eq!(index.nearest_distance(&q), exact, "query {q:?}");
            }
        }
        let truth = at_depth(Rotation3::from_euler_angles(0.3, -0.2, 1.0), 0.02);
        let estimate = at_depth(Rotation3::from_euler_angles(0.5, -0.1, 0.7), 0.03);
        assert!((index.add_s(&estimate, &truth) - exhaustive_add_s(&points, &estimate, &truth)).abs() < 1e-12);
        assert_eq!(NearestPoints::new(&[]).nearest_distance(&Point3::origin()), f64::INFINITY);
    }

    /// The twin order only saves work: the minimum over a continuous
    /// symmetry's twins equals the plain minimum of each twin's maximum.
    #[test]
    fn mssd_and_mspd_equal_the_plain_minimum_over_every_twin() {
        use rand::Rng;
        let mut rng = crate::sampling::seeded_rng(3);
        let points: Vec<Point3<f64>> = (0..300)
            .map(|_| {
                Point3::new(rng.random_range(-0.04..0.04), rng.random_range(-0.04..0.04), rng.random_range(0.0..0.1))
            })
            .collect();
        let info = ModelInfo {
            diameter: 0.1,
            min: None,
            size: None,
            symmetries_discrete: Vec::new(),
            symmetries_continuous: vec![crate::models_info::ContinuousSymmetry {
                axis: Vector3::z_axis(),
                offset: Vector3::zeros(),
            }],
        };
        let symmetries = SymmetrySet::from_model_info(&info, 0.01);
        assert!(symmetries.transforms().len() > 100, "{}", symmetries.transforms().len());
        let camera = Pinhole { fx: 572.0, fy: 573.0, cx: 320.0, cy: 240.0 };
        for _ in 0..5 {
            let turn = |rng: &mut crate::sampling::SeededRng| {
                Rotation3::from_euler_angles(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                )
            };
            let truth = at_depth(turn(&mut rng), 0.0);
            let estimate = at_depth(turn(&mut rng), 0.01);
            let plain = |distance: &dyn Fn(&Point3<f64>, &Pose) -> f64| {
                symmetries
                    .equivalent_poses(&truth)
                    .map(|twin| points.iter().map(|p| distance(p, &twin)).fold(0.0, f64::max))
                    .fold(f64::INFINITY, f64::min)
            };
            let mssd_plain = plain(&|p, twin| (estimate.transform_point(p) - twin.transform_point(p)).norm());
            let mspd_plain = plain(&|p, twin| {
                let (a, b) = (camera.project(&estimate.transform_point(p)), camera.project(&twin.transform_point(p)));
                (a[0] - b[0]).hypot(a[1] - b[1])
            });
            assert_eq!(mssd(&points, &estimate, &truth, &symmetries), mssd_plain);
            assert_eq!(mspd(&points, &estimate, &truth, &symmetries, &camera), mspd_plain);
        }
    }

    #[test]
    fn a_perfect_estimate_scores_zero_everywhere() {
        let points = ring(0.05, 36);
        let truth = at_depth(Rotation3::from_euler_angles(0.3, -0.2, 1.0), 0.02);
        let camera = Pinhole { fx: 572.0, fy: 573.0, cx: 320.0, cy: 240.0 };
        let none = SymmetrySet::identity_only();
        assert_eq!(add(&points, &truth, &truth), 0.0);
        // ADD-S compares in the object frame, through truth⁻¹ · estimate.
        assert!(add_s(&points, &truth, &truth) < 1e-12);
        assert_eq!(mssd(&points, &truth, &truth, &none), 0.0);
        assert_eq!(mspd(&points, &truth, &truth, &none, &camera), 0.0);
    }

    #[test]
    fn known_errors_in_closed_form() {
        let (r, theta, shift) = (0.05, 0.4f64, 0.01);
        let points = ring(r, 360);
        let truth = at_depth(Rotation3::identity(), 0.0);
        // A turn by θ about the ring's axis moves every point by 2 r sin(θ/2).
        let turned = at_depth(Rotation3::from_axis_angle(&Vector3::z_axis(), theta), 0.0);
        let chord = 2.0 * r * (theta / 2.0).sin();
        assert!((add(&points, &turned, &truth) - chord).abs() < 1e-12);
        assert!((mssd(&points, &turned, &truth, &SymmetrySet::identity_only()) - chord).abs() < 1e-12);
        // ...but the ring maps onto itself: ADD-S sees only the sampling gap.
        assert!(add_s(&points, &turned, &truth) < r * std::f64::consts::TAU / 360.0);
        // A shift along x at depth z moves every projection by fx·d/z pixels.
        let shifted = at_depth(Rotation3::identity(), shift);
        let camera = Pinhole { fx: 600.0, fy: 600.0, cx: 320.0, cy: 240.0 };
        let pixels = mspd(&points, &shifted, &truth, &SymmetrySet::identity_only(), &camera);
        assert!((pixels - 600.0 * shift / 0.5).abs() < 1e-9, "{pixels}");
        assert!((add(&points, &shifted, &truth) - shift).abs() < 1e-12);
    }

    #[test]
    fn a_symmetric_twin_scores_zero_on_the_symmetry_aware_metrics() {
        // An object with a half-turn symmetry about z (an eggbox-like box).
        let half_turn =
            Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI), Vector3::zeros());
        let info = ModelInfo {
            diameter: 0.1,
            min: None,
            size: None,
            symmetries_discrete: vec![half_turn],
            symmetries_continuous: Vec::new(),
        };
        let symmetries = SymmetrySet::from_model_info(&info, 0.01);
        let points =
            vec![Point3::new(0.05, 0.02, 0.01), Point3::new(-0.05, 0.02, -0.01), Point3::new(0.01, -0.02, 0.0)];
        let truth = at_depth(Rotation3::from_euler_angles(0.1, 0.2, 0.3), 0.0);
        let twin = truth * half_turn;
        let camera = Pinhole { fx: 572.0, fy: 573.0, cx: 320.0, cy: 240.0 };
        assert!(mssd(&points, &twin, &truth, &symmetries) < 1e-12);
        assert!(mspd(&points, &twin, &truth, &symmetries, &camera) < 1e-9);
        // Without its symmetries the twin is far off.
        assert!(mssd(&points, &twin, &truth, &SymmetrySet::identity_only()) > 0.05);
        assert!(add(&points, &twin, &truth) > 0.05);
    }

    /// A 4×3 camera with unit rays along the centre column's neighbours.
    fn depth_images<'a>(test: &'a [f32], estimate: &'a [f32], truth: &'a [f32]) -> DepthImages<'a> {
        DepthImages { pinhole: Pinhole { fx: 1e6, fy: 1e6, cx: 1.5, cy: 1.0 }, width: 4, test, estimate, truth }
    }

    #[test]
    fn vsd_in_closed_form() {
        let taus = [0.005, 0.02];
        // Truth covers 4 pixels, all seen by the sensor.
        let truth = [0.0, 0.5, 0.5, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0];
        let test = [0.8, 0.5, 0.5, 0.8, 0.8, 0.5, 0.5, 0.8, 0.8, 0.8, 0.8, 0.8];
        assert_eq!(vsd(&depth_images(&test, &truth, &truth), 0.015, &taus), vec![0.0, 0.0]);
        // The estimate 1 cm deeper: misaligned for τ = 5 mm, aligned for 2 cm.
        let deeper = truth.map(|z| if z > 0.0 { z + 0.01 } else { 0.0 });
        assert_eq!(vsd(&depth_images(&test, &deeper, &truth), 0.015, &taus), vec![1.0, 0.0]);
        // Shifted one column right: 2 pixels in both, 2 only in the truth,
        // 2 only in the estimate (in front of the background: visible).
        let shifted = [0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(vsd(&depth_images(&test, &shifted, &truth), 0.015, &taus), vec![4.0 / 6.0, 4.0 / 6.0]);
        // No estimate at all: every truth pixel is unmatched.
        let nothing = [0.0; 12];
        assert_eq!(vsd(&depth_images(&test, &nothing, &truth), 0.015, &taus), vec![1.0, 1.0]);
        // An estimate hidden behind an occluder is not visible, so it is not
        // counted against the estimate: the occluded part of the truth...
        let occluded_test = [0.8, 0.3, 0.3, 0.8, 0.8, 0.5, 0.5, 0.8, 0.8, 0.8, 0.8, 0.8];
        let hidden_top = [0.0, 0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0];
        // ...is invisible under the truth as well, so hiding it costs nothing.
        assert_eq!(vsd(&depth_images(&occluded_test, &hidden_top, &truth), 0.015, &taus), vec![0.0, 0.0]);
        // Mismatched sizes compare nothing.
        assert_eq!(vsd(&depth_images(&test[..4], &truth, &truth), 0.015, &taus), vec![1.0, 1.0]);
    }
}
