//! SE(3) geometry for PoseFlow.
//!
//! # Conventions (hold for every item in this crate)
//!
//! - **Scalars**: `f64` inside the math. Messages carry `f32`; convert at the
//!   boundary with [`Pose::to_f32_row_major`] / [`Pose::from_f32_row_major`].
//! - **Units**: metres and radians. BOP files are in millimetres and are
//!   converted when read ([`models_info`]).
//! - **Poses** are object-to-camera: `x_cam = R · x_obj + t`
//!   ([`Pose`]). Matrices are written row-major wherever they are flattened.
//! - **Rotation tangent vectors** (`ω`, rotation vectors) live in the *body*
//!   frame: a rotation is perturbed on the right, `R ← R · exp(ω)`. This is the
//!   frame of the paper's `log(R_tᵀ R_1)`.
//! - **6-vectors** (twists, tangent vectors, covariance rows) are ordered
//!   translation first, then rotation: `[v_x, v_y, v_z, ω_x, ω_y, ω_z]`.
//! - **Randomness** is always seeded ([`sampling::seeded_rng`]) so every draw
//!   is reproducible.

pub mod category;
pub mod distance;
pub mod eigen;
mod error;
pub mod flow;
pub mod mean;
pub mod metrics;
pub mod models_info;
pub mod pose;
pub mod sampling;
pub mod so3;
pub mod symmetry;
pub mod vectors;

pub use distance::PoseMetric;
pub use error::GeometryError;
pub use flow::Velocity;
pub use mean::{KarcherOptions, PoseStatistics};
pub use pose::Pose;
pub use symmetry::SymmetrySet;

/// Re-exported so callers name the same nalgebra this crate is built on.
pub use nalgebra;
