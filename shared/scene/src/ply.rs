//! PLY reader: ASCII, binary little- and big-endian; `vertex` elements with
//! `x y z` and optional `nx ny nz` and `red green blue`; `face` elements with
//! a `vertex_indices` (or `vertex_index`) list, polygons fanned into
//! triangles. Other elements and properties are skipped.

use std::path::Path;

use nalgebra::{Point3, Vector3};

use crate::{ObjectMesh, SceneError};

#[derive(Debug, Clone, Copy, PartialEq)]
enum Encoding {
    Ascii,
    LittleEndian,
    BigEndian,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
}

#[derive(Debug, Clone)]
enum Property {
    Scalar { name: String, kind: Scalar },
    List { name: String, count: Scalar, item: Scalar },
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

/// Reads values one at a time from the body, in either encoding.
struct Body<'a> {
    encoding: Encoding,
    bytes: &'a [u8],
    pos: usize,
    /// ASCII: the current line's remaining tokens and its number.
    tokens: std::vec::IntoIter<&'a str>,
    line: usize,
}

impl<'a> Body<'a> {
    fn value(&mut self, kind: Scalar) -> Result<f64, String> {
        match self.encoding {
            Encoding::Ascii => {
                let token = self.tokens.next().ok_or("line ends before all properties were read")?;
                token.parse::<f64>().map_err(|_| format!("expected a number, found {token:?}"))
            }
            Encoding::LittleEndian | Encoding::BigEndian => {
                let size = kind.size();
                let raw = self.bytes.get(self.pos..self.pos + size).ok_or("file ends before all elements were read")?;
                self.pos += size;
                let mut buf = [0u8; 8];
                buf[..size].copy_from_slice(raw);
                if self.encoding == Encoding::BigEndian {
                    buf[..size].reverse();
                }
                Ok(match kind {
                    Scalar::I8 => f64::from(buf[0] as i8),
                    Scalar::U8 => f64::from(buf[0]),
                    Scalar::I16 => f64::from(i16::from_le_bytes([buf[0], buf[1]])),
                    Scalar::U16 => f64::from(u16::from_le_bytes([buf[0], buf[1]])),
                    Scalar::I32 => f64::from(i32::from_le_bytes([buf[0], buf[1], buf[2], buf[3]])),
                    Scalar::U32 => f64::from(u32::from_le_bytes([buf[0], buf[1], buf[2], buf[3]])),
                    Scalar::F32 => f64::from(f32::from_le_bytes([buf[0], buf[1], buf[2], buf[3]])),
                    Scalar::F64 => f64::from_le_bytes(buf),
                })
            }
        }
    }

    /// ASCII: moves to the next non-empty line (one element instance each).
    fn next_record(&mut self) -> Result<(), String> {
        if self.encoding != Encoding::Ascii {
            return Ok(());
        }
        loop {
            let rest = &self.bytes[self.pos..];
            if rest.is_empty() {
                return Err("file ends before all elements were read".into());
            }
            let end = rest.iter().position(|&b| b == b'\n').map_or(rest.len(), |i| i + 1);
            let line = std::str::from_utf8(&rest[..end]).map_err(|_| "line is not UTF-8 text")?;
            self.pos += end;
            self.line += 1;
            let tokens: Vec<&'a str> = line.split_whitespace().collect();
            if !tokens.is_empty() {
                self.tokens = tokens.into_iter();
                return Ok(());
            }
        }
    }
}

fn header(bytes: &[u8]) -> Result<(Encoding, Vec<Element>, usize, usize), String> {
    if !bytes.starts_with(b"ply") {
        return Err("does not start with `ply`: not a PLY file".into());
    }
    let end = bytes.windows(10).position(|w| w == b"end_header").ok_or("no `end_header` line: not a PLY file")?;
    let body_start =
        bytes[end..].iter().position(|&b| b == b'\n').map(|i| end + i + 1).ok_or("no line break after `end_header`")?;
    let text = std::str::from_utf8(&bytes[..end]).map_err(|_| "header is not text")?;
    let mut lines = text.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err("first line is not `ply`: not a PLY file".into());
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for (number, line) in lines.enumerate() {
        let at = |detail: String| format!("header line {}: {detail}", number + 2);
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", kind, _version] => {
                encoding = Some(match *kind {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::LittleEndian,
                    "binary_big_endian" => Encoding::BigEndian,
                    other => return Err(at(format!("unknown format {other:?}"))),
                });
            }
            ["element", name, count] => {
                let count = count.parse().map_err(|_| at(format!("element count {count:?} is not a number")))?;
                elements.push(Element { name: name.to_string(), count, properties: Vec::new() });
            }
            ["property", "list", count, item, name] => {
                let element = elements.last_mut().ok_or_else(|| at("property before any element".into()))?;
                let (count, item) = (Scalar::parse(count), Scalar::parse(item));
                let (Some(count), Some(item)) = (count, item) else {
                    return Err(at(format!("unknown list types in {line:?}")));
                };
                element.properties.push(Property::List { name: name.to_string(), count, item });
            }
            ["property", kind, name] => {
                let element = elements.last_mut().ok_or_else(|| at("property before any element".into()))?;
                let kind = Scalar::parse(kind).ok_or_else(|| at(format!("unknown property type {kind:?}")))?;
                element.properties.push(Property::Scalar { name: name.to_string(), kind });
            }
            _ => return Err(at(format!("unexpected line {line:?}"))),
        }
    }
    let encoding = encoding.ok_or("no `format` line in the header")?;
    // Records without properties take no bytes, so nothing bounds how long
    // reading a corrupt count of them would take (found by fuzzing).
    if let Some(empty) = elements.iter().find(|e| e.count > 0 && e.properties.is_empty()) {
        return Err(format!("element `{}` has {} records but no properties", empty.name, empty.count));
    }
    let header_lines = text.lines().count() + 1;
    Ok((encoding, elements, body_start, header_lines))
}

pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<ObjectMesh, SceneError> {
    let malformed =
        |location: String, detail: String| SceneError::Malformed { path: path.to_path_buf(), location, detail };
    let (encoding, elements, body_start, header_lines) = header(bytes).map_err(|d| malformed("header".into(), d))?;
    let mut body = Body { encoding, bytes, pos: body_start, tokens: Vec::new().into_iter(), line: header_lines };
    let mut mesh = ObjectMesh { vertices: Vec::new(), triangles: Vec::new(), normals: None, colors: None };
    for element in &elements {
        let is_vertex = element.name == "vertex";
        let has = |n: &str| element.properties.iter().any(|p| matches!(p, Property::Scalar { name, .. } if name == n));
        if is_vertex {
            if !(has("x") && has("y") && has("z")) {
                return Err(malformed("element vertex".into(), "expected properties x, y and z".into()));
            }
            // The count comes from the file: reserve no more records than the
            // body could hold (each takes at least a byte), so a corrupt
            // count fails at the end of the data, not in the allocator.
            let capacity = element.count.min(bytes.len().saturating_sub(body_start));
            mesh.vertices.reserve(capacity);
            if has("nx") && has("ny") && has("nz") {
                mesh.normals = Some(Vec::with_capacity(capacity));
            }
            if has("red") && has("green") && has("blue") {
                mesh.colors = Some(Vec::with_capacity(capacity));
            }
        }
        for index in 0..element.count {
            read_record(&mut body, element, &mut mesh).map_err(|detail| {
                let place = match encoding {
                    Encoding::Ascii => format!("line {} ({} {index})", body.line, element.name),
                    _ => format!("{} {index}", element.name),
                };
                malformed(place, detail)
            })?;
        }
    }
    Ok(mesh)
}

/// Reads one instance of `element` into `mesh`.
fn read_record(body: &mut Body<'_>, element: &Element, mesh: &mut ObjectMesh) -> Result<(), String> {
    let is_vertex = element.name == "vertex";
    let is_face = element.name == "face";
    body.next_record()?;
    let (mut xyz, mut normal, mut rgb) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3]);
    for property in &element.properties {
        match property {
            Property::Scalar { name, kind } => {
                let value = body.value(*kind)?;
                let slot = match name.as_str() {
                    "x" => Some(&mut xyz[0]),
                    "y" => Some(&mut xyz[1]),
                    "z" => Some(&mut xyz[2]),
                    "nx" => Some(&mut normal[0]),
                    "ny" => Some(&mut normal[1]),
                    "nz" => Some(&mut normal[2]),
                    "red" => Some(&mut rgb[0]),
                    "green" => Some(&mut rgb[1]),
                    "blue" => Some(&mut rgb[2]),
                    _ => None,
                };
                if let Some(slot) = slot {
                    *slot = value;
                }
            }
            Property::List { name, count, item } => {
                let n = body.value(*count)?;
                if !(0.0..=1e6).contains(&n) {
                    return Err(format!("list `{name}` of {n} items"));
                }
                let mut items = Vec::with_capacity(n as usize);
                for _ in 0..n as usize {
                    items.push(body.value(*item)?);
                }
                if is_face && (name == "vertex_indices" || name == "vertex_index") {
                    if items.len() < 3 || items.iter().any(|i| *i < 0.0 || i.fract() != 0.0) {
                        return Err(format!("expected 3 or more vertex indices, found {items:?}"));
                    }
                    // A convex polygon as a fan of triangles around its first corner.
                    for k in 1..items.len() - 1 {
                        mesh.triangles.push([items[0] as u32, items[k] as u32, items[k + 1] as u32]);
                    }
                }
            }
        }
    }
    if is_vertex {
        mesh.vertices.push(Point3::new(xyz[0] as f32, xyz[1] as f32, xyz[2] as f32));
        if let Some(normals) = &mut mesh.normals {
            let n = Vector3::new(normal[0] as f32, normal[1] as f32, normal[2] as f32);
            normals.push(n.try_normalize(1e-12).unwrap_or_else(Vector3::z));
        }
        if let Some(colors) = &mut mesh.colors {
            colors.push(rgb.map(|c| c.clamp(0.0, 255.0) as u8));
        }
    }
    Ok(())
}
