//! Wavefront OBJ reader: `v` (and optional `vn`), `f` with `i`, `i/t`,
//! `i//n` or `i/t/n` corners (1-based or negative relative indices),
//! polygons fanned into triangles. Materials and textures are ignored.

use std::path::Path;

use nalgebra::Point3;

use crate::{ObjectMesh, SceneError};

pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<ObjectMesh, SceneError> {
    let text = std::str::from_utf8(bytes).map_err(|_| SceneError::Malformed {
        path: path.to_path_buf(),
        location: "file".into(),
        detail: "not UTF-8 text".into(),
    })?;
    let mut mesh = ObjectMesh { vertices: Vec::new(), triangles: Vec::new(), normals: None, colors: None };
    for (number, line) in text.lines().enumerate() {
        let malformed = |detail: String| SceneError::Malformed {
            path: path.to_path_buf(),
            location: format!("line {}", number + 1),
            detail,
        };
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let xyz: Vec<f32> = words
                    .take(3)
                    .map(str::parse)
                    .collect::<Result<_, _>>()
                    .map_err(|_| malformed(format!("expected `v x y z` with numbers, found {line:?}")))?;
                if xyz.len() != 3 {
                    return Err(malformed(format!("expected `v x y z`, found {line:?}")));
                }
                mesh.vertices.push(Point3::new(xyz[0], xyz[1], xyz[2]));
            }
            Some("f") => {
                let count = mesh.vertices.len() as i64;
                let corners: Vec<u32> = words
                    .map(|corner| {
                        let index: i64 = corner
                            .split('/')
                            .next()
                            .unwrap_or("")
                            .parse()
                            .map_err(|_| malformed(format!("expected a vertex index in corner {corner:?}")))?;
                        // 1-based, or negative = counted back from the last vertex so far.
                        let zero_based = if index < 0 { count + index } else { index - 1 };
                        if !(0..count).contains(&zero_based) {
                            return Err(malformed(format!("vertex index {index} out of range (1..={count})")));
                        }
                        Ok(zero_based as u32)
                    })
                    .collect::<Result<_, _>>()?;
                if corners.len() < 3 {
                    return Err(malformed(format!("a face needs at least 3 corners, found {line:?}")));
                }
                for k in 1..corners.len() - 1 {
                    mesh.triangles.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(mesh)
}
