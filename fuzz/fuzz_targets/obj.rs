//! Wavefront OBJ meshes: a validated mesh or a named error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use poseflow_scene::{MeshFormat, parse_mesh};

fuzz_target!(|bytes: &[u8]| {
    let _ = parse_mesh(bytes, MeshFormat::Obj, std::path::Path::new("fuzz.obj"));
});
