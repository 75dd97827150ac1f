//! Two hosts on one machine, for the bridge's tests and `poseflow bench ipc
//! --zenoh`: two network namespaces joined by a veth pair, created on
//! demand (as root) and removed when dropped. Processes in them share the
//! file system and shared memory (graph instances keep their iceoryx2
//! services apart) but reach each other only over the veth link.

use std::process::{Command, Stdio};

/// The addresses the pair's two ends get; deploy/two-hosts/ graphs name them.
/// Only these namespaces can reach them.
pub const ADDRESS_A: &str = "10.88.0.1";
pub const ADDRESS_B: &str = "10.88.0.2";

#[derive(Debug)]
pub struct HostPair {
    pub a: String,
    pub b: String,
}

fn ip(args: &[&str]) -> Result<(), String> {
    let output = Command::new("ip")
        .args(args)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("`ip {}` cannot run: {e}", args.join(" ")))?;
    if output.status.success() {
        Ok(())
    } else {
        Err(format!("`ip {}` failed: {}", args.join(" "), String::from_utf8_lossy(&output.stderr).trim()))
    }
}

impl HostPair {
    /// Creates the namespaces `<tag>a<pid>` and `<tag>b<pid>` with the
    /// link between them up; the reason when this machine cannot (not
    /// root, no `ip`, no namespace support).
    pub fn create(tag: &str) -> Result<Self, String> {
        let id = std::process::id() % 100_000;
        let pair = Self { a: format!("{tag}a{id}"), b: format!("{tag}b{id}") };
        // Interface names are limited to 15 characters.
        let (veth_a, veth_b) = (format!("pfva{id}"), format!("pfvb{id}"));
        let steps: Vec<Vec<String>> = vec![
            vec!["netns".into(), "add".into(), pair.a.clone()],
            vec!["netns".into(), "add".into(), pair.b.clone()],
            vec![
                "link".into(),
                "add".into(),
                veth_a.clone(),
                "type".into(),
                "veth".into(),
                "peer".into(),
                "name".into(),
                veth_b.clone(),
            ],
            vec!["link".into(), "set".into(), veth_a.clone(), "netns".into(), pair.a.clone()],
            vec!["link".into(), "set".into(), veth_b.clone(), "netns".into(), pair.b.clone()],
            vec![
                "-n".into(),
                pair.a.clone(),
                "addr".into(),
                "add".into(),
                format!("{ADDRESS_A}/24"),
                "dev".into(),
                veth_a.clone(),
            ],
            vec![
                "-n".into(),
                pair.b.clone(),
                "addr".into(),
                "add".into(),
                format!("{ADDRESS_B}/24"),
                "dev".into(),
                veth_b.clone(),
            ],
            vec!["-n".into(), pair.a.clone(), "link".into(), "set".into(), veth_a, "up".into()],
            vec!["-n".into(), pair.b.clone(), "link".into(), "set".into(), veth_b, "up".into()],
            vec!["-n".into(), pair.a.clone(), "link".into(), "set".into(), "lo".into(), "up".into()],
            vec!["-n".into(), pair.b.clone(), "link".into(), "set".into(), "lo".into(), "up".into()],
        ];
        for step in &steps {
            let args: Vec<&str> = step.iter().map(String::as_str).collect();
            // Dropping `pair` removes whatever was made before a failure.
            ip(&args)?;
        }
        Ok(pair)
    }

    /// `command` run inside namespace `namespace` (its program, arguments,
    /// environment and directory kept).
    pub fn inside(namespace: &str, command: &Command) -> Command {
        let mut wrapped = Command::new("ip");
        wrapped.args(["netns", "exec", namespace]).arg(command.get_program()).args(command.get_args());
        for (key, value) in command.get_envs() {
            match value {
                Some(value) => wrapped.env(key, value),
                None => wrapped.env_remove(key),
            };
        }
        if let Some(dir) = command.get_current_dir() {
            wrapped.current_dir(dir);
        }
        wrapped
    }
}

impl Drop for HostPair {
    fn drop(&mut self) {
        // Removing a namespace removes its end of the veth pair, and the
        // pair with it.
        for namespace in [&self.a, &self.b] {
            let _ = ip(&["netns", "del", namespace]);
        }
    }
}
