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
/// `(0, max_depth]` (row-major rasters of the camera's size), in raster
/// order; only image rows `rows.0..=rows.1` are read (the mask's rows).
pub fn back_project(
    depth: &[f32],
    mask: &[bool],
    camera: &Camera,
    rows: (u32, u32),
    max_depth: f32,
) -> Vec<Point3<f32>> {
    let width = (camera.width as usize).max(1);
    let (fx, fy, cx, cy) = (camera.fx as f32, camera.fy as f32, camera.cx as f32, camera.cy as f32);
    let span = rows.0 as usize * width..((rows.1 as usize + 1) * width).min(mask.len()).min(depth.len());
    let first = span.start;
    mask.get(span.clone())
        .unwrap_or_default()
        .iter()
        .zip(depth.get(span).unwrap_or_default())
        .enumerate()
        .filter(|&(_, (&inside, &z))| inside && z > 0.0 && z <= max_depth)
        .map(|(i, (_, &z))| {
            let i = first + i;
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
/// stray points far from the object would otherwise make a huge, empty grid
/// (an empty cell costs 4 bytes and one step of a prefix sum).
const MAX_CELLS_PER_POINT: usize = 32;

/// Points whose k-th nearest neighbour sizes the statistical filter's grid.
const REACH_PROBES: usize = 32;

/// The statistical filter's cells, in median k-th-neighbour distances:
/// wide enough that most points need one cube of 3 × 3 × 3 cells (`cargo
/// bench -p poseflow-ingest`: 1.2–1.4 fastest, 0.8 and 1.8 slower).
const REACH_MARGIN: f32 = 1.2;

/// A dense uniform grid over the points' bounding box for neighbour
/// queries: points sorted by cell (counting sort), so the cells of one grid
/// row are one run of consecutive points, and a cube of cells is a few
/// such runs.
struct Grid {
    cell: f32,
    origin: Point3<f32>,
    dims: [usize; 3],
    /// Points `starts[c]..starts[c + 1]` of `sorted` are those of cell `c`.
    starts: Vec<u32>,
    /// The points in cell order, and the input index of each.
    sorted: Vec<Point3<f32>>,
    order: Vec<u32>,
}

impl Grid {
    fn new(points: &[Point3<f32>], cell: f32) -> Self {
        let (min, max) = bounds(points);
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
        let mut grid = Self { cell, origin: min, dims, starts: Vec::new(), sorted: Vec::new(), order: Vec::new() };
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
        grid.sorted = order.iter().map(|&i| points[i as usize]).collect();
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

    /// The positions in `sorted` of the points in the cells within
    /// Chebyshev distance `radius` of `key`, as runs (one per grid row).
    fn cube(&self, key: [usize; 3], radius: usize, mut visit: impl FnMut(std::ops::Range<usize>)) {
        let span = |axis: usize| key[axis].saturating_sub(radius)..=(key[axis] + radius).min(self.dims[axis] - 1);
        let (xs, ys) = (span(0), span(1));
        for z in span(2) {
            for y in ys.clone() {
                let first = self.starts[self.index([*xs.start(), y, z])] as usize;
                let last = self.starts[self.index([*xs.end(), y, z]) + 1] as usize;
                visit(first..last);
            }
        }
    }

    /// The squared distances (as [`f32::to_bits`]) from the point at
    /// `sorted[at]` to its `k` nearest other points (fewer if there are not
    /// k), ascending, into `nearest`. Exact: the cube of
    /// cells searched grows until no point outside it can be nearer than
    /// the k-th found (strays far from the rest need a large one).
    fn nearest(&self, at: usize, k: usize, nearest: &mut Vec<u32>) {
        let p = self.sorted[at];
        let key = self.key(&p);
        // How far `p` is from its own cell's nearest wall: every point
        // outside the cube of radius r is at least r · cell + this far away.
        let wall = (0..3)
            .map(|axis| {
                let low = self.origin[axis] + key[axis] as f32 * self.cell;
                (p[axis] - low).min(low + self.cell - p[axis]).max(0.0)
            })
            .fold(f32::INFINITY, f32::min);
        let max_radius = self.dims.iter().max().copied().unwrap_or(1);
        let mut radius = 1;
        loop {
            // Every candidate's squared distance (its own, 0, among them),
            // then the k + 1 smallest: one selection is cheaper than keeping
            // a sorted list as candidates come. Squared distances are never
            // negative, so their bits order as they do (integer compares).
            nearest.clear();
            self.cube(key, radius, |run| {
                nearest.extend(self.sorted[run].iter().map(|q| (q - p).norm_squared().to_bits()))
            });
            if nearest.len() > k + 1 {
                nearest.select_nth_unstable(k);
                nearest.truncate(k + 1);
            }
            nearest.sort_unstable();
            // Its own distance is a smallest one (any other 0 is a duplicate
            // point, a neighbour at the same distance).
            nearest.remove(0);
            if radius >= max_radius {
                return;
            }
            radius = if nearest.len() == k {
                // The cube that holds every point as near as the k-th found:
                // searched once more, it holds the k nearest.
                let needed = ((f32::from_bits(nearest[k - 1]).sqrt() - wall) / self.cell).ceil().max(1.0) as usize;
                if needed <= radius {
                    return;
                }
                needed.min(max_radius)
            } else {
                (2 * radius).min(max_radius)
            };
        }
    }

    /// Mean distance from the point at `sorted[at]` to its `k` nearest
    /// other points.
    fn mean_knn_distance(&self, at: usize, k: usize, nearest: &mut Vec<u32>) -> f32 {
        self.nearest(at, k, nearest);
        nearest.iter().map(|&d2| f32::from_bits(d2).sqrt()).sum::<f32>() / nearest.len().max(1) as f32
    }

    /// How many other points lie within `radius` of the point at
    /// `sorted[at]` (cells at least `radius` wide).
    fn count_within(&self, at: usize, radius: f32) -> usize {
        let p = self.sorted[at];
        let mut count = 0;
        self.cube(self.key(&p), 1, |run| {
            count += run.filter(|&j| j != at && (self.sorted[j] - p).norm() <= radius).count();
        });
        count
    }

    /// `per_point` of every point, indexed as the input, computed in cell
    /// order (neighbouring queries touch the same memory).
    fn map<T: Default + Clone>(&self, mut per_point: impl FnMut(&Self, usize) -> T) -> Vec<T> {
        let mut out = vec![T::default(); self.sorted.len()];
        for (at, &i) in self.order.iter().enumerate() {
            out[i as usize] = per_point(self, at);
        }
        out
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
            let k = neighbours.max(1);
            let grid = Grid::new(&points, knn_reach(&points, k));
            let mut nearest = Vec::with_capacity(k + 1);
            let means = grid.map(|grid, at| grid.mean_knn_distance(at, k, &mut nearest));
            let n = means.len() as f32;
            let mean = means.iter().sum::<f32>() / n;
            let std = (means.iter().map(|m| (m - mean).powi(2)).sum::<f32>() / n).sqrt();
            let limit = mean + std_ratio * std;
            points.iter().zip(&means).filter(|&(_, m)| *m <= limit).map(|(p, _)| *p).collect()
        }
        OutlierFilter::Radius { radius, min_neighbours } => {
            let grid = Grid::new(&points, radius.max(1e-6));
            let keep = grid.map(|grid, at| grid.count_within(at, radius) >= min_neighbours);
            points.iter().zip(&keep).filter(|&(_, keep)| *keep).map(|(p, _)| *p).collect()
        }
    }
}

/// The axis-aligned box `(min, max)` of points (at least one).
fn bounds(points: &[Point3<f32>]) -> (Point3<f32>, Point3<f32>) {
    points.iter().fold((points[0], points[0]), |(min, max), p| (min.inf(p), max.sup(p)))
}

/// About how far the k-th nearest neighbour of a point is: the median over
/// a few points spread through the input, found on a grid sized by a first
/// guess. Cells that wide hold most points' k nearest within the first cube
/// of 3 × 3 × 3 cells, with few other points to look at; a guess from the
/// bounding box alone is far off when a few strays stretch it.
fn knn_reach(points: &[Point3<f32>], k: usize) -> f32 {
    let (min, max) = bounds(points);
    // On a surface filling its box's largest face, the k nearest lie
    // within √(k/π) neighbour gaps.
    let e = max - min;
    let face = (e.x * e.y).max(e.y * e.z).max(e.x * e.z);
    let gap = (face / points.len() as f32).sqrt().max(1e-5);
    let guess = Grid::new(points, gap * (k as f32 / std::f32::consts::PI).sqrt());
    let step = points.len().div_ceil(REACH_PROBES).max(1);
    let mut nearest = Vec::with_capacity(k + 1);
    let mut reach: Vec<f32> = (0..points.len())
        .step_by(step)
        .map(|at| {
            guess.nearest(at, k, &mut nearest);
            nearest.last().map_or(0.0, |&d2| f32::from_bits(d2).sqrt())
        })
        .collect();
    let middle = reach.len() / 2;
    let (_, median, _) = reach.select_nth_unstable_by(middle, f32::total_cmp);
    (*median * REACH_MARGIN).max(1e-5)
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
        let points = back_project(&depth, &mask, &cam, (0, 5), 5.0);
        assert_eq!(points.len(), 1);
        // Rows outside the given ones are not read.
        assert!(back_project(&depth, &mask, &cam, (2, 5), 5.0).is_empty());
        assert_eq!(back_project(&depth, &mask, &cam, (1, 1), 5.0), points);
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
    fn neighbour_queries_are_exact() {
        let (points, _) = plane_with_strays();
        let mut nearest = Vec::new();
        // Cells finer and coarser than the neighbourhood: the search stops
        // only once no unvisited cell can hold a nearer point.
        for cell in [0.0007, 0.003, 0.02] {
            let grid = Grid::new(&points, cell);
            let found = grid.map(|grid, at| grid.mean_knn_distance(at, 6, &mut nearest));
            let within = grid.map(|grid, at| grid.count_within(at, cell));
            for (i, p) in points.iter().enumerate() {
                let mut d: Vec<f32> =
                    points.iter().enumerate().filter(|(j, _)| *j != i).map(|(_, q)| (q - p).norm()).collect();
                d.sort_by(f32::total_cmp);
                let brute = d[..6].iter().sum::<f32>() / 6.0;
                assert!((found[i] - brute).abs() < 1e-6, "cell {cell}, point {i}: {} vs {brute}", found[i]);
                assert_eq!(within[i], d.iter().filter(|&&d| d <= cell).count(), "cell {cell}, point {i}");
            }
        }
    }

    /// Both filters by their definitions, point against every point.
    fn brute_force(points: &[Point3<f32>], filter: &OutlierFilter) -> Vec<Point3<f32>> {
        let distances = |i: usize| -> Vec<f32> {
            let mut d: Vec<f32> =
                (0..points.len()).filter(|&j| j != i).map(|j| (points[j] - points[i]).norm_squared()).collect();
            d.sort_by(f32::total_cmp);
            d
        };
        match *filter {
            OutlierFilter::None => points.to_vec(),
            OutlierFilter::Statistical { neighbours, std_ratio } => {
                if points.len() <= neighbours.max(1) {
                    return points.to_vec();
                }
                let k = neighbours.max(1);
                let means: Vec<f32> = (0..points.len())
                    .map(|i| distances(i)[..k].iter().map(|d2| d2.sqrt()).sum::<f32>() / k as f32)
                    .collect();
                let n = means.len() as f32;
                let mean = means.iter().sum::<f32>() / n;
                let std = (means.iter().map(|m| (m - mean).powi(2)).sum::<f32>() / n).sqrt();
                (0..points.len()).filter(|&i| means[i] <= mean + std_ratio * std).map(|i| points[i]).collect()
            }
            OutlierFilter::Radius { radius, min_neighbours } => (0..points.len())
                .filter(|&i| distances(i).iter().filter(|&&d2| d2.sqrt() <= radius).count() >= min_neighbours)
                .map(|i| points[i])
                .collect(),
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(200))]

        /// The grid gives exactly what the definitions give, whatever the
        /// spread of the cloud: a noisy patch of surface, strays far from
        /// it, repeated points.
        #[test]
        fn the_filters_keep_exactly_what_their_definitions_keep(
            seed in 0u64..1_000_000,
            surface in 20usize..400,
            strays in 0usize..12,
            repeats in 0usize..5,
            neighbours in 1usize..24,
            // Tenths of a millimetre: proptest's f32 range sampler trips a
            // debug assertion on some seeds.
            radius_mm in proptest::strategy::Strategy::prop_map(10u16..200, |tenths| f32::from(tenths) / 10.0),
        ) {
            let mut rng = seeded_rng(seed);
            let mut points: Vec<Point3<f32>> = (0..surface)
                .map(|_| {
                    let (u, v): (f32, f32) = (rng.random_range(-0.05..0.05), rng.random_range(-0.05..0.05));
                    Point3::new(u, v, 0.7 + 0.3 * u * u + rng.random_range(-0.001..0.001))
                })
                .collect();
            for _ in 0..strays {
                points.push(Point3::new(rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3), rng.random_range(0.3..1.5)));
            }
            for r in 0..repeats {
                points.push(points[r * 7 % surface]);
            }
            for filter in [
                OutlierFilter::Statistical { neighbours, std_ratio: 2.0 },
                OutlierFilter::Radius { radius: radius_mm / 1000.0, min_neighbours: neighbours },
            ] {
                proptest::prop_assert_eq!(remove_outliers(points.clone(), &filter), brute_force(&points, &filter), "{:?}", filter);
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
