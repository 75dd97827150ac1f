//! The commands that make and inspect data: `poseflow render` (BOP-format
//! RGB-D scenes), `import-model`, `generate-objects` (procedural category
//! objects), `grasp-data` (the grasp flow's training data), `preview` and
//! `observe` (training shards).

pub mod annotate_category;
pub mod generate_objects;
pub mod grasp_data;
pub mod import_model;
pub mod observe;
pub mod preview;
pub mod render;
