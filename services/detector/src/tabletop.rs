//! Tabletop geometry for the classical detector (no training): the support
//! plane found by RANSAC in the depth image, and the depth pixels above it
//! grouped into clusters, one per object standing on it.
//!
//! Points are in the camera frame (metres, x right, y down, z forward);
//! planes are `n · p = d` with a unit normal `n` pointing towards the
//! camera (`n · (0, 0, -1) > 0` side: the side objects stand on).

use nalgebra::{Matrix3, Point3, SymmetricEigen, Vector3};
use rand::Rng;

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
    use poseflow_geometry::sampling::seeded_rng;
    use proptest::prelude::*;

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
