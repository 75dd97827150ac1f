//! `poseflow sim grasp`: the paper's mug table in simulation. Each trial
//! renders the mug with its handle visible or hidden, estimates its pose
//! distribution with the real pose stages, plans grasps under one
//! hypothesis (the selected pose) and under the mean field of the kept
//! hypotheses, and executes each plan's top grasp on the true pose.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use nalgebra::Point3;
use poseflow_geometry::Pose;
use poseflow_geometry::sampling::seeded_rng;
use poseflow_geometry::so3::geodesic_angle;
use poseflow_grasp::stage::kept_hypotheses;
use poseflow_grasp::{GraspParams, GraspPlanner, Gripper, OnnxGraspField, PlannedGrasp, judge};
use poseflow_runtime::progress::Progress;
use poseflow_scene::ModelLibrary;
use poseflow_scene::part::ObjectPart;
use serde::Serialize;

use super::mug::{Handle, render_mug};
use super::{load_graph, pose_stages, rounded, stage_params, write_trials_csv};

#[derive(Debug, Args)]
#[command(after_help = "Run from the repository root (reads --graph and its config files).\n\n\
    Each trial renders the YCB-V mug alone on a table (camera 0.45–0.65 m away, 15–35° above the table) with its \
    handle turned 60–120° from the line of sight (visible), away from the camera (occluded: hidden behind the body; \
    views where more than 10 handle pixels show are drawn again), or hidden but turned 25–70° from pointing away \
    (hidden_aside: a single hypothesis that puts a hidden handle behind the body is wrong there). The pose stages (ingest, the PoseFlow network, N = 50 \
    samples, K = 5 steps, SDF selection with refinement) estimate the mug's pose distribution. Two grasp plans \
    follow, each --grasps grasps from the grasp flow: `single` under the selected pose alone, `marginalised` in the \
    velocity averaged over the first --hypotheses kept hypotheses (the paper's mean field). Each plan executes its \
    top grasp (the highest score: the share of hypotheses it holds under, ties broken by its friction margin); it \
    succeeds when it is antipodal and collision-free on the true pose and clear of the table.\n\n\
    With --prefer handle the task wants the handle: among the grasps of the highest share, those whose contact \
    point lies on the handle under the plan's first hypothesis go first, so a single hypothesis that puts a hidden \
    handle in the wrong place reaches for it there.\n\n\
    --json prints {\"trials\": n, \"prefer\": \"any\"|\"handle\", \"visible\": {\"single\": rate, \"marginalised\": rate, \
    \"single_handle\": rate, \"marginalised_handle\": rate}, \"occluded\": {...}, \"hidden_aside\": {...}}, rates in \
    percent (*_handle: the executed grasp aimed at the handle).\n\nExample:\n  poseflow sim grasp --trials 20 --seed 0 \
    --prefer handle")]
pub struct GraspSimArgs {
    /// Trials per condition (handle visible, hidden behind the body, hidden and turned aside).
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
    /// Grasp flow model directory.
    #[arg(long, default_value = "models/grasp-flow")]
    pub grasp_model: PathBuf,
    /// BOP models directory holding the mug.
    #[arg(long, default_value = "objects/ycbv/mug-bowl")]
    pub objects: PathBuf,
    /// The mug's object id there.
    #[arg(long, default_value_t = 14)]
    pub mug: u32,
    /// Kept hypotheses the marginalised plan averages over.
    #[arg(long, default_value_t = 8)]
    pub hypotheses: usize,
    /// Grasps sampled per plan.
    #[arg(long, default_value_t = 32)]
    pub grasps: usize,
    /// The graph whose pose stages estimate (in-process, from `frames` to `estimates`) and whose `grasp`
    /// stage's parameters the planners start from.
    #[arg(long, default_value = "deploy/grasping.toml")]
    pub graph: PathBuf,
    /// Also write one row per trial to <out>/trials.csv.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// What the robot wants: `any` grasp that holds, or the `handle` (to hang the mug or hand it over) when
    /// its plan holds a handle grasp as surely as any other grasp.
    #[arg(long, value_enum, default_value_t = Prefer::Any)]
    pub prefer: Prefer,
}

/// The task's preference among a plan's grasps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Prefer {
    /// The planner's order: valid share, then friction margin.
    Any,
    /// Among the grasps of the highest valid share, those that close on the
    /// handle first (under the plan's first hypothesis), then the margin.
    Handle,
}

/// One plan's outcome in one trial.
#[derive(Debug, Clone, Copy, Serialize)]
struct Executed {
    success: bool,
    /// The executed grasp's share of the plan's hypotheses it holds under.
    planned_share: f64,
    /// Share of the plan's grasps that would have succeeded.
    success_any: f64,
    /// Whether the executed grasp closes on the handle where the plan's
    /// first hypothesis puts it.
    aimed_at_handle: bool,
}

/// Per condition, % of trials: the executed grasp succeeded, and it aimed
/// at the handle (`*_handle`).
#[derive(Debug, Default, Serialize)]
struct Rates {
    single: f64,
    marginalised: f64,
    single_handle: f64,
    marginalised_handle: f64,
}

#[derive(Debug, Serialize)]
struct Report {
    trials: usize,
    prefer: Prefer,
    visible: Rates,
    occluded: Rates,
    hidden_aside: Rates,
}

/// Does the gripper at `world_from_grasp` stay above the table (z = 0)?
fn clear_of_table(gripper: &Gripper, world_from_grasp: &Pose) -> bool {
    gripper.parts(gripper.max_opening).iter().all(|part| {
        let h = part.shape.half_extents.cast::<f64>();
        let centre = part.pose.translation.vector.cast::<f64>();
        (0..8).all(|i| {
            let corner = centre
                + h.component_mul(&nalgebra::Vector3::new(
                    if i & 1 == 0 { -1.0 } else { 1.0 },
                    if i & 2 == 0 { -1.0 } else { 1.0 },
                    if i & 4 == 0 { -1.0 } else { 1.0 },
                ));
            world_from_grasp.transform_point(&Point3::from(corner)).z >= 0.0
        })
    })
}

/// One trial's record (a row of trials.csv and of the table).
#[derive(Debug)]
struct Trial {
    handle: Handle,
    index: usize,
    handle_pixels: usize,
    kept: usize,
    /// Rotation error of the selected pose (degrees).
    rotation_error_deg: f64,
    /// Translation error of the selected pose (mm).
    translation_error_mm: f64,
    /// Largest rotation of a marginalised-over hypothesis from the selected
    /// pose (degrees): how much the plan had to hedge.
    spread_deg: f64,
    /// Largest rotation error among the marginalised-over hypotheses.
    worst_error_deg: f64,
    single: Executed,
    marginalised: Executed,
}

/// A row of trials.csv.
#[derive(Serialize)]
struct TrialRow {
    condition: &'static str,
    trial: usize,
    handle_pixels: usize,
    kept: usize,
    rotation_error_deg: f64,
    translation_error_mm: f64,
    spread_deg: f64,
    worst_error_deg: f64,
    single_success: u8,
    single_share: f64,
    single_success_any: f64,
    single_on_handle: u8,
    marginalised_success: u8,
    marginalised_share: f64,
    marginalised_success_any: f64,
    marginalised_on_handle: u8,
}

fn write_trials(out: &Path, trials: &[Trial]) -> anyhow::Result<()> {
    write_trials_csv(
        out,
        trials.iter().map(|t| TrialRow {
            condition: t.handle.name(),
            trial: t.index,
            handle_pixels: t.handle_pixels,
            kept: t.kept,
            rotation_error_deg: rounded(t.rotation_error_deg, 2),
            translation_error_mm: rounded(t.translation_error_mm, 2),
            spread_deg: rounded(t.spread_deg, 2),
            worst_error_deg: rounded(t.worst_error_deg, 2),
            single_success: u8::from(t.single.success),
            single_share: rounded(t.single.planned_share, 4),
            single_success_any: rounded(t.single.success_any, 4),
            single_on_handle: u8::from(t.single.aimed_at_handle),
            marginalised_success: u8::from(t.marginalised.success),
            marginalised_share: rounded(t.marginalised.planned_share, 4),
            marginalised_success_any: rounded(t.marginalised.success_any, 4),
            marginalised_on_handle: u8::from(t.marginalised.aimed_at_handle),
        }),
    )
}

/// `planned` (in the planner's order) reordered for the task: with
/// [`Prefer::Handle`], a grasp whose contact point (the middle of the
/// finger pads, `contact_depth` behind the fingertips) lies on `handle`
/// when the object is at `hypothesis` moves ahead of the grasps of the
/// same valid share. The share stays first: a plan unsure where the handle
/// is holds its handle grasps under few hypotheses and keeps a grasp that
/// holds under all of them on top.
fn ordered_for_task(
    mut planned: Vec<PlannedGrasp>,
    prefer: Prefer,
    hypothesis: &Pose,
    handle: &ObjectPart,
    gripper: &Gripper,
) -> Vec<PlannedGrasp> {
    if prefer == Prefer::Any {
        return planned;
    }
    // Stable, and each grasp's key (a pose inverse and product) computed
    // once: within equal keys the planner's margin order stays.
    planned.sort_by_cached_key(|g| {
        (std::cmp::Reverse(share_key(g.valid_share)), !on_part(g, hypothesis, handle, gripper))
    });
    planned
}

/// Whether the grasp's contact point (the middle of the finger pads) lies
/// on `part` with the object at `hypothesis` (camera frame).
fn on_part(grasp: &PlannedGrasp, hypothesis: &Pose, part: &ObjectPart, gripper: &Gripper) -> bool {
    let contact = Point3::new(0.0, 0.0, -f64::from(gripper.contact_depth));
    part.contains(&(hypothesis.inverse() * grasp.camera_from_grasp).transform_point(&contact))
}

/// A valid share as an orderable key (shares are counts over at most 64
/// hypotheses, so a millionth resolves them).
fn share_key(share: f64) -> i64 {
    (share * 1e6).round() as i64
}

/// Executes the plan's top grasp on the true pose.
fn execute(
    planned: &[PlannedGrasp],
    mesh_check: impl Fn(&PlannedGrasp) -> bool,
    aims_at_handle: impl Fn(&PlannedGrasp) -> bool,
) -> Executed {
    let successes = planned.iter().filter(|g| mesh_check(g)).count();
    Executed {
        success: planned.first().is_some_and(&mesh_check),
        planned_share: planned.first().map_or(0.0, |g| g.valid_share),
        success_any: successes as f64 / planned.len().max(1) as f64,
        aimed_at_handle: planned.first().is_some_and(aims_at_handle),
    }
}

pub fn run(args: &GraspSimArgs) -> anyhow::Result<()> {
    if args.trials == 0 {
        bail!("--trials 0: expected at least one trial per condition");
    }
    let library = ModelLibrary::load(&args.objects, &[args.mug])?;
    let graph = load_graph(&args.graph)?;
    let mut pose = pose_stages(&graph, &args.model, &args.objects)?;
    let grasp = |hypotheses: usize| -> anyhow::Result<GraspPlanner<OnnxGraspField>> {
        let params = GraspParams::from_json(&stage_params(
            &graph,
            "grasp",
            serde_json::json!({
                "model": args.grasp_model, "models": args.objects, "grasps": args.grasps, "hypotheses": hypotheses,
                "seed": args.seed,
            }),
        )?)?;
        Ok(GraspPlanner::load(params)?)
    };
    let (mut single, mut marginal) = (grasp(1)?, grasp(args.hypotheses)?);
    let gripper = single.params().gripper;
    let handle_part = ObjectPart { obj_id: args.mug, ..ObjectPart::ycbv_mug_handle() };

    let mut report = Report {
        trials: args.trials,
        prefer: args.prefer,
        visible: Rates::default(),
        occluded: Rates::default(),
        hidden_aside: Rates::default(),
    };
    let mut rows: Vec<Trial> = Vec::new();
    // Wall time of each plan (grasp flow and checks), single then marginalised.
    let mut plan_ms: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
    let mut progress = Progress::new("sim grasp", 3 * args.trials as u64);
    for (c, handle) in [Handle::Visible, Handle::Occluded, Handle::HiddenAside].into_iter().enumerate() {
        let (mut single_ok, mut marginal_ok, mut single_handle, mut marginal_handle) = (0, 0, 0, 0);
        for trial in 0..args.trials {
            let frame_id = (c * args.trials + trial) as u64;
            let mut rng = seeded_rng(args.seed.wrapping_mul(1_000_003).wrapping_add(frame_id));
            let (_, view) = render_mug(&library, handle, frame_id, &mut rng);
            let (header, payload) = pose
                .estimate(&view.frame, &view.mask)
                .with_context(|| format!("trial {trial} ({handle:?}): pose estimation"))?
                .with_context(|| format!("trial {trial} ({handle:?}): the view shows too little of the mug"))?;
            let kept = kept_hypotheses(&header, &payload)?;
            let truth = view.camera_from_object;
            let world_from_camera = view.camera_from_world.inverse();
            let best = Pose::from_f32_row_major(&header.best)?;
            let started = Instant::now();
            let one_plan = single.plan(frame_id, args.mug, &[best])?;
            plan_ms[0].push(started.elapsed().as_secs_f64() * 1e3);
            let started = Instant::now();
            let many_plan = marginal.plan(frame_id, args.mug, &kept)?;
            plan_ms[1].push(started.elapsed().as_secs_f64() * 1e3);
            let first_kept = kept.first().copied().unwrap_or(best);
            let one_plan = ordered_for_task(one_plan, args.prefer, &best, &handle_part, &gripper);
            let many_plan = ordered_for_task(many_plan, args.prefer, &first_kept, &handle_part, &gripper);
            let mesh = &single.objects().get(args.mug).context("the mug's mesh")?.mesh;
            let holds = |g: &PlannedGrasp| {
                judge(mesh, &gripper, &[truth], &g.camera_from_grasp).valid_share == 1.0
                    && clear_of_table(&gripper, &(world_from_camera * g.camera_from_grasp))
            };
            let one = execute(&one_plan, holds, |g| on_part(g, &best, &handle_part, &gripper));
            let many = execute(&many_plan, holds, |g| on_part(g, &first_kept, &handle_part, &gripper));
            single_ok += usize::from(one.success);
            marginal_ok += usize::from(many.success);
            single_handle += usize::from(one.aimed_at_handle);
            marginal_handle += usize::from(many.aimed_at_handle);
            let angle = |a: &Pose, b: &Pose| geodesic_angle(&a.rotation, &b.rotation).to_degrees();
            let used = &kept[..kept.len().min(args.hypotheses)];
            let widest = |from: &Pose| used.iter().map(|h| angle(h, from)).fold(0.0, f64::max);
            rows.push(Trial {
                handle,
                index: trial,
                handle_pixels: view.handle_pixels,
                kept: kept.len(),
                rotation_error_deg: angle(&best, &truth),
                translation_error_mm: 1000.0 * (best.translation - truth.translation).norm(),
                spread_deg: widest(&best),
                worst_error_deg: widest(&truth),
                single: one,
                marginalised: many,
            });
            progress.update(rows.len() as u64, &format!("{handle:?} trial {trial}"));
        }
        let percent = |count: usize| 100.0 * count as f64 / args.trials as f64;
        let rates = Rates {
            single: percent(single_ok),
            marginalised: percent(marginal_ok),
            single_handle: percent(single_handle),
            marginalised_handle: percent(marginal_handle),
        };
        match handle {
            Handle::Visible => report.visible = rates,
            Handle::Occluded => report.occluded = rates,
            Handle::HiddenAside => report.hidden_aside = rates,
        }
    }
    if let Some(out) = &args.out {
        write_trials(out, &rows)?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
        return Ok(());
    }
    println!(
        "grasp simulation: mug {} ({}), {} trials per condition, seed {}, prefer {:?}",
        args.mug,
        args.objects.display(),
        args.trials,
        args.seed,
        args.prefer
    );
    println!(
        "{:<12} {:>5} {:>9} {:>5} {:>8} {:>8} | {:>6} {:>6} {:>6} | {:>6} {:>6} {:>6}",
        "handle", "trial", "handle px", "kept", "rot err", "spread", "single", "share", "any", "marg.", "share", "any"
    );
    for t in &rows {
        let mark = |e: &Executed| match (e.success, e.aimed_at_handle) {
            (true, false) => "ok",
            (true, true) => "ok·h",
            (false, false) => "fail",
            (false, true) => "fail·h",
        };
        let (one, many) = (&t.single, &t.marginalised);
        println!(
            "{:<12} {:>5} {:>9} {:>5} {:>7.1}° {:>7.1}° | {:>6} {:>6.2} {:>5.0}% | {:>6} {:>6.2} {:>5.0}%",
            t.handle.name(),
            t.index,
            t.handle_pixels,
            t.kept,
            t.rotation_error_deg,
            t.spread_deg,
            mark(one),
            one.planned_share,
            100.0 * one.success_any,
            mark(many),
            many.planned_share,
            100.0 * many.success_any
        );
    }
    let [single_ms, marginal_ms] = plan_ms.map(|mut ms| {
        ms.sort_by(f64::total_cmp);
        ms[ms.len() / 2]
    });
    println!(
        "\nplanning {} grasps, median wall time: single {single_ms:.1} ms, marginalised over {} hypotheses \
         {marginal_ms:.1} ms",
        args.grasps, args.hypotheses
    );
    println!("\nsuccess of the executed (top) grasp, % of trials (aimed at the handle: ·h above, % in brackets):");
    println!("{:<12} {:>15} {:>15}", "condition", "single", "marginalised");
    for (name, rates) in
        [("visible", &report.visible), ("occluded", &report.occluded), ("hidden_aside", &report.hidden_aside)]
    {
        println!(
            "{name:<12} {:>6.1}% ({:>5.1}%) {:>6.1}% ({:>5.1}%)",
            rates.single, rates.single_handle, rates.marginalised, rates.marginalised_handle
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};

    use super::*;

    #[test]
    fn a_gripper_is_clear_of_the_table_only_when_every_box_corner_is_above_it() {
        let gripper = Gripper::default();
        // Approaching straight down (grasp z = world −z), fingertips 1 mm
        // above the table: clear; 1 mm below: not.
        let down = Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        assert!(clear_of_table(&gripper, &Pose::new(down, Vector3::new(0.0, 0.0, 0.001))));
        assert!(!clear_of_table(&gripper, &Pose::new(down, Vector3::new(0.0, 0.0, -0.001))));
        // Approaching from the side, closing vertically, 2 cm up: the lower
        // finger and the 20 cm palm reach below; 11 cm up they clear it.
        let side = Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::FRAC_PI_2);
        assert!(!clear_of_table(&gripper, &Pose::new(side, Vector3::new(0.0, 0.0, 0.02))));
        assert!(clear_of_table(&gripper, &Pose::new(side, Vector3::new(0.0, 0.0, 0.11))));
    }

    #[test]
    fn a_handle_grasp_goes_first_only_among_grasps_held_as_surely() {
        let gripper = Gripper::default();
        let handle = ObjectPart::ycbv_mug_handle();
        // The mug 0.5 m ahead of the camera, unrotated. Grasp poses put the
        // contact point (0, 0, -contact_depth in the grasp frame) at an
        // object point: the rim centre, or 7 cm out along +x (the handle).
        let mug = Pose::new(Rotation3::identity(), Vector3::new(0.0, 0.0, 0.5));
        let at = |x: f64, share: f64, margin: f32| PlannedGrasp {
            camera_from_grasp: Pose::new(
                Rotation3::identity(),
                Vector3::new(x, 0.0, 0.5 + f64::from(gripper.contact_depth)),
            ),
            width: 0.03,
            valid_share: share,
            margin,
        };
        let planned = vec![at(0.0, 1.0, 0.3), at(0.07, 1.0, 0.1), at(0.07, 0.5, 0.3)];
        let xs = |grasps: &[PlannedGrasp]| grasps.iter().map(|g| g.camera_from_grasp.translation.x).collect::<Vec<_>>();
        let any = ordered_for_task(planned.clone(), Prefer::Any, &mug, &handle, &gripper);
        assert_eq!(xs(&any), [0.0, 0.07, 0.07]);
        let first_handle = ordered_for_task(planned.clone(), Prefer::Handle, &mug, &handle, &gripper);
        assert_eq!(xs(&first_handle), [0.07, 0.0, 0.07]);
        assert_eq!(first_handle[0].valid_share, 1.0);
        // With the hypothesis turned 180° about the mug's axis, the same
        // camera point is no longer on the handle: the planner's order stays.
        let turned = Pose::new(Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::PI), mug.translation);
        let elsewhere = ordered_for_task(planned, Prefer::Handle, &turned, &handle, &gripper);
        assert_eq!(xs(&elsewhere), [0.0, 0.07, 0.07]);
    }
}
