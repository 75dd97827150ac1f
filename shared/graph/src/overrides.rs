//! `poseflow run --set STAGE.KEY=VALUE`: one parameter changed for one run
//! without editing the graph or its config files.

use crate::{Graph, GraphError};

impl Graph {
    /// Sets a stage parameter from `STAGE.KEY[.KEY…]=VALUE`. The value is
    /// read as a TOML value (`5000`, `0.5`, `true`, `[0, 1]`, `"text"`); one
    /// that is not valid TOML is taken as a plain string. Nested keys create
    /// tables on the way; a key that runs through a non-table is an error.
    pub fn set_param(&mut self, assignment: &str) -> Result<(), GraphError> {
        let invalid = |expected: &str, found: String| GraphError::Invalid {
            file: self.file.clone(),
            key: format!("--set {assignment}"),
            expected: expected.to_string(),
            found,
        };
        let Some((path, text)) = assignment.split_once('=') else {
            return Err(invalid("STAGE.KEY=VALUE", "no `=`".into()));
        };
        let mut keys = path.trim().split('.');
        let stage_name = keys.next().unwrap_or_default();
        let keys: Vec<&str> = keys.collect();
        if keys.is_empty() || keys.iter().any(|k| k.is_empty()) {
            return Err(invalid("STAGE.KEY=VALUE", format!("key path `{path}`")));
        }
        let value = parse_value(text.trim());
        self.set(stage_name, &keys, value).map_err(|err| match err {
            GraphError::Invalid { file, key, expected, found } if key == "stages" => {
                GraphError::Invalid { file, key: format!("--set {assignment}"), expected, found }
            }
            other => other,
        })
    }

    /// Sets `params.keys[0].keys[1]… = value` of stage `stage_name`: what a
    /// program does where a user would write `--set`. Nested keys create
    /// tables on the way; a key that runs through a non-table is an error.
    pub fn set(&mut self, stage_name: &str, keys: &[&str], value: serde_json::Value) -> Result<(), GraphError> {
        let Some(stage) = self.stages.get_mut(stage_name) else {
            let known = self.stages.keys().cloned().collect::<Vec<_>>().join(", ");
            return Err(GraphError::Invalid {
                file: self.file.clone(),
                key: "stages".into(),
                expected: format!("one of the graph's stages ({known})"),
                found: format!("`{stage_name}`"),
            });
        };
        set_nested(&mut stage.params, keys, value).map_err(|(depth, found)| GraphError::Invalid {
            file: self.file.clone(),
            key: format!("stages.{stage_name}.params.{}", keys[..depth].join(".")),
            expected: format!("a table to set `{}` in", keys[depth]),
            found,
        })
    }
}

/// Sets `table[keys[0]][keys[1]]… = value`; on a non-table at depth `d`,
/// `Err((d, that value))`.
fn set_nested(table: &mut serde_json::Value, keys: &[&str], value: serde_json::Value) -> Result<(), (usize, String)> {
    let Some((key, rest)) = keys.split_first() else {
        *table = value;
        return Ok(());
    };
    if table.is_null() {
        *table = serde_json::Value::Object(Default::default());
    }
    let Some(object) = table.as_object_mut() else {
        return Err((0, table.to_string()));
    };
    let entry = object.entry(key.to_string()).or_insert(serde_json::Value::Null);
    set_nested(entry, rest, value).map_err(|(depth, found)| (depth + 1, found))
}

fn parse_value(text: &str) -> serde_json::Value {
    toml::from_str::<toml::Table>(&format!("value = {text}"))
        .ok()
        .and_then(|mut table| table.remove("value"))
        .and_then(|value| serde_json::to_value(value).ok())
        .unwrap_or_else(|| serde_json::Value::String(text.to_string()))
}
