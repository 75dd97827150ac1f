//! Finding a stage's executable.

use std::path::{Path, PathBuf};

/// Looks up a graph file's `exe`:
///
/// - a path with a `/` is taken relative to the graph file's directory
///   (absolute paths as they are);
/// - a bare name is searched in `search_path` (the launcher passes
///   `--stage-path`, then `POSEFLOW_STAGE_PATH`, then its own directory),
///   then in `PATH`.
///
/// Returns the places searched on failure, for the error message.
pub fn resolve_executable(exe: &str, graph_dir: &Path, search_path: &[PathBuf]) -> Result<PathBuf, Vec<PathBuf>> {
    if exe.contains('/') {
        let candidate = graph_dir.join(exe);
        return if is_executable(&candidate) { Ok(candidate) } else { Err(vec![candidate]) };
    }
    let path_dirs = std::env::var_os("PATH").map(|p| std::env::split_paths(&p).collect::<Vec<_>>()).unwrap_or_default();
    let candidates: Vec<PathBuf> = search_path.iter().chain(&path_dirs).map(|dir| dir.join(exe)).collect();
    candidates.iter().find(|c| is_executable(c)).cloned().ok_or(candidates)
}

fn is_executable(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    path.metadata().map(|m| m.is_file() && m.permissions().mode() & 0o111 != 0).unwrap_or(false)
}
