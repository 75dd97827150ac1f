//! Loading the vendored object models and rejecting broken ones.

use std::io::Write;
use std::path::{Path, PathBuf};

use parry3d::query::{Ray, RayCast};
use poseflow_geometry::models_info::ModelsInfo;
use poseflow_scene::{ObjectMesh, load_mesh};

fn objects() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../../objects"))
}

fn scratch(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("poseflow-scene-{}-{name}", std::process::id()))
}

#[test]
fn lmo_ape_loads_in_metres_with_normals_and_colours() {
    let ape = load_mesh(&objects().join("lmo/obj_000001.ply"), 1e-3).unwrap();
    assert_eq!((ape.vertices.len(), ape.triangles.len()), (5841, 11678));
    assert_eq!(ape.normals.as_ref().map(Vec::len), Some(5841));
    assert_eq!(ape.colors.as_ref().unwrap()[0], [148, 57, 57]);
    // The first vertex of the file, in metres.
    assert!((ape.vertices[0].x + 0.0230565).abs() < 1e-7);
    // BOP's diameter of the ape is 102.099 mm.
    let info = ModelsInfo::from_path(&objects().join("lmo/models_info.json")).unwrap();
    let expected = info.get(1).unwrap().diameter as f32;
    assert!((ape.diameter() - expected).abs() < 1e-3 * expected, "{} vs {expected}", ape.diameter());
}

#[test]
fn ycbv_mug_obj_loads_and_casts_rays() {
    let mug = load_mesh(&objects().join("ycbv/025_mug/textured.obj"), 1.0).unwrap();
    assert_eq!(mug.triangles.len(), 16384);
    assert!(mug.normals.is_none() && mug.colors.is_none());
    let (min, max) = mug.bounds();
    let size = max - min;
    assert!(size.max() < 0.15 && size.min() > 0.05, "a mug is about 10 cm: {size}");
    let trimesh = mug.to_trimesh().unwrap();
    // A ray from 1 m above, straight down through the centre of the bounds,
    // hits the mug before it would reach the bottom of the bounds.
    let centre = nalgebra::center(&min, &max);
    let ray = Ray::new(nalgebra::Point3::new(centre.x, centre.y, max.z + 1.0), -nalgebra::Vector3::z());
    let hit = trimesh.cast_local_ray(&ray, 10.0, false).expect("the ray hits the mug");
    assert!(hit >= 1.0 - 1e-4 && hit <= 1.0 + size.z, "{hit}");
}

/// Writes `mesh` as a binary PLY (metres), as another tool might.
fn write_binary_ply(mesh: &ObjectMesh, path: &Path, big_endian: bool) {
    let mut out = std::fs::File::create(path).unwrap();
    let format = if big_endian { "binary_big_endian" } else { "binary_little_endian" };
    write!(
        out,
        "ply\nformat {format} 1.0\ncomment test\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.vertices.len(),
        mesh.triangles.len()
    )
    .unwrap();
    let f = |v: f32| if big_endian { v.to_be_bytes() } else { v.to_le_bytes() };
    let i = |v: u32| if big_endian { (v as i32).to_be_bytes() } else { (v as i32).to_le_bytes() };
    let colors = mesh.colors.as_ref().unwrap();
    for (v, c) in mesh.vertices.iter().zip(colors) {
        for x in [v.x, v.y, v.z] {
            out.write_all(&f(x)).unwrap();
        }
        out.write_all(c).unwrap();
    }
    for t in &mesh.triangles {
        out.write_all(&[3]).unwrap();
        for k in t {
            out.write_all(&i(*k)).unwrap();
        }
    }
}

#[test]
fn binary_ply_matches_ascii_ply() {
    let ascii = load_mesh(&objects().join("lmo/obj_000011.ply"), 1e-3).unwrap();
    for big_endian in [false, true] {
        let path = scratch(&format!("glue-{big_endian}.ply"));
        write_binary_ply(&ascii, &path, big_endian);
        let binary = load_mesh(&path, 1.0).unwrap();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(binary.vertices, ascii.vertices);
        assert_eq!(binary.triangles, ascii.triangles);
        assert_eq!(binary.colors, ascii.colors);
    }
}

// Broken mesh files: the bad-input corpus, tests/corpus/models (tests/e2e/corpus.rs).
