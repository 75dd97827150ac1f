//! Finding an object's geometric symmetries from its mesh, for
//! `models_info.json`: the rotations that map the surface onto itself.
//!
//! Candidates are turns through the surface centroid (the point every
//! symmetry of a surface keeps fixed) about the three principal axes of the
//! surface (its exact area-weighted second moment) and about the object frame's axes
//! (where a cube's or a sphere's equal principal moments leave the
//! principal axes arbitrary). A turn is accepted when every
//! one of a fixed sample of surface points, turned, lies within `tolerance`
//! (a fraction of the diameter) of the untouched surface, but for 1 % of
//! them (a scan's stray triangles), so a handle or a notch that breaks a
//! symmetry rejects it. An axis about
//! which every tested angle is accepted is a continuous symmetry.
//!
//! Object frame, metres. Discrete symmetries are returned as BOP writes
//! them: `x ↦ R x + t`, the turn about the axis through the centroid.

use nalgebra::{Matrix3, Point3, Rotation3, Unit, Vector3};
use parry3d::query::PointQuery;
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::seeded_rng;
use rand::Rng;

use crate::{ObjectMesh, SceneError};

/// Surface points every candidate is tested on.
const SAMPLE_POINTS: usize = 4000;
/// One sample point in this many may land farther than the tolerance: a
/// scanned mesh's stray triangles and seams would otherwise break every
/// symmetry, while a handle or a notch (several per cent of the surface)
/// still does.
const OUTLIER_SHARE: usize = 100;
/// n-fold turns tried about each principal axis.
const FOLDS: [u32; 4] = [2, 3, 4, 6];
/// Angles (degrees) that must all pass for a continuous symmetry: a prime
/// step, so no discrete symmetry passes them all.
const CONTINUOUS_STEP_DEG: f64 = 13.0;
/// Axes closer than 5° are one axis, rotations closer than 1° one rotation:
/// a symmetry found about a principal axis and again about the frame axis
/// next to it would otherwise compose into ever new rotations.
const SAME_AXIS_COS: f64 = 0.996_2;
const SAME_ROTATION_RAD: f64 = 0.017;
/// No rigid object has a larger finite rotation group (the icosahedron's
/// has 60 elements).
const MAX_GROUP: usize = 60;

/// A symmetry of the mesh.
#[derive(Debug, Clone, PartialEq)]
pub enum Symmetry {
    /// Any rotation about `axis` through `offset` (metres).
    Continuous { axis: Unit<Vector3<f64>>, offset: Vector3<f64> },
    /// The object-frame transform `x ↦ R x + t`.
    Discrete(Pose),
}

/// The symmetries of `mesh` within `tolerance` × its diameter (see the
/// module documentation); the identity is not listed. An axis with a
/// continuous symmetry lists no discrete turns about itself.
pub fn find_symmetries(mesh: &ObjectMesh, diameter: f64, tolerance: f64) -> Result<Vec<Symmetry>, SceneError> {
    let trimesh =
        mesh.to_trimesh().map_err(|source| SceneError::Invalid(format!("mesh for the symmetry search: {source}")))?;
    let samples = surface_samples(mesh, SAMPLE_POINTS);
    let centroid = surface_centroid(mesh);
    let principal = surface_principal_axes(mesh, &centroid);
    let mut axes: Vec<Unit<Vector3<f64>>> = Vec::new();
    // Frame axes first: a modelled object's axes are exact where sampled
    // principal axes are only close.
    for axis in [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()].into_iter().chain(principal) {
        if axes.iter().all(|a| a.dot(&axis).abs() < SAME_AXIS_COS) {
            axes.push(axis);
        }
    }
    let limit = tolerance * diameter;
    // Two turns are one symmetry when they differ by less than the tolerance
    // moves the farthest surface point: a scan's principal axis a degree or
    // two off its frame axis would otherwise give near-twin turns whose
    // products never close into a group.
    let radius = samples.iter().map(|p| (p - centroid).norm()).fold(0.0, f64::max);
    let same_rotation = SAME_ROTATION_RAD.max(limit / radius.max(f64::MIN_POSITIVE));
    let allowed_outliers = SAMPLE_POINTS / OUTLIER_SHARE;
    let maps_onto_itself = |rotation: &Rotation3<f64>| {
        let mut outliers = 0;
        samples.iter().all(|p| {
            let turned = centroid + rotation * (p - centroid);
            let distance =
                f64::from(trimesh.distance_to_local_point(&Point3::from(turned.coords.cast::<f32>()), false));
            outliers += usize::from(distance > limit);
            outliers <= allowed_outliers
        })
    };
    let mut found: Vec<Symmetry> = Vec::new();
    let mut turns: Vec<Rotation3<f64>> = Vec::new();
    // A turn about a continuous axis is no new symmetry, and two turns that
    // differ by one are the same: a cylinder's flips about its diameters are
    // one flip followed by turns about its axis.
    let free_axes = |found: &[Symmetry]| -> Vec<Unit<Vector3<f64>>> {
        found
            .iter()
            .filter_map(|s| match s {
                Symmetry::Continuous { axis, .. } => Some(*axis),
                Symmetry::Discrete(_) => None,
            })
            .collect()
    };
    let trivial = |rotation: &Rotation3<f64>, free: &[Unit<Vector3<f64>>]| match rotation_axis(rotation, same_rotation)
    {
        None => true,
        Some(axis) => free.iter().any(|f| f.dot(&axis).abs() >= SAME_AXIS_COS),
    };
    let known = |turns: &[Rotation3<f64>], rotation: &Rotation3<f64>, free: &[Unit<Vector3<f64>>]| {
        turns.iter().any(|r| trivial(&(r.inverse() * rotation), free))
    };
    // Continuous axes first: turns about them, and turns that differ by
    // one, are then known before the discrete search meets them.
    for axis in &axes {
        let covered = free_axes(&found).iter().any(|a| a.dot(axis).abs() >= SAME_AXIS_COS);
        let continuous = !covered
            && (1..)
                .map(|k| f64::from(k) * CONTINUOUS_STEP_DEG)
                .take_while(|a| *a < 360.0)
                .all(|a| maps_onto_itself(&Rotation3::from_axis_angle(axis, a.to_radians())));
        if continuous {
            found.push(Symmetry::Continuous { axis: *axis, offset: centroid.coords });
        }
    }
    let free = free_axes(&found);
    for axis in &axes {
        for n in FOLDS {
            for k in 1..n {
                let rotation = Rotation3::from_axis_angle(axis, std::f64::consts::TAU * f64::from(k) / f64::from(n));
                if !trivial(&rotation, &free) && !known(&turns, &rotation, &free) && maps_onto_itself(&rotation) {
                    turns.push(rotation);
                }
            }
        }
    }
    // Turns about different axes compose into turns about the third (a box's
    // three half turns); list the whole group, as BOP does.
    let mut grown = true;
    while grown {
        grown = false;
        for i in 0..turns.len() {
            for j in 0..turns.len() {
                let product = turns[i] * turns[j];
                if !trivial(&product, &free) && !known(&turns, &product, &free) {
                    if turns.len() + 1 >= MAX_GROUP {
                        return Err(SceneError::Invalid(format!(
                            "symmetry search: more than {MAX_GROUP} turns map the mesh onto itself within tolerance \
                             {tolerance}; the tolerance is too loose for this mesh"
                        )));
                    }
                    turns.push(product);
                    grown = true;
                }
            }
        }
    }
    found.extend(turns.into_iter().map(|rotation| {
        let translation = centroid.coords - rotation * centroid.coords;
        Symmetry::Discrete(Pose::new(rotation, translation))
    }));
    Ok(found)
}

/// The axis and angle (radians, in [0, π]) of `rotation`, `None` for the
/// identity: unlike nalgebra's `axis_angle`, also at a half turn.
pub fn turn(rotation: &Rotation3<f64>) -> Option<(Unit<Vector3<f64>>, f64)> {
    let axis = rotation_axis(rotation, 1e-12)?;
    Some((axis, clamped_angle(rotation)))
}

/// The rotation angle from the trace, clamped: a product of turns drifts a
/// trace past 3 by rounding, where nalgebra's `angle` is NaN and the
/// identity would pass for a turn.
fn clamped_angle(rotation: &Rotation3<f64>) -> f64 {
    ((rotation.matrix().trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

/// The axis of `rotation`, `None` within `same_rotation` (radians) of the
/// identity. Near a half turn the axis is read from `(R + I) / 2 = a aᵀ`,
/// where nalgebra's `axis_angle` (from the antisymmetric part, which
/// vanishes there) has none.
fn rotation_axis(rotation: &Rotation3<f64>, same_rotation: f64) -> Option<Unit<Vector3<f64>>> {
    let angle = clamped_angle(rotation);
    if angle < same_rotation {
        return None;
    }
    if angle < std::f64::consts::PI - 1e-3 {
        return rotation.axis();
    }
    let outer = (rotation.matrix() + Matrix3::identity()) / 2.0;
    let column = (0..3).max_by(|&i, &j| outer.column(i).norm().total_cmp(&outer.column(j).norm()))?;
    Unit::try_new(outer.column(column).into_owned(), 1e-9)
}

/// `count` points uniform over the surface area (seeded: the same mesh gives
/// the same answer).
fn surface_samples(mesh: &ObjectMesh, count: usize) -> Vec<Point3<f64>> {
    let corners = |t: &[u32; 3]| t.map(|i| mesh.vertices[i as usize].coords.cast::<f64>());
    let mut cumulative = Vec::with_capacity(mesh.triangles.len());
    let mut total = 0.0;
    for t in &mesh.triangles {
        let [a, b, c] = corners(t);
        total += 0.5 * (b - a).cross(&(c - a)).norm();
        cumulative.push(total);
    }
    let mut rng = seeded_rng(0x5e7);
    (0..count)
        .map(|_| {
            let pick = rng.random_range(0.0..total.max(f64::MIN_POSITIVE));
            let index = cumulative.partition_point(|&c| c < pick).min(mesh.triangles.len() - 1);
            let [a, b, c] = corners(&mesh.triangles[index]);
            let (mut s, mut t): (f64, f64) = (rng.random(), rng.random());
            if s + t > 1.0 {
                (s, t) = (1.0 - s, 1.0 - t);
            }
            Point3::from(a + (b - a) * s + (c - a) * t)
        })
        .collect()
}

/// The area-weighted centroid of the surface, exactly (sampled points
/// would put it a fraction of a millimetre off, enough to fail a flip).
fn surface_centroid(mesh: &ObjectMesh) -> Point3<f64> {
    let (mut weighted, mut area) = (Vector3::zeros(), 0.0);
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize].coords.cast::<f64>());
        let triangle_area = 0.5 * (b - a).cross(&(c - a)).norm();
        weighted += triangle_area * (a + b + c) / 3.0;
        area += triangle_area;
    }
    Point3::from(weighted / area.max(f64::MIN_POSITIVE))
}

/// The principal axes of the surface from its exact area-weighted second
/// moment: sampled points tilt a box's axes by a degree or two, which moves
/// a half turn's far corners past a tight tolerance.
fn surface_principal_axes(mesh: &ObjectMesh, centroid: &Point3<f64>) -> [Unit<Vector3<f64>>; 3] {
    let mut moment = Matrix3::zeros();
    for t in &mesh.triangles {
        // ∫ x xᵀ dA over a triangle = A/12 (Σ vᵢvᵢᵀ + (Σ vᵢ)(Σ vᵢ)ᵀ), here
        // with the vertices taken about the centroid.
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize].coords.cast::<f64>() - centroid.coords);
        let area = 0.5 * (b - a).cross(&(c - a)).norm();
        let sum = a + b + c;
        moment += area / 12.0 * (a * a.transpose() + b * b.transpose() + c * c.transpose() + sum * sum.transpose());
    }
    let eigen = moment.symmetric_eigen();
    [0, 1, 2].map(|i| Unit::new_normalize(eigen.eigenvectors.column(i).into_owned()))
}

/// The eigenvectors of the covariance of `points` about `centroid`: the
/// principal axes (arbitrary where principal moments are equal).
pub fn principal_axes(points: &[Point3<f64>], centroid: &Point3<f64>) -> [Unit<Vector3<f64>>; 3] {
    let covariance = points.iter().fold(Matrix3::zeros(), |acc, p| {
        let d = p - centroid;
        acc + d * d.transpose()
    });
    let eigen = covariance.symmetric_eigen();
    [0, 1, 2].map(|i| Unit::new_normalize(eigen.eigenvectors.column(i).into_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::primitives::ClutterShape;

    fn mesh_of(shape: ClutterShape) -> ObjectMesh {
        shape.mesh([100, 100, 100])
    }

    fn continuous_axes(found: &[Symmetry]) -> Vec<Vector3<f64>> {
        found
            .iter()
            .filter_map(|s| match s {
                Symmetry::Continuous { axis, .. } => Some(axis.into_inner()),
                Symmetry::Discrete(_) => None,
            })
            .collect()
    }

    #[test]
    fn a_cylinder_turns_freely_about_its_axis_and_half_turns_about_the_others() {
        let cylinder = mesh_of(ClutterShape::Cylinder { radius: 0.03, height: 0.12 });
        let found = find_symmetries(&cylinder, 0.13, 0.01).unwrap();
        let axes = continuous_axes(&found);
        assert_eq!(axes.len(), 1, "{found:?}");
        assert!(axes[0].z.abs() > 0.999, "the axis is the cylinder's: {}", axes[0]);
        // Upside down about any horizontal axis through the middle: the
        // centroid stays at half height, so t maps the base onto the top.
        let flips: Vec<&Pose> =
            found.iter().filter_map(|s| if let Symmetry::Discrete(p) = s { Some(p) } else { None }).collect();
        assert!(!flips.is_empty(), "{found:?}");
        for flip in flips {
            let base = Point3::new(0.0, 0.0, 0.0);
            assert!((flip.transform_point(&base).z - 0.12).abs() < 1e-3, "{flip:?}");
        }
    }

    #[test]
    fn a_box_with_distinct_sides_has_the_three_half_turns_only() {
        let cuboid = mesh_of(ClutterShape::Box { half_extents: Vector3::new(0.05, 0.03, 0.02) });
        let found = find_symmetries(&cuboid, 0.125, 0.01).unwrap();
        assert!(continuous_axes(&found).is_empty(), "{found:?}");
        assert_eq!(found.len(), 3, "{found:?}");
        for symmetry in &found {
            let Symmetry::Discrete(pose) = symmetry else { unreachable!() };
            assert!((pose.rotation.angle() - std::f64::consts::PI).abs() < 1e-6);
        }
    }

    #[test]
    fn a_box_scanned_a_little_askew_still_has_three_half_turns() {
        // A scan's box sits turned in its own frame: its edges 33° about z
        // from the frame axes and tipped 1.5° about x, so frame z is a near
        // twin of a principal axis.
        let mut cuboid = mesh_of(ClutterShape::Box { half_extents: Vector3::new(0.055, 0.045, 0.018) });
        let askew = Rotation3::from_axis_angle(&Vector3::x_axis(), 1.5_f64.to_radians())
            * Rotation3::from_axis_angle(&Vector3::z_axis(), 33_f64.to_radians());
        for vertex in &mut cuboid.vertices {
            *vertex = Point3::from((askew * vertex.coords.cast::<f64>()).cast::<f32>());
        }
        let found = find_symmetries(&cuboid, 0.146, 0.03).unwrap();
        assert!(continuous_axes(&found).is_empty(), "{found:?}");
        assert_eq!(found.len(), 3, "{found:?}");
    }

    #[test]
    fn a_cube_has_the_rotation_group_of_the_cube() {
        let cube = mesh_of(ClutterShape::Box { half_extents: Vector3::repeat(0.03) });
        let found = find_symmetries(&cube, 0.104, 0.01).unwrap();
        // 24 rotations map a cube onto itself; the turns about its diagonals
        // are products of the quarter turns about its faces.
        assert_eq!(found.len(), 23, "{}", found.len());
    }

    #[test]
    fn half_turns_have_their_axis() {
        for axis in [Vector3::x_axis(), Vector3::y_axis(), Unit::new_normalize(Vector3::new(1.0, -2.0, 0.5))] {
            for angle in [0.5, 2.0, std::f64::consts::PI] {
                let found = rotation_axis(&Rotation3::from_axis_angle(&axis, angle), SAME_ROTATION_RAD).unwrap();
                assert!(found.dot(&axis).abs() > 1.0 - 1e-9, "{angle}: {found:?} vs {axis:?}");
            }
        }
        assert!(rotation_axis(&Rotation3::identity(), SAME_ROTATION_RAD).is_none());
        // Rounding puts the trace of a product of half turns a hair above 3.
        let rounded = Rotation3::from_matrix_unchecked(Matrix3::identity() * (1.0 + 1e-15));
        assert!(rotation_axis(&rounded, SAME_ROTATION_RAD).is_none());
        // A half turn built as a product of two has an exactly symmetric
        // matrix, where nalgebra finds no axis.
        let product = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI);
        let (axis, angle) = turn(&product).unwrap();
        assert!(axis.z.abs() > 1.0 - 1e-9 && (angle - std::f64::consts::PI).abs() < 1e-9, "{axis:?} {angle}");
    }

    #[test]
    fn a_box_with_a_handle_has_no_symmetry_that_moves_the_handle() {
        let mut mesh = mesh_of(ClutterShape::Box { half_extents: Vector3::new(0.05, 0.03, 0.02) });
        let handle = mesh_of(ClutterShape::Box { half_extents: Vector3::new(0.01, 0.005, 0.005) });
        let first = mesh.vertices.len() as u32;
        mesh.vertices.extend(handle.vertices.iter().map(|p| p + Vector3::new(0.06, 0.0, 0.015)));
        mesh.triangles.extend(handle.triangles.iter().map(|t| t.map(|i| i + first)));
        let found = find_symmetries(&mesh, 0.14, 0.01).unwrap();
        for symmetry in &found {
            let Symmetry::Discrete(pose) = symmetry else { panic!("{found:?}") };
            let tip = Point3::new(0.07, 0.0, 0.02);
            assert!((pose.transform_point(&tip) - tip).norm() < 0.02, "the handle moved: {pose:?}");
        }
    }
}
