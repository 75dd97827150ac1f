//! `poseflow bench soak`: a graph run for minutes through `poseflow run`
//! while its stages are SIGKILLed in turn; reports frames, restarts, drops,
//! corrupted estimates, leaked shared memory and every process's resident
//! memory over time.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Args;
use poseflow_contracts::{EstimateHeader, MessageHeader, flags, stamp_clock_ns};
use poseflow_geometry::Pose;
use poseflow_graph::WIRING_ENV;
use poseflow_runtime::progress::Progress;
use poseflow_runtime::recording::{RecordingReader, header_from_bytes};

use super::graph_run::{GraphRun, GraphRunOptions, Scratch, run_summary};
use serde_json::json;

/// How often the soak loop wakes to kill, sample or notice the run ended.
const TICK: Duration = Duration::from_millis(100);

#[derive(Debug, Args)]
pub struct SoakArgs {
    /// Graph to run (as for `poseflow run`, from the repository root).
    #[arg(long, default_value = "deploy/tracking.toml")]
    pub graph: PathBuf,

    /// How long to run (seconds).
    #[arg(long, default_value_t = 600)]
    pub duration_s: u64,

    /// SIGKILL one stage this often (seconds; 0 = never); the stages take
    /// turns.
    #[arg(long, default_value_t = 60)]
    pub kill_every_s: u64,

    /// Stages to kill, in turn (comma-separated; default: every stage of
    /// the graph, in name order).
    #[arg(long, value_delimiter = ',')]
    pub kill: Vec<String>,

    /// Read every process's resident memory this often (seconds).
    #[arg(long, default_value_t = 10)]
    pub sample_every_s: u64,

    /// Memory growth is measured from the last sample at or before this
    /// time (seconds): model loading and caches filling come before it.
    #[arg(long, default_value_t = 60)]
    pub warmup_s: u64,

    /// The edge of Estimates that is recorded and checked: every pose a
    /// proper rotation with finite values, every message within its
    /// contract.
    #[arg(long, default_value = "estimates")]
    pub check_edge: String,

    #[command(flatten)]
    pub run: GraphRunOptions,
}

/// One stage killed by the soak.
#[derive(Debug, Clone)]
struct Kill {
    at_s: f64,
    stage: String,
    pid: u32,
}

/// Resident memory of every process at one moment.
#[derive(Debug, Clone)]
struct Sample {
    at_s: f64,
    /// Stage name (and `supervisor` for `poseflow run` itself) → MiB.
    rss_mib: BTreeMap<String, f64>,
    shared_memory_files: usize,
}

/// What the checked edge carried.
#[derive(Debug, Default, Clone, PartialEq)]
struct EstimateCheck {
    checked: u64,
    corrupted: u64,
    /// Started from the previous estimate (flag TRACKING).
    tracked: u64,
    /// Flagged UPSTREAM_RESTARTED.
    restart_notices: u64,
    /// Estimates received before the first kill, between consecutive kills
    /// and after the last: a graph that stopped recovering shows zeros.
    between_kills: Vec<u64>,
    first_problem: Option<String>,
}

pub fn run(args: &SoakArgs) -> anyhow::Result<()> {
    let graph = {
        let mut graph = poseflow_graph::load(&args.graph, &poseflow_launch::search_path(&args.run.stage_path))?;
        for assignment in &args.run.set {
            graph.set_param(assignment)?;
        }
        graph
    };
    match graph.edges.get(&args.check_edge) {
        Some(edge) if edge.message == EstimateHeader::NAME => {}
        Some(edge) => bail!("--check-edge {}: carries {}, expected Estimate", args.check_edge, edge.message),
        None => bail!("--check-edge {}: no such edge in {}", args.check_edge, args.graph.display()),
    }
    let victims = if args.kill.is_empty() { graph.stages.keys().cloned().collect() } else { args.kill.clone() };
    if let Some(unknown) = victims.iter().find(|v| !graph.stages.contains_key(*v)) {
        let known = graph.stages.keys().cloned().collect::<Vec<_>>().join(", ");
        bail!("--kill {unknown}: not a stage of {} (stages: {known})", args.graph.display());
    }
    if args.sample_every_s == 0 || args.duration_s == 0 {
        bail!("--duration-s and --sample-every-s: expected at least 1 second");
    }
    let scratch = Scratch::new(args.run.out.as_deref(), "soak")?;
    let recording = scratch.dir.join("soak.rec");
    let log = scratch.dir.join("run.log");

    let before = poseflow_transport::shared_memory_files();
    let started = Instant::now();
    let started_ns = stamp_clock_ns();
    let run = GraphRun {
        graph: &args.graph,
        instance: format!("soak-{}", std::process::id()),
        set: &args.run.set,
        stage_path: &args.run.stage_path,
        record: (&recording, &args.check_edge),
    };
    let mut child = run.start(&log)?;
    let supervisor = child.id();
    tracing::info!(graph = %args.graph.display(), pid = supervisor, log = %log.display(), "soak started");
    let duration = Duration::from_secs(args.duration_s);
    let kill_every = Duration::from_secs(args.kill_every_s);
    let sample_every = Duration::from_secs(args.sample_every_s);
    let mut kills = Vec::new();
    let mut samples = Vec::new();
    let mut next_sample = sample_every;
    let mut next_kill = (args.kill_every_s > 0).then_some(kill_every);
    let mut ended_early = None;
    let mut progress = Progress::new("soak", args.duration_s);
    loop {
        std::thread::sleep(TICK);
        if let Some(status) = child.try_wait()? {
            ended_early = Some(status);
            break;
        }
        let now = started.elapsed();
        progress.update(now.as_secs().min(args.duration_s), &format!("s, {} kills", kills.len()));
        if now >= duration {
            break;
        }
        if now >= next_sample {
            samples.push(sample(supervisor, now, &before));
            next_sample += sample_every;
        }
        if next_kill.is_some_and(|at| now >= at) {
            let stage = &victims[kills.len() % victims.len()];
            // A stage still restarting from an earlier kill is tried again
            // on the next tick.
            if let Some(&pid) = stage_processes(supervisor).get(stage) {
                // SAFETY: signalling a stage process of the run this soak started.
                unsafe { libc::kill(pid as i32, libc::SIGKILL) };
                tracing::info!(stage, pid, at_s = now.as_secs_f64(), "killed");
                kills.push(Kill { at_s: now.as_secs_f64(), stage: stage.clone(), pid });
                next_kill = Some(next_kill.unwrap_or_default() + kill_every);
            }
        }
    }
    let elapsed = started.elapsed();
    if ended_early.is_none() {
        // SAFETY: signalling the `poseflow run` child this soak started.
        unsafe { libc::kill(supervisor as i32, libc::SIGINT) };
    }
    let summary = run_summary(child, &log)?;
    let leaked: Vec<PathBuf> = poseflow_transport::shared_memory_files().difference(&before).cloned().collect();
    let kill_times: Vec<f64> = kills.iter().map(|k| k.at_s).collect();
    let estimates = check_estimates(&recording, &args.check_edge, started_ns, &kill_times)?;
    let report =
        report(args, (elapsed, ended_early.map(|s| s.to_string())), &kills, &samples, &estimates, &summary, &leaked);
    if args.run.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", table(&report, &samples));
    }
    scratch.finish();
    Ok(())
}

/// The stage processes of the `poseflow run` with pid `supervisor`, by
/// stage name (read from each child's wiring in its environment).
fn stage_processes(supervisor: u32) -> BTreeMap<String, u32> {
    let mut stages = BTreeMap::new();
    for entry in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Some(pid) = entry.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
        if parent_pid(pid) != Some(supervisor) {
            continue;
        }
        if let Some(name) = stage_name(pid) {
            stages.insert(name, pid);
        }
    }
    stages
}

/// Field 4 of `/proc/PID/stat`, after the parenthesised command name.
fn parent_pid(pid: u32) -> Option<u32> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    stat.rsplit_once(')')?.1.split_whitespace().nth(1)?.parse().ok()
}

fn stage_name(pid: u32) -> Option<String> {
    let environ = std::fs::read(format!("/proc/{pid}/environ")).ok()?;
    let prefix = format!("{WIRING_ENV}=");
    let wiring = environ.split(|&b| b == 0).find_map(|var| var.strip_prefix(prefix.as_bytes()))?;
    let wiring: serde_json::Value = serde_json::from_slice(wiring).ok()?;
    wiring["stage"].as_str().map(str::to_string)
}

/// `VmRSS` of `/proc/PID/status`, in MiB.
fn resident_mib(pid: u32) -> Option<f64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let kib: f64 =
        status.lines().find_map(|l| l.strip_prefix("VmRSS:"))?.trim().trim_end_matches("kB").trim().parse().ok()?;
    Some(kib / 1024.0)
}

fn sample(supervisor: u32, at: Duration, before: &BTreeSet<PathBuf>) -> Sample {
    let mut rss_mib: BTreeMap<String, f64> =
        stage_processes(supervisor).into_iter().filter_map(|(name, pid)| Some((name, resident_mib(pid)?))).collect();
    if let Some(mib) = resident_mib(supervisor) {
        rss_mib.insert("supervisor".into(), mib);
    }
    let shared_memory_files = poseflow_transport::shared_memory_files().difference(before).count();
    Sample { at_s: at.as_secs_f64(), rss_mib, shared_memory_files }
}

/// Every Estimate recorded on `edge`: within its contract, finite, its best
/// and mean poses and kept hypotheses proper rigid transforms; counted
/// between the kills (seconds after `started_ns`, CLOCK_MONOTONIC).
fn check_estimates(recording: &Path, edge: &str, started_ns: u64, kill_times: &[f64]) -> anyhow::Result<EstimateCheck> {
    let mut reader = RecordingReader::open(recording).with_context(|| format!("{}", recording.display()))?;
    let mut check = EstimateCheck { between_kills: vec![0; kill_times.len() + 1], ..Default::default() };
    while let Some(message) = reader.next_message()? {
        if message.edge != edge {
            continue;
        }
        check.checked += 1;
        let at_s = message.received_ns.saturating_sub(started_ns) as f64 * 1e-9;
        check.between_kills[kill_times.partition_point(|&kill| kill <= at_s)] += 1;
        match estimate_problem(&message.header, &message.payload) {
            Ok(header) => {
                check.tracked += u64::from(header.header.has_flag(flags::TRACKING));
                check.restart_notices += u64::from(header.header.has_flag(flags::UPSTREAM_RESTARTED));
            }
            Err(problem) => {
                check.corrupted += 1;
                check.first_problem.get_or_insert(problem);
            }
        }
    }
    Ok(check)
}

/// The estimate's header, or what is wrong with the message.
fn estimate_problem(header: &[u8], payload: &[f32]) -> Result<EstimateHeader, String> {
    let header: EstimateHeader =
        header_from_bytes(header).ok_or_else(|| format!("header of {} bytes is not an Estimate", header.len()))?;
    let frame = header.header.frame_id;
    let poses = header.kept_poses(payload).map_err(|e| format!("frame {frame}: {e}"))?;
    if let Some(i) = payload.iter().position(|v| !v.is_finite()) {
        return Err(format!("frame {frame}: payload value {i} is {}", payload[i]));
    }
    for (what, pose) in [("best", &header.best), ("mean", &header.mean)].into_iter().chain(poses.map(|p| ("kept", p))) {
        Pose::from_f32_row_major(pose).map_err(|e| format!("frame {frame}: {what} pose: {e}"))?;
    }
    Ok(header)
}

/// Memory growth per process after warm-up: the largest sample after
/// `warmup_s` minus the last sample at or before it.
fn growth_after_warmup(samples: &[Sample], warmup_s: f64) -> BTreeMap<String, f64> {
    let names: BTreeSet<&String> = samples.iter().flat_map(|s| s.rss_mib.keys()).collect();
    names
        .into_iter()
        .filter_map(|name| {
            let warm = samples.iter().rev().filter(|s| s.at_s <= warmup_s).find_map(|s| s.rss_mib.get(name))?;
            let peak = samples
                .iter()
                .filter(|s| s.at_s > warmup_s)
                .filter_map(|s| s.rss_mib.get(name))
                .copied()
                .reduce(f64::max)?;
            Some((name.clone(), peak - warm))
        })
        .collect()
}

fn report(
    args: &SoakArgs,
    (elapsed, ended_early): (Duration, Option<String>),
    kills: &[Kill],
    samples: &[Sample],
    estimates: &EstimateCheck,
    summary: &serde_json::Value,
    leaked: &[PathBuf],
) -> serde_json::Value {
    let empty = serde_json::Map::new();
    let stages = summary["stages"].as_object().unwrap_or(&empty);
    let per_stage: serde_json::Map<String, serde_json::Value> = stages
        .iter()
        .map(|(name, s)| {
            let total = &s["total"];
            let kills = kills.iter().filter(|k| &k.stage == name).count();
            (
                name.clone(),
                json!({
                    "killed": kills,
                    "restarts": s["restarts"],
                    "hangs": s["hangs"],
                    "outcome": s["outcome"],
                    "frames_in": total["frames_in"],
                    "frames_out": total["frames_out"],
                    "dropped": total["dropped"],
                    "errors": total["errors"],
                }),
            )
        })
        .collect();
    let sum = |key: &str| stages.values().filter_map(|s| s["total"][key].as_u64()).sum::<u64>();
    let edges_lost: serde_json::Map<String, serde_json::Value> = summary["edges"]
        .as_object()
        .unwrap_or(&empty)
        .iter()
        .map(|(edge, flow)| (edge.clone(), flow["lost"].clone()))
        .collect();
    json!({
        "graph": args.graph,
        "duration_s": elapsed.as_secs_f64(),
        "ended_early": ended_early,
        "kill_every_s": args.kill_every_s,
        "kills": kills.iter().map(|k| json!({"at_s": k.at_s, "stage": k.stage, "pid": k.pid})).collect::<Vec<_>>(),
        "estimates": {
            "edge": args.check_edge,
            "checked": estimates.checked,
            "per_s": estimates.checked as f64 / elapsed.as_secs_f64(),
            "corrupted": estimates.corrupted,
            "first_problem": estimates.first_problem,
            "tracked": estimates.tracked,
            "restart_notices": estimates.restart_notices,
            "between_kills": estimates.between_kills,
        },
        "stages": per_stage,
        "restarts": stages.values().filter_map(|s| s["restarts"].as_u64()).sum::<u64>(),
        "dropped": sum("dropped"),
        "errors": sum("errors"),
        "edges_lost": edges_lost,
        "leaked_shared_memory_files": leaked.len(),
        "leaked": leaked,
        "rss_mib": {
            "warmup_s": args.warmup_s,
            "samples": samples.iter().map(|s| {
                let mut row = json!({"at_s": s.at_s, "shared_memory_files": s.shared_memory_files});
                for (name, mib) in &s.rss_mib {
                    row[name] = json!(mib);
                }
                row
            }).collect::<Vec<_>>(),
            "growth_after_warmup": growth_after_warmup(samples, args.warmup_s as f64),
        },
    })
}

/// The human-readable report.
fn table(report: &serde_json::Value, samples: &[Sample]) -> String {
    use std::fmt::Write;
    let mut out = String::new();
    let estimates = &report["estimates"];
    let _ = writeln!(
        out,
        "soak of {} for {:.0} s{}",
        report["graph"].as_str().unwrap_or_default(),
        report["duration_s"].as_f64().unwrap_or_default(),
        report["ended_early"].as_str().map(|s| format!(" (the run ended early: {s})")).unwrap_or_default()
    );
    let kills: Vec<String> = report["kills"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|k| format!("{:.0} s {}", k["at_s"].as_f64().unwrap_or_default(), k["stage"].as_str().unwrap_or_default()))
        .collect();
    let _ = writeln!(out, "killed ({}): {}", kills.len(), kills.join(", "));
    let _ = writeln!(
        out,
        "estimates on `{}`: {} ({:.2}/s), corrupted {}, tracked {}, restart notices {}",
        estimates["edge"].as_str().unwrap_or_default(),
        estimates["checked"],
        estimates["per_s"].as_f64().unwrap_or_default(),
        estimates["corrupted"],
        estimates["tracked"],
        estimates["restart_notices"]
    );
    let between: Vec<String> =
        estimates["between_kills"].as_array().into_iter().flatten().map(|n| n.to_string()).collect();
    let _ = writeln!(out, "estimates before the first kill, between kills, after the last: {}", between.join(", "));
    if let Some(problem) = estimates["first_problem"].as_str() {
        let _ = writeln!(out, "first corrupted estimate: {problem}");
    }
    let _ = writeln!(
        out,
        "{:<12} {:>6} {:>8} {:>10} {:>10} {:>8} {:>7}",
        "stage", "killed", "restarts", "frames in", "frames out", "dropped", "errors"
    );
    for (name, s) in report["stages"].as_object().into_iter().flatten() {
        // Counts as text: a Value's Display ignores widths.
        let [killed, restarts, frames_in, frames_out, dropped, errors] =
            ["killed", "restarts", "frames_in", "frames_out", "dropped", "errors"].map(|key| s[key].to_string());
        let _ = writeln!(
            out,
            "{name:<12} {killed:>6} {restarts:>8} {frames_in:>10} {frames_out:>10} {dropped:>8} {errors:>7}"
        );
    }
    let lost: Vec<String> =
        report["edges_lost"].as_object().into_iter().flatten().map(|(edge, lost)| format!("{edge} {lost}")).collect();
    let _ = writeln!(out, "lost per attributable edge: {}", if lost.is_empty() { "-".into() } else { lost.join(", ") });
    let _ = writeln!(out, "leaked shared-memory files: {}", report["leaked_shared_memory_files"]);
    let names: BTreeSet<&String> = samples.iter().flat_map(|s| s.rss_mib.keys()).collect();
    let _ = write!(out, "resident memory (MiB)\n{:>7}", "t (s)");
    for name in &names {
        let _ = write!(out, " {:>12}", name);
    }
    let _ = writeln!(out, " {:>10}", "shm files");
    for s in samples {
        let _ = write!(out, "{:>7.0}", s.at_s);
        for name in &names {
            match s.rss_mib.get(*name) {
                Some(mib) => write!(out, " {mib:>12.1}"),
                None => write!(out, " {:>12}", "-"),
            }
            .ok();
        }
        let _ = writeln!(out, " {:>10}", s.shared_memory_files);
    }
    let growth: Vec<String> = report["rss_mib"]["growth_after_warmup"]
        .as_object()
        .into_iter()
        .flatten()
        .map(|(name, mib)| format!("{name} {:+.1}", mib.as_f64().unwrap_or_default()))
        .collect();
    let _ = writeln!(
        out,
        "growth after warm-up ({} s), peak minus warm (MiB): {}",
        report["rss_mib"]["warmup_s"],
        growth.join(", ")
    );
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use poseflow_contracts::{Header, POSE_LEN, SelectionMethod, WEIGHTED_POSE_LEN};
    use poseflow_runtime::recording::header_bytes;

    const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.1, 0.0, 0.5];

    fn estimate(kept: [f32; 12]) -> (Vec<u8>, Vec<f32>) {
        let header = EstimateHeader {
            header: Header::new(7, 1),
            best: IDENTITY,
            mean: IDENTITY,
            selection: SelectionMethod::Sdf as u32,
            hypothesis_count: 2,
            kept_count: 1,
            refined: 1,
            ..Default::default()
        };
        let mut payload = Vec::new();
        for pose in [kept, IDENTITY] {
            payload.extend_from_slice(&pose);
            payload.push(0.0);
        }
        assert_eq!(payload.len(), 2 * WEIGHTED_POSE_LEN);
        (header_bytes(&header), payload)
    }

    #[test]
    fn a_corrupted_estimate_is_named() {
        let (header, payload) = estimate(IDENTITY);
        assert!(estimate_problem(&header, &payload).is_ok());
        let mut sheared = IDENTITY;
        sheared[1] = 0.3;
        let (header, payload) = estimate(sheared);
        let problem = estimate_problem(&header, &payload).unwrap_err();
        assert!(problem.starts_with("frame 7: kept pose"), "{problem}");
        let (header, mut payload) = estimate(IDENTITY);
        payload[POSE_LEN] = f32::NAN;
        assert!(estimate_problem(&header, &payload).unwrap_err().contains("payload value 12 is NaN"));
        assert!(estimate_problem(&header, &payload[1..]).unwrap_err().starts_with("frame 7:"), "short payload");
        assert!(estimate_problem(&header[..10], &payload).unwrap_err().contains("not an Estimate"));
    }

    #[test]
    fn memory_growth_is_measured_from_the_end_of_warm_up() {
        let at = |at_s: f64, mib: f64| Sample {
            at_s,
            rss_mib: [("sampler".to_string(), mib)].into_iter().collect(),
            shared_memory_files: 0,
        };
        let samples = [at(10.0, 50.0), at(60.0, 80.0), at(70.0, 30.0), at(120.0, 81.5), at(130.0, 79.0)];
        let growth = growth_after_warmup(&samples, 60.0);
        assert!((growth["sampler"] - 1.5).abs() < 1e-12, "{growth:?}");
        assert!(growth_after_warmup(&samples[..2], 60.0).is_empty(), "nothing after warm-up");
    }
}
