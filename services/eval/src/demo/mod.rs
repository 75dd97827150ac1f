//! `poseflow demo`: renders a scene of the vendored objects, runs the
//! estimation graph on it as processes, and reports each object's selected
//! pose against the ground truth, with pictures.

pub(crate) mod graph;
mod pictures;
mod tracking;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use poseflow_contracts::{EstimateHeader, HypothesesHeader, POSE_LEN};
use poseflow_geometry::Pose;
use poseflow_geometry::flow::TimeGrid;
use poseflow_graph::Graph;
use poseflow_runtime::recording::{RecordingReader, header_from_bytes};
use poseflow_scene::bop::{CameraEntry, GtEntry, SceneDir, read_json, read_rgb_png};
use poseflow_scene::camera_path::CameraPath;
use poseflow_scene::dataset::{RenderSpec, YCBV_DISTANCE, lmo_camera, write_dataset, ycbv_camera};
use poseflow_scene::scene::{Occlusion, SceneStyle, ViewRange};
use poseflow_scene::sensor::SensorModel;
use poseflow_scene::video::VideoEvents;
use poseflow_scene::{DepthNoise, ModelLibrary};
use serde::Serialize;

use self::graph::{Overrides, graph_with_overrides};
use self::pictures::{Outlined, SamplePanel, mollweide_panels, overlay};
use crate::SymmetriesArg;

/// Rotation steps of continuous symmetries in the reported errors.
const SYMMETRY_STEP_DEG: f64 = 1.0;
/// Hypotheses outlined per object.
const OUTLINED_HYPOTHESES: usize = 5;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SelectionArg {
    None,
    ModelFree,
    Chamfer,
    Sdf,
}

impl SelectionArg {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::ModelFree => "model-free",
            Self::Chamfer => "chamfer",
            Self::Sdf => "sdf",
        }
    }
}

/// Where the sampler's Euler steps ask for the velocity (the sampler's
/// `time_grid`, `poseflow_geometry::flow::TimeGrid`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TimeGridArg {
    /// t = k/K: the paper's.
    Uniform,
    /// t = 1 − (1 − k/K)²: the last step starts nearer t = 1.
    Quadratic,
}

impl From<TimeGridArg> for TimeGrid {
    fn from(arg: TimeGridArg) -> Self {
        match arg {
            TimeGridArg::Uniform => TimeGrid::Uniform,
            TimeGridArg::Quadratic => TimeGrid::Quadratic,
        }
    }
}

/// How the detector stage finds the objects (`--detect`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DetectorMode {
    /// The learned RGB-D segmentation network (`--detector-model`).
    Network,
    /// No training: the support plane removed, the depth clustered, each cluster identified by fitting the
    /// objects' meshes.
    Classical,
}

impl DetectorMode {
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Network => "network",
            Self::Classical => "classical",
        }
    }
}

/// How a set's scenes are rendered: as its model saw them in training.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Look {
    /// LM-O's camera, plain depth noise, one-coloured support.
    Plain,
    /// The YCB-V camera at 0.6–1.6 m, every sensor effect of docs/datasets.md, textured table and backdrop.
    RealCamera,
}

/// A vendored object set `--objects` knows by name.
struct ObjectSet {
    name: &'static str,
    objects: &'static str,
    model: &'static str,
    look: Look,
    /// What its renders can show: the vendored YCB-V meshes have no print, so a box turned end over end looks
    /// the same.
    symmetries: SymmetriesArg,
}

const OBJECT_SETS: [ObjectSet; 2] = [
    ObjectSet {
        name: "lmo",
        objects: "objects/lmo",
        model: "models/poseflow-lmo10",
        look: Look::Plain,
        symmetries: SymmetriesArg::ModelsInfo,
    },
    ObjectSet {
        name: "ycbv",
        objects: "objects/ycbv/models",
        model: "models/poseflow-ycbv",
        look: Look::RealCamera,
        symmetries: SymmetriesArg::Shape,
    },
];

/// `--objects`, `--model` and `--symmetries` resolved against [`OBJECT_SETS`].
struct Setup {
    objects: PathBuf,
    model: PathBuf,
    look: Look,
    symmetries: SymmetriesArg,
}

impl Setup {
    fn of(args: &DemoArgs) -> anyhow::Result<Self> {
        let set = OBJECT_SETS.iter().find(|set| set.name == args.objects);
        if set.is_none() && !Path::new(&args.objects).is_dir() {
            let names: Vec<&str> = OBJECT_SETS.iter().map(|set| set.name).collect();
            bail!("--objects {}: expected a known set ({}) or a BOP models directory", args.objects, names.join(", "));
        }
        let default_set = &OBJECT_SETS[0];
        Ok(Self {
            objects: set.map_or_else(|| PathBuf::from(&args.objects), |set| PathBuf::from(set.objects)),
            model: args.model.clone().unwrap_or_else(|| PathBuf::from(set.unwrap_or(default_set).model)),
            look: set.map_or(Look::Plain, |set| set.look),
            symmetries: args.symmetries.unwrap_or(set.map_or(SymmetriesArg::ModelsInfo, |set| set.symmetries)),
        })
    }
}

#[derive(Debug, Args)]
#[command(after_help = "Run from the repository root after `cargo build --release --workspace` (the stages are \
    separate executables). Writes <out>/scene (the rendered BOP scene), <out>/estimation.toml (the graph run), \
    <out>/estimation.rec (its hypotheses and estimates), <out>/overlay.png (outlines: green = selected pose, \
    orange = hypotheses) and <out>/mollweide.png (one panel per object, top to bottom in the table's order: \
    rotation samples coloured by tilt, the ground truth as a ring).\n\n\
    With --track: <out>/scene (the rendered video), <out>/tracking.toml, <out>/tracking.rec (its estimates) and \
    <out>/tracking.png (rotation error per image, 0–20°, one colour per object, grey lines at 5° and 10°).\n\n\
    Examples:\n  poseflow demo\n  poseflow demo --track\n  poseflow demo --track --graph deploy/estimation.toml \
    --out target/demo-per-image   (the same video estimated image by image)\n  poseflow demo --objects ycbv   \
    (the 21 YCB-V objects with models/poseflow-ycbv)\n  poseflow demo --objects my-objects --model models/mine")]
pub struct DemoArgs {
    /// Output folder.
    #[arg(long, default_value = "target/demo")]
    pub out: PathBuf,
    /// Seed of the rendered scene.
    #[arg(long, default_value_t = 3)]
    pub seed: u64,
    /// The objects to render and score: `lmo` (objects/lmo: three LM-O objects, with models/poseflow-lmo10), `ycbv`
    /// (objects/ycbv/models: the 21 YCB-V objects, with models/poseflow-ycbv, seen by the YCB-V camera with every
    /// sensor effect on textured surroundings, scored up to the shape's symmetries), or a BOP models directory
    /// (rendered as lmo is; write ./lmo for a folder of that name).
    #[arg(long, default_value = "lmo", value_name = "SET|DIR")]
    pub objects: String,
    /// Model directory (encoder.onnx, velocity.onnx) [default: the set's model; models/poseflow-lmo10 for a
    /// directory].
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The symmetries the errors are scored up to: `models-info` (models_info.json, the printed object's) or
    /// `shape` (models_info_shape.json, what a one-coloured render can show) [default: shape for ycbv, else
    /// models-info].
    #[arg(long, value_enum)]
    pub symmetries: Option<SymmetriesArg>,
    /// The graph to run [default: deploy/estimation.toml, with --track deploy/tracking.toml; with --detect
    /// their -detect twins].
    #[arg(long)]
    pub graph: Option<PathBuf>,
    /// Find the objects with the detector stage (models/detector-lmo10) instead of the rendered ground-truth
    /// masks.
    #[arg(long)]
    pub detect: bool,
    /// How the detector finds the objects, with --detect.
    #[arg(long, value_enum, default_value_t = DetectorMode::Network)]
    pub detector_mode: DetectorMode,
    /// How the selector chooses the pose.
    #[arg(long, value_enum, default_value_t = SelectionArg::Sdf)]
    pub selection: SelectionArg,
    /// Skip the refinement of the kept hypotheses.
    #[arg(long)]
    pub no_refine: bool,
    /// Pose samples per object.
    #[arg(long, default_value_t = 50)]
    pub samples: usize,
    /// Euler steps.
    #[arg(long, default_value_t = 5)]
    pub steps: usize,
    /// Where the Euler steps ask for the velocity: `quadratic` ends nearer t = 1, sharper samples but a
    /// narrower spread where the view is ambiguous (docs/distributions.md) [default: the graph's, uniform].
    #[arg(long, value_enum)]
    pub time_grid: Option<TimeGridArg>,
    /// Tracking: render a video (the camera orbits the scene) and run the tracking graph over it, each
    /// estimate seeding the next frame; reports accuracy over the sequence.
    #[arg(long)]
    pub track: bool,
    /// With --track: images in the video.
    #[arg(long, default_value_t = 120)]
    pub frames: u32,
    /// With --track: degrees of camera azimuth per image.
    #[arg(long, default_value_t = 1.0)]
    pub orbit_step_deg: f64,
    /// With --track: occlusion events in the video (an object fully hidden for 5-20 images by a sliding box).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub occlusions: u32,
    /// With --track: teleports in the video (an object turned 90-180° and shifted up to 5 cm between two images).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub teleports: u32,
    /// With --track: frames per second the frame source plays the video at (a camera's pace; a faster pace than
    /// the graph keeps up with shows as growing latency).
    #[arg(long, default_value_t = 5.0)]
    pub rate_hz: f64,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// One object's result.
#[derive(Debug, Serialize)]
struct ObjectReport {
    obj_id: u32,
    /// Selected pose: R row-major, t in metres (camera frame).
    rotation: [f64; 9],
    translation_m: [f64; 3],
    rotation_error_deg: f64,
    translation_error_cm: f64,
    /// √(trace Σ) of the kept hypotheses: rotation (degrees), translation (cm).
    rotation_spread_deg: f64,
    translation_spread_cm: f64,
    /// The largest rotational standard deviation of the kept hypotheses,
    /// folded by the object's symmetries (degrees; `poseflow eval`'s
    /// `rotation_spread_max_deg`): a symmetry is not uncertainty.
    rotation_spread_max_deg: f64,
    modes: u32,
    kept: u32,
    hypotheses: u32,
    /// Share of samples within 10° and 5 cm of the ground truth.
    samples_within_10deg_5cm: f64,
}

#[derive(Debug, Serialize)]
struct Report {
    out: PathBuf,
    selection: &'static str,
    refined: bool,
    /// The symmetries the errors were scored up to.
    symmetries: SymmetriesArg,
    objects: Vec<ObjectReport>,
    overlay: PathBuf,
    mollweide: PathBuf,
}

/// What the graph recorded for one object in one frame.
pub(crate) struct Recorded {
    pub estimate: EstimateHeader,
    /// The sampler's hypotheses, in sample order.
    pub hypotheses: Vec<Pose>,
    /// The hypotheses the selector kept, best first.
    pub kept: Vec<Pose>,
}

fn poses(payload: &[f32], stride: usize) -> anyhow::Result<Vec<Pose>> {
    payload
        .chunks_exact(stride)
        .map(|c| Pose::from_f32_row_major(c[..POSE_LEN].try_into().expect("12 values")).map_err(Into::into))
        .collect()
}

/// The estimates of a recording in the order they were recorded, each with
/// the hypotheses of its frame and object (empty when they were not
/// recorded).
pub(crate) fn read_recording(path: &Path) -> anyhow::Result<Vec<Recorded>> {
    let mut reader = RecordingReader::open(path).with_context(|| format!("{}", path.display()))?;
    let mut estimates = Vec::new();
    let mut hypotheses = std::collections::HashMap::new();
    while let Some(message) = reader.next_message()? {
        match message.edge.as_str() {
            "estimates" => {
                let header: EstimateHeader = header_from_bytes(&message.header).context("estimate header")?;
                let scored = crate::estimates::scored_hypotheses(&header, &message.payload)?;
                let kept = scored.into_iter().take(header.kept_count as usize).map(|(pose, _)| pose).collect();
                estimates.push((header, kept));
            }
            "hypotheses" => {
                let header: HypothesesHeader = header_from_bytes(&message.header).context("hypotheses header")?;
                let key = (header.header.frame_id, header.header.object_id);
                hypotheses.insert(key, poses(&message.payload, POSE_LEN)?);
            }
            _ => {}
        }
    }
    Ok(estimates
        .into_iter()
        .map(|(estimate, kept)| {
            let key = (estimate.header.frame_id, estimate.header.object_id);
            Recorded { hypotheses: hypotheses.remove(&key).unwrap_or_default(), kept, estimate }
        })
        .collect())
}

/// Renders one scene of `frames` images (independent views, or an orbit of
/// `orbit_step_deg` per image) as the `test` split of a BOP dataset.
fn render_scene(
    library: &ModelLibrary,
    seed: u64,
    look: Look,
    frames: u32,
    path: CameraPath,
    out: &Path,
) -> anyhow::Result<()> {
    let plain = look == Look::Plain;
    let spec = RenderSpec {
        split: "test".into(),
        first_scene: 0,
        scenes: 1,
        frames_per_scene: frames,
        seed,
        occlusion: Occlusion::Medium,
        camera: if plain { lmo_camera(640, 480) } else { ycbv_camera(640, 480) },
        views: if plain { ViewRange::default() } else { ViewRange { distance: YCBV_DISTANCE, ..ViewRange::default() } },
        path,
        depth_noise: plain.then(DepthNoise::default),
        rgb_noise: if plain { 2.0 } else { 0.0 },
        sensor: (!plain).then(SensorModel::default),
        style: SceneStyle { textured: !plain, ..SceneStyle::default() },
        condition: None,
    };
    write_dataset(library, &spec, out, |_| {}).with_context(|| format!("{}: cannot write the scene", out.display()))
}

/// Runs `graph` as processes, recording `edges` to `recording`; the
/// stages' log goes to `graph.log` and the run's report (`poseflow run
/// --json`: per stage messages in and out, drops, errors) to `run.json`
/// beside the recording, and `waiting` is called every few hundred
/// milliseconds while the graph runs.
pub(crate) fn run_graph(graph: &Graph, recording: &Path, edges: &str, waiting: impl FnMut()) -> anyhow::Result<()> {
    let log_path = recording.with_file_name("graph.log");
    let report_path = recording.with_file_name("run.json");
    // A recording left by an earlier run in the same folder would show as
    // progress until the new run truncates it.
    match std::fs::remove_file(recording) {
        Err(err) if err.kind() != std::io::ErrorKind::NotFound => {
            return Err(err).with_context(|| format!("{}: cannot remove the old recording", recording.display()));
        }
        _ => {}
    }
    let edges: Vec<String> = edges.split(',').map(str::to_string).collect();
    let options = poseflow_launch::LaunchOptions {
        instance: poseflow_launch::default_instance(graph),
        record: Some((recording.to_path_buf(), poseflow_launch::chosen_edges(graph, &edges)?)),
        ..Default::default()
    };
    let launched = poseflow_launch::launch_quietly(graph, &options, &poseflow_stages::registry(), &log_path, waiting);
    let failure = match &launched {
        Ok(report) => {
            let json = serde_json::to_string_pretty(&report.to_json())?;
            std::fs::write(&report_path, json).with_context(|| format!("{}: cannot write", report_path.display()))?;
            report.failed().then(|| "a stage failed".to_string())
        }
        Err(err) => Some(poseflow_runtime::error_chain(err)),
    };
    if let Some(failure) = failure {
        const TAIL_LINES: usize = 30;
        let log = std::fs::read_to_string(&log_path).unwrap_or_default();
        let lines: Vec<&str> = log.lines().collect();
        let tail = lines[lines.len().saturating_sub(TAIL_LINES)..].join("\n");
        bail!(
            "the graph {} failed ({failure}); the end of its log ({}):\n{tail}\n(build every stage first: cargo build --release --workspace)",
            graph.file.display(),
            log_path.display(),
        );
    }
    Ok(())
}

/// The ground-truth `camera_from_object` poses of every image of scene 0 of
/// the rendered `test` split, by image id.
pub(crate) fn ground_truth(dataset: &Path) -> anyhow::Result<BTreeMap<u32, Vec<(u32, Pose)>>> {
    let scene = SceneDir::new(&dataset.join("test"), 0);
    let gt: BTreeMap<u32, Vec<GtEntry>> = read_json(&scene.scene_gt())?;
    gt.into_iter()
        .map(|(im_id, entries)| {
            let poses = entries
                .iter()
                .enumerate()
                .map(|(i, entry)| Ok((entry.obj_id, entry.pose(&scene.scene_gt(), im_id, i)?)))
                .collect::<anyhow::Result<_>>()?;
            Ok((im_id, poses))
        })
        .collect()
}

/// Renders the scene, writes the graph with the demo's overrides and runs
/// it: the shared first half of both demos. Returns the recording's path.
fn render_and_run(
    args: &DemoArgs,
    setup: &Setup,
    library: &ModelLibrary,
    scene: (u32, CameraPath),
    graph_file: &Path,
    edges: &str,
) -> anyhow::Result<PathBuf> {
    std::fs::create_dir_all(&args.out).with_context(|| format!("--out {}", args.out.display()))?;
    let dataset = args.out.join("scene");
    render_scene(library, args.seed, setup.look, scene.0, scene.1, &dataset)?;
    let overrides = Overrides {
        dataset: &dataset,
        split: "test",
        targets: None,
        model: &setup.model,
        object_models: &setup.objects,
        selection: args.selection.name(),
        refine: !args.no_refine,
        samples: args.samples,
        steps: args.steps,
        time_grid: args.time_grid.map(TimeGrid::from),
        tracking_steps: None,
        rate_hz: args.track.then_some(args.rate_hz),
        rgb: true,
        detector_model: None,
        detector_mode: Some(args.detector_mode),
        detector_objects: Some(library.objects.iter().map(|o| o.obj_id).collect()),
        classes: None,
    };
    let name = graph_file.file_name().map_or("graph.toml".into(), |n| n.to_string_lossy().into_owned());
    let graph = args.out.join(name);
    let run = graph_with_overrides(graph_file, &overrides)?;
    std::fs::write(&graph, run.to_toml()?).with_context(|| format!("{}", graph.display()))?;
    let recording = graph.with_extension("rec");
    run_graph(&run, &recording, edges, || {})?;
    Ok(recording)
}

fn check(args: &DemoArgs) -> anyhow::Result<()> {
    if args.samples == 0 || args.steps == 0 {
        bail!("--samples {} --steps {}: expected at least 1 of each", args.samples, args.steps);
    }
    if args.track {
        if args.frames < 2 {
            bail!("--frames {}: expected at least 2 images to track over", args.frames);
        }
        if !(args.orbit_step_deg.is_finite() && args.orbit_step_deg.abs() <= 90.0) {
            bail!("--orbit-step-deg {}: expected degrees per image within ±90", args.orbit_step_deg);
        }
        if !(args.rate_hz.is_finite() && args.rate_hz > 0.0) {
            bail!("--rate-hz {}: expected frames per second > 0", args.rate_hz);
        }
    } else if args.occlusions > 0 || args.teleports > 0 {
        bail!(
            "--occlusions {} --teleports {}: events happen in the video; add --track",
            args.occlusions,
            args.teleports
        );
    }
    Ok(())
}

/// `deploy/<name>.toml`, or its detecting twin.
fn default_graph(name: &str, detect: bool) -> PathBuf {
    PathBuf::from(format!("deploy/{name}{}.toml", if detect { "-detect" } else { "" }))
}

pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    check(args)?;
    let setup = Setup::of(args)?;
    let library = ModelLibrary::load(&setup.objects, &[])
        .with_context(|| format!("--objects {}: cannot load the object models", setup.objects.display()))?;
    let symmetries = crate::object_symmetries(&library, setup.symmetries, SYMMETRY_STEP_DEG.to_radians())?;
    if args.track {
        let graph = args.graph.clone().unwrap_or_else(|| default_graph("tracking", args.detect));
        let events = VideoEvents { occlusions: args.occlusions, teleports: args.teleports };
        let path = CameraPath::Orbit { step_deg: args.orbit_step_deg, events };
        let recording = render_and_run(args, &setup, &library, (args.frames, path), &graph, "estimates")?;
        return tracking::report(args, &symmetries, setup.symmetries, &recording);
    }
    let graph = args.graph.clone().unwrap_or_else(|| default_graph("estimation", args.detect));
    let recording = render_and_run(args, &setup, &library, (1, CameraPath::Random), &graph, "hypotheses,estimates")?;
    let recorded = read_recording(&recording)?;

    let dataset = args.out.join("scene");
    let scene = SceneDir::new(&dataset.join("test"), 0);
    let truths = ground_truth(&dataset)?.remove(&0).unwrap_or_default();
    let cameras: BTreeMap<String, CameraEntry> = read_json(&scene.scene_camera())?;
    let rgb = read_rgb_png(&scene.rgb(0))?;
    let camera = cameras["0"].camera(rgb.width, rgb.height, &scene.scene_camera(), 0)?;

    let mut objects = Vec::new();
    let mut outlined = Vec::new();
    let mut panels = Vec::new();
    for entry in &recorded {
        let estimate = &entry.estimate;
        let obj_id = estimate.header.object_id;
        let Some((_, truth)) = truths.iter().find(|(id, _)| *id == obj_id) else { continue };
        let object = library.objects.iter().find(|o| o.obj_id == obj_id).context("an object of the scene")?;
        let symmetries = symmetries.get(&obj_id).context("an object of the scene")?;
        let best = Pose::from_f32_row_major(&estimate.best)?;
        let error = symmetries.pose_error(&best, truth);
        let within = entry
            .hypotheses
            .iter()
            .filter(|p| {
                let e = symmetries.pose_error(p, truth);
                e.rotation.to_degrees() < 10.0 && e.translation < 0.05
            })
            .count();
        let kept: Vec<_> = entry.kept.iter().map(|p| p.rotation).collect();
        let rotation_spread_max_deg = symmetries
            .folded_max_rotation_std(&kept, &best.rotation)
            .with_context(|| format!("object {obj_id}: the spread of its kept hypotheses"))?
            .to_degrees();
        let c = &estimate.covariance;
        let rotation_trace = f64::from(estimate.rotation_trace);
        let translation_trace = f64::from(c[0] + c[7] + c[14]);
        objects.push(ObjectReport {
            obj_id,
            rotation: std::array::from_fn(|i| best.rotation.matrix()[(i / 3, i % 3)]),
            translation_m: [best.translation.x, best.translation.y, best.translation.z],
            rotation_error_deg: error.rotation.to_degrees(),
            translation_error_cm: error.translation * 100.0,
            rotation_spread_deg: rotation_trace.max(0.0).sqrt().to_degrees(),
            translation_spread_cm: translation_trace.max(0.0).sqrt() * 100.0,
            rotation_spread_max_deg,
            modes: estimate.mode_count,
            kept: estimate.kept_count,
            hypotheses: estimate.hypothesis_count,
            samples_within_10deg_5cm: within as f64 / entry.hypotheses.len().max(1) as f64,
        });
        outlined.push(Outlined {
            obj_id,
            model: &object.model,
            selected: best,
            hypotheses: entry.hypotheses.iter().take(OUTLINED_HYPOTHESES).copied().collect(),
        });
        panels.push(SamplePanel { obj_id, samples: &entry.hypotheses, truth: *truth });
    }
    if objects.is_empty() {
        bail!("the graph produced no estimate for the scene's objects (see {})", recording.display());
    }
    let overlay_path = args.out.join("overlay.png");
    overlay(&rgb, &camera, &outlined, &overlay_path)?;
    let mollweide_path = args.out.join("mollweide.png");
    mollweide_panels(&panels, &mollweide_path)?;
    let report = Report {
        out: args.out.clone(),
        selection: args.selection.name(),
        refined: !args.no_refine,
        symmetries: setup.symmetries,
        objects,
        overlay: overlay_path,
        mollweide: mollweide_path,
    };
    print_report(&report, args.json, print_table)
}

/// How the table names a scoring up to the shape's symmetries.
pub(crate) fn symmetries_note(symmetries: SymmetriesArg) -> &'static str {
    match symmetries {
        SymmetriesArg::ModelsInfo => "",
        SymmetriesArg::Shape => " (the shape's, models_info_shape.json: the renders show no print)",
    }
}

/// Prints `report` as one JSON object, or as the text `table` writes.
pub(crate) fn print_report<R: Serialize>(report: &R, json: bool, table: impl Fn(&R)) -> anyhow::Result<()> {
    if json {
        println!("{}", serde_json::to_string(report)?);
    } else {
        table(report);
    }
    Ok(())
}

fn print_table(report: &Report) {
    println!(
        "selection {}{}; errors against the ground truth and rotation spread (largest std of the kept hypotheses) \
         folded by the object's symmetries{}; translation spread = √trace of their covariance",
        report.selection,
        if report.refined { " + refinement" } else { "" },
        symmetries_note(report.symmetries)
    );
    println!(
        "object  t (m)                    rot err °  trans err cm  rot spread °  trans spread cm  modes  samples ≤10°5cm"
    );
    for o in &report.objects {
        println!(
            "{:>6}  [{:+.3}, {:+.3}, {:+.3}]  {:>9.1}  {:>12.2}  {:>12.1}  {:>15.2}  {:>5}  {:>14.0} %",
            o.obj_id,
            o.translation_m[0],
            o.translation_m[1],
            o.translation_m[2],
            o.rotation_error_deg,
            o.translation_error_cm,
            o.rotation_spread_max_deg,
            o.translation_spread_cm,
            o.modes,
            100.0 * o.samples_within_10deg_5cm
        );
    }
    println!("pictures: {} and {}", report.overlay.display(), report.mollweide.display());
}
