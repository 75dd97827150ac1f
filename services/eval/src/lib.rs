//! `poseflow eval` and `poseflow demo` as libraries.
//!
//! `poseflow eval`: runs the estimation graph over a BOP-format dataset and
//! scores every targeted instance: n°m cm accuracy, ADD(-S), MSSD/MSPD
//! recall, mode recall, calibration and runtime; writes the estimates in
//! the BOP19 CSV format.

mod bop_csv;
pub mod category;
mod dataset;
pub mod demo;
pub mod detection;
pub(crate) mod estimates;
pub mod recovery;
mod score;
mod summary;
pub mod tracking;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use nalgebra::Point3;
use poseflow_geometry::flow::TimeGrid;
use poseflow_geometry::metrics::NearestPoints;
use poseflow_geometry::models_info::ModelsInfo;
use poseflow_geometry::sampling::sample_seed;
use poseflow_geometry::symmetry::BOP_MAX_SYMMETRY_STEP;
use poseflow_geometry::{Pose, SymmetrySet};
use poseflow_graph::Graph;
use poseflow_ingest::sources::{BopFrames, Masks};
use poseflow_scene::ModelLibrary;
use poseflow_scene::import::SHAPE_SYMMETRIES_FILE;
use serde::Serialize;

use self::bop_csv::to_csv;
use self::dataset::{TruthImage, read_truth};
use self::estimates::{Estimated, bop_rows, count_estimates, read_recording, read_results};
use self::score::{EstimatedInstance, ScoredObject, score_instance};
use self::summary::{InstanceOutcome, Summary, instances_csv, summarise};
use crate::demo::graph::{Overrides, graph_with_overrides};
use crate::demo::{DetectorMode, SelectionArg, TimeGridArg};
use crate::demo::{print_report, run_graph};
use poseflow_runtime::progress::Progress;

#[derive(Debug, Clone, Args)]
#[command(after_help = "Run from the repository root after `cargo build --release --workspace` (the stages are \
    separate executables). Writes <out>/<graph>.toml (the graph run, with the frame source on the dataset), \
    <out>/<graph>.rec (its estimates), <out>/graph.log (the stages' log), <out>/run.json (its report), \
    <out>/poseflow_<dataset>-<split>.csv (BOP19 results: scene_id,im_id,obj_id,score,R,t,time; t in mm, time = \
    seconds the graph spent on the image), <out>/instances.csv (per scored instance: the selected pose's errors and \
    reported spread) and <out>/summary.json.\n\n\
    With a tracking graph (its sampler starting from earlier estimates, e.g. deploy/tracking.toml) each scene is \
    also reported as a video: per object the images estimated, tracked, flagged lost, unsure and reinitialised, \
    5°5cm and 10°5cm (a hidden image is a miss), and for each event of video_events.json the images from the \
    object reappearing (≥ 30 % visible) or moving to its estimate being back within 10°5cm; every estimate with its \
    errors and flags in <out>/tracking.csv.\n\n\
    Scored instances: the targets of test_targets_bop19.json (or --targets) with at least 10 % of their silhouette \
    visible (scene_gt_info.json), as BOP19; an instance without an estimate counts as a miss. Symmetric objects \
    (models_info.json) are scored against the closest symmetric twin, continuous symmetries discretised as the \
    BOP toolkit does. With --selection none every hypothesis is scored and the accuracies are averaged over \
    them (the accuracy of one random sample).\n\n\
    VSD (BOP19: δ 15 mm, τ and θ from 0.05 to 0.5) renders the model at the estimate and the truth against the \
    image's depth PNG (no depth: no VSD); without selection it averages over a seeded random 10 of the samples. \
    MSSD, MSPD and ADD(-S) use every vertex of the --objects meshes. The BOP19 average recall is the mean of the \
    VSD, MSSD and MSPD recalls.\n\n\
    The distribution: coverage is the share of instances with at least one hypothesis within 10°5cm (5°5cm) of \
    the truth, symmetry-aware; the hypotheses are those the selector kept (all samples with --selection none). \
    spread max is the largest rotational standard deviation of the kept hypotheses, each folded onto its \
    symmetric twin nearest the selected pose (√ of the largest eigenvalue of their rotation covariance); \
    within 1×/2× spread is the share of estimated instances whose selected pose's rotation error is at most \
    1×/2× it.\n\n\
    Runtime: ms/object is the interval between consecutive estimates leaving the selector while the graph is \
    kept busy (the cost of one more object; the CSV's time is their sum over an image); latency is from the \
    frame source reading an image to each estimate, queueing included (--rate-hz below the graph's pace \
    measures an idle graph).\n\n\
    --results FILE scores another method's BOP19 results file on the same instances instead of running the \
    graph (its time per image is shared evenly by the image's estimates).\n\n\
    Examples:\n  poseflow render --objects objects/lmo --out target/heldout --scenes 4 --frames-per-scene 10 --seed 77\n  \
    poseflow eval --dataset target/heldout --objects objects/lmo --json\n  \
    poseflow eval --dataset target/heldout --objects objects/lmo --selection none --out target/eval-none\n  \
    poseflow eval --dataset target/heldout --objects objects/lmo --results baseline_heldout-test.csv")]
pub struct EvalArgs {
    /// BOP dataset root (split folders, optionally test_targets_bop19.json and models/).
    #[arg(long)]
    pub dataset: PathBuf,
    /// Split folder.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// BOP19 targets file [default: <dataset>/test_targets_bop19.json for a test split, else every annotated
    /// instance].
    #[arg(long)]
    pub targets: Option<PathBuf>,
    /// BOP models directory (meshes and models_info.json) for selection and metrics [default: <dataset>/models].
    #[arg(long)]
    pub objects: Option<PathBuf>,
    /// The graph to run.
    #[arg(long, default_value = "deploy/estimation.toml")]
    pub graph: PathBuf,
    /// Override one stage parameter of the graph, after this command's own
    /// options (repeatable), as for `poseflow run`: for example
    /// `--set selector.tracking.remember_frames=0`.
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    pub set: Vec<String>,
    /// Model directory (encoder.onnx, velocity.onnx).
    #[arg(long, default_value = "models/poseflow-lmo10")]
    pub model: PathBuf,
    /// How the selector chooses the pose (`none`: score every hypothesis).
    #[arg(long, value_enum, default_value_t = SelectionArg::Sdf)]
    pub selection: SelectionArg,
    /// Refine the kept hypotheses against the observed points.
    #[arg(long)]
    pub refine: bool,
    /// Pose samples per object.
    #[arg(long, default_value_t = 50)]
    pub samples: usize,
    /// Euler steps.
    #[arg(long, default_value_t = 5)]
    pub steps: usize,
    /// Where the Euler steps ask for the velocity: `uniform` (t = k/K) or `quadratic` (t = 1 − (1 − k/K)²:
    /// sharper samples, a narrower spread where the view is ambiguous; docs/distributions.md) [default: the
    /// graph's sampler setting, uniform].
    #[arg(long, value_enum)]
    pub time_grid: Option<TimeGridArg>,
    /// Euler steps of a frame that starts from an earlier estimate or a prior (tracking graphs, e.g.
    /// evaluation/graphs/tracking-from-truth.toml) [default: the graph's].
    #[arg(long)]
    pub tracking_steps: Option<usize>,
    /// Frames per second the frame source reads at [default: as fast as the graph takes them].
    #[arg(long)]
    pub rate_hz: Option<f64>,
    /// Hand the network no image (a blank crop with every image token masked out): the depth-only ablation of
    /// the same model.
    #[arg(long)]
    pub no_rgb: bool,
    /// Output folder.
    #[arg(long, default_value = "target/eval")]
    pub out: PathBuf,
    /// Score this BOP19 results file (another method's, e.g. evaluation/baseline) instead of running the graph.
    #[arg(long)]
    pub results: Option<PathBuf>,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Find the objects with the detector instead of the ground-truth masks: scores the detector on the
    /// split's images (AP50 and mask IoU per object) and runs the graph with a detector stage
    /// (deploy/estimation-detect.toml unless --graph names another).
    #[arg(long)]
    pub detect: bool,
    /// The detector's model directory (detector.onnx, detector.json, and the identifier's identify.onnx and
    /// identify.json if present), with --detect.
    #[arg(long, default_value = "models/detector-lmo10")]
    pub detector_model: PathBuf,
    /// How the detector finds the objects, with --detect (classical: the objects of --objects).
    #[arg(long, value_enum, default_value_t = DetectorMode::Network)]
    pub detector_mode: DetectorMode,
    /// Category-level evaluation (REAL275's protocol): --model is a category-level model, each object's
    /// category comes from <objects>/categories.json (`poseflow generate-objects`), the selector scores
    /// against category templates (evaluation/graphs/estimation-category.toml unless --graph names another), and the
    /// report adds 5°2cm … 10°5cm with turns about the symmetry axis ignored and 3D IoU25/50 per category.
    /// The model defaults to models/poseflow-cat, and `--selection sdf` (the default) scores as `chamfer`.
    #[arg(long, conflicts_with_all = ["detect", "results"])]
    pub category: bool,
    /// The symmetries a pose is scored up to: `models-info` (models_info.json, the real object's as BOP records
    /// them, print included) or `shape` (models_info_shape.json, the one-coloured shape's: what a render without
    /// the print can show; `poseflow import-model --shape-symmetries`).
    #[arg(long, value_enum, default_value_t = SymmetriesArg::ModelsInfo)]
    pub symmetries: SymmetriesArg,
}

/// Which file's symmetries score a pose (`--symmetries`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SymmetriesArg {
    ModelsInfo,
    Shape,
}

/// The graph `--detect` runs when `--graph` was left at its default.
pub const DETECT_GRAPH: &str = "deploy/estimation-detect.toml";
/// The graph `--category` runs when `--graph` was left at its default.
pub const CATEGORY_GRAPH: &str = "evaluation/graphs/estimation-category.toml";

/// The model `--category` runs when `--model` was left at its default.
pub const CATEGORY_MODEL: &str = "models/poseflow-cat";

impl EvalArgs {
    /// The arguments as run: with `--category`, the default model is the
    /// category-level one and `sdf` selection scores as `chamfer` (a
    /// template is built per message; a signed-distance grid for each would
    /// cost more than the estimate).
    fn resolved(&self) -> Self {
        let mut args = self.clone();
        if self.category {
            if self.model == Path::new("models/poseflow-lmo10") {
                args.model = PathBuf::from(CATEGORY_MODEL);
            }
            if self.selection == SelectionArg::Sdf {
                args.selection = SelectionArg::Chamfer;
            }
        }
        args
    }

    /// The graph file to run: `--graph`, or with `--detect` or `--category`
    /// and the default graph, its detecting or category-level twin.
    fn graph_file(&self) -> PathBuf {
        let default = self.graph == Path::new("deploy/estimation.toml");
        match (default, self.detect, self.category) {
            (true, true, _) => PathBuf::from(DETECT_GRAPH),
            (true, _, true) => PathBuf::from(CATEGORY_GRAPH),
            _ => self.graph.clone(),
        }
    }
}

/// What produced the scored estimates.
#[derive(Debug, Serialize)]
#[serde(tag = "method", rename_all = "snake_case")]
enum Method {
    Graph {
        graph: PathBuf,
        model: PathBuf,
        selection: &'static str,
        refine: bool,
        samples: usize,
        steps: usize,
        /// The sampler's time grid as the graph ran it.
        time_grid: TimeGrid,
        #[serde(skip_serializing_if = "Option::is_none")]
        tracking_steps: Option<usize>,
        rgb: bool,
    },
    Results {
        results: PathBuf,
    },
}

#[derive(Debug, Serialize)]
struct EvalReport {
    dataset: PathBuf,
    split: String,
    /// The symmetries the poses were scored up to.
    symmetries: SymmetriesArg,
    #[serde(flatten)]
    method: Method,
    /// Estimates that match no scored instance (an object not in the image,
    /// a hidden instance, an image not targeted).
    unmatched_estimates: usize,
    /// The estimates in BOP19 format.
    csv: PathBuf,
    /// The graph's own counts per stage (from its run report): a frame
    /// lost on the way shows here as well as in the accuracies.
    #[serde(skip_serializing_if = "Option::is_none")]
    stages: Option<serde_json::Value>,
    /// With a tracking graph: each scene as a video ([`tracking`]), and the
    /// per-image CSV of them all.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    videos: Vec<tracking::VideoSummary>,
    #[serde(skip_serializing_if = "Option::is_none")]
    per_image: Option<PathBuf>,
    /// With --detect: the detector scored on the same images.
    #[serde(skip_serializing_if = "Option::is_none")]
    detection: Option<detection::DetectionSummary>,
    /// With `--category`: the REAL275-style tables.
    #[serde(skip_serializing_if = "Option::is_none")]
    category: Option<category::CategorySummary>,
    #[serde(flatten)]
    summary: Summary,
}

fn check(args: &EvalArgs) -> anyhow::Result<()> {
    if args.samples == 0 || args.steps == 0 || args.tracking_steps == Some(0) {
        bail!(
            "--samples {} --steps {} --tracking-steps {:?}: expected at least 1 of each",
            args.samples,
            args.steps,
            args.tracking_steps
        );
    }
    if let Some(rate) = args.rate_hz
        && !(rate.is_finite() && rate > 0.0)
    {
        bail!("--rate-hz {rate}: expected frames per second > 0");
    }
    Ok(())
}

/// Each object of `library` with its symmetries as `source` records them,
/// continuous ones discretised at `step` radians: BOP's models_info.json
/// beside the meshes, or the shape's own file
/// ([`SHAPE_SYMMETRIES_FILE`]), which must then have an entry for every
/// object.
pub(crate) fn object_symmetries(
    library: &ModelLibrary,
    source: SymmetriesArg,
    step: f64,
) -> anyhow::Result<BTreeMap<u32, SymmetrySet>> {
    let shape_path = library.dir.join(SHAPE_SYMMETRIES_FILE);
    let shape = match source {
        SymmetriesArg::ModelsInfo => None,
        SymmetriesArg::Shape => Some(ModelsInfo::from_path(&shape_path).with_context(|| {
            format!("--symmetries shape: {} (poseflow import-model --shape-symmetries writes it)", shape_path.display())
        })?),
    };
    library
        .objects
        .iter()
        .map(|object| {
            let info = match &shape {
                None => &object.info,
                Some(table) => table.get(object.obj_id).with_context(|| {
                    format!(
                        "--symmetries shape: {} has no entry for object {} (import it with --shape-symmetries)",
                        shape_path.display(),
                        object.obj_id
                    )
                })?,
            };
            Ok((object.obj_id, SymmetrySet::from_model_info(info, step)))
        })
        .collect()
}

/// The metrics' view of every object of the library, scored up to the
/// symmetries of `source`.
fn scored_objects(library: &ModelLibrary, source: SymmetriesArg) -> anyhow::Result<BTreeMap<u32, ScoredObject>> {
    let mut symmetries = object_symmetries(library, source, BOP_MAX_SYMMETRY_STEP)?;
    Ok(library
        .objects
        .iter()
        .map(|object| {
            let points: Vec<Point3<f64>> = object.model.mesh.vertices.iter().map(|v| v.cast::<f64>()).collect();
            let scored = ScoredObject {
                nearest: NearestPoints::new(&points),
                points,
                diameter: object.info.diameter,
                symmetries: symmetries.remove(&object.obj_id).expect("one set per object of the library"),
                model: object.model.clone(),
            };
            (object.obj_id, scored)
        })
        .collect())
}

/// Messages in and out, drops and errors of every stage, from the run's
/// report; warns when fewer estimates left the graph than observations
/// entered it.
fn stage_counts(report: &Path) -> anyhow::Result<serde_json::Value> {
    let text = std::fs::read_to_string(report).with_context(|| format!("{}", report.display()))?;
    let run: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{}: not the JSON report of poseflow run", report.display()))?;
    let stages = run["stages"].as_object().cloned().unwrap_or_default();
    let counts: serde_json::Map<String, serde_json::Value> = stages
        .iter()
        .map(|(name, stage)| {
            let keep = ["frames_in", "frames_out", "dropped", "errors", "restarts"];
            let fields = keep.iter().map(|k| (k.to_string(), stage[*k].clone())).collect();
            (name.clone(), serde_json::Value::Object(fields))
        })
        .collect();
    let out_of = |stage: &str| stages.get(stage).and_then(|s| s["frames_out"].as_u64());
    if let (Some(observations), Some(estimates)) = (out_of("ingest"), out_of("selector"))
        && estimates < observations
    {
        tracing::warn!(
            observations,
            estimates,
            "fewer estimates left the graph than observations entered it (see run.json)"
        );
    }
    Ok(serde_json::Value::Object(counts))
}

/// Scores every scored instance of `images` against the estimates
/// (matched within an image by object, nearest translation first).
/// Returns the outcomes and how many estimates matched no scored instance.
fn evaluate(
    images: &[TruthImage],
    estimates: &[Estimated],
    objects: &BTreeMap<u32, ScoredObject>,
    every_hypothesis: bool,
) -> anyhow::Result<(Vec<InstanceOutcome>, usize)> {
    let mut by_image: BTreeMap<(u32, u32), Vec<&Estimated>> = BTreeMap::new();
    for estimate in estimates {
        by_image.entry((estimate.scene_id, estimate.im_id)).or_default().push(estimate);
    }
    let jobs: Vec<(&TruthImage, Vec<&Estimated>)> = images
        .iter()
        .map(|image| (image, by_image.remove(&(image.scene_id, image.im_id)).unwrap_or_default()))
        .collect();
    // Estimates of images the dataset's targets do not name.
    let mut unmatched: usize = by_image.values().map(Vec::len).sum();
    // Scoring every sample against every model vertex is the slow part of
    // an evaluation: images are scored on all cores, in order.
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
    let per_worker = jobs.len().div_ceil(workers).max(1);
    let parts: Vec<anyhow::Result<(Vec<InstanceOutcome>, usize)>> = std::thread::scope(|scope| {
        let handles: Vec<_> = jobs
            .chunks(per_worker)
            .map(|part| scope.spawn(move || score_images(part, objects, every_hypothesis)))
            .collect();
        handles.into_iter().map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
    });
    let mut outcomes = Vec::new();
    for part in parts {
        let (part_outcomes, part_unmatched) = part?;
        outcomes.extend(part_outcomes);
        unmatched += part_unmatched;
    }
    Ok((outcomes, unmatched))
}

/// [`evaluate`] for some of the images, each with its estimates.
fn score_images(
    jobs: &[(&TruthImage, Vec<&Estimated>)],
    objects: &BTreeMap<u32, ScoredObject>,
    every_hypothesis: bool,
) -> anyhow::Result<(Vec<InstanceOutcome>, usize)> {
    let (mut outcomes, mut unmatched) = (Vec::new(), 0);
    for (image, image_estimates) in jobs {
        let depth = if image.instances.iter().any(|i| i.scored) {
            image.depth.as_ref().map(|file| file.read()).transpose()?
        } else {
            None
        };
        let mut matched: Vec<Option<&Estimated>> = vec![None; image.instances.len()];
        for &estimate in image_estimates {
            let nearest = image
                .instances
                .iter()
                .enumerate()
                .filter(|(i, truth)| truth.obj_id == estimate.obj_id && matched[*i].is_none())
                .min_by(|(_, a), (_, b)| {
                    let distance = |p: &Pose| (p.translation - estimate.selected.translation).norm();
                    distance(&a.pose).total_cmp(&distance(&b.pose))
                });
            match nearest {
                Some((i, truth)) => {
                    matched[i] = Some(estimate);
                    unmatched += usize::from(!truth.scored);
                }
                None => unmatched += 1,
            }
        }
        for (truth, estimate) in image.instances.iter().zip(matched) {
            if !truth.scored {
                continue;
            }
            let object = objects.get(&truth.obj_id).with_context(|| {
                format!(
                    "scene {} image {}: object {} has no model in --objects",
                    image.scene_id, image.im_id, truth.obj_id
                )
            })?;
            let score = estimate.map(|e| {
                let estimated = EstimatedInstance {
                    selected: e.selected,
                    hypotheses: &e.hypotheses,
                    kept: e.kept,
                    seed: sample_seed(u64::from(image.scene_id), u64::from(image.im_id), truth.obj_id),
                    rotation_trace: e.rotation_trace,
                    score_every_hypothesis: every_hypothesis,
                };
                score_instance(&estimated, &truth.pose, object, &image.camera, depth.as_ref())
            });
            outcomes.push(InstanceOutcome {
                scene_id: image.scene_id,
                im_id: image.im_id,
                obj_id: truth.obj_id,
                score,
                service_time: estimate.and_then(|e| e.service_time),
                latency: estimate.and_then(|e| e.latency),
                flags: estimate.map_or(0, |e| e.flags),
                visib_fract: truth.visib_fract,
            });
        }
    }
    Ok((outcomes, unmatched))
}

/// The graph the evaluation runs: `--graph` (or its detecting twin) with
/// the dataset, model and options set on its stages.
fn eval_graph(args: &EvalArgs, objects_dir: &Path, object_ids: Vec<u32>) -> anyhow::Result<Graph> {
    let classes = objects_dir.join(poseflow_scene::category::CATEGORIES_FILE);
    let overrides = Overrides {
        dataset: &args.dataset,
        split: &args.split,
        targets: args.targets.as_deref(),
        model: &args.model,
        object_models: objects_dir,
        selection: args.selection.name(),
        refine: args.refine,
        samples: args.samples,
        steps: args.steps,
        time_grid: args.time_grid.map(TimeGrid::from),
        tracking_steps: args.tracking_steps,
        rate_hz: args.rate_hz,
        rgb: !args.no_rgb,
        detector_model: args.detect.then_some(args.detector_model.as_path()),
        detector_mode: args.detect.then_some(args.detector_mode),
        detector_objects: args.detect.then_some(object_ids),
        classes: args.category.then_some(classes.as_path()),
    };
    let graph_file = args.graph_file();
    let mut run = graph_with_overrides(&graph_file, &overrides)?;
    for assignment in &args.set {
        run.set_param(assignment)?;
    }
    if args.detect && !run.stages.values().any(|stage| stage.exe_name() == "detector") {
        bail!("--detect --graph {}: the graph has no stage with exe = \"detector\"", graph_file.display());
    }
    Ok(run)
}

/// Runs `run` over the dataset; its estimates and the results file written
/// from them.
/// With `categories`, estimates of category objects are carried to their
/// model frames before the results file is written.
fn run_graph_on(
    args: &EvalArgs,
    images: &[TruthImage],
    run: &Graph,
    categories: Option<&BTreeMap<u32, poseflow_scene::category::CategoryEntry>>,
) -> anyhow::Result<(Vec<Estimated>, PathBuf, Method)> {
    let graph_file = args.graph_file();
    let name = graph_file.file_name().map_or("graph.toml".into(), |n| n.to_string_lossy().into_owned());
    let graph = args.out.join(name);
    std::fs::write(&graph, run.to_toml()?).with_context(|| format!("{}", graph.display()))?;
    let recording = graph.with_extension("rec");
    let detections: usize = images.iter().map(|image| image.instances.len()).sum();
    let mut progress = Progress::new("eval", detections as u64);
    run_graph(run, &recording, "estimates", || progress.update(count_estimates(&recording), "estimates"))?;
    progress.update(detections as u64, "estimates");
    let mut estimates = read_recording(&recording, images)?;
    if let Some(categories) = categories {
        category::to_model_frames(&mut estimates, categories);
    }
    let dataset_name = args.dataset.file_name().map_or("dataset".into(), |n| n.to_string_lossy().into_owned());
    let csv = args.out.join(format!("poseflow_{dataset_name}-{}.csv", args.split));
    std::fs::write(&csv, to_csv(&bop_rows(&estimates))).with_context(|| format!("{}", csv.display()))?;
    let method = Method::Graph {
        graph: graph_file,
        model: args.model.clone(),
        selection: args.selection.name(),
        refine: args.refine,
        samples: args.samples,
        steps: args.steps,
        time_grid: sampler_time_grid(run),
        tracking_steps: args.tracking_steps,
        rgb: !args.no_rgb,
    };
    Ok((estimates, csv, method))
}

/// The `time_grid` of the graph's sampler stage (after the graph file, its
/// config and every override), uniform when unset (as the sampler reads it).
fn sampler_time_grid(run: &Graph) -> TimeGrid {
    let sampler = run.stages.values().find(|stage| stage.exe_name() == "sampler");
    let grid = sampler.and_then(|stage| stage.params.get("time_grid"));
    grid.and_then(|grid| serde_json::from_value(grid.clone()).ok()).unwrap_or_default()
}

/// What a model's `objects.json` (written at export) says it was trained on.
#[derive(Debug, serde::Deserialize)]
struct TrainedObjects {
    object_ids: Vec<u32>,
    diameters_mm: Vec<f64>,
}

/// Diameters further apart than this share are different objects.
const SAME_OBJECT_DIAMETER: f64 = 0.05;

/// Refuses a model trained on other objects than `library`'s under the same
/// ids (LM-O's 1 is the ape, YCB-V's 1 the master chef can): they would be
/// estimated as the wrong object without a word. Models without
/// `objects.json` are not checked.
fn check_model_objects(model: &std::path::Path, library: &ModelLibrary) -> anyhow::Result<()> {
    let path = model.join("objects.json");
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(());
    };
    let trained: TrainedObjects = serde_json::from_str(&text)
        .with_context(|| format!("{}: expected object_ids and diameters_mm", path.display()))?;
    for (obj_id, trained_mm) in trained.object_ids.iter().zip(&trained.diameters_mm) {
        let Some(object) = library.objects.iter().find(|o| o.obj_id == *obj_id) else { continue };
        let given_mm = object.info.diameter * 1e3;
        if (given_mm - trained_mm).abs() > SAME_OBJECT_DIAMETER * trained_mm {
            bail!(
                "--model {}: trained on object {obj_id} with diameter {trained_mm:.1} mm, but --objects {} has \
                 object {obj_id} with diameter {given_mm:.1} mm: a different object under the same id (another \
                 dataset's models?)",
                model.display(),
                library.dir.display()
            );
        }
    }
    let unknown: Vec<u32> =
        library.objects.iter().map(|o| o.obj_id).filter(|id| !trained.object_ids.contains(id)).collect();
    if !unknown.is_empty() {
        tracing::warn!(
            model = %model.display(),
            ?unknown,
            "the model was not trained on these objects: their instances are counted as not estimated"
        );
    }
    Ok(())
}

/// Each scene of a tracking graph's run as a video: its estimated
/// instances in image order (an image's position in its scene is its
/// frame), summarised per object, and all of them written to `per_image`.
fn summarise_videos(
    split: &Path,
    images: &[TruthImage],
    outcomes: &[summary::InstanceOutcome],
    per_image: &Path,
) -> anyhow::Result<Vec<tracking::VideoSummary>> {
    let mut frames: BTreeMap<u32, u32> = BTreeMap::new();
    for image in images {
        *frames.entry(image.scene_id).or_default() += 1;
    }
    let mut by_scene: BTreeMap<u32, Vec<tracking::TrackedImage>> = BTreeMap::new();
    for outcome in outcomes {
        if let Some(score) = &outcome.score {
            by_scene.entry(outcome.scene_id).or_default().push(tracking::TrackedImage {
                im_id: outcome.im_id,
                obj_id: outcome.obj_id,
                rotation_error_deg: score.rotation_error_deg,
                translation_error_m: score.translation_error_cm / 100.0,
                flags: outcome.flags,
                latency: outcome.latency,
            });
        }
    }
    let videos: Vec<(u32, &[tracking::TrackedImage])> = by_scene.iter().map(|(s, i)| (*s, i.as_slice())).collect();
    tracking::write_per_image(per_image, &videos)?;
    frames
        .iter()
        .map(|(&scene_id, &count)| {
            let estimated = by_scene.get(&scene_id).map_or(&[][..], Vec::as_slice);
            tracking::summarise_video(split, scene_id, count, estimated)
                .with_context(|| format!("scene {scene_id} of {}", split.display()))
        })
        .collect()
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    let args = &args.resolved();
    check(args)?;
    let frames = BopFrames::open(&args.dataset, &args.split, &[], args.targets.as_deref(), Masks::GroundTruth)
        .with_context(|| format!("--dataset {} --split {}", args.dataset.display(), args.split))?;
    let mut images = read_truth(&args.dataset.join(&args.split), &frames)?;
    let objects_dir = args.objects.clone().unwrap_or_else(|| args.dataset.join("models"));
    let library = ModelLibrary::load(&objects_dir, &[])
        .with_context(|| format!("--objects {}: cannot load the object models", objects_dir.display()))?;
    let objects = scored_objects(&library, args.symmetries)?;
    let categories = args
        .category
        .then(|| {
            poseflow_scene::category::read_categories(&objects_dir)
                .with_context(|| format!("--category: the categories of --objects {}", objects_dir.display()))
        })
        .transpose()?;
    if args.results.is_none() && !args.category {
        check_model_objects(&args.model, &library)?;
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("--out {}", args.out.display()))?;
    let with_category_targets;
    let args = match &categories {
        Some(categories) => {
            let targets = category::targets(&images, categories);
            if targets.is_empty() {
                bail!(
                    "--category: no annotated instance of --dataset {} is an object of {} (objects {:?}; \
                     `poseflow annotate-category` adds one)",
                    args.dataset.display(),
                    objects_dir.join(poseflow_scene::category::CATEGORIES_FILE).display(),
                    categories.keys().collect::<Vec<_>>()
                );
            }
            for image in &mut images {
                image.instances.retain(|i| categories.contains_key(&i.obj_id));
            }
            let path = args.out.join("category_targets.json");
            poseflow_scene::bop::write_json(&path, &targets)?;
            with_category_targets = EvalArgs { targets: Some(path), ..args.clone() };
            &with_category_targets
        }
        None => args,
    };
    let graph = (args.results.is_none() || args.detect)
        .then(|| eval_graph(args, &objects_dir, objects.keys().copied().collect()))
        .transpose()?;
    let detection = match (&graph, args.detect) {
        (Some(graph), true) => Some(score_detector(args, graph)?),
        _ => None,
    };

    let (estimates, csv, method) = match (&args.results, &graph) {
        (Some(results), _) => (read_results(results)?, results.clone(), Method::Results { results: results.clone() }),
        (None, Some(graph)) => run_graph_on(args, &images, graph, categories.as_ref())?,
        (None, None) => unreachable!("the graph is built unless --results"),
    };
    let stages = args.results.is_none().then(|| stage_counts(&args.out.join("run.json"))).transpose()?;
    let every_hypothesis = args.results.is_none() && args.selection == SelectionArg::None;
    let (outcomes, unmatched_estimates) = evaluate(&images, &estimates, &objects, every_hypothesis)?;
    let category_outcomes = categories
        .as_ref()
        .map(|categories| category::score(&args.dataset.join(&args.split), &images, &estimates, categories))
        .transpose()?;
    let (videos, per_image) = if outcomes.iter().any(InstanceOutcome::tracked) {
        let per_image = args.out.join("tracking.csv");
        (summarise_videos(&args.dataset.join(&args.split), &images, &outcomes, &per_image)?, Some(per_image))
    } else {
        (Vec::new(), None)
    };
    let report = EvalReport {
        dataset: args.dataset.clone(),
        split: args.split.clone(),
        symmetries: args.symmetries,
        method,
        unmatched_estimates,
        csv,
        stages,
        videos,
        per_image,
        detection,
        category: category_outcomes.as_deref().map(category::summarise),
        summary: summarise(&outcomes),
    };
    if let Some(outcomes) = &category_outcomes {
        let path = args.out.join("category.csv");
        std::fs::write(&path, category::instances_csv(outcomes)).with_context(|| format!("{}", path.display()))?;
    }
    let instances_path = args.out.join("instances.csv");
    std::fs::write(&instances_path, instances_csv(&outcomes))
        .with_context(|| format!("{}", instances_path.display()))?;
    if let Some(detection) = &report.detection {
        let path = args.out.join("detections.csv");
        std::fs::write(&path, detection::instances_csv(&detection.instances))
            .with_context(|| format!("{}", path.display()))?;
    }
    let summary_path = args.out.join("summary.json");
    std::fs::write(&summary_path, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("{}", summary_path.display()))?;
    print_report(&report, args.json, print_table)
}

/// The detector alone on the split's images (`--detect`), with the
/// parameters of the graph's (first) detector stage.
fn score_detector(args: &EvalArgs, graph: &Graph) -> anyhow::Result<detection::DetectionSummary> {
    let stage =
        graph.stages.values().find(|stage| stage.exe_name() == "detector").context("the graph has no detector")?;
    let params = poseflow_detector::DetectorParams::from_json(&stage.params)
        .with_context(|| format!("{}: the detector stage `{}`", args.graph_file().display(), stage.name))?;
    let mut detector = poseflow_detector::Detector::new(params).with_context(|| match args.detector_mode {
        DetectorMode::Network => format!("--detector-model {}", args.detector_model.display()),
        DetectorMode::Classical => "--detector-mode classical".to_string(),
    })?;
    detection::evaluate_split(&args.dataset.join(&args.split), &mut detector)
}

fn optional(value: Option<f64>, precision: usize) -> String {
    value.map_or("-".into(), |v| format!("{v:.precision$}"))
}

fn print_table(report: &EvalReport) {
    let s = &report.summary;
    let method = match &report.method {
        Method::Graph { selection, refine, samples, steps, time_grid, tracking_steps, rgb, .. } => format!(
            "selection {selection}{}, {samples} samples, {steps} steps{}{}{}; accuracies in % of instances{}",
            if *refine { " + refinement" } else { "" },
            match time_grid {
                TimeGrid::Uniform => "",
                TimeGrid::Quadratic => " on the quadratic time grid",
            },
            tracking_steps.map_or(String::new(), |k| format!(" ({k} when tracked)")),
            if *rgb { "" } else { ", no image (depth only)" },
            if *selection == "none" { ", averaged over the samples" } else { "" }
        ),
        Method::Results { results } => format!("{}; accuracies in % of instances", results.display()),
    };
    println!("{} ({}): {method}", report.dataset.display(), report.split);
    if report.symmetries == SymmetriesArg::Shape {
        println!("scored up to the shape's symmetries ({SHAPE_SYMMETRIES_FILE}), not the printed object's");
    }
    println!(
        "object  instances  estimated  5°2cm  5°5cm  10°2cm  10°5cm  ADD(-S)  MSSD  MSPD   VSD  modes  med rot °  ms/object p50/p99"
    );
    let row = |label: String, a: &summary::Accuracies, latency: (f64, f64)| {
        println!(
            "{label:>6}  {:>9}  {:>9}  {:>5.1}  {:>5.1}  {:>6.1}  {:>6.1}  {:>7.1}  {:>4.1}  {:>4.1}  {:>4}  {:>5}  {:>9}  {:>8.0}/{:.0}",
            a.instances,
            a.estimated,
            a.acc_5deg_2cm,
            a.acc_5deg_5cm,
            a.acc_10deg_2cm,
            a.acc_10deg_5cm,
            a.add_s,
            a.mssd_recall,
            a.mspd_recall,
            optional(a.vsd_recall, 1),
            optional(a.mode_recall, 0),
            optional(a.median_rotation_error_deg, 1),
            latency.0,
            latency.1
        );
    };
    for (obj_id, object) in &s.per_object {
        row(obj_id.to_string(), &object.accuracies, (object.ms_per_object.p50_ms, object.ms_per_object.p99_ms));
    }
    row("all".into(), &s.overall, (s.ms_per_object_p50, s.ms_per_object_p99));
    if s.overall.tracked > 0 {
        println!(
            "tracked (started from an earlier estimate or a prior): {} of {}",
            s.overall.tracked, s.overall.estimated
        );
    }
    println!(
        "distribution: coverage 10°5cm {:.1} %, 5°5cm {:.1} %; spread max (folded) median {}°; selected rotation error within 1× / 2× spread: {} / {} %; Spearman(spread max, error) = {}",
        s.overall.coverage_10deg_5cm,
        s.overall.coverage_5deg_5cm,
        optional(s.overall.median_rotation_spread_max_deg, 2),
        optional(s.overall.within_1_spread, 1),
        optional(s.overall.within_2_spread, 1),
        optional(s.spread_max_error_spearman, 2),
    );
    println!(
        "calibration: Spearman(reported spread √trace, rotation error) = {}; latency image read → estimate p50/p99 {:.0}/{:.0} ms (queueing included); unmatched estimates: {}",
        optional(s.spread_error_spearman, 2),
        s.latency.p50_ms,
        s.latency.p99_ms,
        report.unmatched_estimates
    );
    if let Some(ar) = s.overall.bop_ar {
        println!("BOP19 average recall (VSD, MSSD, MSPD): {ar:.1}");
    }
    if let Method::Graph { .. } = report.method {
        println!("BOP19 results: {}", report.csv.display());
    }
    if let Some(d) = &report.detection {
        print_detection(d);
    }
    if let Some(c) = &report.category {
        category::print(c);
    }
    for video in &report.videos {
        println!(
            "\nscene {} as a video of {} images: 5°5cm {:.1} %, 10°5cm {:.1} % of object-images",
            video.scene_id, video.frames, video.acc_5deg_5cm, video.acc_10deg_5cm
        );
        tracking::print_video(video);
    }
    if let Some(per_image) = &report.per_image {
        println!("per image: {}", per_image.display());
    }
}

fn print_detection(d: &detection::DetectionSummary) {
    println!(
        "\ndetector on the same {} images (masks against the annotated visible masks; instances under 10 % visible ignored):",
        d.images
    );
    println!("object  instances  detections  AP50 %  mask IoU %  found %");
    for (obj_id, o) in &d.per_object {
        println!(
            "{obj_id:>6}  {:>9}  {:>10}  {:>6}  {:>10}  {:>7}",
            o.instances,
            o.detections,
            optional(o.ap50, 1),
            optional(o.mask_iou, 1),
            optional(o.found, 1)
        );
    }
    println!(
        "{:>6}  {:>9}  {:>10}  {:>6}  {:>10}  {:>7}",
        "mean",
        "",
        "",
        optional(d.ap50, 1),
        optional(d.mask_iou, 1),
        ""
    );
    println!(
        "found (a detection of the object at mask IoU >= {}): {} % of the {} instances",
        detection::MATCH_IOU,
        optional(d.found, 1),
        d.per_object.values().map(|o| o.instances).sum::<usize>()
    );
    println!("detector ms per image p50/p99 {:.1}/{:.1} (in this process)", d.ms_p50, d.ms_p99);
}
