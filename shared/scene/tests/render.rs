//! The renderer against closed forms: depth of a sphere, occlusion order,
//! and determinism.

use nalgebra::{Point3, Rotation3, Vector3};
use poseflow_geometry::Pose;
use poseflow_scene::{Camera, Light, ObjectMesh, Placed, RenderModel, render};

/// A UV sphere of radius `r` around the origin, outward-facing.
fn sphere(r: f32, segments: u32, rings: u32) -> ObjectMesh {
    let mut vertices = vec![Point3::new(0.0, 0.0, r)];
    for i in 1..rings {
        let theta = std::f32::consts::PI * i as f32 / rings as f32;
        for j in 0..segments {
            let phi = std::f32::consts::TAU * j as f32 / segments as f32;
            vertices.push(Point3::new(r * theta.sin() * phi.cos(), r * theta.sin() * phi.sin(), r * theta.cos()));
        }
    }
    vertices.push(Point3::new(0.0, 0.0, -r));
    let ring = |i: u32, j: u32| 1 + (i - 1) * segments + j % segments;
    let bottom = vertices.len() as u32 - 1;
    let mut triangles = Vec::new();
    for j in 0..segments {
        triangles.push([0, ring(1, j), ring(1, j + 1)]);
        for i in 1..rings - 1 {
            triangles.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
            triangles.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
        }
        triangles.push([ring(rings - 1, j), bottom, ring(rings - 1, j + 1)]);
    }
    ObjectMesh { vertices, triangles, normals: None, colors: None }
}

const CAMERA: Camera = Camera { fx: 200.0, fy: 200.0, cx: 79.5, cy: 59.5, width: 160, height: 120 };

/// Where the ray through pixel (u, v) meets a sphere (centre `c`, radius
/// `r`): the z of the first intersection and the cosine of the incidence
/// angle there, if the ray hits.
fn sphere_depth(u: f64, v: f64, c: &Vector3<f64>, r: f64) -> Option<(f64, f64)> {
    let d = CAMERA.ray_direction(u, v);
    let b = d.dot(c);
    let disc = b * b - (c.norm_squared() - r * r);
    (disc > 0.0).then(|| {
        let t = b - disc.sqrt();
        let normal = (d * t - c) / r;
        (t * d.z, normal.dot(&d).abs())
    })
}

#[test]
fn sphere_depth_matches_the_closed_form_within_a_millimetre() {
    let model = RenderModel::new(sphere(0.1, 128, 64)).unwrap();
    let centre = Vector3::new(0.02, -0.01, 0.6);
    let pose = Pose::new(Rotation3::from_euler_angles(0.3, -0.2, 1.0), centre);
    let frame = render(&CAMERA, &[Placed { model: &model, pose: &pose }], &Light::default());
    let (mut compared, mut silhouette_mismatch) = (0, 0);
    for v in 0..CAMERA.height {
        for u in 0..CAMERA.width {
            let i = (v * CAMERA.width + u) as usize;
            let exact = sphere_depth(u as f64, v as f64, &centre, 0.1);
            match (exact, frame.label[i]) {
                // The polygon's radial error (0.1 mm here) grows as 1/cos along
                // grazing rays; those count with the silhouette.
                (Some((_, cos)), _) if cos < 0.3 => silhouette_mismatch += 1,
                (Some((z, _)), 1) => {
                    assert!(
                        (f64::from(frame.depth[i]) - z).abs() < 1e-3,
                        "pixel ({u}, {v}): {} vs {z}",
                        frame.depth[i]
                    );
                    compared += 1;
                }
                (None, 0) => assert_eq!(frame.depth[i], 0.0),
                // Only at the silhouette, where the polygon and the sphere differ.
                _ => silhouette_mismatch += 1,
            }
        }
    }
    // The sphere covers about π(200·0.1/0.6)² ≈ 3,500 pixels, of which the
    // grazing rim (cos < 0.3) is about 9 %.
    assert!(compared > 3000, "{compared}");
    assert!(silhouette_mismatch < 400, "{silhouette_mismatch}");
}

#[test]
fn nearer_objects_occlude_farther_ones() {
    let model = RenderModel::new(sphere(0.05, 32, 16)).unwrap();
    let far = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.8));
    let near = Pose::new(Rotation3::identity(), Vector3::new(0.03, 0.0, 0.5));
    let objects = [Placed { model: &model, pose: &far }, Placed { model: &model, pose: &near }];
    let frame = render(&CAMERA, &objects, &Light::default());
    // The centre pixel sees through both spheres' line of sight: the near one wins.
    let (u, v) = CAMERA.project(&Point3::new(0.0, 0.0, 0.5)).unwrap();
    let i = (v.round() as u32 * CAMERA.width + u.round() as u32) as usize;
    assert_eq!(frame.label[i], 2);
    assert!((frame.depth[i] - 0.5).abs() < 0.06, "{}", frame.depth[i]);
    // Both objects are visible somewhere.
    assert!(frame.label.contains(&1) && frame.label.contains(&2));
    // Lit surfaces are not black; the background is.
    assert!(frame.rgb[i].iter().all(|&c| c > 0));
    assert_eq!(frame.rgb[0], [0, 0, 0]);
    // The albedo is the mesh's colour (flat grey without vertex colours),
    // unshaded: never darker than the shaded pixel, and the same on the lit
    // and the unlit side.
    let seen: Vec<usize> = (0..frame.label.len()).filter(|&k| frame.label[k] > 0).collect();
    for &k in &seen {
        assert_eq!(frame.albedo[k], [179, 179, 179], "pixel {k}");
        assert!(frame.rgb[k].iter().zip(&frame.albedo[k]).all(|(shaded, albedo)| shaded <= albedo));
    }
    assert!(seen.iter().any(|&k| frame.rgb[k][0] < 150), "some of the sphere is in shade");
    assert_eq!(frame.albedo[0], [0, 0, 0]);
}

#[test]
fn rendering_is_deterministic() {
    let mesh = poseflow_scene::load_mesh(
        std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects/lmo/obj_000001.ply")),
        1e-3,
    )
    .unwrap();
    let model = RenderModel::new(mesh).unwrap();
    let pose = Pose::new(Rotation3::from_euler_angles(2.0, 0.4, -0.7), Vector3::new(0.0, 0.01, 0.5));
    let a = render(&CAMERA, &[Placed { model: &model, pose: &pose }], &Light::default());
    let b = render(&CAMERA, &[Placed { model: &model, pose: &pose }], &Light::default());
    assert_eq!(a, b);
    assert!(a.label.iter().filter(|&&l| l == 1).count() > 500);
}

#[test]
fn full_masks_contain_the_visible_ones() {
    let model = RenderModel::new(sphere(0.05, 32, 16)).unwrap();
    let far = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.8));
    let near = Pose::new(Rotation3::identity(), Vector3::new(0.03, 0.0, 0.5));
    let objects = [Placed { model: &model, pose: &far }, Placed { model: &model, pose: &near }];
    let frame = render(&CAMERA, &objects, &Light::default());
    let full = poseflow_scene::silhouettes(&CAMERA, &objects);
    for (k, mask) in full.iter().enumerate() {
        let visible: Vec<bool> = frame.label.iter().map(|&l| usize::from(l) == k + 1).collect();
        assert!(visible.iter().zip(mask).all(|(v, f)| !v || *f), "object {k}: visible outside its full mask");
        let fraction = visible.iter().filter(|v| **v).count() as f64 / mask.iter().filter(|f| **f).count() as f64;
        // The far sphere is partly hidden by the near one; the near one is not.
        if k == 0 {
            assert!(fraction < 0.9, "{fraction}");
        } else {
            assert_eq!(fraction, 1.0);
        }
    }
}

#[test]
fn an_objects_own_depth_equals_the_rendered_depth_where_nothing_hides_it() {
    let model = RenderModel::new(sphere(0.05, 32, 16)).unwrap();
    let far = Pose::new(Rotation3::from_euler_angles(0.2, 0.1, 0.3), Vector3::new(0.0, 0.0, 0.8));
    let near = Pose::new(Rotation3::identity(), Vector3::new(0.03, 0.0, 0.5));
    let alone = render(&CAMERA, &[Placed { model: &model, pose: &far }], &Light::default());
    let own = poseflow_scene::object_depth(&CAMERA, &Placed { model: &model, pose: &far });
    assert_eq!(own, alone.depth);
    // With an occluder in front, the object's own depth still sees all of it.
    let both = render(
        &CAMERA,
        &[Placed { model: &model, pose: &far }, Placed { model: &model, pose: &near }],
        &Light::default(),
    );
    let hidden = own.iter().zip(&both.label).filter(|&(&z, &label)| z > 0.0 && label == 2).count();
    assert!(hidden > 50, "{hidden} pixels of the far sphere behind the near one");
}

#[test]
fn the_part_of_a_silhouette_beyond_the_image_border_is_counted_as_bop_does() {
    let model = RenderModel::new(sphere(0.1, 128, 64)).unwrap();
    let on_axis = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.6));
    let placed = Placed { model: &model, pose: &on_axis };
    let in_image = |camera: &Camera| {
        poseflow_scene::silhouettes(camera, &[placed])[0].iter().filter(|inside| **inside).count() as u64
    };
    // Wholly inside the image: nothing is cut off.
    assert_eq!(poseflow_scene::truncated_pixels(&CAMERA, &placed), 0);
    let whole = in_image(&CAMERA);
    // The principal point half a pixel left of the first column: the image
    // holds the right half of the disc (columns u and −1 − u mirror).
    let cut = Camera { cx: -0.5, ..CAMERA };
    let (inside, beyond) = (in_image(&cut), poseflow_scene::truncated_pixels(&cut, &placed));
    assert!(inside.abs_diff(beyond) <= whole / 100, "{inside} in the image, {beyond} beyond it");
    assert!((inside + beyond).abs_diff(whole) <= whole / 100, "{} against {whole}", inside + beyond);
    // Wholly outside the image, within the canvas BOP renders: all counted.
    let outside = Camera { cx: -60.0, ..CAMERA };
    assert_eq!(in_image(&outside), 0);
    assert!(poseflow_scene::truncated_pixels(&outside, &placed).abs_diff(whole) <= whole / 100);
}
