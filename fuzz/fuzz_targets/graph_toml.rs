//! Graph files: any text is a runnable graph or an error naming the key;
//! a valid graph wires every stage and takes a `--set`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|bytes: &[u8]| {
    let Ok(text) = std::str::from_utf8(bytes) else { return };
    let Ok(mut graph) = poseflow_graph::parse(text, std::path::Path::new("/fuzz/graph.toml"), &[]) else { return };
    for stage in graph.stages.values() {
        let _ = graph.wiring(stage, "fuzz");
    }
    let first = graph.stages.keys().next().cloned().unwrap_or_default();
    let _ = graph.set_param(&format!("{first}.fuzz.nested=[1, 2]"));
});
