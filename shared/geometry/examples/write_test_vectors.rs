//! Regenerates the shared geometry test vectors:
//! `cargo run -p poseflow-geometry --example write_test_vectors -- tests/vectors/se3_flow.json`

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let path = std::env::args().nth(1).ok_or("usage: write_test_vectors OUTPUT.json")?;
    let json = serde_json::to_string_pretty(&poseflow_geometry::vectors::generate())?;
    std::fs::write(&path, json + "\n")?;
    println!("wrote {path}");
    Ok(())
}
