//! Finding and loading the ONNX Runtime shared library (`ort` with
//! `load-dynamic`): `ORT_DYLIB_PATH`, then the `onnxruntime` Python
//! package (the project's `target/python-venv`, `$VIRTUAL_ENV`, the user's
//! and the system's site-packages), then system library folders.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use crate::OnnxError;

const LIBRARY: &str = "libonnxruntime.so";

/// Library files in `dir` named `libonnxruntime.so*`, newest name first.
fn libraries_in(dir: &Path) -> Vec<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with(LIBRARY)))
        .collect();
    found.sort();
    found.reverse();
    found
}

/// `site-packages` folders of the Python environments under `root`
/// (`root/lib/python3.*/site-packages`).
fn site_packages(root: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(root.join("lib"))
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("python3")))
        .flat_map(|p| [p.join("site-packages"), p.join("dist-packages")])
        .collect()
}

/// The places searched, in order.
fn candidates() -> Vec<PathBuf> {
    let mut roots: Vec<PathBuf> = Vec::new();
    // The project's environment, from the working directory or the
    // executable's target directory (target/<profile>/<exe>).
    roots.push(PathBuf::from("target/python-venv"));
    if let Ok(exe) = std::env::current_exe() {
        roots.extend(exe.ancestors().skip(1).take(3).map(|dir| dir.join("python-venv")));
    }
    if let Some(venv) = std::env::var_os("VIRTUAL_ENV") {
        roots.push(PathBuf::from(venv));
    }
    if let Some(home) = std::env::var_os("HOME") {
        roots.push(PathBuf::from(home).join(".local"));
    }
    roots.extend(["/usr/local", "/usr"].map(PathBuf::from));
    let mut dirs: Vec<PathBuf> =
        roots.iter().flat_map(|r| site_packages(r)).map(|site| site.join("onnxruntime/capi")).collect();
    dirs.extend(
        ["/usr/local/lib", "/usr/lib", "/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu"].map(PathBuf::from),
    );
    dirs
}

/// The ONNX Runtime library this process will load.
pub fn find_library() -> Result<PathBuf, OnnxError> {
    if let Some(path) = std::env::var_os("ORT_DYLIB_PATH") {
        let path = PathBuf::from(path);
        return if path.is_file() {
            Ok(path)
        } else {
            Err(OnnxError::RuntimeMissing { searched: format!("ORT_DYLIB_PATH={} (no such file)", path.display()) })
        };
    }
    let dirs = candidates();
    dirs.iter().find_map(|dir| libraries_in(dir).into_iter().next()).ok_or_else(|| OnnxError::RuntimeMissing {
        searched: std::iter::once("ORT_DYLIB_PATH (unset)".to_string())
            .chain(dirs.iter().map(|d| d.display().to_string()))
            .collect::<Vec<_>>()
            .join(", "),
    })
}

/// Loads ONNX Runtime once per process and returns its environment.
pub fn environment() -> Result<&'static ort::environment::Environment, OnnxError> {
    static ENVIRONMENT: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();
    let path = find_library()?;
    let result = ENVIRONMENT.get_or_init(|| {
        tracing::info!(library = %path.display(), "loading ONNX Runtime");
        ort::init_from(&path)
            .map_err(|e| e.to_string())
            .and_then(|builder| builder.with_name("poseflow").build().map_err(|e| e.to_string()))
    });
    result.as_ref().map_err(|detail| OnnxError::RuntimeLoad { path, detail: detail.clone() })
}
