//! The partial point cloud of one object: back-projection of masked depth,
//! outlier removal, farthest-point sampling to a fixed count, centring.
//!
//! Points are camera-frame metres (OpenCV axes), `f32`.

use nalgebra::Point3;
use poseflow_geometry::sampling::farthest_point_indices;
use poseflow_scene::Camera;
use rand::Rng;
use serde::{Deserialize, Serialize};

/// How stray points (sensor noise at edges, background pixels inside a
/// loose mask) are removed before sampling.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum OutlierFilter {
    None,
    /// Statistical: drop points whose mean distance to their `neighbours`
    /// nearest neighbours exceeds the mean of that statistic by more than
    /// `std_ratio` standard deviations.
    Statistical {
        neighbours: usize,
        std_ratio: f32,
    },
    /// Radius: drop points with fewer than `min_neighbours` others within
    /// `radius` metres.
    Radius {
        radius: f32,
        min_neighbours: usize,
    },
}

impl Default for OutlierFilter {
    fn default() -> Self {
        Self::Statistical { neighbours: 16, std_ratio: 2.0 }
    }
}

/// Camera-frame points of the `mask` pixels that have a depth in
/// `(0, max_depth]` (row-major rasters of the camera's size).
pub fn back_project(depth: &[f32], mask: &[bool], camera: &Camera, max_depth: f32) -> Vec<Point3<f32>> {
    let width = camera.width as usize;
    let (fx, fy, cx, cy) = (camera.fx as f32, camera.fy as f32, camera.cx as f32, camera.cy as f32);
    mask.iter()
        .zip(depth)
        .enumerate()
        .filter(|&(_, (&inside, &z))| inside && z > 0.0 && z <= max_depth)
        .map(|(i, (_, &z))| {
            let (u, v) = ((i % width) as f32, (i / width) as f32);
            Point3::new((u - cx) * z / fx, (v - cy) * z / fy, z)
        })
        .collect()
}

/// Every `k`-th point so that at most `limit` remain, keeping order.
pub fn thin(points: Vec<Point3<f32>>, limit: usize) -> Vec<Point3<f32>> {
    if points.len() <= limit || limit == 0 {
        return points;
    }
    let step = points.len().div_ceil(limit);
    points.into_iter().step_by(step).collect()
}

/// Cells per point a neighbour grid may have at most (coarser cells beyond):
/// stray points far from the object would otherwise make a huge, empty grid.
const MAX_CELLS_PER_POINT: usize = 4;

/// A dense uniform grid over the points' bounding box for neighbour
/// queries: point indices sorted by cell (counting sort), so a cell's
/// points are one slice.
struct Grid<'a> {
    points: &'a [Point3<f32>],
    cell: f32,
    origin: Point3<f32>,
    dims: [usize; 3],
    /// `order[starts[c]..starts[c + 1]]` are the points of cell `c`.
    starts: Vec<u32>,
    order: Vec<u32>,
}

impl<'a> Grid<'a> {
    fn new(points: &'a [Point3<f32>], cell: f32) -> Self {
        let (mut min, mut max) = (points[0], points[0]);
        for p in points {
            min = min.inf(p);
            max = max.sup(p);
        }
        let extent = max - min;
        let dims_for = |cell: f32| extent.map(|e| (e / cell).floor() as usize + 1);
        let mut cell = cell.max(1e-6);
        let mut dims = dims_for(cell);
        let max_cells = (MAX_CELLS_PER_POINT * points.len()).max(64);
        while dims.iter().product::<usize>() > max_cells {
            cell *= 2.0;
            dims = dims_for(cell);
        }
        let dims = [dims.x, dims.y, dims.z];
        let mut grid = Self { points, cell, origin: min, dims, starts: Vec::new(), order: Vec::new() };
        let cells: Vec<u32> = points.iter().map(|p| grid.index(grid.key(p)) as u32).collect();
        let mut starts = vec![0u32; dims.iter().product::<usize>() + 1];
        for &c in &cells {
            starts[c as usize + 1] += 1;
        }
        for c in 1..starts.len() {
            starts[c] += starts[c - 1];
        }
        let mut next = starts.clone();
        let mut order = vec![0u32; points.len()];
        for (i, &c) in cells.iter().enumerate() {
            order[next[c as usize] as usize] = i as u32;
            next[c as usize] += 1;
        }
        grid.starts = starts;
        grid.order = order;
        grid
    }

    fn key(&self, p: &Point3<f32>) -> [usize; 3] {
        let d = (p - self.origin) / self.cell;
        [0, 1, 2].map(|k| (d[k].max(0.0) as usize).min(self.dims[k] - 1))
    }

    fn index(&self, [x, y, z]: [usize; 3]) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    /// Calls `visit` with every point index in the cells at Chebyshev
    /// distance exactly `ring` from `key`.
    fn ring(&self, key: [usize; 3], ring: isize, visit: &mut impl FnMut(u32)) {
        // The neighbouring coordinate along `axis`, if inside the grid.
        let step = |axis: usize, d: isize| {
            let v = key[axis] as isize + d;
            (v >= 0 && (v as usize) < self.dims[axis]).then_some(v as usize)
        };
        for dz in -ring..=ring {
            let Some(z) = step(2, dz) else { continue };
            for dy in -ring..=ring {
                let Some(y) = step(1, dy) else { continue };
                for dx in -ring..=ring {
                    if dx.abs().max(dy.abs()).max(dz.abs()) != ring {
                        continue;
                    }
                    let Some(x) = step(0, dx) else { continue };
                    let c = self.index([x, y, z]);
                    for &j in &self.order[self.starts[c] as usize..self.starts[c + 1] as usize] {
                        visit(j);
                    }
                }
            }
        }
    }

    /// Mean distance from point `i` to its `k` nearest other points (exact:
    /// rings grow until no unvisited cell can hold a closer point).
    fn mean_knn_distance(&self, i: usize, k: usize, nearest: &mut Vec<f32>) -> f32 {
        let p = &self.points[i];
        let key = self.key(p);
        // How far `p` is from its own cell's nearest wall: every point in
        // ring r + 1 is at least r · cell + this far away.
        let wall = (0..3)
            .map(|axis| {
                let low = self.origin[axis] + key[axis] as f32 * self.cell;
                (p[axis] - low).min(low + self.cell - p[axis]).max(0.0)
            })
            .fold(f32::INFINITY, f32::min);
        nearest.clear();
        let max_ring = self.dims.iter().max().copied().unwrap_or(1) as isize;
        let mut ring = 0;
        loop {
            self.ring(key, ring, &mut |j| {
                // Squared distances, sorted ascending; most candidates fail
                // the first comparison once k are known.
                let d2 = (self.points[j as usize] - p).norm_squared();
                if j as usize != i && (nearest.len() < k || d2 < nearest[k - 1]) {
                    let at = nearest.partition_point(|&x| x < d2);
                    nearest.insert(at, d2);
                    nearest.truncate(k);
                }
            });
            let reach = ring as f32 * self.cell + wall;
            if (nearest.len() == k && nearest[k - 1] <= reach * reach) || ring >= max_ring {
                break;
            }
            ring += 1;
        }
        nearest.iter().map(|d2| d2.sqrt()).sum::<f32>() / nearest.len().max(1) as f32
    }

    fn count_within(&self, i: usize, radius: f32) -> usize {
        let p = &self.points[i];
        let mut count = 0;
        for ring in 0..=1 {
            self.ring(self.key(p), ring, &mut |j| {
                count += usize::from(j as usize != i && (self.points[j as usize] - p).norm() <= radius)
            });
        }
        count
    }
}

/// The points that pass `filter`, in their original order.
pub fn remove_outliers(points: Vec<Point3<f32>>, filter: &OutlierFilter) -> Vec<Point3<f32>> {
    match *filter {
        OutlierFilter::None => points,
        OutlierFilter::Statistical { neighbours, std_ratio } => {
            if points.len() <= neighbours.max(1) {
                return points;
            }
            // On a surface the k nearest lie within about √(k/π) neighbour
            // gaps: cells half of √k gaps wide hold them within one or two
            // rings while each ring stays small (`cargo bench -p
            // poseflow-ingest`: 14 % faster than √k-wide cells).
            let k = neighbours.max(1);
            let grid = Grid::new(&points, typical_spacing(&points) * (k as f32).sqrt() / 2.0);
            let mut nearest = Vec::with_capacity(k + 1);
            let means: Vec<f32> = (0..points.len()).map(|i| grid.mean_knn_distance(i, k, &mut nearest)).collect();
            let n = means.len() as f32;
            let mean = means.iter().sum::<f32>() / n;
            let std = (means.iter().map(|m| (m - mean).powi(2)).sum::<f32>() / n).sqrt();
            let limit = mean + std_ratio * std;
            points.iter().zip(&means).filter(|&(_, m)| *m <= limit).map(|(p, _)| *p).collect()
        }
        OutlierFilter::Radius { radius, min_neighbours } => {
            let grid = Grid::new(&points, radius.max(1e-6));
            (0..points.len()).filter(|&i| grid.count_within(i, radius) >= min_neighbours).map(|i| points[i]).collect()
        }
    }
}

/// The side of a cube holding one point, if the points filled their
/// bounding box's largest face: a scale for neighbour grids.
fn typical_spacing(points: &[Point3<f32>]) -> f32 {
    let (mut min, mut max) = (points[0], points[0]);
    for p in points {
        min = min.inf(p);
        max = max.sup(p);
    }
    let e = max - min;
    let face = (e.x * e.y).max(e.y * e.z).max(e.x * e.z);
    (face / points.len() as f32).sqrt().max(1e-5)
}

/// `count` points: farthest-point sampled when there are enough, otherwise
/// all of them plus draws with replacement. Returns the points and how many
/// distinct input points they hold.
pub fn sample_fixed<R: Rng + ?Sized>(points: &[Point3<f32>], count: usize, rng: &mut R) -> (Vec<Point3<f32>>, usize) {
    if points.len() >= count {
        return (farthest_point_indices(points, count).into_iter().map(|i| points[i]).collect(), count);
    }
    let mut out = points.to_vec();
    out.extend((points.len()..count).map(|_| points[rng.random_range(0..points.len())]));
    (out, points.len())
}

/// Subtracts the mean; returns it.
pub fn centre(points: &mut [Point3<f32>]) -> Point3<f32> {
    let mean = points.iter().map(|p| p.coords).sum::<nalgebra::Vector3<f32>>() / points.len().max(1) as f32;
    for p in points.iter_mut() {
        *p -= mean;
    }
    Point3::from(mean)
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_geometry::sampling::seeded_rng;

    fn camera() -> Camera {
        Camera { fx: 500.0, fy: 400.0, cx: 4.0, cy: 3.0, width: 8, height: 6 }
    }

    #[test]
    fn back_projection_inverts_the_pinhole_model() {
        let cam = camera();
        let mut depth = vec![0.0f32; 48];
        let mut mask = vec![false; 48];
        // Pixel (u = 6, v = 1) at 0.8 m; a masked pixel without depth; a
        // pixel with depth outside the mask; one beyond the range.
        depth[8 + 6] = 0.8;
        mask[8 + 6] = true;
        mask[2 * 8 + 2] = true;
        depth[3 * 8 + 3] = 1.0;
        depth[5 * 8 + 7] = 9.0;
        mask[5 * 8 + 7] = true;
        let points = back_project(&depth, &mask, &cam, 5.0);
        assert_eq!(points.len(), 1);
        let p = points[0];
        assert!((p - Point3::new(2.0 * 0.8 / 500.0, -2.0 * 0.8 / 400.0, 0.8)).norm() < 1e-7, "{p}");
        let (u, v) = cam.project(&p.cast::<f64>()).unwrap();
        assert!((u - 6.0).abs() < 1e-5 && (v - 1.0).abs() < 1e-5);
    }

    /// A 20 × 20 grid on the plane z = 1, 5 mm apart, plus stray points.
    fn plane_with_strays() -> (Vec<Point3<f32>>, usize) {
        let mut points: Vec<Point3<f32>> =
            (0..400).map(|i| Point3::new((i % 20) as f32 * 0.005, (i / 20) as f32 * 0.005, 1.0)).collect();
        let strays = [Point3::new(0.05, 0.05, 1.2), Point3::new(0.3, 0.0, 1.0), Point3::new(-0.2, 0.1, 0.9)];
        points.extend(strays);
        (points, 400)
    }

    #[test]
    fn both_filters_drop_strays_and_keep_the_surface() {
        let (points, surface) = plane_with_strays();
        for filter in [
            OutlierFilter::Statistical { neighbours: 8, std_ratio: 2.0 },
            OutlierFilter::Radius { radius: 0.012, min_neighbours: 4 },
        ] {
            let kept = remove_outliers(points.clone(), &filter);
            assert!(kept.iter().all(|p| p.z == 1.0 && p.x <= 0.1), "{filter:?} kept a stray");
            assert!(kept.len() >= surface - 5, "{filter:?} kept only {}", kept.len());
        }
        assert_eq!(remove_outliers(points.clone(), &OutlierFilter::None), points);
    }

    #[test]
    fn knn_distances_are_exact() {
        let (points, _) = plane_with_strays();
        let mut nearest = Vec::new();
        // Cells finer and coarser than the neighbourhood: the search stops
        // only once no unvisited cell can hold a nearer point.
        for cell in [0.0007, 0.003, 0.02] {
            let grid = Grid::new(&points, cell);
            for i in 0..points.len() {
                let mut d: Vec<f32> =
                    points.iter().enumerate().filter(|(j, _)| *j != i).map(|(_, q)| (q - points[i]).norm()).collect();
                d.sort_by(f32::total_cmp);
                let brute = d[..6].iter().sum::<f32>() / 6.0;
                let found = grid.mean_knn_distance(i, 6, &mut nearest);
                assert!((found - brute).abs() < 1e-6, "cell {cell}, point {i}: {found} vs {brute}");
            }
        }
    }

    #[test]
    fn too_few_points_are_resampled_and_reported() {
        let points = vec![Point3::new(1.0, 0.0, 0.0), Point3::new(0.0, 1.0, 0.0), Point3::new(0.0, 0.0, 1.0)];
        let (sampled, distinct) = sample_fixed(&points, 10, &mut seeded_rng(1));
        assert_eq!((sampled.len(), distinct), (10, 3));
        assert!(sampled.iter().all(|p| points.contains(p)));
        assert_eq!(&sampled[..3], &points[..]);
        let (sampled, distinct) = sample_fixed(&points, 2, &mut seeded_rng(1));
        assert_eq!((sampled.len(), distinct), (2, 2));
    }

    #[test]
    fn centring_leaves_zero_mean_and_returns_the_offset() {
        let mut points = vec![Point3::new(1.0, 2.0, 3.0), Point3::new(3.0, 2.0, 1.0)];
        let c = centre(&mut points);
        assert_eq!(c, Point3::new(2.0, 2.0, 2.0));
        assert_eq!(points[0] + points[1].coords, Point3::origin());
    }

    #[test]
    fn thinning_keeps_at_most_the_limit() {
        let points: Vec<Point3<f32>> = (0..1000).map(|i| Point3::new(i as f32, 0.0, 0.0)).collect();
        assert_eq!(thin(points.clone(), 300).len(), 250);
        assert_eq!(thin(points.clone(), 2000).len(), 1000);
    }
}
