//! Which graph stage writes which timestamp slot.

use std::collections::{BTreeMap, BTreeSet};

use poseflow_contracts::StampSlot;
use poseflow_graph::{Graph, Stamp};
use poseflow_runtime::Registry;

use crate::LaunchError;

/// The stage of `graph` that writes each slot: its `stamp` key, else its
/// registration's default (a stage outside `registry` writes only what its
/// `stamp` names). Two stages that write one slot where one is downstream of
/// the other would overwrite each other's stamp: that is an error naming
/// both. Stages on separate branches may share a slot; the map names the
/// first by stage name.
pub fn stamp_owners(graph: &Graph, registry: &Registry) -> Result<BTreeMap<StampSlot, String>, LaunchError> {
    let mut writers: BTreeMap<StampSlot, Vec<&String>> = BTreeMap::new();
    for (name, stage) in &graph.stages {
        let default = registry.get(stage.exe_name()).and_then(|r| r.default_stamp());
        if let Some(slot) = Stamp::resolve(stage.stamp, default) {
            writers.entry(slot).or_default().push(name);
        }
    }
    for (slot, names) in &writers {
        let reach: Vec<BTreeSet<&String>> = names.iter().map(|name| downstream(graph, name)).collect();
        for (i, first) in names.iter().enumerate() {
            for (j, second) in names.iter().enumerate().skip(i + 1) {
                if reach[i].contains(second) || reach[j].contains(first) {
                    return Err(LaunchError::StampClash {
                        file: graph.file.clone(),
                        slot: slot.name(),
                        first: (*first).clone(),
                        second: (*second).clone(),
                    });
                }
            }
        }
    }
    Ok(writers.into_iter().map(|(slot, names)| (slot, names[0].clone())).collect())
}

/// Stages a message of `from` can reach through publish-subscribe edges
/// (inputs and side inputs), `from` itself only through a loop.
fn downstream<'g>(graph: &'g Graph, from: &str) -> BTreeSet<&'g String> {
    let mut reached = BTreeSet::new();
    let mut frontier = vec![from];
    while let Some(stage) = frontier.pop() {
        for edge in &graph.stages[stage].outputs {
            for (name, reader) in &graph.stages {
                if reader.reads(edge) && reached.insert(name) {
                    frontier.push(name);
                }
            }
        }
    }
    reached
}
