//! The sampler's parameters (graph `params` over `config/sampler.toml`).

use poseflow_geometry::flow::TimeGrid;
use serde::Deserialize;

use crate::SamplerError;

/// | key | meaning | default |
/// |---|---|---|
/// | `samples` | N hypotheses per observation | 50 |
/// | `steps` | K Euler steps from t = 0 | 5 |
/// | `time_grid` | where the steps ask for the velocity: `uniform` (t = k/K) or `quadratic` (t = 1 − (1 − k/K)², ending nearer 1) | `uniform` |
/// | `seed` | seed of the initial draws (mixed with frame and object ids) | 0 |
/// | `translation_noise_std` | σ of the initial translations, metres; must match the model's `translation_noise_std` metadata | 0.05 |
/// | `velocity_timeout_ms` | how long one velocity request may take before the frame is dropped (counted) | 5000 |
/// | `batch` | most observations of one frame sampled together, one velocity request per Euler step for all | 1 |
/// | `tracking` | see [`TrackingParams`] | off |
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplerParams {
    #[serde(default = "default_samples")]
    pub samples: usize,
    #[serde(default = "default_steps")]
    pub steps: usize,
    /// Of every integration, the prior's and a tracked group's.
    #[serde(default)]
    pub time_grid: TimeGrid,
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "default_noise")]
    pub translation_noise_std: f64,
    #[serde(default = "default_timeout")]
    pub velocity_timeout_ms: u64,
    #[serde(default = "default_batch")]
    pub batch: usize,
    #[serde(default)]
    pub tracking: TrackingParams,
}

fn default_batch() -> usize {
    8
}

/// Tracking mode: a frame whose object has an estimate from an earlier frame
/// (or of this very frame, from a stage that knows it beforehand such as
/// `truth-prior`) starts from that estimate instead of the uniform prior.
///
/// | key | meaning | default |
/// |---|---|---|
/// | `enabled` | start from the previous estimate when there is one | false |
/// | `steps` | Euler steps from `start_time` to 1 | 1 |
/// | `start_time` | flow time the previous estimate is placed at (the network trusts poses near t = 1 more) | 0.8 |
/// | `rotation_noise_deg` | σ per axis of the perturbation about the previous rotation | 5 |
/// | `translation_noise` | σ per axis of the perturbation of the previous translation, metres | 0.01 |
/// | `max_age_frames` | an estimate older than this many frames is not used | 5 |
/// | `prior_share` | after an estimate flagged `UNSURE`: share of the samples drawn from the prior (K = `steps` from t = 0) beside the tracked ones | 0.5 |
/// | `keep_previous` | one tracked sample is the previous estimate itself, neither perturbed nor integrated | true |
/// | `network_every` | a held track (its previous estimate unflagged) runs the networks on every this-many-th frame only, staggered by object id; in between its samples are the previous estimate perturbed, without an Euler step, and the selector's fit places it (`NETWORK_SKIPPED`); 1 = every frame | 1 |
/// | `await_estimate_ms` | before a frame that would start from the prior, wait up to this long for its object's estimate of the frame sampled last when that is on its way (at a graph's start its first frames queue up and arrive together); 0 = never wait | 1000 |
///
/// After an estimate flagged `LOST` (the selector's track check) the object's
/// next frame starts from the prior, every sample.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackingParams {
    #[serde(default)]
    pub enabled: bool,
    #[serde(default = "default_tracking_steps")]
    pub steps: usize,
    #[serde(default = "default_start_time")]
    pub start_time: f64,
    #[serde(default = "default_rotation_noise")]
    pub rotation_noise_deg: f64,
    #[serde(default = "default_translation_noise")]
    pub translation_noise: f64,
    #[serde(default = "default_max_age")]
    pub max_age_frames: u64,
    #[serde(default = "default_prior_share")]
    pub prior_share: f64,
    /// The perturbed samples after one Euler step land several degrees
    /// from a pose that still fits, and where the flow prefers another
    /// mode of a near-symmetric view, all of them do; the previous
    /// estimate itself lets the selector keep a track that still explains
    /// the observation.
    #[serde(default = "default_keep_previous")]
    pub keep_previous: bool,
    /// The encoder and velocity network are most of a tracked frame's
    /// cost, and a track that holds needs little of them: the selector's
    /// fit follows small motions, and the track check hands the object
    /// back to the networks the frame it doubts the fit.
    #[serde(default = "default_network_every")]
    pub network_every: u64,
    /// A frame sampled while its object's previous estimate is still on
    /// its way starts from an older one or the prior: at a graph's start
    /// its first frames queue up behind the selector's grids and then
    /// arrive together.
    #[serde(default = "default_await_estimate_ms")]
    pub await_estimate_ms: u64,
}

impl Default for TrackingParams {
    fn default() -> Self {
        Self {
            enabled: false,
            steps: default_tracking_steps(),
            start_time: default_start_time(),
            rotation_noise_deg: default_rotation_noise(),
            translation_noise: default_translation_noise(),
            max_age_frames: default_max_age(),
            prior_share: default_prior_share(),
            keep_previous: default_keep_previous(),
            network_every: default_network_every(),
            await_estimate_ms: default_await_estimate_ms(),
        }
    }
}

fn default_await_estimate_ms() -> u64 {
    1000
}
fn default_samples() -> usize {
    50
}
fn default_steps() -> usize {
    5
}
fn default_noise() -> f64 {
    0.05
}
fn default_timeout() -> u64 {
    5000
}
fn default_tracking_steps() -> usize {
    1
}
fn default_start_time() -> f64 {
    0.8
}
fn default_rotation_noise() -> f64 {
    5.0
}
fn default_translation_noise() -> f64 {
    0.01
}
fn default_max_age() -> u64 {
    5
}
fn default_prior_share() -> f64 {
    0.5
}
fn default_keep_previous() -> bool {
    true
}
fn default_network_every() -> u64 {
    1
}

impl Default for SamplerParams {
    fn default() -> Self {
        serde_json::from_value(serde_json::json!({})).expect("every field has a default")
    }
}

impl SamplerParams {
    /// Reads the graph's `params`, naming the key that is wrong.
    pub fn from_json(value: &serde_json::Value) -> Result<Self, SamplerError> {
        let params: Self = serde_json::from_value(value.clone())
            .map_err(|e| SamplerError::Params { key: "sampler", detail: e.to_string() })?;
        params.validate()?;
        Ok(params)
    }

    fn validate(&self) -> Result<(), SamplerError> {
        let max = poseflow_contracts::limits::MAX_SAMPLES as usize;
        let checks: [(&'static str, bool, String); 11] = [
            ("samples", (1..=max).contains(&self.samples), format!("{}: expected 1 to {max}", self.samples)),
            ("batch", (1..=64).contains(&self.batch), format!("{}: expected 1 to 64", self.batch)),
            ("steps", (1..=1000).contains(&self.steps), format!("{}: expected 1 to 1000", self.steps)),
            (
                "translation_noise_std",
                self.translation_noise_std.is_finite() && self.translation_noise_std >= 0.0,
                format!("{}: expected metres >= 0", self.translation_noise_std),
            ),
            ("velocity_timeout_ms", self.velocity_timeout_ms > 0, "0: expected at least 1".into()),
            (
                "tracking.steps",
                (1..=1000).contains(&self.tracking.steps),
                format!("{}: expected 1 to 1000", self.tracking.steps),
            ),
            (
                "tracking.network_every",
                (1..=1000).contains(&self.tracking.network_every),
                format!("{}: expected 1 (every frame) to 1000", self.tracking.network_every),
            ),
            (
                "tracking.await_estimate_ms",
                self.tracking.await_estimate_ms <= 60_000,
                format!("{}: expected 0 (never wait) to 60000 ms", self.tracking.await_estimate_ms),
            ),
            (
                "tracking.start_time",
                (0.0..1.0).contains(&self.tracking.start_time),
                format!("{}: expected a flow time 0 <= t < 1", self.tracking.start_time),
            ),
            (
                "tracking.prior_share",
                self.tracking.prior_share > 0.0 && self.tracking.prior_share < 1.0,
                format!("{}: expected a share strictly between 0 and 1", self.tracking.prior_share),
            ),
            (
                "tracking.rotation_noise_deg / translation_noise",
                [self.tracking.rotation_noise_deg, self.tracking.translation_noise]
                    .iter()
                    .all(|x| x.is_finite() && *x >= 0.0),
                format!(
                    "{} / {}: expected numbers >= 0",
                    self.tracking.rotation_noise_deg, self.tracking.translation_noise
                ),
            ),
        ];
        match checks.into_iter().find(|(_, ok, _)| !ok) {
            Some((key, _, detail)) => Err(SamplerError::Params { key, detail }),
            None => Ok(()),
        }
    }
}
