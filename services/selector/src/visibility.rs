//! Whether a pose explains what the camera saw of the object, beyond the
//! observed points' distances to its surface. A turned pose can fit every
//! point onto some part of the surface and still be wrong in two ways the
//! distances miss:
//! - its silhouette covers image cells where the mask has no point, or
//!   leaves masked cells unexplained ([`silhouette`]);
//! - it puts points on surface the object itself would hide from the
//!   camera ([`PointFit::hidden_share`]);
//! - it puts the object where the camera saw past it: outside the mask,
//!   the depth lies behind the posed object ([`free_space`]). Unlike an
//!   empty silhouette cell, this cannot be an occluder, which would lie in
//!   front.
//!
//! Camera frame: x right, y down, z forward (metres); pixels: u right, v
//! down, from the image's top-left corner.

use nalgebra::{Point3, Vector3};
use poseflow_geometry::Pose;
use poseflow_geometry::metrics::Pinhole;

/// A line of sight passing this deep inside the object (metres) passes
/// through it: beyond the signed-distance grid's interpolation error at thin
/// parts.
pub const INSIDE_DEPTH: f64 = 0.004;

/// The crop's depth and the object's mask on a G×G grid, as an Observation
/// carries them: row-major over grid rows, cell `(j, i)` sampled at the
/// image pixel nearest to `(x_min + (j + ½)·side/G, y_min + (i + ½)·side/G)`.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthGrid {
    /// The square crop: top-left corner and side, full-image pixels.
    pub x_min: f64,
    pub y_min: f64,
    pub side: f64,
    /// G.
    pub cells: usize,
    /// Camera z, metres; 0 = no depth.
    pub depth: Vec<f32>,
    /// Whether the cell's pixel is the object's.
    pub mask: Vec<bool>,
}

impl DepthGrid {
    /// The image pixel cell `k` sampled (as ingest chose it).
    fn pixel(&self, k: usize) -> (f64, f64) {
        let cell = self.side / self.cells as f64;
        let (j, i) = ((k % self.cells) as f64, (k / self.cells) as f64);
        ((self.x_min + (j + 0.5) * cell).round(), (self.y_min + (i + 0.5) * cell).round())
    }

    /// The cell holding image pixel `(u, v)`; `None` outside the grid.
    fn cell_at(&self, (u, v): (f64, f64)) -> Option<usize> {
        let cell = self.side / self.cells as f64;
        let (j, i) = (((u - self.x_min) / cell).floor(), ((v - self.y_min) / cell).floor());
        let range = 0.0..self.cells as f64;
        (range.contains(&j) && range.contains(&i)).then(|| i as usize * self.cells + j as usize)
    }
}

/// What [`free_space`] found on the lines of sight of a [`DepthGrid`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FreeSpace {
    /// Cells outside the mask where the camera saw past the posed object:
    /// their line of sight passes through it in front of the observed depth.
    pub violated: usize,
    /// Cells in the mask with a depth: the object's observed extent.
    pub masked: usize,
}

impl FreeSpace {
    /// Violations per cell of object the pose claims or the camera saw
    /// (`violated / (violated + masked)`); 0 with nothing to judge.
    pub fn share(&self) -> f64 {
        let judged = self.violated + self.masked;
        if judged == 0 { 0.0 } else { self.violated as f64 / judged as f64 }
    }
}

/// How [`free_space`] tests a line of sight, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FreeSpaceSettings {
    /// The line of sight must pass this deep inside the object …
    pub inside: f64,
    /// … at least this far in front of the observed depth (depth noise,
    /// and mixed pixels at the object's outline).
    pub margin: f64,
}

/// Tests the lines of sight of `grid`'s cells outside the mask against the
/// object at `pose`, by `signed` (model-frame signed distance, negative
/// inside) within the bounding sphere `(centre, radius)` (model frame).
/// Sphere tracing from where the line enters the sphere: each step is the
/// distance to the surface, at least `settings.inside`, so it cannot step
/// over a region deeper than that.
pub fn free_space(
    pose: &Pose,
    grid: &DepthGrid,
    camera: &Pinhole,
    sphere: (Point3<f64>, f64),
    settings: &FreeSpaceSettings,
    signed: impl Fn(&Point3<f64>) -> f64,
) -> FreeSpace {
    let model_from_camera = pose.inverse();
    let centre = pose.transform_point(&sphere.0).coords;
    let mut found = FreeSpace::default();
    for k in 0..grid.cells * grid.cells {
        let observed = f64::from(grid.depth[k]);
        if observed <= 0.0 {
            continue;
        }
        if grid.mask[k] {
            found.masked += 1;
            continue;
        }
        // The line of sight x(z) = z·ray, z the camera depth.
        let (u, v) = grid.pixel(k);
        let ray = Vector3::new((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0);
        let (a, b, c) = (ray.norm_squared(), ray.dot(&centre), centre.norm_squared() - sphere.1 * sphere.1);
        let discriminant = b * b - a * c;
        if discriminant <= 0.0 {
            continue;
        }
        let (enter, leave) = ((b - discriminant.sqrt()) / a, (b + discriminant.sqrt()) / a);
        let end = leave.min(observed - settings.margin);
        let mut z = enter.max(0.0);
        let length = ray.norm();
        while z < end {
            let value = signed(&model_from_camera.transform_point(&Point3::from(ray * z)));
            if value < -settings.inside {
                found.violated += 1;
                break;
            }
            z += value.max(settings.inside) / length;
        }
    }
    found
}

/// How the posed object's silhouette and the observed points agree, on a
/// grid of square cells laid over the silhouette's bounding box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Silhouette {
    /// Share of the silhouette's interior cells (not on its edge) holding an
    /// observed point. Low when the pose puts the object where the mask is
    /// empty (or the object is occluded there).
    pub covered: f64,
    /// Share of the observed points inside the silhouette (grown by one
    /// cell). Low when the pose leaves masked points unexplained.
    pub explained: f64,
}

/// Fewer interior cells than this (a thin object seen edge-on, or one
/// mostly outside the image or behind other things) are too few to judge
/// the silhouette by.
const MIN_INTERIOR_CELLS: usize = 8;

/// Depth this much nearer than the posed object's front surface (metres)
/// is something in front of it: beyond depth noise at working range.
const OCCLUDER_MARGIN: f64 = 0.01;

/// What the camera could have seen of a silhouette. A correct pose's
/// silhouette holds no observed points where it runs off the image or lies
/// behind a nearer surface (a neighbouring object, a hand), so those cells
/// say nothing about the pose.
#[derive(Debug, Clone, Copy, Default)]
pub struct Sightlines<'a> {
    /// The image's width and height, pixels; `None`: not known, every
    /// pixel counts as inside.
    pub image: Option<(f64, f64)>,
    /// The Observation's depth grid, whose unmasked cells show what lies in
    /// front of the object.
    pub depth: Option<&'a DepthGrid>,
}

impl Sightlines<'_> {
    /// Whether the camera could see the object's surface at `depth`
    /// (camera z, metres) along pixel `(u, v)`.
    fn could_see(&self, (u, v): (f64, f64), depth: f64) -> bool {
        let in_image = self.image.is_none_or(|(width, height)| (0.0..width).contains(&u) && (0.0..height).contains(&v));
        let occluded = self.depth.is_some_and(|grid| {
            grid.cell_at((u, v)).is_some_and(|k| {
                let seen = f64::from(grid.depth[k]);
                !grid.mask[k] && seen > 0.0 && seen < depth - OCCLUDER_MARGIN
            })
        });
        in_image && !occluded
    }
}

/// Compares the silhouette of `surface` (model frame, metres: points
/// spread over the whole surface) at `pose` with the pixels of `observed`
/// (camera frame: the object's masked depth points, spread over the mask),
/// on cells `cells_across` to the silhouette's larger side. Interior cells
/// the camera could not see (`sight`) are left out of `covered`. `None`
/// when nothing projects, or too few interior cells are left to judge.
pub fn silhouette(
    pose: &Pose,
    surface: &[Point3<f64>],
    observed: &[Point3<f64>],
    camera: &Pinhole,
    cells_across: usize,
    sight: &Sightlines,
) -> Option<Silhouette> {
    let posed: Vec<(f64, (f64, f64))> = surface
        .iter()
        .map(|p| pose.transform_point(p))
        .filter_map(|x| camera.pixel(&x).map(|pixel| (x.z, pixel)))
        .collect();
    let seen: Vec<(f64, f64)> = observed.iter().filter_map(|x| camera.pixel(x)).collect();
    if posed.is_empty() || seen.is_empty() {
        return None;
    }
    let (mut low, mut high) = ((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY));
    for &(_, (u, v)) in &posed {
        (low, high) = ((low.0.min(u), low.1.min(v)), (high.0.max(u), high.1.max(v)));
    }
    let cell = ((high.0 - low.0).max(high.1 - low.1) / cells_across.max(1) as f64).max(1.0);
    // A margin of two cells around the silhouette, so that grown cells and
    // nearby observed points index inside the grid.
    let side = (cells_across + 5) as i64;
    let index = |(u, v): (f64, f64)| -> Option<usize> {
        let (i, j) = (((u - low.0) / cell).floor() as i64 + 2, ((v - low.1) / cell).floor() as i64 + 2);
        ((0..side).contains(&i) && (0..side).contains(&j)).then(|| (j * side + i) as usize)
    };
    let n = (side * side) as usize;
    let mut inside = vec![false; n];
    // The object's front surface in each cell: camera z, metres.
    let mut front = vec![f64::INFINITY; n];
    for &(z, pixel) in &posed {
        if let Some(k) = index(pixel) {
            inside[k] = true;
            front[k] = front[k].min(z);
        }
    }
    let centre = |k: usize| {
        let (i, j) = ((k as i64 % side - 2) as f64, (k as i64 / side - 2) as f64);
        (low.0 + (i + 0.5) * cell, low.1 + (j + 0.5) * cell)
    };
    let mut hit = vec![false; n];
    for &pixel in &seen {
        if let Some(k) = index(pixel) {
            hit[k] = true;
        }
    }
    // Only the silhouette's interior is judged: a cell on its edge may hold
    // a sliver of the mask, and the sensor loses depth at object edges, so
    // an edge cell without points says nothing. Nor does a cell the camera
    // could not see.
    let interior: Vec<usize> = (0..n)
        .filter(|&k| {
            let (i, j) = ((k as i64) % side, (k as i64) / side);
            inside[k]
                && [(-1, 0), (1, 0), (0, -1), (0, 1)].iter().all(|(di, dj)| {
                    let (a, b) = (i + di, j + dj);
                    (0..side).contains(&a) && (0..side).contains(&b) && inside[(b * side + a) as usize]
                })
                && sight.could_see(centre(k), front[k])
        })
        .collect();
    if interior.len() < MIN_INTERIOR_CELLS {
        return None;
    }
    let covered = interior.iter().filter(|&&k| hit[k]).count();
    let grown = |k: usize| -> bool {
        let (i, j) = ((k as i64) % side, (k as i64) / side);
        (-1..=1).any(|dj| {
            (-1..=1).any(|di| {
                let (a, b) = (i + di, j + dj);
                (0..side).contains(&a) && (0..side).contains(&b) && inside[(b * side + a) as usize]
            })
        })
    };
    let explained = seen.iter().filter(|&&pixel| index(pixel).is_some_and(grown)).count();
    Some(Silhouette {
        covered: covered as f64 / interior.len() as f64,
        explained: explained as f64 / seen.len() as f64,
    })
}

/// How the observed points sit on the surface at a pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointFit {
    /// Share of the points within the inlier distance of the surface.
    pub inlier_share: f64,
    /// Root mean square of the points' distances to the surface, each
    /// capped at the inlier distance (metres): the fit's quality where the
    /// inlier share saturates.
    pub rms_residual: f64,
    /// Share of the inliers the object at the pose would hide from the
    /// camera: the line of sight to them passes through the object.
    pub hidden_share: f64,
}

/// How [`point_fit`] measures, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitSettings {
    /// A point this close to the surface is an inlier; residuals are capped
    /// here.
    pub inlier_distance: f64,
    /// A line of sight passing this deep inside the object hides its point.
    pub hidden_depth: f64,
    /// How far towards the camera a line of sight is followed: the object's
    /// size.
    pub reach: f64,
}

/// Measures how `points` (camera frame) fit the object at `pose`, by
/// `signed`: the signed distance of model-frame points, negative inside.
/// `None` without points.
pub fn point_fit(
    pose: &Pose,
    points: &[Point3<f64>],
    settings: &FitSettings,
    signed: impl Fn(&Point3<f64>) -> f64,
) -> Option<PointFit> {
    if points.is_empty() {
        return None;
    }
    let inverse = pose.inverse();
    let (mut inliers, mut hidden, mut squares) = (0usize, 0usize, 0.0);
    for x in points {
        let residual = signed(&inverse.transform_point(x)).abs().min(settings.inlier_distance);
        squares += residual * residual;
        if residual < settings.inlier_distance {
            inliers += 1;
            hidden += usize::from(line_of_sight_enters(&inverse, x, settings, &signed));
        }
    }
    Some(PointFit {
        inlier_share: inliers as f64 / points.len() as f64,
        rms_residual: (squares / points.len() as f64).sqrt(),
        hidden_share: if inliers == 0 { 0.0 } else { hidden as f64 / inliers as f64 },
    })
}

/// Whether the segment from `x` (camera frame) towards the camera passes
/// more than `hidden_depth` inside the object. Starts past the point's own
/// surface band and steps by the distance to the surface where that is
/// larger than `hidden_depth` (it cannot skip the surface).
fn line_of_sight_enters(
    model_from_camera: &Pose,
    x: &Point3<f64>,
    settings: &FitSettings,
    signed: &impl Fn(&Point3<f64>) -> f64,
) -> bool {
    let towards_camera = -x.coords.normalize();
    let mut travelled = settings.inlier_distance;
    while travelled < settings.reach {
        let value = signed(&model_from_camera.transform_point(&(x + towards_camera * travelled)));
        if value < -settings.hidden_depth {
            return true;
        }
        travelled += value.max(settings.hidden_depth);
    }
    false
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;

    use super::*;

    const CAMERA: Pinhole = Pinhole { fx: 600.0, fy: 600.0, cx: 320.0, cy: 240.0 };

    /// A sphere of radius 5 cm about the model origin: signed distance.
    fn sphere(p: &Point3<f64>) -> f64 {
        p.coords.norm() - 0.05
    }

    /// Points on a sphere of radius `r` (model frame), a Fibonacci lattice.
    fn sphere_points(r: f64, count: usize) -> Vec<Point3<f64>> {
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        (0..count)
            .map(|i| {
                let y = 1.0 - 2.0 * (i as f64 + 0.5) / count as f64;
                let ring = (1.0 - y * y).sqrt();
                let phi = golden * i as f64;
                Point3::new(ring * phi.cos(), y, ring * phi.sin()) * r
            })
            .collect()
    }

    fn at(z: f64) -> Pose {
        Pose::new(nalgebra::Rotation3::identity(), Vector3::new(0.0, 0.0, z))
    }

    const SETTINGS: FitSettings = FitSettings { inlier_distance: 0.005, hidden_depth: 0.004, reach: 0.1 };

    #[test]
    fn the_near_half_of_a_sphere_is_seen_and_the_far_half_hidden() {
        let pose = at(0.5);
        let on_sphere: Vec<_> = sphere_points(0.05, 400).into_iter().map(|p| pose.transform_point(&p)).collect();
        let near: Vec<_> = on_sphere.iter().filter(|x| x.z < 0.49).copied().collect();
        // The far cap, whose lines of sight cross the sphere's middle.
        let far: Vec<_> = on_sphere.iter().filter(|x| x.z > 0.53).copied().collect();
        let fit = point_fit(&pose, &near, &SETTINGS, sphere).unwrap();
        assert_eq!((fit.inlier_share, fit.hidden_share), (1.0, 0.0));
        assert!(fit.rms_residual < 1e-9, "{fit:?}");
        assert_eq!(point_fit(&pose, &far, &SETTINGS, sphere).unwrap().hidden_share, 1.0);
        assert!(point_fit(&pose, &[], &SETTINGS, sphere).is_none());
    }

    #[test]
    fn residuals_are_capped_and_only_inliers_can_be_hidden() {
        let pose = at(0.5);
        // On the near surface, 2 mm off it, and 30 cm off it (capped at 5 mm).
        let points = [Point3::new(0.0, 0.0, 0.45), Point3::new(0.0, 0.0, 0.448), Point3::new(0.0, 0.0, 0.15)];
        let fit = point_fit(&pose, &points, &SETTINGS, sphere).unwrap();
        assert!((fit.inlier_share - 2.0 / 3.0).abs() < 1e-12, "{fit:?}");
        let rms = ((0.002f64.powi(2) + 0.005f64.powi(2)) / 3.0).sqrt();
        assert!((fit.rms_residual - rms).abs() < 1e-9, "{fit:?} {rms}");
        assert_eq!(fit.hidden_share, 0.0);
    }

    #[test]
    fn a_sphere_seen_where_it_is_fills_its_silhouette_and_explains_every_point() {
        let pose = at(0.5);
        let surface = sphere_points(0.05, 2000);
        // The visible cap's points, as a mask would give them.
        let observed: Vec<_> =
            sphere_points(0.05, 3000).into_iter().map(|p| pose.transform_point(&p)).filter(|x| x.z < 0.5).collect();
        let agreement = silhouette(&pose, &surface, &observed, &CAMERA, 12, &Sightlines::default()).unwrap();
        assert!(agreement.covered > 0.95, "{agreement:?}");
        assert_eq!(agreement.explained, 1.0);

        // Moved by a radius sideways: half the silhouette is empty, and the
        // points on the far side of the true one are not explained.
        let shifted = at(0.5);
        let moved = Pose::new(shifted.rotation, shifted.translation + Vector3::new(0.05, 0.0, 0.0));
        let agreement = silhouette(&moved, &surface, &observed, &CAMERA, 12, &Sightlines::default()).unwrap();
        assert!((0.3..0.7).contains(&agreement.covered), "{agreement:?}");
        assert!((0.3..0.8).contains(&agreement.explained), "{agreement:?}");
        assert!(silhouette(&pose, &surface, &[], &CAMERA, 12, &Sightlines::default()).is_none());
        // A rod seen side-on has no interior to judge.
        let rod: Vec<_> = (0..200).map(|i| Point3::new(-0.05 + i as f64 * 5e-4, 0.0, 0.0)).collect();
        assert!(silhouette(&pose, &rod, &observed, &CAMERA, 12, &Sightlines::default()).is_none());
    }

    /// The depth grid of the sphere at `pose` in front of a wall at depth
    /// `wall`, on 32 cells over a 240-pixel crop around the image centre;
    /// `occluder` puts a plate at that depth over the crop's right third.
    fn sphere_depth(pose: &Pose, wall: f32, occluder: Option<f32>) -> DepthGrid {
        let (cells, side) = (32, 240.0);
        let mut grid = DepthGrid {
            x_min: CAMERA.cx - side / 2.0,
            y_min: CAMERA.cy - side / 2.0,
            side,
            cells,
            depth: vec![wall; cells * cells],
            mask: vec![false; cells * cells],
        };
        let centre = pose.translation;
        for k in 0..cells * cells {
            let (u, v) = grid.pixel(k);
            let ray = Vector3::new((u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, 1.0);
            let (a, b, c) = (ray.norm_squared(), ray.dot(&centre), centre.norm_squared() - 0.05 * 0.05);
            if b * b - a * c > 0.0 {
                grid.depth[k] = ((b - (b * b - a * c).sqrt()) / a) as f32;
                grid.mask[k] = true;
            }
            if let Some(z) = occluder.filter(|_| k % cells >= 2 * cells / 3) {
                grid.depth[k] = z;
                grid.mask[k] = false;
            }
        }
        grid
    }

    const FREE: FreeSpaceSettings = FreeSpaceSettings { inside: 0.004, margin: 0.01 };

    #[test]
    fn a_pose_where_the_camera_saw_past_the_object_violates_free_space_and_an_occluded_one_does_not() {
        let truth = at(0.5);
        let sphere_bound = (Point3::origin(), 0.05);
        let grid = sphere_depth(&truth, 0.8, None);
        let seen = free_space(&truth, &grid, &CAMERA, sphere_bound, &FREE, sphere);
        // The sphere (radius 600·0.05/0.5 = 60 pixels) spans half the crop:
        // about π/4·16² cells.
        assert!((150..250).contains(&seen.masked), "{seen:?}");
        assert_eq!(seen.violated, 0);

        // 3 cm to the right: the lines of sight past the true outline's
        // right side cross the moved sphere in front of the wall.
        let moved = Pose::new(truth.rotation, truth.translation + Vector3::new(0.03, 0.0, 0.0));
        let found = free_space(&moved, &grid, &CAMERA, sphere_bound, &FREE, sphere);
        assert!((0.2..0.6).contains(&found.share()), "{found:?}");

        // With a plate in front over the right third, the camera cannot have
        // seen past the moved sphere there: fewer violations, none of them
        // under the plate.
        let plated = sphere_depth(&truth, 0.8, Some(0.3));
        let occluded = free_space(&moved, &plated, &CAMERA, sphere_bound, &FREE, sphere);
        assert!(occluded.violated < found.violated, "{occluded:?} {found:?}");
        let uncovered = DepthGrid {
            depth: plated.depth.iter().enumerate().map(|(k, &z)| if k % 32 >= 21 { 0.0 } else { z }).collect(),
            ..plated.clone()
        };
        assert_eq!(free_space(&moved, &uncovered, &CAMERA, sphere_bound, &FREE, sphere).violated, occluded.violated);

        // Behind the wall (the wall hides it): nothing seen past it.
        let behind = at(0.9);
        assert_eq!(free_space(&behind, &grid, &CAMERA, sphere_bound, &FREE, sphere).violated, 0);
        // Nothing to judge: no depth at all.
        let blind = DepthGrid { depth: vec![0.0; 32 * 32], ..grid };
        assert_eq!(free_space(&moved, &blind, &CAMERA, sphere_bound, &FREE, sphere), FreeSpace::default());
        assert_eq!(FreeSpace::default().share(), 0.0);
    }

    /// The sphere at 0.5 m seen in front of a wall at 0.8 m, with a plate at
    /// 0.3 m over the right half of the crop (from the image centre's
    /// column on): the points the camera sees of the sphere, and the grid.
    fn sphere_behind_plate(truth: &Pose) -> (Vec<Point3<f64>>, DepthGrid) {
        let mut grid = sphere_depth(truth, 0.8, None);
        for k in (0..32 * 32).filter(|k| k % 32 >= 16) {
            (grid.depth[k], grid.mask[k]) = (0.3, false);
        }
        let observed = sphere_points(0.05, 3000)
            .into_iter()
            .map(|p| truth.transform_point(&p))
            .filter(|x| x.z < 0.5 && x.x < 0.0)
            .collect();
        (observed, grid)
    }

    #[test]
    fn silhouette_cells_behind_a_nearer_surface_or_off_the_image_are_not_judged() {
        let truth = at(0.5);
        let surface = sphere_points(0.05, 2000);
        let (observed, plated) = sphere_behind_plate(&truth);
        let blind = silhouette(&truth, &surface, &observed, &CAMERA, 12, &Sightlines::default()).unwrap();
        assert!(blind.covered < 0.6, "{blind:?}");
        let sight = Sightlines { image: None, depth: Some(&plated) };
        let seen = silhouette(&truth, &surface, &observed, &CAMERA, 12, &sight).unwrap();
        assert!(seen.covered > 0.95, "{seen:?}");
        assert_eq!(seen.explained, blind.explained);

        // Moved 5 cm into the open, left of the truth: the wall behind it is
        // no occluder, so its empty cells still count.
        let moved = Pose::new(truth.rotation, truth.translation - Vector3::new(0.05, 0.0, 0.0));
        let open = silhouette(&moved, &surface, &observed, &CAMERA, 12, &sight).unwrap();
        assert!(open.covered < 0.6, "{open:?}");
        // Moved 5 cm to the right, wholly behind the plate: nothing to judge.
        let hidden = Pose::new(truth.rotation, truth.translation + Vector3::new(0.05, 0.0, 0.0));
        assert!(silhouette(&hidden, &surface, &observed, &CAMERA, 12, &sight).is_none());

        // The image ends at the sphere's centre column: the same points, and
        // only the part inside the image is judged.
        let cut = Sightlines { image: Some((CAMERA.cx, 480.0)), depth: None };
        let inside = silhouette(&truth, &surface, &observed, &CAMERA, 12, &cut).unwrap();
        assert!(inside.covered > 0.95, "{inside:?}");
        // An image that ends before the sphere leaves nothing to judge.
        let gone = Sightlines { image: Some((200.0, 480.0)), depth: None };
        assert!(silhouette(&truth, &surface, &observed, &CAMERA, 12, &gone).is_none());
    }
}
