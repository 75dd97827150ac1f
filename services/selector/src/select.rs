//! The selector's plain function: hypotheses (and, for model-based scores
//! and refinement, the observed points and the object model) in, a
//! [`Selection`] out.

use nalgebra::{Point3, Rotation3, Vector3};
use poseflow_contracts::limits;
use poseflow_geometry::mean::karcher_mean_poses;
use poseflow_geometry::metrics::Pinhole;
use poseflow_geometry::{KarcherOptions, Pose, PoseStatistics};
use poseflow_scene::ObjectGeometry;
use poseflow_scene::sdf_refine::{Likelihood, refine};

use crate::cluster::{Clusters, Neighbourhood, dbscan};
use crate::score::{FreeSpaceTerm, Residuals, Scorer};
use crate::visibility::{DepthGrid, FreeSpaceSettings, INSIDE_DEPTH};
use crate::{Distribution, Method, SelectorError, SelectorParams, Turns};

/// What the model-based scores compare poses with, camera frame.
#[derive(Debug, Clone, Copy)]
pub struct Observed<'a> {
    /// The object's observed points, metres.
    pub points: &'a [Point3<f64>],
    /// The crop's depth grid and the camera, for the free-space term.
    pub depth: Option<(&'a DepthGrid, &'a Pinhole)>,
}

impl<'a> Observed<'a> {
    /// Points alone: no free-space term.
    pub fn points(points: &'a [Point3<f64>]) -> Self {
        Self { points, depth: None }
    }
}

/// The scorer of `params`' model-based method, or `None` for the others.
pub(crate) fn scorer<'a>(
    params: &SelectorParams,
    object: &'a ObjectGeometry,
    observed: Observed<'a>,
) -> Option<Scorer<'a>> {
    let residuals = match params.method {
        Method::Chamfer => Residuals::Chamfer(object),
        Method::Sdf => Residuals::Sdf(object),
        Method::None | Method::ModelFree => return None,
    };
    let free_space = observed.depth.map(|(grid, camera)| FreeSpaceTerm {
        grid,
        camera,
        settings: FreeSpaceSettings { inside: INSIDE_DEPTH, margin: params.free_space_margin },
        weight: params.free_space_weight,
    });
    Some(Scorer { residuals, points: observed.points, likelihood: likelihood(params), free_space })
}

fn likelihood(params: &SelectorParams) -> Likelihood {
    Likelihood { noise_std: params.noise_std, outlier_distance: params.outlier_distance }
}

/// The outcome for one object in one frame. Poses are camera-frame.
#[derive(Debug, Clone)]
pub struct Selection {
    pub method: Method,
    /// The selected pose.
    pub best: Pose,
    /// Karcher mean and tangent covariance of the kept hypotheses.
    pub statistics: PoseStatistics,
    /// DBSCAN clusters of all hypotheses, largest first: (Karcher mean,
    /// share of samples).
    pub modes: Vec<(Pose, f64)>,
    /// Every hypothesis with its score, best first; the first `kept` were
    /// kept (with refinement: in the refined scores' order, as the refined
    /// poses or the samples they came from, per `distribution`).
    pub scored: Vec<(Pose, f64)>,
    pub kept: usize,
    pub refined: bool,
    /// The poses `best` was chosen among, with their scores: `best` first,
    /// then best score first (a turned candidate that beat `best` by less
    /// than [`TURN_MARGIN`] follows it); the refined ones with refinement,
    /// otherwise the best sample alone.
    pub candidates: Vec<(Pose, f64)>,
}

impl Selection {
    /// Adds to the candidates the `count` best ones turned by each of
    /// `turns` (rigid motions of the model frame, [`crate::Turns::of`]),
    /// refined and scored, and selects the best-scored candidate. On a
    /// partial view the flow's samples can all land on a turned-over pose,
    /// and a local refinement does not turn them back. Returns whether
    /// `best` changed.
    pub fn search_turns(
        &mut self,
        turns: &[(Rotation3<f64>, Vector3<f64>)],
        object: &ObjectGeometry,
        observed: Observed<'_>,
        params: &SelectorParams,
        count: usize,
    ) -> bool {
        let starts: Vec<Pose> = self
            .candidates
            .iter()
            .take(count)
            .flat_map(|(pose, _)| {
                turns
                    .iter()
                    .map(|(turn, shift)| Pose::new(pose.rotation * turn, pose.translation + pose.rotation * shift))
            })
            .collect();
        self.consider(&starts, object, observed, params)
    }

    /// Puts the selected pose first among the kept hypotheses, in place of
    /// the worst-scored hypothesis, and recomputes their statistics: when a
    /// turned candidate wins, the flow's samples missed it, and a
    /// distribution that leaves out the selected pose would be confident
    /// about the wrong one.
    fn keep_best(&mut self, karcher: &KarcherOptions) -> Result<(), SelectorError> {
        let score = self.candidates.first().map_or(0.0, |c| c.1);
        self.scored.pop();
        self.scored.insert(0, (self.best, score));
        self.kept = (self.kept + 1).min(self.scored.len());
        let kept: Vec<Pose> = self.scored[..self.kept].iter().map(|(p, _)| *p).collect();
        self.statistics = PoseStatistics::compute(&kept, None, karcher).map_err(failed)?;
        Ok(())
    }

    /// Refines and scores `starts` (camera frame) as further candidates,
    /// and selects the best-scored candidate: poses the samples may have
    /// missed, such as where the motion so far predicts the object. Returns
    /// whether `best` changed; a selection without a model-based score, or
    /// without points, is left as it is.
    pub fn consider(
        &mut self,
        starts: &[Pose],
        object: &ObjectGeometry,
        observed: Observed<'_>,
        params: &SelectorParams,
    ) -> bool {
        let Some(scorer) = scorer(params, object, observed) else { return false };
        if observed.points.is_empty() || starts.is_empty() {
            return false;
        }
        let poses: Vec<Pose> = starts
            .iter()
            .map(|start| {
                refine(object.grid(), start, observed.points, &scorer.likelihood, params.refine_iterations).pose
            })
            .collect();
        let fits: Vec<f64> = poses.iter().map(|pose| scorer.fit(pose)).collect();
        let floor = self.candidates.first().map_or(f64::NEG_INFINITY, |c| c.1);
        let scores = scorer.scores(&poses, &fits, floor);
        self.candidates.extend(poses.into_iter().zip(scores));
        self.candidates.sort_by(|a, b| b.1.total_cmp(&a.1));
        let best = self.candidates[0].0;
        std::mem::replace(&mut self.best, best) != best
    }

    /// Selects the best-scored candidate that `near` accepts in place of
    /// the best one when that scores at most `margin` above it (its score
    /// recomputed in full: a candidate scored below the best keeps its fit,
    /// an upper bound, [`Scorer::scores`]). Returns the score difference
    /// when it did; `None` when `best` is near already, no candidate is, or
    /// the best one is better by more than `margin`. A tracked object's
    /// turned-over pose can fit its points nearly as well as the pose its
    /// motion leads to, and the track must not change branch on the noise.
    pub fn prefer(
        &mut self,
        near: impl Fn(&Pose) -> bool,
        margin: f64,
        object: &ObjectGeometry,
        observed: Observed<'_>,
        params: &SelectorParams,
    ) -> Option<f64> {
        let &(best, best_score) = self.candidates.first()?;
        if near(&best) {
            return None;
        }
        let scorer = scorer(params, object, observed)?;
        let i = self.candidates.iter().position(|(pose, _)| near(pose))?;
        let pose = self.candidates[i].0;
        let score = scorer.scores(&[pose], &[scorer.fit(&pose)], f64::NEG_INFINITY)[0];
        let behind = best_score - score;
        if behind > margin {
            tracing::debug!(
                behind,
                margin,
                "the best candidate jumped and scored more than the margin above the nearest"
            );
            return None;
        }
        self.candidates.remove(i);
        self.candidates.insert(0, (pose, score));
        self.best = pose;
        Some(behind)
    }

    /// As [`Self::search_turns`], but a turned candidate is selected only
    /// if it scores more than `margin` above the best before: a symmetric
    /// object's turns that map it onto itself fit the points as well, and
    /// must not move the selected pose to a twin by rounding.
    pub fn search_turns_with_margin(
        &mut self,
        turns: &[(Rotation3<f64>, Vector3<f64>)],
        object: &ObjectGeometry,
        observed: Observed<'_>,
        params: &SelectorParams,
        margin: f64,
    ) -> bool {
        let Some(&before) = self.candidates.first() else { return false };
        if !self.search_turns(turns, object, observed, params, params.turned_candidates) {
            return false;
        }
        if self.candidates[0].1 > before.1 + margin {
            return true;
        }
        // Not better by the margin: the pose before stays first.
        if let Some(i) = self.candidates.iter().position(|c| c.0 == before.0) {
            let kept = self.candidates.remove(i);
            self.candidates.insert(0, kept);
        }
        self.best = before.0;
        false
    }
}

fn failed(detail: impl std::fmt::Display) -> SelectorError {
    SelectorError::Selection { detail: detail.to_string() }
}

/// Selects a pose from `hypotheses`. `observed` and `object` are needed by
/// the model-based methods and by refinement.
pub fn select(
    hypotheses: &[Pose],
    observed: Option<Observed<'_>>,
    object: Option<&ObjectGeometry>,
    params: &SelectorParams,
) -> Result<Selection, SelectorError> {
    select_turning(hypotheses, observed, object, params, params.turns)
}

/// [`select`] with `turns` in place of `params.turns`: the stage turns
/// fewer messages than its parameters say (category templates, a held
/// track's frames without network passes) without a copy of them.
pub(crate) fn select_turning(
    hypotheses: &[Pose],
    observed: Option<Observed<'_>>,
    object: Option<&ObjectGeometry>,
    params: &SelectorParams,
    turns: Turns,
) -> Result<Selection, SelectorError> {
    let n = hypotheses.len();
    if n == 0 {
        return Err(failed("no hypotheses to select from"));
    }
    let karcher = KarcherOptions::default();
    let neighbourhood = Neighbourhood {
        rotation: params.epsilon_rotation_deg.to_radians(),
        translation: params.epsilon_translation,
        min_samples: params.min_samples,
    };
    let clusters = dbscan(hypotheses, &neighbourhood);
    let modes = modes(hypotheses, &clusters, &karcher)?;
    let likelihood = likelihood(params);
    let needs_points = params.method.needs_model() || params.refine;
    let (observed, object) = match (observed, object) {
        (Some(p), Some(o)) => (p, Some(o)),
        _ if needs_points => {
            return Err(failed(format!(
                "method {:?}{} needs the observed points and the object model, and {} missing",
                params.method,
                if params.refine { " with refine" } else { "" },
                if observed.is_none() { "the points are" } else { "the model is" }
            )));
        }
        _ => (Observed::points(&[]), None),
    };
    let points = observed.points;
    let scorer = object.and_then(|o| scorer(params, o, observed));

    // Score, then order: best score first; model-free ties go to the larger
    // cluster, then to sample order (a stable, seed-independent order). The
    // samples are scored by their points alone: the free-space term is for
    // the few refined candidates, whose outline it judges.
    let score = |i: usize| -> f64 {
        match (params.method, scorer) {
            (Method::ModelFree, _) => clusters.labels[i].map_or(0.0, |c| clusters.sizes[c] as f64 / n as f64),
            (_, Some(s)) => s.residuals.score(&hypotheses[i], points, &likelihood),
            _ => 0.0,
        }
    };
    let scores: Vec<f64> = (0..n).map(score).collect();
    let mut order: Vec<usize> = (0..n).collect();
    let cluster_rank = |i: usize| clusters.labels[i].unwrap_or(usize::MAX);
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(cluster_rank(a).cmp(&cluster_rank(b))));
    let mut scored: Vec<(Pose, f64)> = order.iter().map(|&i| (hypotheses[i], scores[i])).collect();
    let by_fraction = ((params.keep_fraction * n as f64).ceil() as usize).clamp(1, n);
    let kept = match params.method {
        Method::None => n,
        Method::ModelFree => clusters.sizes.first().copied().unwrap_or(n),
        Method::Chamfer | Method::Sdf => {
            let best = scored.first().map_or(0.0, |(_, s)| *s);
            let by_margin = scored.iter().take_while(|(_, s)| *s >= best - params.keep_margin).count();
            by_fraction.max(by_margin)
        }
    };
    // The best pose is found among the `keep_fraction` best; hypotheses kept
    // beyond them by the margin are reported as sampled, so they cost no
    // refinement unless the refined poses are what is reported.
    let refined_count = match (params.method, params.distribution) {
        (Method::Chamfer | Method::Sdf, Distribution::Samples) => kept.min(by_fraction),
        _ => kept,
    };

    let mut refined_kept: Option<Vec<(Pose, f64)>> = None;
    if let (true, Some(object)) = (params.refine, object) {
        let grid = object.grid();
        // (refined pose, its score, the sample it came from), best first.
        let poses: Vec<Pose> = scored[..refined_count]
            .iter()
            .map(|sample| refine(grid, &sample.0, points, &likelihood, params.refine_iterations).pose)
            .collect();
        let scores = match scorer {
            Some(s) => s.scores(&poses, &poses.iter().map(|pose| s.fit(pose)).collect::<Vec<_>>(), f64::NEG_INFINITY),
            None => scored[..refined_count].iter().map(|sample| sample.1).collect(),
        };
        let mut refined: Vec<(Pose, f64, (Pose, f64))> = poses
            .into_iter()
            .zip(scores)
            .zip(&scored[..refined_count])
            .map(|((p, s), &sample)| (p, s, sample))
            .collect();
        if scorer.is_some() {
            refined.sort_by(|a, b| b.1.total_cmp(&a.1));
        }
        refined_kept = Some(refined.iter().map(|r| (r.0, r.1)).collect());
        for (entry, (pose, score, sample)) in scored[..refined_count].iter_mut().zip(refined) {
            *entry = match params.distribution {
                Distribution::Refined => (pose, score),
                Distribution::Samples => sample,
            };
        }
    }

    let kept_poses: Vec<Pose> = scored[..kept].iter().map(|(p, _)| *p).collect();
    let statistics = PoseStatistics::compute(&kept_poses, None, &karcher).map_err(failed)?;
    let best = match (params.method, &refined_kept) {
        (Method::None | Method::ModelFree, None) => statistics.mean.mean,
        (Method::None | Method::ModelFree, Some(refined)) => {
            let poses: Vec<Pose> = refined.iter().map(|r| r.0).collect();
            karcher_mean_poses(&poses, None, &karcher).map_err(failed)?.mean
        }
        (Method::Chamfer | Method::Sdf, Some(refined)) => refined[0].0,
        (Method::Chamfer | Method::Sdf, None) => scored[0].0,
    };
    let candidates = match (params.method, refined_kept) {
        (Method::Chamfer | Method::Sdf, Some(refined)) => refined,
        (Method::Chamfer | Method::Sdf, None) => vec![scored[0]],
        _ => vec![(best, 0.0)],
    };
    let mut selection =
        Selection { method: params.method, best, statistics, modes, scored, kept, refined: params.refine, candidates };
    if let (true, Some(object)) = (params.refine, object)
        && selection.search_turns_with_margin(turns.of(object), object, observed, params, TURN_MARGIN)
    {
        selection.keep_best(&karcher)?;
    }
    Ok(selection)
}

/// How much better (per-point log-likelihood, the scores' unit) a turned
/// candidate must explain the points than the best refined sample to be
/// selected by `turns`: above the rounding between a symmetric object's
/// twins, below the gain of a pose turned back from a wrong face. Chosen
/// on the development splits (LM-O and YCB-V `test`): 0.01 cost a point of
/// YCB-V 10°5cm there.
pub const TURN_MARGIN: f64 = 0.002;

/// Karcher mean and share of samples of each cluster (at most the
/// contract's 64), largest first.
fn modes(
    hypotheses: &[Pose],
    clusters: &Clusters,
    karcher: &KarcherOptions,
) -> Result<Vec<(Pose, f64)>, SelectorError> {
    let n = hypotheses.len() as f64;
    (0..clusters.sizes.len().min(limits::MAX_MODES as usize))
        .map(|c| {
            let members: Vec<Pose> = clusters.members(c).map(|i| hypotheses[i]).collect();
            let mean = karcher_mean_poses(&members, None, karcher).map_err(failed)?;
            Ok((mean.mean, members.len() as f64 / n))
        })
        .collect()
}
