//! The selector's parameters (graph `params` over `config/selector.toml`).

use std::path::PathBuf;

use nalgebra::{Rotation3, Vector3};
use serde::Deserialize;

use crate::SelectorError;

/// How the selected pose is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// No selection: the Karcher mean of all samples.
    None,
    /// The Karcher mean of the largest DBSCAN cluster.
    ModelFree,
    /// The best one-sided Chamfer score (exact point-to-mesh distances).
    Chamfer,
    /// The best signed-distance score (a grid precomputed per object).
    Sdf,
}

/// Which poses the Estimate reports as its kept hypotheses (and their mean
/// and covariance) when `refine` is on; the selected pose is the best
/// refined one either way.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Distribution {
    /// The flow's samples as they were kept (in the refined scores' order):
    /// refinement pulls every sample near one optimum onto it, which says
    /// how precise the selected pose is, not how uncertain the estimate is.
    Samples,
    /// The refined hypotheses.
    Refined,
}

/// Which turned copies of the best refined candidates are refined and
/// scored as well: the poses a depth fit of a partial view confuses, which
/// a local refinement does not reach.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Turns {
    None,
    /// Half turns about the object's principal axes (3 per candidate).
    Half,
    /// Quarter, half and three-quarter turns about them (9 per candidate).
    Quarter,
}

impl Turns {
    /// The turns of `object`, as rigid motions of its model frame.
    pub fn of(self, object: &poseflow_scene::ObjectGeometry) -> &[(Rotation3<f64>, Vector3<f64>)] {
        match self {
            Self::None => &[],
            Self::Half => object.half_turns(),
            Self::Quarter => object.quarter_turns(),
        }
    }
}

impl Method {
    pub fn needs_model(self) -> bool {
        matches!(self, Self::Chamfer | Self::Sdf)
    }
}

/// | key | meaning | default |
/// |---|---|---|
/// | `method` | `none`, `model-free`, `chamfer` or `sdf` | `model-free` |
/// | `epsilon_rotation_deg` | DBSCAN neighbourhood: rotation (paper: 10°) | 10 |
/// | `epsilon_translation` | DBSCAN neighbourhood: translation, metres | 0.02 |
/// | `min_samples` | DBSCAN core-point size (the point itself included) | 3 |
/// | `keep_fraction` | share of best-scored hypotheses kept (model-based) | 0.2 |
/// | `keep_margin` | model-based: also keep every hypothesis scored within this of the best (per-point log-likelihood; 0.5 = a mean squared residual one σ² worse; 0: `keep_fraction` alone) | 0.25 |
/// | `models` | BOP models directory (`models_info.json`, `obj_NNNNNN.ply`, mm) for `chamfer`, `sdf`, `refine` | none |
/// | `category_templates` | instead of `models`: score a category-level model's hypotheses against its category's mean shape stretched to the size the model predicted (the Hypotheses' `category`) | false |
/// | `score_points` | observed points scored (a prefix of the farthest-point order) | 256 |
/// | `noise_std` | σ of point-to-surface residuals in the likelihood, metres | 0.005 |
/// | `outlier_distance` | residuals are truncated here (occluders, mask bleed), metres | 0.02 |
/// | `sdf_resolution` | grid cells along the object's longest side | 64 |
/// | `refine` | refine the kept hypotheses (Levenberg-Marquardt on the grid) | false |
/// | `refine_iterations` | iterations per hypothesis | 10 |
/// | `turns` | with `refine` and a model-based method: also refine and score the `turned_candidates` best refined candidates turned about the object's principal axes, `none`, `half` (3 turns each) or `quarter` (9); the selected pose joins the kept hypotheses when a turn wins; not for category templates | `quarter` |
/// | `turned_candidates` | how many of the best refined candidates `turns` turns | 2 |
/// | `turn_skipped_frames` | turn a held track's frames without network passes too (header flag `NETWORK_SKIPPED`: its last estimate perturbed); off, only the frames the networks ran are turned, which is cheaper and re-acquires later | true |
/// | `distribution` | with `refine`: the kept hypotheses reported are the `samples` or the `refined` ones | `samples` |
/// | `observations` | Observations kept while their Hypotheses are awaited | 64 |
/// | `batch` | most Hypotheses of one frame selected from together | 8 |
/// | `threads` | threads a batch's objects are selected on (the estimates are the same for any number) | 2 |
/// | `free_space_weight` | refined candidates lose this times an outlier point's log-likelihood per share of lines of sight on which the camera saw past the posed object (the Observation's depth grid; none: no term); 0: off | 1 |
/// | `free_space_margin` | such a line of sight passes through the posed object at least this far in front of the observed depth, metres | 0.01 |
/// | `tracking` | the track check of a tracking graph ([`crate::track::TrackCheckParams`]) | off |
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SelectorParams {
    #[serde(default = "default_method")]
    pub method: Method,
    #[serde(default = "default_epsilon_rotation")]
    pub epsilon_rotation_deg: f64,
    #[serde(default = "default_epsilon_translation")]
    pub epsilon_translation: f64,
    #[serde(default = "default_min_samples")]
    pub min_samples: usize,
    #[serde(default = "default_keep_fraction")]
    pub keep_fraction: f64,
    /// Hypotheses the observed points cannot tell apart from the best (a
    /// mug whose handle is out of sight fits its body equally at every turn)
    /// are all kept, however many that is; `keep_fraction` stays the minimum.
    #[serde(default = "default_keep_margin")]
    pub keep_margin: f64,
    #[serde(default)]
    pub models: Option<PathBuf>,
    /// Category-level hypotheses are scored against a template: the mean
    /// shape of their category stretched to their predicted size
    /// (`poseflow_scene::category::template`); no meshes are loaded.
    #[serde(default)]
    pub category_templates: bool,
    #[serde(default = "default_score_points")]
    pub score_points: usize,
    #[serde(default = "default_noise_std")]
    pub noise_std: f64,
    #[serde(default = "default_outlier_distance")]
    pub outlier_distance: f64,
    #[serde(default = "default_sdf_resolution")]
    pub sdf_resolution: usize,
    #[serde(default)]
    pub refine: bool,
    #[serde(default = "default_refine_iterations")]
    pub refine_iterations: usize,
    #[serde(default = "default_turns")]
    pub turns: Turns,
    #[serde(default = "default_turned_candidates")]
    pub turned_candidates: usize,
    #[serde(default = "default_true")]
    pub turn_skipped_frames: bool,
    #[serde(default = "default_distribution")]
    pub distribution: Distribution,
    #[serde(default = "default_observations")]
    pub observations: usize,
    /// Hypotheses of one frame held and selected from together
    /// ([`poseflow_runtime::FrameBatches`]); 1 selects from each at once.
    #[serde(default = "default_batch")]
    pub batch: usize,
    /// Threads a batch's objects are spread over: where a frame holds
    /// several objects and a core is free (the networks wait on the
    /// sampler), the frame's estimates come sooner.
    #[serde(default = "default_threads")]
    pub threads: usize,
    /// How much a refined candidate loses for putting the object where the
    /// camera saw past it (1: each such line of sight costs like an outlier
    /// point); 0 switches the free-space term off.
    #[serde(default = "default_free_space_weight")]
    pub free_space_weight: f64,
    /// The free-space test's allowance: a line of sight counts only where it
    /// passes through the posed object this far (metres) in front of the
    /// observed depth.
    #[serde(default = "default_free_space_margin")]
    pub free_space_margin: f64,
    #[serde(default)]
    pub tracking: crate::track::TrackCheckParams,
}

fn default_method() -> Method {
    Method::ModelFree
}
fn default_epsilon_rotation() -> f64 {
    10.0
}
fn default_epsilon_translation() -> f64 {
    0.02
}
fn default_min_samples() -> usize {
    3
}
fn default_keep_fraction() -> f64 {
    0.2
}
fn default_keep_margin() -> f64 {
    0.25
}
fn default_score_points() -> usize {
    256
}
fn default_noise_std() -> f64 {
    0.005
}
fn default_outlier_distance() -> f64 {
    0.02
}
fn default_sdf_resolution() -> usize {
    64
}
fn default_distribution() -> Distribution {
    Distribution::Samples
}
fn default_true() -> bool {
    true
}
fn default_turns() -> Turns {
    Turns::Quarter
}
fn default_turned_candidates() -> usize {
    2
}
fn default_refine_iterations() -> usize {
    10
}
fn default_observations() -> usize {
    64
}
fn default_batch() -> usize {
    8
}
fn default_threads() -> usize {
    2
}
fn default_free_space_weight() -> f64 {
    1.0
}
fn default_free_space_margin() -> f64 {
    0.01
}

impl Default for SelectorParams {
    fn default() -> Self {
        serde_json::from_value(serde_json::json!({})).expect("every field has a default")
    }
}

impl SelectorParams {
    /// Reads the graph's `params`, naming the key that is wrong.
    pub fn from_json(value: &serde_json::Value) -> Result<Self, SelectorError> {
        let params: Self = serde_json::from_value(value.clone())
            .map_err(|e| SelectorError::Params { key: "selector", detail: e.to_string() })?;
        params.validate()?;
        Ok(params)
    }

    /// Whether the object models must be loaded.
    pub fn needs_models(&self) -> bool {
        (self.method.needs_model() || self.refine) && !self.category_templates
    }

    pub fn validate(&self) -> Result<(), SelectorError> {
        let positive = |x: f64| x.is_finite() && x > 0.0;
        let checks: [(&'static str, bool, String); 15] = [
            (
                "epsilon_rotation_deg",
                positive(self.epsilon_rotation_deg) && self.epsilon_rotation_deg <= 180.0,
                format!("{}: expected degrees in (0, 180]", self.epsilon_rotation_deg),
            ),
            (
                "epsilon_translation",
                positive(self.epsilon_translation),
                format!("{}: expected metres > 0", self.epsilon_translation),
            ),
            ("min_samples", self.min_samples >= 1, format!("{}: expected at least 1", self.min_samples)),
            (
                "keep_fraction",
                self.keep_fraction > 0.0 && self.keep_fraction <= 1.0,
                format!("{}: expected a share in (0, 1]", self.keep_fraction),
            ),
            (
                "keep_margin",
                self.keep_margin.is_finite() && self.keep_margin >= 0.0,
                format!("{}: expected a score margin ≥ 0", self.keep_margin),
            ),
            ("score_points", self.score_points >= 3, format!("{}: expected at least 3", self.score_points)),
            (
                "noise_std / outlier_distance",
                positive(self.noise_std) && positive(self.outlier_distance),
                format!("{} / {}: expected metres > 0", self.noise_std, self.outlier_distance),
            ),
            (
                "sdf_resolution",
                (8..=256).contains(&self.sdf_resolution),
                format!("{}: expected 8 to 256 cells", self.sdf_resolution),
            ),
            (
                "refine_iterations",
                (1..=100).contains(&self.refine_iterations),
                format!("{}: expected 1 to 100", self.refine_iterations),
            ),
            (
                "turned_candidates",
                (1..=64).contains(&self.turned_candidates),
                format!("{}: expected 1 to 64", self.turned_candidates),
            ),
            ("observations", self.observations >= 1, format!("{}: expected at least 1", self.observations)),
            ("batch", (1..=64).contains(&self.batch), format!("{}: expected 1 to 64", self.batch)),
            ("threads", (1..=64).contains(&self.threads), format!("{}: expected 1 to 64", self.threads)),
            (
                "free_space_weight",
                self.free_space_weight.is_finite() && self.free_space_weight >= 0.0,
                format!("{}: expected a weight ≥ 0 (0: off)", self.free_space_weight),
            ),
            (
                "free_space_margin",
                self.free_space_margin.is_finite() && self.free_space_margin >= 0.0,
                format!("{}: expected metres ≥ 0", self.free_space_margin),
            ),
        ];
        if let Some((key, _, detail)) = checks.into_iter().find(|(_, ok, _)| !ok) {
            return Err(SelectorError::Params { key, detail });
        }
        self.tracking.validate()?;
        if self.category_templates && self.models.is_some() {
            return Err(SelectorError::Params {
                key: "category_templates",
                detail: "true with `models` set: a category-level graph scores against templates, an instance-level \
                         one against its meshes; set one of the two"
                    .into(),
            });
        }
        if self.needs_models() && self.models.is_none() {
            return Err(SelectorError::Params {
                key: "models",
                detail: format!(
                    "method {:?}{} needs the object models: set `models` to a BOP models directory (or \
                     `category_templates = true` for a category-level model)",
                    self.method,
                    if self.refine { " with refine" } else { "" }
                ),
            });
        }
        Ok(())
    }
}
