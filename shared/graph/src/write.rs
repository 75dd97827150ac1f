//! A graph written back as a self-contained graph file: every stage's
//! parameters inline (config files merged in), executables as resolved.
//! What a run records beside its results, to be run again as it was.

use crate::spec::EdgePattern;
use crate::{Graph, GraphError};

impl Graph {
    /// This graph as graph-file TOML; parsing it gives this graph again.
    pub fn to_toml(&self) -> Result<String, GraphError> {
        let invalid = |key: String, found: String| GraphError::Invalid {
            file: self.file.clone(),
            key,
            expected: "parameters representable in TOML (no nulls)".into(),
            found,
        };
        let mut file = toml::Table::new();
        let mut graph = toml::Table::new();
        graph.insert("name".into(), self.name.clone().into());
        graph.insert("description".into(), self.description.clone().into());
        graph.insert("heartbeat_ms".into(), (self.heartbeat.as_millis() as i64).into());
        graph.insert("heartbeat_timeout_ms".into(), (self.heartbeat_timeout.as_millis() as i64).into());
        graph.insert("silence_timeout_ms".into(), (self.silence_timeout.as_millis() as i64).into());
        file.insert("graph".into(), graph.into());

        let mut edges = toml::Table::new();
        for (name, edge) in &self.edges {
            let mut table = toml::Table::new();
            table.insert("message".into(), edge.message.clone().into());
            let pattern = match edge.pattern {
                EdgePattern::PublishSubscribe => "publish-subscribe",
                EdgePattern::RequestResponse => "request-response",
            };
            table.insert("pattern".into(), pattern.into());
            table.insert("queue".into(), (edge.queue as i64).into());
            let overflow =
                toml::Value::try_from(edge.overflow).map_err(|e| invalid(format!("edges.{name}"), e.to_string()))?;
            table.insert("overflow".into(), overflow);
            table.insert("max_payload_len".into(), (edge.max_payload_len as i64).into());
            edges.insert(name.clone(), table.into());
        }
        file.insert("edges".into(), edges.into());

        let mut stages = toml::Table::new();
        let list = |names: &[String]| toml::Value::Array(names.iter().map(|n| n.clone().into()).collect());
        for (name, stage) in &self.stages {
            let mut table = toml::Table::new();
            table.insert("exe".into(), stage.exe.display().to_string().into());
            table.insert("args".into(), list(&stage.args));
            table.insert("inputs".into(), list(&stage.inputs));
            table.insert("outputs".into(), list(&stage.outputs));
            table.insert("side_inputs".into(), list(&stage.side_inputs));
            table.insert("serves".into(), list(&stage.serves));
            table.insert("calls".into(), list(&stage.calls));
            let key = || format!("stages.{name}.params");
            let params = match &stage.params {
                serde_json::Value::Null => toml::Table::new(),
                params => toml::Table::try_from(params).map_err(|e| invalid(key(), e.to_string()))?,
            };
            table.insert("params".into(), params.into());
            if let Some(stamp) = stage.stamp {
                table.insert("stamp".into(), stamp.name().into());
            }
            let restart = toml::Value::try_from(stage.restart.policy)
                .map_err(|e| invalid(format!("stages.{name}.restart"), e.to_string()))?;
            table.insert("restart".into(), restart);
            table.insert("backoff_ms".into(), (stage.restart.backoff.as_millis() as i64).into());
            table.insert("max_backoff_ms".into(), (stage.restart.max_backoff.as_millis() as i64).into());
            table.insert("max_restarts".into(), i64::from(stage.restart.max_restarts).into());
            stages.insert(name.clone(), table.into());
        }
        file.insert("stages".into(), stages.into());
        toml::to_string(&file).map_err(|e| invalid("graph".into(), e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use poseflow_contracts::StampSlot;

    use crate::{Stamp, parse_in_process};

    /// Every graph in `deploy/`, with a parameter set the way a program
    /// sets it, written and read back: the same graph.
    #[test]
    fn a_written_graph_reads_back_as_the_same_graph() {
        let deploy = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../../deploy"));
        let mut checked = 0;
        for entry in std::fs::read_dir(deploy).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_none_or(|e| e != "toml") {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            let mut graph = parse_in_process(&text, &path).unwrap();
            let first = graph.stages.keys().next().unwrap().clone();
            graph.set(&first, &["nested", "value"], serde_json::json!([1.5, 2.5])).unwrap();
            // One stage with a timestamp slot of the graph's choice.
            graph.stages.get_mut(&first).unwrap().stamp = Some(Stamp::Slot(StampSlot::Grasp));
            let written = graph.to_toml().unwrap();
            let read = parse_in_process(&written, &path).unwrap();
            assert_eq!(read.edges, graph.edges, "{}", path.display());
            assert_eq!(read.stages, graph.stages, "{}", path.display());
            assert_eq!(
                (&read.name, &read.description, read.heartbeat, read.heartbeat_timeout, read.silence_timeout),
                (&graph.name, &graph.description, graph.heartbeat, graph.heartbeat_timeout, graph.silence_timeout)
            );
            checked += 1;
        }
        assert!(checked >= 6);
    }

    #[test]
    fn a_parameter_set_through_a_scalar_is_named() {
        let text = "[graph]\nname = \"g\"\n[stages.a]\nexe = \"a\"\nparams = { x = 1 }\n";
        let mut graph = parse_in_process(text, Path::new("g.toml")).unwrap();
        let err = graph.set("a", &["x", "y"], 2.into()).unwrap_err().to_string();
        assert_eq!(err, "g.toml: `stages.a.params.x`: expected a table to set `y` in, found 1");
        let err = graph.set("b", &["x"], 2.into()).unwrap_err().to_string();
        assert!(err.contains("one of the graph's stages (a)"), "{err}");
    }
}
