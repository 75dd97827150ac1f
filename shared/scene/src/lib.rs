//! Object models, the ray-cast RGB-D renderer, random tabletop scenes and
//! the BOP dataset format.
//!
//! Meshes are read from BOP PLY files (ASCII or binary, usually millimetres,
//! with per-vertex normals and colours) and Wavefront OBJ files, scaled to
//! metres at the boundary, and turned into parry triangle meshes (with their
//! BVH) once per object. Coordinates are `f32` in the object frame; poses
//! and cameras are `f64`, metres, OpenCV camera axes.

pub mod bop;
pub mod camera_path;
pub mod category;
pub mod dataset;
mod error;
pub mod import;
mod library;
mod mesh;
mod noise;
mod obj;
mod object_geometry;
pub mod part;
mod ply;
pub mod primitives;
mod render;
pub mod scene;
pub mod sdf;
pub mod sdf_refine;
pub mod sensor;
pub mod symmetry;
pub mod video;

pub use error::SceneError;
pub use library::{LibraryObject, ModelLibrary, load_bop_model, model_file_name};
pub use mesh::{MeshFormat, ObjectMesh, load_mesh, oriented_trimesh, parse_mesh, surface_points};
pub use noise::DepthNoise;
pub use object_geometry::{ObjectGeometry, ObjectLibrary};
pub use render::{Camera, Frame, Light, Placed, RenderModel, object_depth, render, silhouettes, truncated_pixels};
