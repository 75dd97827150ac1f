//! The demo's and the evaluation's graph: `deploy/estimation.toml` (or
//! `deploy/tracking.toml`) itself, with the frame source pointed at the dataset and the
//! paths made absolute (the copy lives in the output folder).

use std::path::Path;

use anyhow::{Context, bail};

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
    /// Euler steps of a tracked frame (the sampler's `tracking.steps`), when
    /// set.
    pub tracking_steps: Option<usize>,
    /// The frame source's pace (a video), or as fast as the graph takes.
    pub rate_hz: Option<f64>,
    /// `false`: the ingest stage hands the network no image.
    pub rgb: bool,
}

fn absolute(path: &Path) -> anyhow::Result<String> {
    let path = std::path::absolute(path).with_context(|| format!("{}: cannot make absolute", path.display()))?;
    Ok(path.display().to_string())
}

/// The graph of `graph_file` with `overrides`, as TOML text.
pub fn graph_with_overrides(graph_file: &Path, overrides: &Overrides<'_>) -> anyhow::Result<String> {
    let text = std::fs::read_to_string(graph_file)
        .with_context(|| format!("{}: cannot read the graph (run from the repository root)", graph_file.display()))?;
    let mut graph: toml::Table = text.parse().with_context(|| format!("{}: not TOML", graph_file.display()))?;
    let graph_dir = graph_file.parent().unwrap_or(Path::new("."));
    let Some(stages) = graph.get_mut("stages").and_then(|s| s.as_table_mut()) else {
        bail!("{}: no [stages] table", graph_file.display());
    };
    for (name, stage) in stages.iter_mut() {
        let Some(stage) = stage.as_table_mut() else { bail!("{}: stages.{name} is not a table", graph_file.display()) };
        if name == "frames" {
            stage.remove("config");
        }
        if let Some(config) = stage.get("config").and_then(|c| c.as_str()) {
            let resolved = absolute(&graph_dir.join(config))?;
            stage.insert("config".into(), resolved.into());
        }
        let truth_prior = stage.get("exe").and_then(|e| e.as_str()) == Some("truth-prior");
        let params = stage.entry("params").or_insert_with(|| toml::Table::new().into());
        let Some(params) = params.as_table_mut() else {
            bail!("{}: stages.{name}.params is not a table", graph_file.display())
        };
        if truth_prior {
            // The priors name the frame source's images.
            params.insert("dataset".into(), absolute(overrides.dataset)?.into());
            params.insert("split".into(), overrides.split.into());
            match overrides.targets {
                Some(targets) => params.insert("targets".into(), absolute(targets)?.into()),
                None => params.remove("targets"),
            };
            continue;
        }
        match name.as_str() {
            "frames" => {
                // The rendered scene, not the graph's own source settings.
                params.clear();
                params.insert("source".into(), "bop".into());
                params.insert("dataset".into(), absolute(overrides.dataset)?.into());
                params.insert("split".into(), overrides.split.into());
                if let Some(targets) = overrides.targets {
                    params.insert("targets".into(), absolute(targets)?.into());
                }
                if let Some(rate_hz) = overrides.rate_hz {
                    params.insert("rate_hz".into(), rate_hz.into());
                }
            }
            "ingest" if !overrides.rgb => {
                params.insert("rgb".into(), false.into());
            }
            "inference" => {
                params.insert("model".into(), absolute(overrides.model)?.into());
            }
            "sampler" => {
                params.insert("samples".into(), (overrides.samples as i64).into());
                params.insert("steps".into(), (overrides.steps as i64).into());
                if let Some(steps) = overrides.tracking_steps {
                    let tracking = params.entry("tracking").or_insert_with(|| toml::Table::new().into());
                    let Some(tracking) = tracking.as_table_mut() else {
                        bail!("{}: stages.{name}.params.tracking is not a table", graph_file.display())
                    };
                    tracking.insert("steps".into(), (steps as i64).into());
                }
            }
            "selector" => {
                params.insert("method".into(), overrides.selection.into());
                params.insert("models".into(), absolute(overrides.object_models)?.into());
                params.insert("refine".into(), overrides.refine.into());
            }
            _ => {}
        }
    }
    Ok(toml::to_string(&graph)?)
}
