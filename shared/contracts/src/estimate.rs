//! Sampler → selector (Hypotheses) and selector → consumers (Estimate).

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::message::{MessageHeader, POSE_LEN, bounded, header_accessors, limits, sections};
use crate::{ContractError, Header, ObjectCategory};

/// User header of Hypotheses (104 bytes, alignment 8).
///
/// | offset | size | field        | type | meaning |
/// |-------:|-----:|--------------|------|---------|
/// | 0      | 80   | header       | [`Header`] | `flags` has TRACKING in tracking mode |
/// | 80     | 4    | sample_count | u32  | N |
/// | 84     | 4    | step_count   | u32  | K Euler steps that produced them |
/// | 88     | 16   | category     | [`ObjectCategory`] | copied from the Condition |
///
/// Payload (`f32`): N object-to-camera poses × 12 (`R` row-major, `t` in
/// metres), camera frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Default, ZeroCopySend)]
#[type_name("poseflow/Hypotheses/v2")]
pub struct HypothesesHeader {
    pub header: Header,
    pub sample_count: u32,
    pub step_count: u32,
    pub category: ObjectCategory,
}

impl MessageHeader for HypothesesHeader {
    const NAME: &'static str = "Hypotheses";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        self.category.check(Self::NAME)?;
        let n = bounded(Self::NAME, "sample_count", self.sample_count, 1, limits::MAX_SAMPLES, "1..=4096")?;
        Ok(n * POSE_LEN)
    }
}

/// How the selector chose [`EstimateHeader::best`]; stored as `u32`.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SelectionMethod {
    /// No selection: `best` is the Karcher mean of all hypotheses.
    None = 0,
    /// DBSCAN with the paper's distance, Karcher mean of the largest cluster.
    ModelFree = 1,
    /// One-sided Chamfer distance to the object model.
    Chamfer = 2,
    /// Signed distance to the object surface.
    Sdf = 3,
}

impl SelectionMethod {
    pub fn from_code(code: u32) -> Option<Self> {
        [Self::None, Self::ModelFree, Self::Chamfer, Self::Sdf].into_iter().find(|m| *m as u32 == code)
    }
}

/// `f32` values per mode or scored hypothesis: pose (12) then a weight or
/// score (1).
pub const WEIGHTED_POSE_LEN: usize = POSE_LEN + 1;

/// User header of an Estimate (360 bytes, alignment 8).
///
/// | offset | size | field            | type      | meaning |
/// |-------:|-----:|------------------|-----------|---------|
/// | 0      | 80   | header           | [`Header`] | |
/// | 80     | 48   | best             | [f32; 12] | selected pose, camera frame |
/// | 128    | 48   | mean             | [f32; 12] | Karcher mean of the kept hypotheses |
/// | 176    | 144  | covariance       | [f32; 36] | 6×6 row-major tangent covariance at `mean`, order `[t; ω]` (m², rad²) |
/// | 320    | 4    | rotation_trace   | f32       | trace of the rotational 3×3 block (rad²) |
/// | 324    | 4    | selection        | u32       | [`SelectionMethod`] |
/// | 328    | 4    | mode_count       | u32       | M clusters found |
/// | 332    | 4    | hypothesis_count | u32       | N hypotheses scored (every sample) |
/// | 336    | 4    | kept_count       | u32       | K ≤ N of them kept (the first K) |
/// | 340    | 4    | refined          | u32       | 1 when the kept hypotheses were refined against the observed points |
/// | 344    | 16   | category         | [`ObjectCategory`] | a category-level model's category and size (the poses are then in the category's canonical frame); zeros otherwise |
///
/// Payload (`f32`): M modes × 13 (pose, weight = share of samples) ‖ N
/// hypotheses × 13 (pose, score), best score first; each pose `R` row-major
/// then `t`. Scores: log-likelihood of the observed points (Chamfer, SDF),
/// the share of samples in the hypothesis's cluster (model-free, 0 for
/// noise), 0 without selection.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[type_name("poseflow/Estimate/v3")]
pub struct EstimateHeader {
    pub header: Header,
    pub best: [f32; 12],
    pub mean: [f32; 12],
    pub covariance: [f32; 36],
    pub rotation_trace: f32,
    pub selection: u32,
    pub mode_count: u32,
    pub hypothesis_count: u32,
    pub kept_count: u32,
    pub refined: u32,
    pub category: ObjectCategory,
}

impl Default for EstimateHeader {
    fn default() -> Self {
        Self {
            header: Header::default(),
            best: [0.0; 12],
            mean: [0.0; 12],
            covariance: [0.0; 36],
            rotation_trace: 0.0,
            selection: SelectionMethod::None as u32,
            mode_count: 0,
            hypothesis_count: 0,
            kept_count: 0,
            refined: 0,
            category: ObjectCategory::default(),
        }
    }
}

/// The sections of an Estimate payload.
#[derive(Debug, Clone, Copy)]
pub struct EstimateView<'a> {
    pub modes: &'a [f32],
    pub hypotheses: &'a [f32],
}

impl EstimateHeader {
    fn section_lengths(&self) -> Result<[usize; 2], ContractError> {
        SelectionMethod::from_code(self.selection).ok_or(ContractError::FieldOutOfRange {
            message: Self::NAME,
            field: "selection",
            value: u64::from(self.selection),
            expected: "0 (none), 1 (model-free), 2 (chamfer) or 3 (sdf)",
        })?;
        let m = bounded(Self::NAME, "mode_count", self.mode_count, 0, limits::MAX_MODES, "0..=64")?;
        let n = bounded(Self::NAME, "hypothesis_count", self.hypothesis_count, 1, limits::MAX_SAMPLES, "1..=4096")?;
        if self.kept_count == 0 || self.kept_count > self.hypothesis_count {
            return Err(ContractError::FieldOutOfRange {
                message: Self::NAME,
                field: "kept_count",
                value: u64::from(self.kept_count),
                expected: "1..=hypothesis_count",
            });
        }
        Ok([m * WEIGHTED_POSE_LEN, n * WEIGHTED_POSE_LEN])
    }

    pub fn view<'a>(&self, payload: &'a [f32]) -> Result<EstimateView<'a>, ContractError> {
        self.check_payload(payload)?;
        let [modes, hypotheses] = sections(payload, self.section_lengths()?);
        Ok(EstimateView { modes, hypotheses })
    }

    /// The kept hypotheses' poses (object-to-camera, `R` row-major then
    /// `t`), best first.
    pub fn kept_poses<'a>(&self, payload: &'a [f32]) -> Result<impl Iterator<Item = &'a [f32; 12]>, ContractError> {
        let view = self.view(payload)?;
        Ok(view
            .hypotheses
            .chunks_exact(WEIGHTED_POSE_LEN)
            .take(self.kept_count as usize)
            .map(|chunk| chunk[..POSE_LEN].try_into().expect("a weighted pose starts with 12 values")))
    }
}

impl MessageHeader for EstimateHeader {
    const NAME: &'static str = "Estimate";

    header_accessors!();

    fn payload_len(&self) -> Result<usize, ContractError> {
        self.category.check(Self::NAME)?;
        Ok(self.section_lengths()?.iter().sum())
    }
}
