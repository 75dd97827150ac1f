//! The demo's and the evaluation's graph: `deploy/estimation.toml` (or
//! `deploy/tracking.toml`) itself, with the frame source pointed at the
//! dataset and the paths made absolute (its copy lives in the output
//! folder).

use std::path::Path;

use anyhow::Context;
use poseflow_geometry::flow::TimeGrid;
use poseflow_graph::Graph;
use serde_json::json;

use super::DetectorMode;

/// Per-stage inline parameters the demo sets on top of the graph file's.
pub struct Overrides<'a> {
    pub dataset: &'a Path,
    pub split: &'a str,
    /// A BOP19 targets file instead of the dataset's own.
    pub targets: Option<&'a Path>,
    pub model: &'a Path,
    pub object_models: &'a Path,
    pub selection: &'a str,
    pub refine: bool,
    pub samples: usize,
    pub steps: usize,
    /// The sampler's time grid, when set.
    pub time_grid: Option<TimeGrid>,
    /// Euler steps of a tracked frame (the sampler's `tracking.steps`), when
    /// set.
    pub tracking_steps: Option<usize>,
    /// The frame source's pace (a video), or as fast as the graph takes.
    pub rate_hz: Option<f64>,
    /// `false`: the ingest stage hands the network no image.
    pub rgb: bool,
    /// The model of the graph's detector stages, when set.
    pub detector_model: Option<&'a Path>,
    /// The mode of the graph's detector stages, when set; `classical` finds
    /// the objects of `object_models`.
    pub detector_mode: Option<DetectorMode>,
    /// The objects the detector stages report (those the selector has
    /// models of), when set.
    pub detector_objects: Option<Vec<u32>>,
    /// A category-level run: the inference stage's `classes` file (each
    /// object id's category); the selector then scores against category
    /// templates instead of `object_models`.
    pub classes: Option<&'a Path>,
}

fn absolute(path: &Path) -> anyhow::Result<String> {
    let path = std::path::absolute(path).with_context(|| format!("{}: cannot make absolute", path.display()))?;
    Ok(path.display().to_string())
}

/// The graph of `graph_file` with `overrides` set on its stages (as `--set`
/// would), paths made absolute: the run's copy of it, written beside the
/// results (`Graph::to_toml`), runs again from anywhere.
pub fn graph_with_overrides(graph_file: &Path, overrides: &Overrides<'_>) -> anyhow::Result<Graph> {
    let mut graph = poseflow_graph::load(graph_file, &poseflow_launch::search_path(&[]))
        .with_context(|| format!("{}: cannot load the graph (run from the repository root)", graph_file.display()))?;
    let stages: Vec<(String, String)> =
        graph.stages.iter().map(|(name, stage)| (name.clone(), stage.exe_name().to_string())).collect();
    for (name, exe) in stages {
        let stage = name.as_str();
        if exe == "detector" {
            if let Some(model) = overrides.detector_model {
                graph.set(stage, &["model"], absolute(model)?.into())?;
            }
            if let Some(mode) = overrides.detector_mode {
                graph.set(stage, &["mode"], mode.name().into())?;
                if mode == DetectorMode::Classical {
                    graph.set(stage, &["classical", "models"], absolute(overrides.object_models)?.into())?;
                }
            }
            if let Some(objects) = &overrides.detector_objects {
                graph.set(stage, &["objects"], objects.clone().into())?;
            }
            continue;
        }
        let truth_prior = exe == "truth-prior";
        if truth_prior {
            // The priors name the frame source's images.
            graph.set(stage, &["dataset"], absolute(overrides.dataset)?.into())?;
            graph.set(stage, &["split"], overrides.split.into())?;
            match overrides.targets {
                Some(targets) => graph.set(stage, &["targets"], absolute(targets)?.into())?,
                None => {
                    if let Some(params) = graph.stages.get_mut(stage).and_then(|s| s.params.as_object_mut()) {
                        params.remove("targets");
                    }
                }
            }
            continue;
        }
        match stage {
            "frames" => {
                // The dataset, not the graph's own source settings.
                let mut params =
                    json!({"source": "bop", "dataset": absolute(overrides.dataset)?, "split": overrides.split});
                if let Some(targets) = overrides.targets {
                    params["targets"] = absolute(targets)?.into();
                }
                if let Some(rate_hz) = overrides.rate_hz {
                    params["rate_hz"] = rate_hz.into();
                }
                graph.set(stage, &[], params)?;
            }
            "ingest" if !overrides.rgb => graph.set(stage, &["rgb"], false.into())?,
            "inference" => {
                graph.set(stage, &["model"], absolute(overrides.model)?.into())?;
                if let Some(classes) = overrides.classes {
                    graph.set(stage, &["classes"], absolute(classes)?.into())?;
                }
            }
            "sampler" => {
                graph.set(stage, &["samples"], overrides.samples.into())?;
                graph.set(stage, &["steps"], overrides.steps.into())?;
                if let Some(grid) = overrides.time_grid {
                    graph.set(stage, &["time_grid"], serde_json::to_value(grid)?)?;
                }
                if let Some(steps) = overrides.tracking_steps {
                    graph.set(stage, &["tracking", "steps"], steps.into())?;
                }
            }
            "selector" => {
                graph.set(stage, &["method"], overrides.selection.into())?;
                match overrides.classes {
                    Some(_) => graph.set(stage, &["category_templates"], true.into())?,
                    None => graph.set(stage, &["models"], absolute(overrides.object_models)?.into())?,
                }
                graph.set(stage, &["refine"], overrides.refine.into())?;
            }
            _ => {}
        }
    }
    Ok(graph)
}
