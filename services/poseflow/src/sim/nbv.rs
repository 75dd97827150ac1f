//! `poseflow sim nbv`: active perception in simulation. Each trial starts
//! from a view of the mug with its handle hidden, estimates its pose
//! distribution, then moves the camera twice under each policy — the
//! next-best view, a random candidate view, or staying put — estimating
//! again after each move.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use nalgebra::Vector3;
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_geometry::so3::geodesic_angle;
use poseflow_nbv::stage::kept_hypotheses;
use poseflow_nbv::{NbvParams, NbvPlanner};
use poseflow_pipeline::{Estimated, PosePipeline};
use poseflow_scene::ModelLibrary;
use poseflow_scene::scene::Scene;
use rand::Rng;
use serde::Serialize;

use super::mug::{Handle, MugView, render_mug, view_mug};
use super::{pose_pipeline, stage_params};

#[derive(Debug, Args)]
#[command(after_help = "Run from the repository root (reads config/*.toml as the graph does).\n\n\
    Each trial renders the YCB-V mug alone on a table with its handle turned away from the camera (hidden behind \
    the body; camera 0.45–0.65 m away, 15–35° above the table) and estimates its pose distribution with the pose \
    stages (N = 50 samples, K = 5 steps, SDF selection with refinement). Then, per policy, the camera moves twice \
    and the pose is estimated afresh from each new view:\n  \
    nbv     the next-best view: the candidate (config/nbv.toml: sphere, elevation band, count) whose views simulated \
    under the current Estimate's hypotheses leave the least rotational uncertainty, or staying put when the current \
    viewpoint scores best (include_current);\n  \
    random  a candidate drawn uniformly from the same set;\n  \
    stay    the same camera (a new frame: new light and sensor noise).\n\
    Each new estimate stands alone (no fusion with the earlier views' hypotheses).\n\n\
    --json prints {\"trials\": n, \"start\": {...}, \"nbv\": {...}, \"random\": {...}, \"stay\": {...}}: per \
    policy the means over trials of rot_trace_1, rot_trace_2 (tr Σ_R of the kept hypotheses after one and two \
    moves, rad²) and rot_err_deg_1, rot_err_deg_2 (rotation error of the selected pose, degrees).\n\n\
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
    /// Pose model directory.
    #[arg(long, default_value = "models/poseflow-lmo10")]
    pub model: PathBuf,
    /// BOP models directory holding the mug.
    #[arg(long, default_value = "objects/ycbv/models")]
    pub objects: PathBuf,
    /// The mug's object id there.
    #[arg(long, default_value_t = 14)]
    pub mug: u32,
    /// Stage parameter files (the graph's; the planner reads nbv.toml).
    #[arg(long, default_value = "config")]
    pub config: PathBuf,
    /// Also write one row per trial, policy and move to <out>/trials.csv.
    #[arg(long)]
    pub out: Option<PathBuf>,
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
    /// tr Σ_R of the kept hypotheses (rad²).
    trace: f64,
    /// Rotation error of the selected pose (degrees).
    error_deg: f64,
    handle_pixels: usize,
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
    /// Share of views (%) that show the handle (≥ 150 pixels).
    handle_seen_1: f64,
    handle_seen_2: f64,
}

#[derive(Debug, Default, Serialize)]
struct StartMeans {
    rot_trace: f64,
    rot_err_deg: f64,
}

#[derive(Debug, Serialize)]
struct Report {
    trials: usize,
    start: StartMeans,
    nbv: PolicyMeans,
    random: PolicyMeans,
    stay: PolicyMeans,
}

/// A trial's start and its moves under each policy.
#[derive(Debug)]
struct Trial {
    start: Outcome,
    moves: Vec<(Policy, [Outcome; 2])>,
}

fn outcome(view: &MugView, estimate: &Estimated) -> anyhow::Result<Outcome> {
    let best = Pose::from_f32_row_major(&estimate.header.best)?;
    Ok(Outcome {
        trace: f64::from(estimate.header.rotation_trace),
        error_deg: geodesic_angle(&best.rotation, &view.camera_from_object.rotation).to_degrees(),
        handle_pixels: view.handle_pixels,
        expected_trace: None,
        plan_ms: None,
        turn_deg: 0.0,
    })
}

/// What the simulation needs besides the policy.
struct World<'a> {
    library: &'a ModelLibrary,
    pipeline: &'a mut PosePipeline,
    planner: &'a mut NbvPlanner,
    mug: u32,
}

/// Two moves under `policy` from the start view and its estimate.
fn run_policy(
    world: &mut World<'_>,
    scene: &Scene,
    start: (&MugView, &Estimated),
    policy: Policy,
    seed: u64,
) -> anyhow::Result<[Outcome; 2]> {
    let mut rng = seeded_rng(seed);
    let (mut view, mut estimate) = (start.0.clone(), start.1.clone());
    let mut outcomes = Vec::with_capacity(2);
    for step in 1..=2u64 {
        let frame = view.frame.frame_id;
        let kept = kept_hypotheses(&estimate.header, &estimate.payload)?;
        // The world's up (+z) in the current camera: what a robot's
        // kinematics would tell the stage.
        let up = view.camera_from_world.rotation * Vector3::z();
        let (camera_from_next, expected_trace, plan_ms) = match policy {
            Policy::Stay => (Pose::identity(), None, None),
            Policy::Random => {
                let candidates = world.planner.candidates(frame, world.mug, &kept, &up)?;
                (candidates[rng.random_range(0..candidates.len())], None, None)
            }
            Policy::Nbv => {
                let plan = world.planner.plan(frame, world.mug, &kept, &up)?;
                let best = plan.views[0];
                (best.camera_from_next, Some(best.expected_trace), Some(plan.cost.wall_ms))
            }
        };
        let camera_from_world = camera_from_next.inverse() * view.camera_from_world;
        view = view_mug(world.library, scene, &camera_from_world, frame + 1, &mut rng);
        estimate = world
            .pipeline
            .estimate(&view.frame, &view.mask)
            .with_context(|| format!("{} move {step}: pose estimation", policy.name()))?;
        let turn_deg = geodesic_angle(&camera_from_next.rotation, &nalgebra::Rotation3::identity()).to_degrees();
        outcomes.push(Outcome { expected_trace, plan_ms, turn_deg, ..outcome(&view, &estimate)? });
    }
    Ok([outcomes[0], outcomes[1]])
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    sum / n.max(1) as f64
}

fn policy_means(trials: &[Trial], policy: Policy) -> PolicyMeans {
    let moves = || trials.iter().flat_map(|t| t.moves.iter().filter(move |(p, _)| *p == policy).map(|(_, m)| m));
    let seen = |o: &Outcome| if o.handle_pixels >= 150 { 100.0 } else { 0.0 };
    PolicyMeans {
        rot_trace_1: mean(moves().map(|m| m[0].trace)),
        rot_trace_2: mean(moves().map(|m| m[1].trace)),
        rot_err_deg_1: mean(moves().map(|m| m[0].error_deg)),
        rot_err_deg_2: mean(moves().map(|m| m[1].error_deg)),
        handle_seen_1: mean(moves().map(|m| seen(&m[0]))),
        handle_seen_2: mean(moves().map(|m| seen(&m[1]))),
    }
}

fn write_trials(out: &Path, trials: &[Trial]) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let mut text =
        String::from("trial,policy,move,rot_trace,rot_err_deg,handle_pixels,turn_deg,expected_trace,plan_ms\n");
    let row = |text: &mut String, trial: usize, policy: &str, step: usize, o: &Outcome| {
        let optional = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.4e}"));
        *text += &format!(
            "{trial},{policy},{step},{:.4e},{:.2},{},{:.1},{},{}\n",
            o.trace,
            o.error_deg,
            o.handle_pixels,
            o.turn_deg,
            optional(o.expected_trace),
            o.plan_ms.map_or(String::new(), |v| format!("{v:.0}"))
        );
    };
    for (i, trial) in trials.iter().enumerate() {
        row(&mut text, i, "start", 0, &trial.start);
        for (policy, moves) in &trial.moves {
            for (step, o) in moves.iter().enumerate() {
                row(&mut text, i, policy.name(), step + 1, o);
            }
        }
    }
    let path = out.join("trials.csv");
    std::fs::write(&path, text).with_context(|| format!("{}: cannot write", path.display()))
}

pub fn run(args: &NbvSimArgs) -> anyhow::Result<()> {
    if args.trials == 0 {
        bail!("--trials 0: expected at least one trial");
    }
    let library = ModelLibrary::load(&args.objects, &[args.mug])?;
    let mut pipeline = pose_pipeline(&args.config, &args.model, &args.objects)?;
    let nbv = stage_params(&args.config, "nbv", serde_json::json!({"models": args.objects, "seed": args.seed}))?;
    let mut nbv = NbvParams::from_json(&nbv)?;
    nbv.inference.model.clone_from(&args.model);
    let mut planner = NbvPlanner::load(nbv)?;
    let mut world = World { library: &library, pipeline: &mut pipeline, planner: &mut planner, mug: args.mug };

    let mut trials = Vec::with_capacity(args.trials);
    for trial in 0..args.trials {
        // Frame ids: 100 per trial, the start at its first.
        let frame_id = 100 * trial as u64;
        let mut rng = seeded_rng(args.seed.wrapping_mul(1_000_003).wrapping_add(trial as u64));
        let (scene, start) = render_mug(&library, Handle::Occluded, frame_id, &mut rng);
        let estimate = world
            .pipeline
            .estimate(&start.frame, &start.mask)
            .with_context(|| format!("trial {trial}: pose estimation at the start"))?;
        let mut moves = Vec::new();
        for (p, policy) in Policy::ALL.into_iter().enumerate() {
            let seed = rng.random::<u64>() ^ p as u64;
            let outcomes = run_policy(&mut world, &scene, (&start, &estimate), policy, seed)
                .with_context(|| format!("trial {trial}, policy {}", policy.name()))?;
            moves.push((policy, outcomes));
        }
        trials.push(Trial { start: outcome(&start, &estimate)?, moves });
    }
    if let Some(out) = &args.out {
        write_trials(out, &trials)?;
    }
    let report = Report {
        trials: args.trials,
        start: StartMeans {
            rot_trace: mean(trials.iter().map(|t| t.start.trace)),
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
    print_table(args, &trials, &report);
    Ok(())
}

fn print_table(args: &NbvSimArgs, trials: &[Trial], report: &Report) {
    println!(
        "next-best-view simulation: mug {} ({}), handle hidden at the start, {} trials, seed {}",
        args.mug,
        args.objects.display(),
        args.trials,
        args.seed
    );
    println!(
        "{:<6} {:<7} {:>12} {:>9} {:>10} | {:>12} {:>9} {:>10}",
        "trial", "policy", "trace 1", "err 1", "handle 1", "trace 2", "err 2", "handle 2"
    );
    for (i, trial) in trials.iter().enumerate() {
        let s = &trial.start;
        println!("{i:<6} {:<7} {:>12.2e} {:>8.1}° {:>10} |", "start", s.trace, s.error_deg, s.handle_pixels);
        for (policy, [one, two]) in &trial.moves {
            println!(
                "{:<6} {:<7} {:>12.2e} {:>8.1}° {:>10} | {:>12.2e} {:>8.1}° {:>10}",
                "",
                policy.name(),
                one.trace,
                one.error_deg,
                one.handle_pixels,
                two.trace,
                two.error_deg,
                two.handle_pixels
            );
        }
    }
    let plans: Vec<f64> =
        trials.iter().flat_map(|t| t.moves.iter().flat_map(|(_, m)| m.iter().filter_map(|o| o.plan_ms))).collect();
    let mut sorted = plans.clone();
    sorted.sort_by(f64::total_cmp);
    if let Some(median) = sorted.get(sorted.len() / 2) {
        println!("\nnext-view plans: {}, median wall time {median:.0} ms", plans.len());
    }
    println!(
        "\nmeans over trials (start: tr Σ_R {:.5} rad², rotation error {:.1}°):",
        report.start.rot_trace, report.start.rot_err_deg
    );
    println!(
        "{:<8} {:>12} {:>12} {:>10} {:>10} {:>9} {:>9}",
        "policy", "trace 1", "trace 2", "err 1", "err 2", "handle 1", "handle 2"
    );
    for (name, m) in [("nbv", &report.nbv), ("random", &report.random), ("stay", &report.stay)] {
        println!(
            "{name:<8} {:>12.2e} {:>12.2e} {:>9.1}° {:>9.1}° {:>8.0}% {:>8.0}%",
            m.rot_trace_1, m.rot_trace_2, m.rot_err_deg_1, m.rot_err_deg_2, m.handle_seen_1, m.handle_seen_2
        );
    }
}
