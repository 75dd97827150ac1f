//! Results in the BOP19 CSV format (`bop_toolkit_lib.inout.save_bop_results`):
//! `scene_id,im_id,obj_id,score,R,t,time`, `R` the 9 values of the rotation
//! row-major and `t` the translation in millimetres, each space-separated,
//! `time` the seconds spent on the image (-1 when unknown).

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use poseflow_geometry::Pose;
use poseflow_geometry::pose::project_to_rotation;

pub const HEADER: &str = "scene_id,im_id,obj_id,score,R,t,time";

/// One estimate of one object in one image.
#[derive(Debug, Clone, Copy)]
pub struct BopRow {
    pub scene_id: u32,
    pub im_id: u32,
    pub obj_id: u32,
    pub score: f64,
    pub pose: Pose,
    pub time_s: Option<f64>,
}

impl BopRow {
    pub fn line(&self) -> String {
        let m = self.pose.rotation.matrix();
        let rotation: Vec<String> = (0..9).map(|i| format!("{}", m[(i / 3, i % 3)])).collect();
        let t = self.pose.translation * 1000.0;
        let mut line = format!("{},{},{},{},", self.scene_id, self.im_id, self.obj_id, self.score);
        let _ = write!(line, "{},{} {} {},{}", rotation.join(" "), t.x, t.y, t.z, self.time_s.unwrap_or(-1.0));
        line
    }
}

/// The whole file: the header line and one line per row.
pub fn to_csv(rows: &[BopRow]) -> String {
    let mut out = format!("{HEADER}\n");
    for row in rows {
        out.push_str(&row.line());
        out.push('\n');
    }
    out
}

/// How far a file's `R` may be from a rotation before it is rejected
/// (largest entry of |RᵀR − I|): BOP files carry about 6 significant digits.
const ROTATION_TOLERANCE: f64 = 1e-3;

/// The rows of a BOP19 results file; an error names the file, line and
/// field and what was expected.
pub fn parse(text: &str, file: &Path) -> anyhow::Result<Vec<BopRow>> {
    let mut lines = text.lines().enumerate().filter(|(_, line)| !line.trim().is_empty());
    match lines.next() {
        Some((_, header)) if header.trim() == HEADER => {}
        Some((_, header)) => {
            anyhow::bail!("{}: line 1 is {header:?}, expected the header {HEADER:?}", file.display())
        }
        None => anyhow::bail!("{}: empty, expected the header {HEADER:?} and one line per estimate", file.display()),
    }
    lines
        .map(|(index, line)| {
            parse_row(line).map_err(|err| anyhow::anyhow!("{}: line {}: {err}", file.display(), index + 1))
        })
        .collect()
}

fn numbers<const N: usize>(field: &str, name: &str) -> Result<[f64; N], String> {
    let values: Vec<f64> = field
        .split_whitespace()
        .map(|v| v.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("{name} {field:?}: expected {N} finite numbers separated by spaces"))?;
    values.try_into().map_err(|values: Vec<f64>| format!("{name}: {} numbers, expected {N}", values.len()))
}

fn parse_row(line: &str) -> Result<BopRow, String> {
    let fields: Vec<&str> = line.split(',').map(str::trim).collect();
    let [scene_id, im_id, obj_id, score, r, t, time] = fields[..] else {
        return Err(format!("{} fields, expected 7 ({HEADER})", fields.len()));
    };
    let id =
        |value: &str, name: &str| value.parse::<u32>().map_err(|_| format!("{name} {value:?}: expected an integer"));
    let [score] = numbers::<1>(score, "score")?;
    let [time_s] = numbers::<1>(time, "time")?;
    let rotation = project_to_rotation(&Matrix3::from_row_slice(&numbers::<9>(r, "R")?), "R", ROTATION_TOLERANCE)
        .map_err(|err| err.to_string())?;
    let translation = Vector3::from(numbers::<3>(t, "t")?) / 1000.0;
    Ok(BopRow {
        scene_id: id(scene_id, "scene_id")?,
        im_id: id(im_id, "im_id")?,
        obj_id: id(obj_id, "obj_id")?,
        score,
        pose: Pose::new(rotation, translation),
        // BOP writes -1 for an unknown time.
        time_s: (time_s >= 0.0).then_some(time_s),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    #[test]
    fn rows_follow_the_bop19_layout() {
        let pose = Pose::new(
            Rotation3::from_axis_angle(&Vector3::z_axis(), std::f64::consts::FRAC_PI_2),
            Vector3::new(0.1, -0.02, 0.75),
        );
        let row = BopRow { scene_id: 2, im_id: 17, obj_id: 5, score: 0.5, pose, time_s: Some(0.25) };
        let csv = to_csv(&[row, BopRow { time_s: None, ..row }]);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], HEADER);
        let fields: Vec<&str> = lines[1].split(',').collect();
        assert_eq!(fields.len(), 7);
        assert_eq!(&fields[..4], ["2", "17", "5", "0.5"]);
        let r: Vec<f64> = fields[4].split(' ').map(|v| v.parse().unwrap()).collect();
        let expected = [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        assert!(r.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12), "{r:?}");
        let t: Vec<f64> = fields[5].split(' ').map(|v| v.parse().unwrap()).collect();
        assert!(t.iter().zip([100.0, -20.0, 750.0]).all(|(a, b)| (a - b).abs() < 1e-9), "{t:?}");
        assert_eq!(fields[6], "0.25");
        assert!(lines[2].ends_with(",-1"));
        // What is written reads back.
        let read = parse(&csv, Path::new("results.csv")).unwrap();
        assert_eq!(read.len(), 2);
        assert_eq!((read[0].scene_id, read[0].im_id, read[0].obj_id, read[0].time_s), (2, 17, 5, Some(0.25)));
        assert!((read[0].pose.translation - pose.translation).norm() < 1e-12);
        assert!(read[0].pose.rotation.angle_to(&pose.rotation) < 1e-9);
        assert_eq!(read[1].time_s, None);
    }

    #[test]
    fn bad_results_files_are_named_with_line_and_field() {
        let file = Path::new("method_lmo-test.csv");
        let row = "1,2,5,0.9,1 0 0 0 1 0 0 0 1,10 20 800,0.1";
        let error = |text: &str| parse(text, file).unwrap_err().to_string();
        assert!(error("").contains("empty"));
        assert!(error("scene,im\n").contains("line 1"));
        let with = |line: &str| format!("{HEADER}\n{row}\n{line}\n");
        assert!(error(&with("1,2,5,0.9")).contains("line 3: 4 fields, expected 7"), "{}", error(&with("1,2,5,0.9")));
        assert!(error(&with("1,x,5,0.9,1 0 0 0 1 0 0 0 1,0 0 1,1")).contains("im_id \"x\""));
        assert!(error(&with("1,2,5,0.9,1 0 0 0 1 0 0 0,0 0 1,1")).contains("R: 8 numbers, expected 9"));
        assert!(error(&with("1,2,5,0.9,1 0 0 0 1 0 0 0 NaN,0 0 1,1")).contains("R \"1 0 0 0 1 0 0 0 NaN\""));
        assert!(error(&with("1,2,5,0.9,2 0 0 0 1 0 0 0 1,0 0 1,1")).contains("line 3"), "not a rotation");
        assert_eq!(parse(&with(row), file).unwrap().len(), 2);
    }
}
