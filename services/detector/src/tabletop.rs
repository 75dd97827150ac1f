//! Tabletop geometry: the support plane found by RANSAC in the depth image,
//! and the depth pixels above it grouped into clusters, one per object
//! standing on it (the classical detector); masks cleared of the table
//! (both modes).
//!
//! Points are in the camera frame (metres, x right, y down, z forward);
//! planes are `n · p = d` with a unit normal `n` pointing towards the
//! camera (`n · (0, 0, -1) > 0` side: the side objects stand on).

use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};
use poseflow_geometry::sampling::seeded_rng;
use rand::Rng;

use crate::classical::SampledDepth;
use crate::{DetectedObject, ImageView};

/// A plane `normal · p = offset`, `normal` a unit vector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    pub normal: Vector3<f64>,
    pub offset: f64,
}

impl Plane {
    /// Signed distance of `p`, positive on the normal's side.
    pub fn distance(&self, p: &Point3<f64>) -> f64 {
        self.normal.dot(&p.coords) - self.offset
    }

    /// The plane through three points, its normal towards the camera;
    /// `None` when they are (nearly) collinear.
    pub fn through(a: &Point3<f64>, b: &Point3<f64>, c: &Point3<f64>) -> Option<Self> {
        let normal = (b - a).cross(&(c - a));
        let norm = normal.norm();
        (norm > 1e-9).then(|| Self::facing_camera(normal / norm, a))
    }

    /// The least-squares plane of `points` (the smallest principal axis
    /// through their centroid), its normal towards the camera.
    pub fn fit(points: &[Point3<f64>]) -> Option<Self> {
        if points.len() < 3 {
            return None;
        }
        let centroid = points.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / points.len() as f64;
        let scatter = points.iter().fold(Matrix3::zeros(), |s, p| {
            let d = p.coords - centroid;
            s + d * d.transpose()
        });
        let eigen = SymmetricEigen::new(scatter);
        let smallest = eigen.eigenvalues.imin();
        let normal = eigen.eigenvectors.column(smallest).into_owned();
        Some(Self::facing_camera(normal, &Point3::from(centroid)))
    }

    fn facing_camera(normal: Vector3<f64>, on: &Point3<f64>) -> Self {
        // The camera is at the origin: the side it sees has n · (0 − p) > 0.
        let normal = if normal.dot(&on.coords) > 0.0 { -normal } else { normal };
        Self { normal, offset: normal.dot(&on.coords) }
    }
}

/// The plane with the most points within `tolerance` over `iterations`
/// random triples, refitted to its inliers; `None` for fewer than three
/// points.
pub fn ransac_plane(points: &[Point3<f64>], tolerance: f64, iterations: usize, rng: &mut impl Rng) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let inliers = |plane: &Plane| points.iter().filter(|p| plane.distance(p).abs() <= tolerance).count();
    let mut best: Option<(usize, Plane)> = None;
    for _ in 0..iterations {
        let pick = |rng: &mut dyn rand::RngCore| points[rng.random_range(0..points.len())];
        let (a, b, c) = (pick(rng), pick(rng), pick(rng));
        let Some(plane) = Plane::through(&a, &b, &c) else { continue };
        let count = inliers(&plane);
        if best.as_ref().is_none_or(|(n, _)| count > *n) {
            best = Some((count, plane));
        }
    }
    let (_, plane) = best?;
    let support: Vec<Point3<f64>> = points.iter().copied().filter(|p| plane.distance(p).abs() <= tolerance).collect();
    Plane::fit(&support).or(Some(plane))
}

/// The support plane: the RANSAC plane of `points`, if it holds a tenth of
/// them (else the frame has no table in view, or too little of it).
pub fn support_plane(points: &[Point3<f64>], tolerance: f64, iterations: usize, rng: &mut impl Rng) -> Option<Plane> {
    let plane = ransac_plane(points, tolerance, iterations, rng)?;
    let support = points.iter().filter(|p| plane.distance(p).abs() <= tolerance).count();
    (support * 10 >= points.len()).then_some(plane)
}

/// The support plane is sought on every 8th pixel of each 8th row…
const SUPPORT_GRID_DOWN: usize = 8;
/// …among points this close to a candidate plane…
const SUPPORT_TOLERANCE_M: f64 = 0.01;
/// …over this many random triples, with a fixed seed (same frame, same
/// masks).
const SUPPORT_ITERATIONS: usize = 300;
const SUPPORT_SEED: u64 = 0;

/// Removes from each mask of `objects` the pixels whose depth puts them on
/// the frame's support plane or behind it (less than `margin` metres in
/// front of it): the table under and around an object, which masks scaled
/// up from coarse cells take in, and which turns the pose stages. A mask
/// that would lose every pixel is kept whole (an object lying flat), and
/// masks stay as they are when the frame has no support plane. Each box is
/// shrunk to its mask. Returns the pixels removed.
pub fn drop_support_pixels(objects: &mut [DetectedObject], image: &ImageView<'_>, margin: f64) -> usize {
    if objects.is_empty() {
        return 0;
    }
    let grid = SampledDepth::of(image, SUPPORT_GRID_DOWN, f64::INFINITY);
    let measured: Vec<Point3<f64>> = grid.points.iter().flatten().copied().collect();
    let mut rng = seeded_rng(SUPPORT_SEED);
    let Some(plane) = support_plane(&measured, SUPPORT_TOLERANCE_M, SUPPORT_ITERATIONS, &mut rng) else {
        return 0;
    };
    let c = &image.camera;
    let mut removed = 0;
    for object in objects.iter_mut() {
        let [x, y, w, _] = object.bbox.map(|v| v as usize);
        let on_table = |i: usize| {
            let (u, v) = (x + i % w, y + i / w);
            let z = f64::from(image.depth[v * image.width + u]);
            let point = Point3::new((u as f64 - c.cx) / c.fx * z, (v as f64 - c.cy) / c.fy * z, z);
            z.is_finite() && z > 0.0 && plane.distance(&point) < margin
        };
        let kept: Vec<bool> = object.mask.iter().enumerate().map(|(i, &inside)| inside && !on_table(i)).collect();
        if !kept.contains(&true) {
            continue;
        }
        removed += object.mask.iter().filter(|&&m| m).count() - kept.iter().filter(|&&m| m).count();
        (object.bbox, object.mask) = tight(object.bbox, &kept);
    }
    removed
}

/// A box and its row-major mask cut down to the mask's own bounds (`mask`
/// holds at least one pixel).
fn tight(bbox: [u32; 4], mask: &[bool]) -> ([u32; 4], Vec<bool>) {
    let w = bbox[2] as usize;
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for i in (0..mask.len()).filter(|&i| mask[i]) {
        let (x, y) = (i % w, i / w);
        (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x), y1.max(y));
    }
    let cut = (y0..=y1).flat_map(|y| mask[y * w + x0..=y * w + x1].iter().copied()).collect();
    ([bbox[0] + x0 as u32, bbox[1] + y0 as u32, (x1 - x0 + 1) as u32, (y1 - y0 + 1) as u32], cut)
}

/// Clusters of an organised point grid (`width` columns, `None` where there
/// is no point): 4-neighbours closer than `gap` metres join. Returns each
/// cluster's cell indices, largest first.
pub fn clusters(grid: &[Option<Point3<f64>>], width: usize, gap: f64) -> Vec<Vec<usize>> {
    let height = grid.len() / width.max(1);
    let mut seen = vec![false; grid.len()];
    let mut found = Vec::new();
    let mut stack = Vec::new();
    for start in 0..grid.len() {
        if seen[start] || grid[start].is_none() {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut cluster = Vec::new();
        while let Some(i) = stack.pop() {
            cluster.push(i);
            let p = grid[i].expect("only points are pushed");
            for n in crate::grid_neighbours(i, width, height).into_iter().flatten() {
                if let Some(q) = grid[n]
                    && !seen[n]
                    && (q - p).norm() < gap
                {
                    seen[n] = true;
                    stack.push(n);
                }
            }
        }
        found.push(cluster);
    }
    found.sort_by(|a, b| b.len().cmp(&a.len()).then(a[0].cmp(&b[0])));
    found
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::Rng;

    #[test]
    fn three_points_give_their_plane_facing_the_camera() {
        // The table z = 1 m seen from the origin: normal (0, 0, −1), offset −1.
        let plane =
            Plane::through(&Point3::new(0.0, 0.0, 1.0), &Point3::new(1.0, 0.0, 1.0), &Point3::new(0.0, 1.0, 1.0))
                .unwrap();
        assert!((plane.normal - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
        assert!((plane.offset + 1.0).abs() < 1e-12);
        // A point 10 cm nearer the camera is 10 cm above the table.
        assert!((plane.distance(&Point3::new(0.3, 0.2, 0.9)) - 0.1).abs() < 1e-12);
        assert!(Plane::through(&Point3::origin(), &Point3::new(1.0, 1.0, 1.0), &Point3::new(2.0, 2.0, 2.0)).is_none());
    }

    #[test]
    fn ransac_finds_the_table_under_clutter() {
        let mut rng = seeded_rng(1);
        // A tilted table z = 1 + y (its camera-facing normal ∝ (0, 1, −1))
        // sampled on a grid, plus points standing 5–10 cm above it: 400
        // table, 100 clutter.
        let normal = Vector3::new(0.0, 1.0, -1.0).normalize();
        let on_table = |u: f64, v: f64| Point3::new(u, v, 1.0 + v);
        let mut points: Vec<Point3<f64>> =
            (0..400).map(|i| on_table(-0.5 + (i % 20) as f64 * 0.05, -0.5 + (i / 20) as f64 * 0.05)).collect();
        points.extend(
            (0..100).map(|i| {
                on_table(0.05 * (i % 10) as f64, 0.05 * (i / 10) as f64) + normal * (0.05 + 0.0005 * i as f64)
            }),
        );
        let plane = ransac_plane(&points, 0.005, 100, &mut rng).unwrap();
        assert!((plane.normal - normal).norm() < 1e-9, "{plane:?}");
        let above = points.iter().filter(|p| plane.distance(p) > 0.01).count();
        assert_eq!(above, 100);
    }

    /// A 64 × 48 frame of a table 1 m ahead, facing the camera, with a box
    /// whose top stands 5 cm above it on pixels 20..30 × 10..20.
    fn tabletop_frame() -> (Vec<f32>, Vec<f32>) {
        let (w, h) = (64, 48);
        let on_box = |u: usize, v: usize| (20..30).contains(&u) && (10..20).contains(&v);
        let depth = (0..w * h).map(|i| if on_box(i % w, i / w) { 0.95 } else { 1.0 }).collect();
        (vec![128.0; 3 * w * h], depth)
    }

    fn image<'a>(rgb: &'a [f32], depth: &'a [f32]) -> ImageView<'a> {
        let camera = poseflow_geometry::metrics::Pinhole { fx: 60.0, fy: 60.0, cx: 32.0, cy: 24.0 };
        ImageView { rgb, depth, width: 64, height: 48, camera }
    }

    fn detection(bbox: [u32; 4]) -> DetectedObject {
        let mask = vec![true; (bbox[2] * bbox[3]) as usize];
        DetectedObject { obj_id: 1, instance: 0, score: 1.0, bbox, mask }
    }

    #[test]
    fn the_table_around_an_object_leaves_its_mask() {
        let (rgb, depth) = tabletop_frame();
        // The box's mask, two pixels too wide all round; a second mask lying
        // all on the table; a third that starts without its box tight.
        let mut objects = vec![detection([18, 8, 14, 14]), detection([40, 30, 6, 6]), detection([20, 10, 10, 10])];
        objects[2].mask.iter_mut().take(10).for_each(|m| *m = false);
        let removed = drop_support_pixels(&mut objects, &image(&rgb, &depth), 0.005);
        assert_eq!(removed, 14 * 14 - 100);
        assert_eq!(objects[0].bbox, [20, 10, 10, 10]);
        assert!(objects[0].mask.iter().all(|&m| m));
        assert_eq!(objects[1], detection([40, 30, 6, 6]), "a mask all on the table is kept whole");
        assert_eq!(objects[2].bbox, [20, 11, 10, 9], "each box is shrunk to its mask");
        // A box 3 mm tall is on the table at a 5 mm margin but not at 2 mm.
        let depth: Vec<f32> = depth.iter().map(|&z| if z < 1.0 { 0.997 } else { z }).collect();
        let mut objects = vec![detection([18, 8, 14, 14])];
        assert_eq!(drop_support_pixels(&mut objects, &image(&rgb, &depth), 0.002), 14 * 14 - 100);
    }

    #[test]
    fn masks_stay_as_they_are_without_a_support_plane() {
        // Depth scattered over 0.5–1.5 m: no plane holds a tenth of it.
        let (rgb, _) = tabletop_frame();
        let mut rng = seeded_rng(3);
        let depth: Vec<f32> = (0..64 * 48).map(|_| rng.random_range(0.5..1.5)).collect();
        let mut objects = vec![detection([18, 8, 14, 14])];
        assert_eq!(drop_support_pixels(&mut objects, &image(&rgb, &depth), 0.005), 0);
        assert_eq!(objects, vec![detection([18, 8, 14, 14])]);
    }

    proptest! {
        #[test]
        fn dropping_the_table_only_removes_pixels(
            x in 0u32..50, y in 0u32..36, w in 1u32..14, h in 1u32..12, bits in proptest::collection::vec(any::<bool>(), 20)
        ) {
            let (rgb, depth) = tabletop_frame();
            let mask: Vec<bool> = (0..(w * h) as usize).map(|i| bits[i % bits.len()]).collect();
            let before = DetectedObject { obj_id: 1, instance: 0, score: 1.0, bbox: [x, y, w, h], mask };
            let mut objects = vec![before.clone()];
            let removed = drop_support_pixels(&mut objects, &image(&rgb, &depth), 0.005);
            let after = &objects[0];
            let frame_before = before.frame_mask(64, 48);
            let frame_after = after.frame_mask(64, 48);
            let count = |m: &[bool]| m.iter().filter(|&&p| p).count();
            prop_assert_eq!(count(&frame_before) - count(&frame_after), removed);
            prop_assert!(frame_after.iter().zip(&frame_before).all(|(&a, &b)| !a || b));
            prop_assert!(count(&frame_after) > 0 || count(&frame_before) == 0);
        }
    }

    #[test]
    fn clusters_split_at_depth_gaps_and_missing_points() {
        // A 4 × 2 grid: two points at 1 m, a hole, one at 1.5 m (a gap), and
        // below them a row joining the first two.
        let at = |z: f64| Some(Point3::new(0.0, 0.0, z));
        let grid = [at(1.0), at(1.001), None, at(1.5), at(1.0), None, None, at(1.501)];
        let found = clusters(&grid, 4, 0.01);
        assert_eq!(found.len(), 2);
        let mut first = found[0].clone();
        first.sort_unstable();
        assert_eq!(first, [0, 1, 4]);
        let mut second = found[1].clone();
        second.sort_unstable();
        assert_eq!(second, [3, 7]);
    }

    proptest! {
        /// Every point belongs to exactly one cluster, and neighbours closer
        /// than the gap share theirs.
        #[test]
        fn clusters_partition_the_points(
            depths in proptest::collection::vec(proptest::option::of(1.0f64..1.05), 6 * 5),
        ) {
            let grid: Vec<Option<Point3<f64>>> = depths.iter().map(|d| d.map(|z| Point3::new(0.0, 0.0, z))).collect();
            let found = clusters(&grid, 6, 0.02);
            let mut owner = vec![usize::MAX; grid.len()];
            for (k, cluster) in found.iter().enumerate() {
                for &i in cluster {
                    prop_assert_eq!(owner[i], usize::MAX, "cell {} in two clusters", i);
                    owner[i] = k;
                }
            }
            for (i, p) in grid.iter().enumerate() {
                prop_assert_eq!(p.is_some(), owner[i] != usize::MAX);
                if let (Some(p), true) = (p, i % 6 + 1 < 6)
                    && let Some(q) = grid[i + 1]
                    && (q - p).norm() < 0.02
                {
                    prop_assert_eq!(owner[i], owner[i + 1]);
                }
            }
        }
    }
}
