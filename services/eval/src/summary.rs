//! The evaluation summary: instance scores averaged overall and per
//! object, calibration, runtime.

use std::collections::BTreeMap;
use std::time::Duration;

use poseflow_contracts::flags;
use serde::Serialize;

use super::score::InstanceScore;
use poseflow_runtime::timing::Timing;

/// One ground-truth instance's outcome: its scores, or none when the graph
/// gave no estimate for it (a miss: 0 on every accuracy).
#[derive(Debug, Clone)]
pub struct InstanceOutcome {
    pub scene_id: u32,
    pub im_id: u32,
    pub obj_id: u32,
    pub score: Option<InstanceScore>,
    /// The graph's time on this object: the interval since the previous
    /// frame's estimates left the selector, shared among its frame's
    /// estimates.
    pub service_time: Option<Duration>,
    /// From the frame source reading the image to the selector's estimate.
    pub latency: Option<Duration>,
    /// The estimate's header flags (0 without an estimate).
    pub flags: u32,
    /// The instance's visible fraction (`scene_gt_info.json`), when known.
    pub visib_fract: Option<f64>,
}

impl InstanceOutcome {
    /// The estimate's samples started from an earlier estimate or a prior.
    pub fn tracked(&self) -> bool {
        self.flags & flags::TRACKING != 0
    }
}

/// Accuracies in percent over a set of instances.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Accuracies {
    pub instances: usize,
    pub estimated: usize,
    /// Estimated from an earlier estimate or a prior (tracking graphs).
    pub tracked: usize,
    pub acc_5deg_2cm: f64,
    pub acc_5deg_5cm: f64,
    pub acc_10deg_2cm: f64,
    pub acc_10deg_5cm: f64,
    /// ADD (ADD-S for symmetric objects) below 0.1 × diameter.
    pub add_s: f64,
    pub mssd_recall: f64,
    pub mspd_recall: f64,
    /// When the dataset has depth images; an instance without an estimate
    /// counts 0.
    pub vsd_recall: Option<f64>,
    /// BOP19's average recall, the mean of the VSD, MSSD and MSPD recalls
    /// (with VSD only).
    pub bop_ar: Option<f64>,
    /// Over the symmetric objects' instances with an estimate; `None` when
    /// there are none.
    pub mode_recall: Option<f64>,
    /// Of the selected pose, over the estimated instances.
    pub median_rotation_error_deg: Option<f64>,
    pub median_translation_error_cm: Option<f64>,
    /// Instances with some kept hypothesis within 10°5cm / 5°5cm of the
    /// truth (a miss counts 0).
    pub coverage_10deg_5cm: f64,
    pub coverage_5deg_5cm: f64,
    /// Median over the estimated instances of the largest folded rotational
    /// standard deviation of the kept hypotheses.
    pub median_rotation_spread_max_deg: Option<f64>,
    /// Of the estimated instances with a spread: the share whose selected
    /// pose's rotation error is at most 1× / 2× it.
    pub within_1_spread: Option<f64>,
    pub within_2_spread: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    #[serde(flatten)]
    pub overall: Accuracies,
    /// Spearman correlation between the reported rotational spread (√trace
    /// of the Estimate's covariance) and the selected pose's rotation error;
    /// `None` below 3 estimated instances or when either is constant.
    pub spread_error_spearman: Option<f64>,
    /// The same against the largest folded standard deviation of the kept
    /// hypotheses (symmetry not counted as spread).
    pub spread_max_error_spearman: Option<f64>,
    /// Over the service times: the graph's cost per object.
    pub ms_per_object_mean: f64,
    pub ms_per_object_p50: f64,
    pub ms_per_object_p99: f64,
    /// Frame source to estimate, queueing included.
    pub latency: Timing,
    pub per_object: BTreeMap<u32, ObjectSummary>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ObjectSummary {
    #[serde(flatten)]
    pub accuracies: Accuracies,
    /// Of the service times.
    pub ms_per_object: Timing,
}

fn percent(sum: f64, count: usize) -> f64 {
    if count == 0 { 0.0 } else { 100.0 * sum / count as f64 }
}

fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(values[n / 2]),
        _ => Some(0.5 * (values[n / 2 - 1] + values[n / 2])),
    }
}

fn accuracies<'a>(outcomes: impl Iterator<Item = &'a InstanceOutcome>) -> Accuracies {
    let outcomes: Vec<&InstanceOutcome> = outcomes.collect();
    let scores: Vec<&InstanceScore> = outcomes.iter().filter_map(|o| o.score.as_ref()).collect();
    let n = outcomes.len();
    // fold from +0.0: an empty f64 sum is -0.0, printed as "-0.0".
    let sum = |f: &dyn Fn(&InstanceScore) -> f64| scores.iter().fold(0.0, |total, s| total + f(s));
    let modes: Vec<f64> = scores.iter().filter_map(|s| s.mode_recall).collect();
    let spreads: Vec<(f64, f64)> =
        scores.iter().filter_map(|s| Some((s.rotation_spread_max_deg?, s.rotation_error_deg))).collect();
    let has_depth = scores.iter().any(|s| s.vsd_recall.is_some());
    let vsd_recall = has_depth.then(|| percent(sum(&|s| s.vsd_recall.unwrap_or(0.0)), n));
    let (mssd_recall, mspd_recall) = (percent(sum(&|s| s.mssd_recall), n), percent(sum(&|s| s.mspd_recall), n));
    Accuracies {
        instances: n,
        estimated: scores.len(),
        tracked: outcomes.iter().filter(|o| o.tracked()).count(),
        acc_5deg_2cm: percent(sum(&|s| s.accuracy[0]), n),
        acc_5deg_5cm: percent(sum(&|s| s.accuracy[1]), n),
        acc_10deg_2cm: percent(sum(&|s| s.accuracy[2]), n),
        acc_10deg_5cm: percent(sum(&|s| s.accuracy[3]), n),
        add_s: percent(sum(&|s| s.add_s), n),
        mssd_recall,
        mspd_recall,
        vsd_recall,
        bop_ar: vsd_recall.map(|vsd| (vsd + mssd_recall + mspd_recall) / 3.0),
        mode_recall: (!modes.is_empty()).then(|| percent(modes.iter().fold(0.0, |a, b| a + b), modes.len())),
        median_rotation_error_deg: median(scores.iter().map(|s| s.rotation_error_deg).collect()),
        median_translation_error_cm: median(scores.iter().map(|s| s.translation_error_cm).collect()),
        coverage_10deg_5cm: percent(sum(&|s| f64::from(u8::from(s.covered[0]))), n),
        coverage_5deg_5cm: percent(sum(&|s| f64::from(u8::from(s.covered[1]))), n),
        median_rotation_spread_max_deg: median(spreads.iter().map(|&(spread, _)| spread).collect()),
        within_1_spread: within_spread(&spreads, 1.0),
        within_2_spread: within_spread(&spreads, 2.0),
    }
}

/// Percent of (spread, error) pairs with error ≤ `factor` × spread.
fn within_spread(pairs: &[(f64, f64)], factor: f64) -> Option<f64> {
    let within = pairs.iter().filter(|(spread, error)| *error <= factor * spread).count();
    (!pairs.is_empty()).then(|| percent(within as f64, pairs.len()))
}

/// Ranks from 1, ties sharing their mean rank.
fn ranks(values: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut ranks = vec![0.0; values.len()];
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        while end < order.len() && values[order[end]] == values[order[start]] {
            end += 1;
        }
        let mean_rank = (start + end + 1) as f64 / 2.0;
        for &i in &order[start..end] {
            ranks[i] = mean_rank;
        }
        start = end;
    }
    ranks
}

/// Spearman's rank correlation (Pearson on tie-averaged ranks); `None` for
/// fewer than 3 pairs or a constant side.
pub fn spearman(a: &[f64], b: &[f64]) -> Option<f64> {
    if a.len() != b.len() || a.len() < 3 {
        return None;
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let mean = (a.len() as f64 + 1.0) / 2.0;
    let (mut cov, mut va, mut vb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        cov += (x - mean) * (y - mean);
        va += (x - mean).powi(2);
        vb += (y - mean).powi(2);
    }
    (va > 0.0 && vb > 0.0).then(|| cov / (va * vb).sqrt())
}

/// One line per instance (for plots of accuracy against thresholds):
/// `scene_id,im_id,obj_id,estimated,rotation_error_deg,translation_error_cm,rotation_spread_deg,
/// rotation_spread_max_deg,covered_10deg_5cm,covered_5deg_5cm`: errors of the selected pose, the
/// reported and the folded spread, whether a kept hypothesis covers the truth; empty fields when
/// unknown.
pub fn instances_csv(outcomes: &[InstanceOutcome]) -> String {
    let mut out = String::from(
        "scene_id,im_id,obj_id,visib_fract,estimated,rotation_error_deg,translation_error_cm,rotation_spread_deg,\
         rotation_spread_max_deg,covered_10deg_5cm,covered_5deg_5cm\n",
    );
    for o in outcomes {
        let field = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.4}"));
        let flag = |v: Option<bool>| v.map_or(String::new(), |v| u8::from(v).to_string());
        let score = o.score.as_ref();
        out.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{},{}\n",
            o.scene_id,
            o.im_id,
            o.obj_id,
            field(o.visib_fract),
            u8::from(score.is_some()),
            field(score.map(|s| s.rotation_error_deg)),
            field(score.map(|s| s.translation_error_cm)),
            field(score.and_then(|s| s.rotation_spread_deg)),
            field(score.and_then(|s| s.rotation_spread_max_deg)),
            flag(score.map(|s| s.covered[0])),
            flag(score.map(|s| s.covered[1])),
        ));
    }
    out
}

pub fn summarise(outcomes: &[InstanceOutcome]) -> Summary {
    let scores: Vec<&InstanceScore> = outcomes.iter().filter_map(|o| o.score.as_ref()).collect();
    let (spreads, errors): (Vec<f64>, Vec<f64>) =
        scores.iter().filter_map(|s| Some((s.rotation_spread_deg?, s.rotation_error_deg))).unzip();
    let (spread_maxima, max_errors): (Vec<f64>, Vec<f64>) =
        scores.iter().filter_map(|s| Some((s.rotation_spread_max_deg?, s.rotation_error_deg))).unzip();
    let service_times = |obj: Option<u32>| -> Vec<Duration> {
        outcomes.iter().filter(|o| obj.is_none_or(|id| o.obj_id == id)).filter_map(|o| o.service_time).collect()
    };
    let per_object_time = Timing::of(service_times(None));
    let mut ids: Vec<u32> = outcomes.iter().map(|o| o.obj_id).collect();
    ids.sort_unstable();
    ids.dedup();
    let per_object = ids
        .into_iter()
        .map(|id| {
            let summary = ObjectSummary {
                accuracies: accuracies(outcomes.iter().filter(|o| o.obj_id == id)),
                ms_per_object: Timing::of(service_times(Some(id))),
            };
            (id, summary)
        })
        .collect();
    Summary {
        overall: accuracies(outcomes.iter()),
        spread_error_spearman: spearman(&spreads, &errors),
        spread_max_error_spearman: spearman(&spread_maxima, &max_errors),
        ms_per_object_mean: per_object_time.mean_ms,
        ms_per_object_p50: per_object_time.p50_ms,
        ms_per_object_p99: per_object_time.p99_ms,
        latency: Timing::of(outcomes.iter().filter_map(|o| o.latency).collect()),
        per_object,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn outcome(obj_id: u32, accuracy: [f64; 4], rotation_error_deg: f64, spread: f64) -> InstanceOutcome {
        InstanceOutcome {
            scene_id: 0,
            im_id: 0,
            obj_id,
            score: Some(InstanceScore {
                rotation_error_deg,
                translation_error_cm: 1.0,
                accuracy,
                add_s: accuracy[3],
                mssd_recall: 0.5,
                mspd_recall: 0.25,
                vsd_recall: Some(0.75),
                mode_recall: (obj_id == 10).then_some(0.5),
                rotation_spread_deg: Some(spread),
                covered: [accuracy[3] > 0.0, accuracy[1] > 0.0],
                rotation_spread_max_deg: Some(spread / 2.0),
            }),
            service_time: Some(Duration::from_millis(u64::from(obj_id) * 10)),
            latency: Some(Duration::from_millis(500)),
            flags: if obj_id == 10 { flags::TRACKING } else { 0 },
            visib_fract: None,
        }
    }

    #[test]
    fn a_missed_instance_counts_as_a_failure() {
        let outcomes = [
            outcome(1, [1.0; 4], 2.0, 1.0),
            InstanceOutcome {
                scene_id: 0,
                im_id: 1,
                obj_id: 1,
                score: None,
                service_time: None,
                latency: None,
                flags: 0,
                visib_fract: Some(0.25),
            },
            outcome(10, [0.0, 0.0, 1.0, 1.0], 8.0, 3.0),
            outcome(10, [0.0; 4], 90.0, 9.0),
        ];
        let summary = summarise(&outcomes);
        assert_eq!((summary.overall.instances, summary.overall.estimated, summary.overall.tracked), (4, 3, 2));
        assert_eq!(summary.overall.acc_5deg_2cm, 25.0);
        assert_eq!(summary.overall.acc_10deg_5cm, 50.0);
        assert_eq!(summary.overall.add_s, 50.0);
        assert_eq!(summary.overall.mssd_recall, 37.5);
        // VSD 0.75 on 3 of 4; AR = mean(56.25, 37.5, 18.75).
        assert_eq!(summary.overall.vsd_recall, Some(56.25));
        assert_eq!(summary.overall.bop_ar, Some(37.5));
        assert_eq!(summary.overall.mode_recall, Some(50.0));
        assert_eq!(summary.overall.median_rotation_error_deg, Some(8.0));
        assert_eq!(summary.per_object[&1].accuracies.acc_10deg_5cm, 50.0);
        assert_eq!(summary.per_object[&10].accuracies.acc_10deg_2cm, 50.0);
        assert_eq!(summary.per_object[&1].accuracies.mode_recall, None);
        assert_eq!(summary.per_object[&10].ms_per_object.p50_ms, 100.0);
        assert_eq!(summary.ms_per_object_p50, 100.0);
        assert_eq!(summary.latency.p50_ms, 500.0);
        // Spread grows with error here: a perfect rank correlation.
        assert_eq!(summary.spread_error_spearman, Some(1.0));
        assert_eq!(summary.spread_max_error_spearman, Some(1.0));
        // Covered: the first two estimates within 10°5cm, the first within
        // 5°5cm; the miss counts 0.
        assert_eq!((summary.overall.coverage_10deg_5cm, summary.overall.coverage_5deg_5cm), (50.0, 25.0));
        // Folded spreads 0.5, 1.5, 4.5 against errors 2, 8, 90: none within
        // 1×, none within 2× (2 > 1.0, 8 > 3.0, 90 > 9.0).
        assert_eq!(summary.overall.median_rotation_spread_max_deg, Some(1.5));
        assert_eq!((summary.overall.within_1_spread, summary.overall.within_2_spread), (Some(0.0), Some(0.0)));
        let csv = instances_csv(&outcomes);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines.len(), 5);
        assert_eq!(lines[1], "0,0,1,,1,2.0000,1.0000,1.0000,0.5000,1,1");
        assert_eq!(lines[2], "0,1,1,0.2500,0,,,,,,");
    }

    #[test]
    fn calibration_counts_errors_within_one_and_two_spreads() {
        let pairs = [(1.0, 0.5), (1.0, 1.5), (1.0, 2.0), (1.0, 3.0)];
        assert_eq!(within_spread(&pairs, 1.0), Some(25.0));
        assert_eq!(within_spread(&pairs, 2.0), Some(75.0));
        assert_eq!(within_spread(&[], 2.0), None);
    }

    #[test]
    fn spearman_matches_closed_forms() {
        assert_eq!(spearman(&[1.0, 2.0, 3.0, 4.0], &[10.0, 20.0, 30.0, 40.0]), Some(1.0));
        assert_eq!(spearman(&[1.0, 2.0, 3.0, 4.0], &[4.0, 3.0, 2.0, 1.0]), Some(-1.0));
        // Monotone but not linear: still 1.
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[1.0, 100.0, 1000.0]), Some(1.0));
        // Ranks [1,2,3,4] against [1,3,2,4]: 1 - 6·2/(4·15) = 0.8.
        assert!((spearman(&[1.0, 2.0, 3.0, 4.0], &[1.0, 3.0, 2.0, 4.0]).unwrap() - 0.8).abs() < 1e-12);
        // Ties share the mean rank.
        assert_eq!(ranks(&[5.0, 1.0, 5.0]), [2.5, 1.0, 2.5]);
        assert_eq!(spearman(&[1.0, 1.0, 1.0], &[1.0, 2.0, 3.0]), None);
        assert_eq!(spearman(&[1.0, 2.0], &[1.0, 2.0]), None);
    }
}
