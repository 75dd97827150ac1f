//! The repository's own size rules (training/README.md): PyTorch checkpoints
//! in git only within a budget, and only those the shipped models resume
//! from, plus the portable weights of the one run in progress.

use std::path::Path;
use std::process::Command;

/// training/README.md states this budget.
const CHECKPOINT_BUDGET_BYTES: u64 = 50_000_000;

/// The checkpoints the shipped models were exported from, and the portable
/// weights (half precision, no optimiser) the YCB-V run and the detector's
/// run resume from on a new machine.
const ALLOWED_CHECKPOINTS: [&str; 4] = [
    "training/checkpoints/lmo10-energy3/checkpoint.pt",
    "training/checkpoints/grasp/checkpoint.pt",
    "training/checkpoints/ycbv/weights.pt",
    "training/checkpoints/detect-lmo10-fine/weights.pt",
];

#[test]
fn tracked_checkpoints_stay_within_the_repository_budget() {
    let repository = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."));
    if !repository.join(".git").exists() {
        eprintln!("not a git checkout: no tracked files to check");
        return;
    }
    let listed = Command::new("git")
        .current_dir(repository)
        .args(["ls-files", "-z", "--", "*.pt", "*.pth", "*.ckpt"])
        .output()
        .expect("git runs");
    assert!(listed.status.success(), "git ls-files: {}", String::from_utf8_lossy(&listed.stderr));
    let tracked: Vec<String> = listed
        .stdout
        .split(|&b| b == 0)
        .filter(|name| !name.is_empty())
        .map(|name| String::from_utf8_lossy(name).into_owned())
        .collect();
    let strays: Vec<&String> = tracked.iter().filter(|t| !ALLOWED_CHECKPOINTS.contains(&t.as_str())).collect();
    assert!(
        strays.is_empty(),
        "checkpoints tracked that neither a shipped model nor the run in progress resumes from: {strays:?}"
    );
    let total: u64 = tracked.iter().map(|t| std::fs::metadata(repository.join(t)).map_or(0, |m| m.len())).sum();
    assert!(
        total <= CHECKPOINT_BUDGET_BYTES,
        "tracked checkpoints take {total} bytes, the budget is {CHECKPOINT_BUDGET_BYTES}: {tracked:?}"
    );
}
