//! `poseflow sim nbv`: active perception in simulation. Each trial starts
//! from an ambiguous view (the mug with its handle hidden, or an LM-O
//! object mostly hidden in clutter), estimates its pose distribution, then
//! moves the camera twice under each policy — the next-best view, a random
//! candidate view, or staying put — estimating again after each move.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use nalgebra::Vector3;
use poseflow_contracts::EstimateHeader;
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::{SeededRng, seeded_rng};
use poseflow_geometry::so3::geodesic_angle;
use poseflow_geometry::symmetry::{BOP_MAX_SYMMETRY_STEP, SymmetrySet};
use poseflow_ingest::{ObjectMask, RgbdFrame};
use poseflow_nbv::PoseStages;
use poseflow_nbv::stage::kept_hypotheses;
use poseflow_nbv::{NbvParams, NbvPlanner, Occluders};
use poseflow_runtime::progress::Progress;
use poseflow_scene::ModelLibrary;
use poseflow_scene::scene::Scene;
use rand::Rng;
use serde::Serialize;

use super::clutter::{ClutterView, render_occluded, view_clutter};
use super::mug::{Handle, MugView, render_mug, view_mug};
use super::{load_graph, pose_stages, rounded, stage_params, write_trials_csv};

/// Where the trials start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum StartScene {
    /// The YCB-V mug alone, its handle hidden behind its body.
    Mug,
    /// One of the LM-O objects in a crowded scene, 15–45 % of it visible.
    Clutter,
}

#[derive(Debug, Args)]
#[command(after_help = "Run from the repository root (reads --graph and its config files).\n\n\
    --scene mug (default): each trial renders the YCB-V mug alone on a table with its handle turned away from the \
    camera (hidden behind the body; camera 0.45–0.65 m away, 15–35° above the table). --scene clutter: the LM-O \
    objects of --objects among distractors (heavy occlusion), seen 0.4–0.8 m away so that the trial's target (the \
    objects in turn) shows 15–45 % of its silhouette. The pose stages (N = 50 samples, K = 5 steps, SDF selection \
    with refinement) estimate the target's pose distribution. Then, per policy, the camera moves twice and the pose \
    is estimated afresh from each new view:\n  \
    nbv     the next-best view: the candidate (config/nbv.toml: sphere, elevation band, count) whose views simulated \
    under the current Estimate's hypotheses (hidden where the current frame's observed surface lies in front) leave \
    the least rotational uncertainty, or staying put when the current viewpoint scores best (include_current);\n  \
    random  a candidate drawn uniformly from the same sphere;\n  \
    stay    the same camera (a new frame: new light and sensor noise).\n\
    Each new estimate stands alone (no fusion with the earlier views' hypotheses). A view that shows too little of \
    the target to estimate is `lost`: the camera goes back and the previous estimate stands. Rotation errors are \
    symmetry-aware (BOP symmetries of models_info.json).\n\n\
    --json prints {\"trials\": n, \"start\": {...}, \"nbv\": {...}, \"random\": {...}, \"stay\": {...}}: per \
    policy the means over trials of rot_trace_1, rot_trace_2 (tr Σ_R of the kept hypotheses after one and two \
    moves, rad²) and rot_err_deg_1, rot_err_deg_2 (rotation error of the selected pose, degrees), the same spread \
    modulo the object's symmetries (folded_trace_1, folded_trace_2: what the planner minimises), the share of \
    views revealing what the start hid (revealed_1, revealed_2, %: the mug's handle in view, ≥ 150 pixels; ≥ 75 % of \
    the cluttered target visible) and the lost views.\n\n\
    Example:\n  poseflow sim nbv --trials 20 --seed 0")]
pub struct NbvSimArgs {
    /// Trials (each runs every policy from the same start).
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Where the trials start.
    #[arg(long, value_enum, default_value_t = StartScene::Mug)]
    pub scene: StartScene,
    /// Pose model directory.
    #[arg(long, default_value = "models/poseflow-lmo10")]
    pub model: PathBuf,
    /// BOP models directory [default: objects/ycbv/mug-bowl for the mug, objects/lmo for clutter].
    #[arg(long)]
    pub objects: Option<PathBuf>,
    /// The mug's object id (--scene mug).
    #[arg(long, default_value_t = 14)]
    pub mug: u32,
    /// The graph whose pose stages estimate (in-process, from `frames` to `estimates`) and whose `nbv` stage's
    /// parameters the planner starts from.
    #[arg(long, default_value = "deploy/next-view.toml")]
    pub graph: PathBuf,
    /// Also write one row per trial, policy and move to <out>/trials.csv.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// What a camera sees of the target: the frame the pipeline reads, the
/// truth, and whether the view reveals what the start hid.
#[derive(Debug, Clone)]
struct Seen {
    frame: RgbdFrame,
    mask: ObjectMask,
    camera_from_object: Pose,
    camera_from_world: Pose,
    revealed: bool,
    /// Handle pixels (mug) or visible share of the silhouette, % (clutter).
    detail: f64,
}

impl From<MugView> for Seen {
    fn from(v: MugView) -> Self {
        Self {
            revealed: v.handle_pixels >= 150,
            detail: v.handle_pixels as f64,
            frame: v.frame,
            mask: v.mask,
            camera_from_object: v.camera_from_object,
            camera_from_world: v.camera_from_world,
        }
    }
}

impl From<ClutterView> for Seen {
    fn from(v: ClutterView) -> Self {
        Self {
            revealed: v.visible_share >= 0.75,
            detail: 100.0 * v.visible_share,
            frame: v.frame,
            mask: v.mask,
            camera_from_object: v.camera_from_object,
            camera_from_world: v.camera_from_world,
        }
    }
}

/// A trial's scene and its target (library index).
struct TrialScene {
    kind: StartScene,
    scene: Scene,
    target: usize,
}

impl TrialScene {
    /// Trial `trial`'s scene and its ambiguous start view.
    fn draw(
        kind: StartScene,
        library: &ModelLibrary,
        trial: usize,
        frame_id: u64,
        rng: &mut SeededRng,
    ) -> (Self, Seen) {
        match kind {
            StartScene::Mug => {
                let (scene, view) = render_mug(library, Handle::Occluded, frame_id, rng);
                (Self { kind, scene, target: 0 }, view.into())
            }
            StartScene::Clutter => {
                let target = trial % library.objects.len();
                let (scene, view) = render_occluded(library, target, frame_id, rng);
                (Self { kind, scene, target }, view.into())
            }
        }
    }

    fn view(&self, library: &ModelLibrary, camera_from_world: &Pose, frame_id: u64, rng: &mut SeededRng) -> Seen {
        match self.kind {
            StartScene::Mug => view_mug(library, &self.scene, camera_from_world, frame_id, rng).into(),
            StartScene::Clutter => {
                view_clutter(library, &self.scene, self.target, camera_from_world, frame_id, rng).into()
            }
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Policy {
    Nbv,
    Random,
    Stay,
}

impl Policy {
    const ALL: [Policy; 3] = [Policy::Nbv, Policy::Random, Policy::Stay];

    fn name(self) -> &'static str {
        match self {
            Policy::Nbv => "nbv",
            Policy::Random => "random",
            Policy::Stay => "stay",
        }
    }
}

/// One estimate's outcome.
#[derive(Debug, Clone, Copy)]
struct Outcome {
    /// tr Σ_R of the kept hypotheses (rad²), as the Estimate reports it.
    trace: f64,
    /// Their spread modulo the object's symmetries (rad²; what the planner
    /// minimises).
    folded: f64,
    /// Rotation error of the selected pose (degrees, symmetry-aware).
    error_deg: f64,
    revealed: bool,
    /// [`Seen::detail`] of the view.
    detail: f64,
    /// The view showed too little to estimate: the previous estimate stands.
    lost: bool,
    /// The planner's expected trace for the view moved to (nbv only).
    expected_trace: Option<f64>,
    /// Wall time of the plan (nbv only).
    plan_ms: Option<f64>,
    /// How far the camera turned for this view (degrees; 0 at the start
    /// and when staying).
    turn_deg: f64,
}

#[derive(Debug, Default, Serialize)]
struct PolicyMeans {
    rot_trace_1: f64,
    rot_trace_2: f64,
    rot_err_deg_1: f64,
    rot_err_deg_2: f64,
    folded_trace_1: f64,
    folded_trace_2: f64,
    /// Share of views (%) revealing what the start hid.
    revealed_1: f64,
    revealed_2: f64,
    /// Moves whose view showed too little to estimate.
    lost: usize,
}

#[derive(Debug, Default, Serialize)]
struct StartMeans {
    rot_trace: f64,
    folded_trace: f64,
    rot_err_deg: f64,
}

#[derive(Debug, Serialize)]
struct Report {
    trials: usize,
    scene: &'static str,
    start: StartMeans,
    nbv: PolicyMeans,
    random: PolicyMeans,
    stay: PolicyMeans,
}

/// A trial's start and its moves under each policy.
#[derive(Debug)]
struct Trial {
    obj_id: u32,
    start: Outcome,
    moves: Vec<(Policy, [Outcome; 2])>,
}

/// One Estimate as the selector published it.
#[derive(Debug, Clone)]
struct Estimated {
    header: EstimateHeader,
    payload: Vec<f32>,
}

/// What the simulation needs besides the trial and the policy.
struct World<'a> {
    library: &'a ModelLibrary,
    pose: &'a mut PoseStages,
    planner: &'a mut NbvPlanner,
}

impl World<'_> {
    /// The estimate from `seen` and its outcome; `None` when the view shows
    /// too little of the target (the ingest rejects it).
    fn estimate(&mut self, seen: &Seen, symmetries: &SymmetrySet) -> anyhow::Result<Option<(Estimated, Outcome)>> {
        let Some((header, payload)) = self.pose.estimate(&seen.frame, &seen.mask)? else {
            return Ok(None);
        };
        let estimate = Estimated { header, payload };
        let best = Pose::from_f32_row_major(&estimate.header.best)?;
        let kept = kept_hypotheses(&estimate.header, &estimate.payload)?;
        let rotations: Vec<_> = kept.iter().map(|pose| pose.rotation).collect();
        let outcome = Outcome {
            trace: f64::from(estimate.header.rotation_trace),
            folded: symmetries.folded_rotation_spread(&rotations),
            error_deg: symmetries.rotation_error(&best.rotation, &seen.camera_from_object.rotation).to_degrees(),
            revealed: seen.revealed,
            detail: seen.detail,
            lost: false,
            expected_trace: None,
            plan_ms: None,
            turn_deg: 0.0,
        };
        Ok(Some((estimate, outcome)))
    }
}

/// Two moves under `policy` from the start view, its estimate and outcome.
fn run_policy(
    world: &mut World<'_>,
    trial: &TrialScene,
    symmetries: &SymmetrySet,
    start: (&Seen, &Estimated, Outcome),
    policy: Policy,
    seed: u64,
) -> anyhow::Result<[Outcome; 2]> {
    let mut rng = seeded_rng(seed);
    let (mut seen, mut estimate, mut last) = (start.0.clone(), start.1.clone(), start.2);
    let obj_id = seen.mask.obj_id;
    let mut outcomes = Vec::with_capacity(2);
    for step in 1..=2u64 {
        let frame = seen.frame.frame_id;
        let kept = kept_hypotheses(&estimate.header, &estimate.payload)?;
        // The world's up (+z) in the current camera: what a robot's
        // kinematics would tell the stage.
        let up = seen.camera_from_world.rotation * Vector3::z();
        let (camera_from_next, expected_trace, plan_ms) = match policy {
            Policy::Stay => (Pose::identity(), None, None),
            Policy::Random => {
                let candidates = world.planner.candidates(frame, obj_id, &kept, &up)?;
                (candidates[rng.random_range(0..candidates.len())], None, None)
            }
            Policy::Nbv => {
                // What may hide the target: the current frame's surface.
                let stride = world.planner.params().occluder_stride;
                let occluders = Occluders::from_depth(&seen.frame, &seen.mask, stride);
                let plan = world.planner.plan(frame, obj_id, &kept, &up, Some(&occluders))?;
                let best = plan.views[0];
                (best.camera_from_next, Some(best.expected_trace), Some(plan.cost.wall_ms))
            }
        };
        let turn_deg = geodesic_angle(&camera_from_next.rotation, &nalgebra::Rotation3::identity()).to_degrees();
        let camera_from_world = camera_from_next.inverse() * seen.camera_from_world;
        let next = trial.view(world.library, &camera_from_world, frame + 1, &mut rng);
        let moved = Outcome { expected_trace, plan_ms, turn_deg, ..last };
        match world.estimate(&next, symmetries).with_context(|| format!("move {step}: pose estimation"))? {
            Some((next_estimate, outcome)) => {
                last = Outcome { expected_trace, plan_ms, turn_deg, ..outcome };
                (seen, estimate) = (next, next_estimate);
            }
            // Nothing to estimate from: back to the previous camera, whose
            // estimate stands.
            None => {
                last = Outcome { lost: true, revealed: next.revealed, detail: next.detail, ..moved };
                seen.frame.frame_id = frame + 1;
            }
        }
        outcomes.push(last);
        last.lost = false;
    }
    Ok([outcomes[0], outcomes[1]])
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n.max(1) as f64
}

fn policy_means(trials: &[Trial], policy: Policy) -> PolicyMeans {
    let moves = || trials.iter().flat_map(|t| t.moves.iter().filter(move |(p, _)| *p == policy).map(|(_, m)| m));
    let revealed = |o: &Outcome| if o.revealed { 100.0 } else { 0.0 };
    PolicyMeans {
        rot_trace_1: mean(moves().map(|m| m[0].trace)),
        rot_trace_2: mean(moves().map(|m| m[1].trace)),
        rot_err_deg_1: mean(moves().map(|m| m[0].error_deg)),
        rot_err_deg_2: mean(moves().map(|m| m[1].error_deg)),
        folded_trace_1: mean(moves().map(|m| m[0].folded)),
        folded_trace_2: mean(moves().map(|m| m[1].folded)),
        revealed_1: mean(moves().map(|m| revealed(&m[0]))),
        revealed_2: mean(moves().map(|m| revealed(&m[1]))),
        lost: moves().flat_map(|m| m.iter()).filter(|o| o.lost).count(),
    }
}

/// A row of trials.csv: one trial, policy and move.
#[derive(Serialize)]
struct TrialRow {
    trial: usize,
    object: u32,
    policy: &'static str,
    #[serde(rename = "move")]
    step: usize,
    rot_trace: f64,
    folded_trace: f64,
    rot_err_deg: f64,
    revealed: u8,
    detail: f64,
    lost: u8,
    turn_deg: f64,
    expected_trace: Option<f64>,
    plan_ms: Option<f64>,
}

fn write_trials(out: &Path, trials: &[Trial]) -> anyhow::Result<()> {
    let row = |trial: usize, object: u32, policy: &'static str, step: usize, o: &Outcome| TrialRow {
        trial,
        object,
        policy,
        step,
        rot_trace: significant(o.trace),
        folded_trace: significant(o.folded),
        rot_err_deg: rounded(o.error_deg, 2),
        revealed: u8::from(o.revealed),
        detail: rounded(o.detail, 1),
        lost: u8::from(o.lost),
        turn_deg: rounded(o.turn_deg, 1),
        expected_trace: o.expected_trace.map(significant),
        plan_ms: o.plan_ms.map(|ms| rounded(ms, 0)),
    };
    let row = &row;
    let rows = trials.iter().enumerate().flat_map(|(i, trial)| {
        let start = std::iter::once(row(i, trial.obj_id, "start", 0, &trial.start));
        let moves = trial.moves.iter().flat_map(move |(policy, moves)| {
            moves.iter().enumerate().map(move |(step, o)| row(i, trial.obj_id, policy.name(), step + 1, o))
        });
        start.chain(moves)
    });
    write_trials_csv(out, rows)
}

/// `value` to 5 significant digits (traces span many decades).
fn significant(value: f64) -> f64 {
    if value == 0.0 || !value.is_finite() {
        return value;
    }
    let digits = 4 - value.abs().log10().floor() as i32;
    rounded(value, digits)
}

pub fn run(args: &NbvSimArgs) -> anyhow::Result<()> {
    if args.trials == 0 {
        bail!("--trials 0: expected at least one trial");
    }
    let (objects, ids) = match args.scene {
        StartScene::Mug => (args.objects.clone().unwrap_or_else(|| "objects/ycbv/mug-bowl".into()), vec![args.mug]),
        StartScene::Clutter => (args.objects.clone().unwrap_or_else(|| "objects/lmo".into()), Vec::new()),
    };
    let library = ModelLibrary::load(&objects, &ids)?;
    let graph = load_graph(&args.graph)?;
    let mut pose = pose_stages(&graph, &args.model, &objects)?;
    let mut nbv = stage_params(&graph, "nbv", serde_json::json!({"models": objects, "seed": args.seed}))?;
    // The planner scores views with the same network as the estimates.
    nbv["inference"]["model"] = serde_json::json!(args.model);
    let mut planner = NbvPlanner::load(NbvParams::from_json(&nbv)?)?;
    let mut world = World { library: &library, pose: &mut pose, planner: &mut planner };

    let mut trials = Vec::with_capacity(args.trials);
    let mut progress = Progress::new("sim nbv", args.trials as u64);
    for trial in 0..args.trials {
        // Frame ids: 100 per trial, the start at its first.
        let frame_id = 100 * trial as u64;
        let mut rng = seeded_rng(args.seed.wrapping_mul(1_000_003).wrapping_add(trial as u64));
        let (scene, seen) = TrialScene::draw(args.scene, &library, trial, frame_id, &mut rng);
        let object = &library.objects[scene.target];
        let symmetries = SymmetrySet::from_model_info(&object.info, BOP_MAX_SYMMETRY_STEP);
        let (estimate, start) = world
            .estimate(&seen, &symmetries)
            .with_context(|| format!("trial {trial}: pose estimation at the start"))?
            .with_context(|| format!("trial {trial}: the start view shows too little of object {}", object.obj_id))?;
        let mut moves = Vec::new();
        for (p, policy) in Policy::ALL.into_iter().enumerate() {
            let seed = rng.random::<u64>() ^ p as u64;
            let outcomes = run_policy(&mut world, &scene, &symmetries, (&seen, &estimate, start), policy, seed)
                .with_context(|| format!("trial {trial}, policy {}", policy.name()))?;
            moves.push((policy, outcomes));
        }
        trials.push(Trial { obj_id: object.obj_id, start, moves });
        progress.update(trials.len() as u64, &format!("trial {trial}"));
    }
    if let Some(out) = &args.out {
        write_trials(out, &trials)?;
    }
    let report = Report {
        trials: args.trials,
        scene: match args.scene {
            StartScene::Mug => "mug",
            StartScene::Clutter => "clutter",
        },
        start: StartMeans {
            rot_trace: mean(trials.iter().map(|t| t.start.trace)),
            folded_trace: mean(trials.iter().map(|t| t.start.folded)),
            rot_err_deg: mean(trials.iter().map(|t| t.start.error_deg)),
        },
        nbv: policy_means(&trials, Policy::Nbv),
        random: policy_means(&trials, Policy::Random),
        stay: policy_means(&trials, Policy::Stay),
    };
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
        return Ok(());
    }
    print_table(args, &objects, &trials, &report);
    Ok(())
}

fn print_table(args: &NbvSimArgs, objects: &Path, trials: &[Trial], report: &Report) {
    let (start, detail) = match args.scene {
        StartScene::Mug => ("the mug's handle hidden", "handle px"),
        StartScene::Clutter => ("the target 15–45 % visible in clutter", "visible %"),
    };
    println!("next-best-view simulation: {start} ({}), {} trials, seed {}", objects.display(), args.trials, args.seed);
    println!(
        "{:<6} {:>6} {:<7} {:>10} {:>8} {:>10} | {:>10} {:>8} {:>10}",
        "trial", "object", "policy", "trace 1", "err 1", detail, "trace 2", "err 2", detail
    );
    let lost = |o: &Outcome| if o.lost { " lost" } else { "" };
    for (i, trial) in trials.iter().enumerate() {
        let s = &trial.start;
        println!(
            "{i:<6} {:>6} {:<7} {:>10.2e} {:>7.1}° {:>10.0} |",
            trial.obj_id, "start", s.trace, s.error_deg, s.detail
        );
        for (policy, [one, two]) in &trial.moves {
            println!(
                "{:<6} {:>6} {:<7} {:>10.2e} {:>7.1}° {:>10.0} | {:>10.2e} {:>7.1}° {:>10.0}{}{}",
                "",
                "",
                policy.name(),
                one.trace,
                one.error_deg,
                one.detail,
                two.trace,
                two.error_deg,
                two.detail,
                lost(one),
                lost(two)
            );
        }
    }
    let mut plans: Vec<f64> =
        trials.iter().flat_map(|t| t.moves.iter().flat_map(|(_, m)| m.iter().filter_map(|o| o.plan_ms))).collect();
    plans.sort_by(f64::total_cmp);
    if let Some(median) = plans.get(plans.len() / 2) {
        println!("\nnext-view plans: {}, median wall time {median:.0} ms", plans.len());
    }
    println!(
        "\nmeans over trials (start: tr Σ_R {:.2e} rad², rotation error {:.1}°):",
        report.start.rot_trace, report.start.rot_err_deg
    );
    println!(
        "{:<8} {:>10} {:>10} {:>8} {:>8} {:>10} {:>10} {:>5}",
        "policy", "trace 1", "trace 2", "err 1", "err 2", "revealed 1", "revealed 2", "lost"
    );
    for (name, m) in [("nbv", &report.nbv), ("random", &report.random), ("stay", &report.stay)] {
        println!(
            "{name:<8} {:>10.2e} {:>10.2e} {:>7.1}° {:>7.1}° {:>9.0}% {:>9.0}% {:>5}",
            m.rot_trace_1, m.rot_trace_2, m.rot_err_deg_1, m.rot_err_deg_2, m.revealed_1, m.revealed_2, m.lost
        );
    }
}
