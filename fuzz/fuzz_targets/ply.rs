//! PLY meshes (ASCII and binary, either endianness): any bytes give a mesh
//! that passed validation or a named error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use poseflow_scene::{MeshFormat, parse_mesh};

fuzz_target!(|bytes: &[u8]| {
    let _ = parse_mesh(bytes, MeshFormat::Ply, std::path::Path::new("fuzz.ply"));
});
