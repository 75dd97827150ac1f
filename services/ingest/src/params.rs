//! What the ingest function does, from the stage's parameters (graph file
//! `params` merged with `config/ingest.toml`).

use serde::{Deserialize, Serialize};

use crate::IngestError;
use crate::crop::Normalisation;
use crate::edges::EdgeFilter;
use crate::points::OutlierFilter;

/// Parameters of [`crate::prepare`]; every field has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IngestParams {
    /// S: the crop is resized to S×S pixels (the image encoder's input).
    pub image_size: u32,
    /// P: the encoder sees P×P patches (S must be a multiple of P).
    pub patch_grid: u32,
    /// Extra margin on each side of the mask's box, as a fraction of its
    /// longer side.
    pub padding: f64,
    pub normalisation: Normalisation,
    /// N: points per observation.
    pub point_count: usize,
    pub outliers: OutlierFilter,
    /// Mask pixels behind a nearer mask pixel (background seen past the
    /// object's outline) are dropped before back-projection.
    pub behind_edges: EdgeFilter,
    /// Masks with more valid depth pixels are thinned to this many before
    /// outlier removal and sampling (bounds the cost for near objects).
    pub max_filter_points: usize,
    /// Smaller masks are rejected as detections too small to use.
    pub min_mask_pixels: usize,
    /// Fewer points with valid depth (after outlier removal) reject the object.
    pub min_points: usize,
    /// Depths beyond this (metres) are treated as missing.
    pub max_depth: f32,
    /// G: the Observation carries the depth and the object's mask on a G×G
    /// grid, for the selector's free-space test; 0 leaves them out.
    pub depth_grid: u32,
    /// The depth grid covers the crop scaled by this about its centre:
    /// wider than the crop, so that a pose putting the object well beyond
    /// its mask is seen there.
    pub depth_span: f32,
    /// `false`: the network gets no image (a blank crop, every image token
    /// masked out): the depth-only ablation, or a camera without colour.
    pub rgb: bool,
}

impl Default for IngestParams {
    /// The paper's encoder input (224 px, 16×16 patches of 14 px) and point
    /// count (1024).
    fn default() -> Self {
        Self {
            image_size: 224,
            patch_grid: 16,
            padding: 0.1,
            normalisation: Normalisation::default(),
            point_count: 1024,
            outliers: OutlierFilter::default(),
            behind_edges: EdgeFilter::default(),
            max_filter_points: 4096,
            min_mask_pixels: 16,
            min_points: 16,
            max_depth: 6.0,
            depth_grid: 32,
            depth_span: 2.0,
            rgb: true,
        }
    }
}

impl IngestParams {
    /// Reads the ingest stage's parameters.
    pub fn from_json(value: &serde_json::Value) -> Result<Self, IngestError> {
        let params: Self =
            serde_json::from_value(value.clone()).map_err(|err| IngestError::ParamsFormat(err.to_string()))?;
        params.validate()?;
        Ok(params)
    }

    pub fn validate(&self) -> Result<(), IngestError> {
        let bad = |key: &str, detail: String| Err(IngestError::Params { key: key.into(), detail });
        if !(8..=1024).contains(&self.image_size) {
            return bad("image_size", format!("expected 8 to 1024 pixels, got {}", self.image_size));
        }
        if self.patch_grid == 0 || !self.image_size.is_multiple_of(self.patch_grid) {
            return bad(
                "patch_grid",
                format!("expected a divisor of image_size {}, got {}", self.image_size, self.patch_grid),
            );
        }
        if !(self.padding.is_finite() && (0.0..=2.0).contains(&self.padding)) {
            return bad("padding", format!("expected 0 to 2 (fraction of the box side), got {}", self.padding));
        }
        if !(1..=65536).contains(&self.point_count) {
            return bad("point_count", format!("expected 1 to 65536, got {}", self.point_count));
        }
        if self.normalisation.std.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return bad("normalisation.std", format!("expected positive values, got {:?}", self.normalisation.std));
        }
        if !(self.max_depth.is_finite() && self.max_depth > 0.0) {
            return bad("max_depth", format!("expected a positive number of metres, got {}", self.max_depth));
        }
        if self.depth_grid > 256 {
            return bad("depth_grid", format!("expected 0 (off) to 256 cells, got {}", self.depth_grid));
        }
        if !(self.depth_span.is_finite() && (1.0..=8.0).contains(&self.depth_span)) {
            return bad("depth_span", format!("expected 1 to 8 (times the crop's side), got {}", self.depth_span));
        }
        let edges = &self.behind_edges;
        if edges.radius > 64 {
            return bad("behind_edges.radius", format!("expected 0 (off) to 64 pixels, got {}", edges.radius));
        }
        if !(edges.jump.is_finite() && edges.jump > 0.0) {
            return bad("behind_edges.jump", format!("expected a positive number of metres, got {}", edges.jump));
        }
        if self.max_filter_points < self.point_count {
            return bad(
                "max_filter_points",
                format!("expected at least point_count {}, got {}", self.point_count, self.max_filter_points),
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_keys_and_bad_values_are_named() {
        let err = IngestParams::from_json(&serde_json::json!({ "image_sise": 224 })).unwrap_err().to_string();
        assert!(err.starts_with("params: unknown field `image_sise`"), "{err}");
        let err = IngestParams::from_json(&serde_json::json!({ "patch_grid": 15 })).unwrap_err().to_string();
        assert!(err.contains("param `patch_grid`") && err.contains("divisor of image_size 224"), "{err}");
        let err = IngestParams::from_json(&serde_json::json!({ "behind_edges": { "radius": 100 } })).unwrap_err();
        assert!(err.to_string().contains("param `behind_edges.radius`"), "{err}");
        let err = IngestParams::from_json(&serde_json::json!({ "behind_edges": { "jump": -0.1 } })).unwrap_err();
        assert!(err.to_string().contains("param `behind_edges.jump`") && err.to_string().contains("-0.1"), "{err}");
        let err = IngestParams::from_json(&serde_json::json!({ "behind_edges": { "radius_px": 2 } })).unwrap_err();
        assert!(err.to_string().contains("unknown field `radius_px`"), "{err}");
        let ok = IngestParams::from_json(&serde_json::json!({ "image_size": 112, "patch_grid": 8 })).unwrap();
        assert_eq!((ok.image_size, ok.point_count), (112, 1024));
    }
}
