//! Object models for rendering and geometric scoring.
//!
//! Meshes are read from BOP PLY files (ASCII or binary, usually millimetres,
//! with per-vertex normals and colours) and Wavefront OBJ files, scaled to
//! metres at the boundary, and turned into parry triangle meshes (with their
//! BVH) once per object. Coordinates are `f32` in the object frame.

mod error;
mod mesh;
mod noise;
mod obj;
mod ply;
mod render;

pub use error::MeshError;
pub use mesh::{MeshFormat, ObjectMesh, load_mesh};
pub use noise::DepthNoise;
pub use render::{Camera, Frame, Light, Placed, RenderModel, render, silhouettes};
