//! `poseflow bench pipeline`: frames per second and per-frame latency of
//! the estimation and tracking graphs, through the process graph and in
//! one process, on the default model and a rendered sequence (`--objects`
//! objects occluding each other, one by default; an orbiting camera; every
//! frame rendered before the first is sent).
//!
//! Per mode (estimation, tracking):
//! 1. **in-process**: the graph's stages between its frame source and its
//!    estimates as threads of this process, built by the same
//!    registrations, one frame at a time (the baseline: no transport, no
//!    pipelining across frames);
//! 2. **graph, saturated**: `poseflow run` with the frame source as fast as
//!    the graph accepts: frames per second, stages overlapping across
//!    frames;
//! 3. **graph, paced**: the frame source at `--latency-load` × the
//!    in-process frame rate, so frames rarely overlap: the per-frame
//!    latency and per-stage process times;
//! 4. **in-process, paced**: the pipeline at the same rate, the latency the
//!    graph's is compared with (idle time between frames costs both: caches
//!    and the network's thread pool go cold).
//!
//! Reported: `fps` of the graph from 2, of in-process from 1; `p50_ms`,
//! `p99_ms` of both from the paced runs (3, 4). With `--paced-rounds R`,
//! 4 and 3 run R times in turn and their frames are pooled, so that a host
//! whose speed drifts over minutes slows both sides alike.

mod graph;
mod in_process;

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Args, ValueEnum};
use poseflow_ingest::sources::LoadedFrame;
use serde::Serialize;
use serde_json::json;

use super::graph_run::{GraphRun, GraphRunOptions, Scratch};
use graph::{GraphRunFigures, StageLatency};
use poseflow_runtime::timing::Timing;

#[derive(Debug, Args)]
pub struct PipelineArgs {
    /// The estimation graph.
    #[arg(long, default_value = "deploy/estimation.toml")]
    pub estimation_graph: PathBuf,

    /// The tracking graph.
    #[arg(long, default_value = "deploy/tracking.toml")]
    pub tracking_graph: PathBuf,

    /// Measure the graphs with the detector stage between the frame source and ingest
    /// (deploy/estimation-detect.toml, deploy/tracking-detect.toml) where the graph options were left at
    /// their defaults; the detector reports only the sequence's objects.
    #[arg(long)]
    pub detect: bool,

    /// What to measure (comma-separated).
    #[arg(long, value_delimiter = ',', default_values = ["estimation", "tracking"])]
    pub modes: Vec<Mode>,

    /// Frames of the rendered sequence.
    #[arg(long, default_value_t = 110)]
    pub frames: u32,

    /// Leading frames run but not counted (model warm-up, signed distance
    /// grids, stages still connecting).
    #[arg(long, default_value_t = 10)]
    pub warmup: u32,

    /// The object in every frame (BOP id of the models in `--models`); with
    /// `--objects N` > 1, the first of them.
    #[arg(long, default_value_t = 1)]
    pub object: u32,

    /// Objects per frame: `--object` and the next N − 1 ids of `--models`
    /// (all eight LM-O objects of the default model with N = 8), placed
    /// at random so that they occlude each other.
    #[arg(long, default_value_t = 1)]
    pub objects: usize,

    /// BOP models directory the sequence is rendered from (and the
    /// selector's models) [default: objects/lmo for one object,
    /// objects/lmo8 (the eight LM-O objects) for more].
    #[arg(long)]
    pub models: Option<PathBuf>,

    /// Camera orbit per frame, degrees (a video: tracking follows it).
    #[arg(long, default_value_t = 2.0)]
    pub orbit_step_deg: f64,

    /// Seed of the rendered scene.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,

    /// The paced runs send frames at this share of the in-process frame
    /// rate (0 < load ≤ 1).
    #[arg(long, default_value_t = 0.5)]
    pub latency_load: f64,

    /// Paced in-process and graph runs, in turn, whose frames are pooled
    /// for the latency comparison: more than 1 evens out a host whose speed
    /// drifts between the two (one run each moved the tracking graph's
    /// overhead between −8 and +14 % on a 2-core VM).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=20))]
    pub paced_rounds: u32,

    /// The edge of Estimates that is recorded.
    #[arg(long, default_value = "estimates")]
    pub estimates_edge: String,

    #[command(flatten)]
    pub run: GraphRunOptions,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Mode {
    Estimation,
    Tracking,
}

impl Mode {
    fn name(self) -> &'static str {
        match self {
            Mode::Estimation => "estimation",
            Mode::Tracking => "tracking",
        }
    }
}

/// Per counted frame: its id, the estimates it produced, its latency.
#[derive(Debug, Default)]
pub(super) struct FrameLatencies {
    frames: Vec<(u64, usize, Duration)>,
}

impl FrameLatencies {
    /// Adds another run's frames.
    fn extend(&mut self, other: FrameLatencies) {
        self.frames.extend(other.frames);
    }

    fn record(&mut self, frame_id: u64, estimates: usize, latency: Duration) {
        self.frames.push((frame_id, estimates, latency));
    }

    /// Frames with at least one estimate.
    fn estimated(&self) -> usize {
        self.frames.iter().filter(|f| f.1 > 0).count()
    }

    fn estimates(&self) -> usize {
        self.frames.iter().map(|f| f.1).sum()
    }

    fn timing(&self) -> Timing {
        Timing::of(self.frames.iter().filter(|f| f.1 > 0).map(|f| f.2).collect())
    }
}

/// The counted Estimates by the track check's verdict in their header
/// ([`poseflow_contracts::flags`]): what each object's next frame costs
/// the tracking sampler (one Euler step for a tracked object, the prior's
/// K steps for all of a lost one's samples and part of an unsure one's).
/// A graph without the check reports every estimate under `unflagged`.
/// Beside the verdicts, `network_skipped` counts the estimates of any
/// verdict that no network looked at (a held track between its network
/// passes, [`poseflow_contracts::flags::NETWORK_SKIPPED`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub(super) struct VerdictCounts {
    pub unflagged: usize,
    pub unsure: usize,
    pub lost: usize,
    pub reinitialised: usize,
    pub network_skipped: usize,
}

impl VerdictCounts {
    pub(super) fn count(&mut self, flags: u32) {
        use poseflow_contracts::flags::{LOST, NETWORK_SKIPPED, REINITIALISED, UNSURE};
        if flags & NETWORK_SKIPPED != 0 {
            self.network_skipped += 1;
        }
        let counter = if flags & LOST != 0 {
            &mut self.lost
        } else if flags & UNSURE != 0 {
            &mut self.unsure
        } else if flags & REINITIALISED != 0 {
            &mut self.reinitialised
        } else {
            &mut self.unflagged
        };
        *counter += 1;
    }
}

/// One configuration's figures, as `--json` reports them.
#[derive(Debug, Clone, Serialize)]
struct Figures {
    fps: f64,
    p50_ms: f64,
    p99_ms: f64,
    mean_ms: f64,
    /// Counted frames with an estimate, of `expected_frames`.
    frames: usize,
    expected_frames: usize,
    estimates: usize,
}

impl Figures {
    fn new(fps: f64, latencies: &FrameLatencies, expected_frames: usize) -> Self {
        let timing = latencies.timing();
        Self {
            fps,
            p50_ms: timing.p50_ms,
            p99_ms: timing.p99_ms,
            mean_ms: timing.mean_ms,
            frames: latencies.estimated(),
            expected_frames,
            estimates: latencies.estimates(),
        }
    }
}

/// Everything measured for one mode.
#[derive(Debug)]
struct ModeFigures {
    /// fps back to back, latency paced as the graph's.
    in_process: Figures,
    /// Frames back to back: fps and latency without idle time between.
    back_to_back: Figures,
    in_process_stages: serde_json::Value,
    /// fps from the saturated run, latency from the paced run.
    graph: Figures,
    saturated: Figures,
    paced_hz: f64,
    /// Paced runs of each kind whose frames are pooled.
    paced_rounds: u32,
    /// The saturated run's estimates by verdict.
    verdicts: VerdictCounts,
    stages: std::collections::BTreeMap<String, StageLatency>,
    /// The paced run's path intervals, milliseconds.
    path: serde_json::Value,
    restarts: u64,
    errors: u64,
}

pub fn run(args: &PipelineArgs) -> anyhow::Result<()> {
    if args.frames <= args.warmup + 1 {
        anyhow::bail!("--frames {}: expected more than --warmup + 1 ({})", args.frames, args.warmup + 1);
    }
    if !(args.latency_load > 0.0 && args.latency_load <= 1.0) {
        anyhow::bail!("--latency-load {}: expected a share in (0, 1]", args.latency_load);
    }
    sequence_objects(args)?;
    let scratch = Scratch::new(args.run.out.as_deref(), "bench-pipeline")?;
    let mut measured = Vec::new();
    for &mode in &args.modes {
        tracing::info!(mode = mode.name(), "measuring");
        measured.push((mode, measure_mode(args, mode, &scratch)?));
    }
    let report = report(args, &measured);
    if args.run.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", table(&measured));
    }
    scratch.finish();
    Ok(())
}

/// The models directory of the sequence.
fn models_dir(args: &PipelineArgs) -> PathBuf {
    args.models.clone().unwrap_or_else(|| PathBuf::from(if args.objects > 1 { "objects/lmo8" } else { "objects/lmo" }))
}

/// The objects of every frame: `--object`, then the next ids of the models
/// directory (`models_info.json` entries with a model file), up to `--objects`.
fn sequence_objects(args: &PipelineArgs) -> anyhow::Result<Vec<u32>> {
    let models = models_dir(args);
    if args.objects == 0 {
        anyhow::bail!("--objects 0: expected at least 1");
    }
    let info_path = models.join("models_info.json");
    let info = poseflow_geometry::models_info::ModelsInfo::from_path(&info_path)
        .with_context(|| format!("--models {}: reading {}", models.display(), info_path.display()))?;
    let available: Vec<u32> =
        info.objects.keys().copied().filter(|&id| models.join(poseflow_scene::model_file_name(id)).is_file()).collect();
    if !available.contains(&args.object) {
        anyhow::bail!("--object {}: {} has no such model (it has {available:?})", args.object, models.display());
    }
    let objects: Vec<u32> = std::iter::once(args.object)
        .chain(available.iter().copied().filter(|&id| id > args.object))
        .chain(available.iter().copied().filter(|&id| id < args.object))
        .take(args.objects)
        .collect();
    if objects.len() < args.objects {
        anyhow::bail!(
            "--objects {}: {} has only {} models ({available:?}); give --models a directory with more",
            args.objects,
            models.display(),
            objects.len()
        );
    }
    Ok(objects)
}

/// `--set` assignments that make the graph's frame source the benchmark's
/// sequence (and its selectors score the sequence's models), then the
/// user's own.
fn sequence_sets(args: &PipelineArgs, graph: &poseflow_graph::Graph, source: &str) -> anyhow::Result<Vec<String>> {
    let models = toml::Value::String(models_dir(args).display().to_string());
    let objects = sequence_objects(args)?;
    let ids: Vec<String> = objects.iter().map(u32::to_string).collect();
    let mut sets: Vec<String> = [
        "source=\"synthetic\"".to_string(),
        format!("models={models}"),
        format!("objects=[{}]", ids.join(", ")),
        "scenes=1".into(),
        format!("frames_per_scene={}", args.frames),
        format!("orbit_step_deg={:?}", args.orbit_step_deg),
        format!("seed={}", args.seed),
        "preload=true".into(),
    ]
    .iter()
    .map(|assignment| format!("{source}.{assignment}"))
    .collect();
    // Selectors that score against meshes need the sequence's, and
    // detectors report only the objects those meshes are of.
    for selector in graph.stages.values().filter(|s| s.exe_name() == "selector" && s.params.get("models").is_some()) {
        sets.push(format!("{}.models={models}", selector.name));
    }
    for detector in graph.stages.values().filter(|s| s.exe_name() == "detector") {
        sets.push(format!("{}.objects=[{}]", detector.name, ids.join(", ")));
    }
    sets.extend(args.run.set.iter().cloned());
    Ok(sets)
}

fn measure_mode(args: &PipelineArgs, mode: Mode, scratch: &Scratch) -> anyhow::Result<ModeFigures> {
    let chosen = match mode {
        Mode::Estimation => &args.estimation_graph,
        Mode::Tracking => &args.tracking_graph,
    };
    let default = PathBuf::from(format!("deploy/{}.toml", mode.name()));
    let detect_twin = PathBuf::from(format!("deploy/{}-detect.toml", mode.name()));
    let graph_file = if args.detect && *chosen == default { &detect_twin } else { chosen };
    let search = poseflow_launch::search_path(&args.run.stage_path);
    let mut graph = poseflow_graph::load(graph_file, &search)?;
    let source = graph
        .stages
        .values()
        .find(|s| s.exe_name() == "frame-source")
        .map(|s| s.name.clone())
        .with_context(|| format!("{}: no stage with exe = \"frame-source\"", graph_file.display()))?;
    let sets = sequence_sets(args, &graph, &source)?;
    for assignment in &sets {
        graph.set_param(assignment)?;
    }
    let warmup = args.warmup as usize;
    let expected = (args.frames - args.warmup) as usize;

    let frames = render_sequence(&graph.stages[&source].params)?;
    let frames_edge = graph.stages[&source].outputs.first().cloned().unwrap_or_default();
    let owners = poseflow_launch::stamp_owners(&graph, &poseflow_stages::registry())?;
    let mut local_graph = in_process::start(&graph, &frames_edge, &args.estimates_edge)?;
    let local = in_process::measure(&mut local_graph, &frames, warmup, None, &owners)?;
    let in_process_fps = local.frames.frames.len() as f64 / local.wall.as_secs_f64().max(1e-9);
    let paced_hz = args.latency_load * in_process_fps;
    let period = Duration::from_secs_f64(1.0 / paced_hz);
    tracing::info!(mode = mode.name(), fps = in_process_fps, "in-process measured");

    let run = |label: &str, extra: Option<String>| -> anyhow::Result<GraphRunFigures> {
        let mut run_sets = sets.clone();
        run_sets.extend(extra);
        let recording = scratch.dir.join(format!("{}-{label}.rec", mode.name()));
        let log = scratch.dir.join(format!("{}-{label}.log", mode.name()));
        let run = GraphRun {
            graph: graph_file,
            instance: format!("bench-{}-{label}-{}", mode.name(), std::process::id()),
            set: &run_sets,
            stage_path: &args.run.stage_path,
            record: (&recording, &args.estimates_edge),
        };
        let figures = graph::measure(&run, &log, u64::from(args.warmup), &owners)?;
        tracing::info!(mode = mode.name(), run = label, frames = figures.frames.estimated(), "graph measured");
        Ok(figures)
    };
    let saturated = run("saturated", None)?;
    let saturated_fps = saturated.frames.estimated().saturating_sub(1) as f64 / saturated.span.as_secs_f64().max(1e-9);

    // The paced runs in turn, in-process first (as with one round), pooled.
    let (mut local_paced, mut paced) = (FrameLatencies::default(), FrameLatencies::default());
    let (mut local_path, mut paced_path) = (Default::default(), Default::default());
    let (mut stages, mut restarts, mut errors) = (Default::default(), saturated.restarts, saturated.errors);
    for round in 0..args.paced_rounds {
        let local = in_process::measure(&mut local_graph, &frames, warmup, Some(period), &owners)?;
        local_paced.extend(local.frames);
        merge_paths(&mut local_path, local.path);
        let label = if args.paced_rounds == 1 { "paced".to_string() } else { format!("paced-{}", round + 1) };
        let graph_paced = run(&label, Some(format!("{source}.rate_hz={paced_hz}")))?;
        paced.extend(graph_paced.frames);
        merge_paths(&mut paced_path, graph_paced.path);
        // Process times are percentiles per run: the last round's.
        stages = graph_paced.stages;
        (restarts, errors) = (restarts + graph_paced.restarts, errors + graph_paced.errors);
    }
    errors += local_graph.finish()?.values().map(|beat| beat.errors).sum::<u64>();
    drop(frames);

    // Frame counts from the saturated run, latency from the pooled paced runs.
    let mut graph_figures = Figures::new(saturated_fps, &paced, expected);
    graph_figures.frames = saturated.frames.estimated();
    graph_figures.estimates = saturated.frames.estimates();
    let paced_expected = expected * args.paced_rounds as usize;
    Ok(ModeFigures {
        in_process: Figures::new(in_process_fps, &local_paced, paced_expected),
        back_to_back: Figures::new(in_process_fps, &local.frames, expected),
        in_process_stages: path_breakdown(&local_path),
        graph: graph_figures,
        saturated: Figures::new(saturated_fps, &saturated.frames, expected),
        paced_hz,
        paced_rounds: args.paced_rounds,
        verdicts: saturated.verdicts,
        path: path_breakdown(&paced_path),
        stages,
        restarts,
        errors,
    })
}

/// Adds one run's path intervals to the pooled ones.
fn merge_paths(
    pooled: &mut std::collections::BTreeMap<String, Vec<Duration>>,
    run: std::collections::BTreeMap<String, Vec<Duration>>,
) {
    for (interval, durations) in run {
        pooled.entry(interval).or_default().extend(durations);
    }
}

/// The sequence's frames, rendered here for the in-process run.
fn render_sequence(params: &serde_json::Value) -> anyhow::Result<Vec<LoadedFrame>> {
    let mut source = poseflow_ingest::stage::frame_source(params)?;
    std::iter::from_fn(|| source.next_frame()).map(|frame| frame.map_err(anyhow::Error::from)).collect()
}

/// p50 and p99 of each interval of the estimates' path, milliseconds.
fn path_breakdown(path: &std::collections::BTreeMap<String, Vec<Duration>>) -> serde_json::Value {
    path.iter()
        .map(|(interval, durations)| {
            let timing = Timing::of(durations.clone());
            (interval.clone(), json!({"p50_ms": timing.p50_ms, "p99_ms": timing.p99_ms}))
        })
        .collect::<serde_json::Map<_, _>>()
        .into()
}

fn cpu_model() -> Option<String> {
    let info = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    info.lines().find_map(|l| l.strip_prefix("model name")).map(|v| v.trim_start_matches([' ', '\t', ':']).to_string())
}

fn report(args: &PipelineArgs, measured: &[(Mode, ModeFigures)]) -> serde_json::Value {
    let mut report = json!({
        "machine": {
            "cores": std::thread::available_parallelism().map_or(0, |n| n.get()),
            "cpu": cpu_model(),
        },
        "objects": args.objects,
        "sequence": {
            "object": args.object,
            "objects": sequence_objects(args).unwrap_or_default(),
            "models": models_dir(args),
            "frames": args.frames,
            "warmup": args.warmup,
            "orbit_step_deg": args.orbit_step_deg,
            "seed": args.seed,
        },
        "latency_load": args.latency_load,
        "paced_rounds": args.paced_rounds,
    });
    for (mode, figures) in measured {
        let name = mode.name();
        report[name] = json!(figures.graph);
        report[format!("{name}_in_process")] = json!(figures.in_process);
        report[format!("{name}_saturated")] = json!(figures.saturated);
        report[format!("{name}_in_process_back_to_back")] = json!(figures.back_to_back);
        report[format!("{name}_paced_hz")] = json!(figures.paced_hz);
        report[format!("{name}_overhead_pct")] = json!({
            "p50": 100.0 * (figures.graph.p50_ms / figures.in_process.p50_ms - 1.0),
            "mean": 100.0 * (figures.graph.mean_ms / figures.in_process.mean_ms - 1.0),
        });
        report[format!("{name}_in_process_stages")] = figures.in_process_stages.clone();
        report[format!("{name}_path")] = figures.path.clone();
        report[format!("{name}_restarts")] = json!(figures.restarts);
        report[format!("{name}_errors")] = json!(figures.errors);
        report[format!("{name}_verdicts")] = json!(figures.verdicts);
        // `stages` is the estimation graph's (the first mode run when both
        // are); each mode's own is under `<mode>_stages`.
        report[format!("{name}_stages")] = json!(figures.stages);
        if report.get("stages").is_none() {
            report["stages"] = json!(figures.stages);
        }
    }
    report
}

/// `name p50, …` of a `{name: {"p50_ms": …}}` object.
fn one_line(figures: &serde_json::Value) -> String {
    figures
        .as_object()
        .map(|o| {
            o.iter()
                .map(|(name, f)| format!("{name} {:.2}", f["p50_ms"].as_f64().unwrap_or(f64::NAN)))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default()
}

fn table(measured: &[(Mode, ModeFigures)]) -> String {
    let mut out =
        format!("{:<24} {:>8} {:>9} {:>9} {:>9}  {}\n", "", "fps", "p50 ms", "p99 ms", "mean ms", "frames (estimates)");
    for (mode, f) in measured {
        let rows = [
            (format!("{} graph", mode.name()), &f.graph),
            (format!("{} in-process", mode.name()), &f.in_process),
            (format!("{} graph, saturated", mode.name()), &f.saturated),
            (format!("{} in-process, b2b", mode.name()), &f.back_to_back),
        ];
        for (label, figures) in rows {
            out.push_str(&format!(
                "{label:<24} {:>8.1} {:>9.2} {:>9.2} {:>9.2}  {}/{} ({})\n",
                figures.fps,
                figures.p50_ms,
                figures.p99_ms,
                figures.mean_ms,
                figures.frames,
                figures.expected_frames,
                figures.estimates
            ));
        }
        out.push_str(&format!(
            "  graph latency paced at {:.1} Hz{}; graph over in-process: p50 {:+.1} %, mean {:+.1} %; restarts {}, errors {}\n",
            f.paced_hz,
            if f.paced_rounds > 1 { format!(" ({} rounds in turn, pooled)", f.paced_rounds) } else { String::new() },
            100.0 * (f.graph.p50_ms / f.in_process.p50_ms - 1.0),
            100.0 * (f.graph.mean_ms / f.in_process.mean_ms - 1.0),
            f.restarts,
            f.errors
        ));
        let v = f.verdicts;
        out.push_str(&format!(
            "  estimates (graph, saturated): {} unflagged, {} unsure, {} lost, {} reinitialised; {} without the networks\n",
            v.unflagged, v.unsure, v.lost, v.reinitialised, v.network_skipped
        ));
        out.push_str("  stage process time per frame (graph, paced, p50/p99): ");
        let stages: Vec<String> = f
            .stages
            .iter()
            .map(|(name, s)| format!("{name} {:.2}/{:.2} ms", s.p50_us as f64 / 1e3, s.p99_us as f64 / 1e3))
            .collect();
        out.push_str(&stages.join(", "));
        out.push('\n');
        out.push_str(&format!("  graph path (paced, p50 ms): {}\n", one_line(&f.path)));
        out.push_str(&format!("  in-process path (paced, p50 ms): {}\n", one_line(&f.in_process_stages)));
    }
    out
}
