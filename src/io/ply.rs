//! PLY reading (ASCII and binary, any numeric property type, CRLF headers, extra elements,
//! faces) and writing (binary little-endian `x y z` float, `red green blue` uchar, optional
//! normals and `rim_px` uchar — what Open3D and MeshLab read; they pass over `rim_px`).

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use crate::cloud::{Mesh, PointCloud};

/// Why a PLY file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum PlyError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: header line {line}: {what}")]
    Header { path: PathBuf, line: usize, what: String },
    #[error("{path}: element `{element}` #{index}: {what}")]
    Body { path: PathBuf, element: String, index: usize, what: String },
}

/// What is wrong with one record of the body.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum BodyError {
    #[error("file ends early")]
    EndsEarly,
    #[error("line is not text")]
    NotText,
    #[error("line has too few values")]
    FewValues,
    #[error("`{0}` is not a number")]
    NotNumber(String),
    #[error("{0}")]
    Invalid(String),
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
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn decode(self, b: &[u8], big: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().unwrap();
                (if big { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }) as f64
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => num!(i16, 2),
            Scalar::U16 => num!(u16, 2),
            Scalar::I32 => num!(i32, 4),
            Scalar::U32 => num!(u32, 4),
            Scalar::F32 => num!(f32, 4),
            Scalar::F64 => num!(f64, 8),
        }
    }
}

#[derive(Debug, Clone)]
struct Property {
    name: String,
    /// `Some(count type)` for a list property.
    list: Option<Scalar>,
    ty: Scalar,
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Binary { big: bool },
}

/// Reads a PLY file: its `vertex` element (x y z, optional colours and normals) and its
/// `face` element if any; other elements are skipped.
pub fn read_ply(path: &Path) -> Result<Mesh, PlyError> {
    let file = std::fs::File::open(path).map_err(|source| PlyError::Io { path: path.to_path_buf(), source })?;
    read_ply_from(BufReader::new(file), path)
}

/// [`read_ply`] from any reader; `path` names the source in errors.
pub fn read_ply_from(mut reader: impl BufRead, path: &Path) -> Result<Mesh, PlyError> {
    let io = |source| PlyError::Io { path: path.to_path_buf(), source };
    let header_err = |line: usize, what: String| PlyError::Header { path: path.to_path_buf(), line, what };

    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut line_no = 0;
    loop {
        let mut raw = Vec::new();
        let n = reader.read_until(b'\n', &mut raw).map_err(io)?;
        line_no += 1;
        if n == 0 {
            return Err(header_err(line_no, "file ends before `end_header`".into()));
        }
        let line = String::from_utf8_lossy(&raw);
        let line = line.trim_end_matches(['\n', '\r']).trim();
        if line_no == 1 {
            if line != "ply" {
                return Err(header_err(1, format!("expected `ply`, found `{}`", line.chars().take(40).collect::<String>())));
            }
            continue;
        }
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["format", f, _version] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::Binary { big: false },
                    "binary_big_endian" => Format::Binary { big: true },
                    other => return Err(header_err(line_no, format!("unknown format `{other}`"))),
                })
            }
            ["element", name, count] => {
                let count = count.parse().map_err(|_| header_err(line_no, format!("element count `{count}` is not a number")))?;
                // Which one would hold the vertices (or faces)? Refused, not guessed.
                if matches!(*name, "vertex" | "face") && elements.iter().any(|e| e.name == *name) {
                    return Err(header_err(line_no, format!("a second `{name}` element (a PLY file has one)")));
                }
                elements.push(Element { name: name.to_string(), count, props: Vec::new() });
            }
            ["property", "list", ct, ty, name] => {
                let el = elements.last_mut().ok_or_else(|| header_err(line_no, "property before any element".into()))?;
                let (Some(ct), Some(ty)) = (Scalar::parse(ct), Scalar::parse(ty)) else {
                    return Err(header_err(line_no, format!("unknown list types `{ct} {ty}`")));
                };
                el.props.push(Property { name: name.to_string(), list: Some(ct), ty });
            }
            ["property", ty, name] => {
                let el = elements.last_mut().ok_or_else(|| header_err(line_no, "property before any element".into()))?;
                let ty = Scalar::parse(ty).ok_or_else(|| header_err(line_no, format!("unknown property type `{ty}`")))?;
                el.props.push(Property { name: name.to_string(), list: None, ty });
            }
            ["end_header"] => break,
            _ => return Err(header_err(line_no, format!("cannot read `{line}`"))),
        }
    }
    let format = format.ok_or_else(|| header_err(line_no, "no `format` line".into()))?;
    let vertex = elements.iter().find(|e| e.name == "vertex").ok_or_else(|| header_err(line_no, "no `vertex` element".into()))?;
    let find = |name: &str| vertex.props.iter().position(|p| p.name == name);
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        return Err(header_err(line_no, "the vertex element lacks x, y or z".into()));
    };
    let rgb = match (find("red").or(find("r")), find("green").or(find("g")), find("blue").or(find("b"))) {
        (Some(r), Some(g), Some(b)) => Some([r, g, b]),
        _ => None,
    };
    let normals = match (find("nx"), find("ny"), find("nz")) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    // How far inside the silhouette each point's pixel lay (spinscan's views).
    let rim = find("rim_px");

    let mut body = Vec::new();
    reader.read_to_end(&mut body).map_err(io)?;
    let mut src = Source::new(&body, format);
    let mut mesh = Mesh::default();
    if normals.is_some() {
        mesh.cloud.normals = Some(Vec::new());
    }
    if rim.is_some() {
        mesh.cloud.rim_px = Some(Vec::new());
    }
    let mut values: Vec<f64> = Vec::new();
    let mut list: Vec<f64> = Vec::new();
    for el in &elements {
        for index in 0..el.count {
            let body_err = |e: BodyError| PlyError::Body { path: path.to_path_buf(), element: el.name.clone(), index, what: e.to_string() };
            values.clear();
            list.clear();
            src.start_record().map_err(body_err)?;
            for p in &el.props {
                match p.list {
                    None => values.push(src.scalar(p.ty).map_err(body_err)?),
                    Some(ct) => {
                        let n = src.scalar(ct).map_err(body_err)?;
                        if !(0.0..=1e6).contains(&n) {
                            return Err(body_err(BodyError::Invalid(format!("list `{}` has an impossible length {n}", p.name))));
                        }
                        values.push(f64::NAN);
                        for _ in 0..n as usize {
                            let v = src.scalar(p.ty).map_err(body_err)?;
                            if el.name == "face" && (p.name == "vertex_indices" || p.name == "vertex_index") {
                                list.push(v);
                            }
                        }
                    }
                }
            }
            if el.name == "vertex" {
                mesh.cloud.points.push([values[ix] as f32, values[iy] as f32, values[iz] as f32]);
                if let Some([r, g, b]) = rgb {
                    let c = |i: usize| {
                        let v = values[i];
                        // Float colours are 0…1, integer ones 0…255.
                        let v = if matches!(vertex.props[i].ty, Scalar::F32 | Scalar::F64) { v * 255.0 } else { v };
                        v.round().clamp(0.0, 255.0) as u8
                    };
                    mesh.cloud.colors.push([c(r), c(g), c(b)]);
                } else {
                    mesh.cloud.colors.push([200, 200, 200]);
                }
                if let (Some([a, b, c]), Some(n)) = (normals, mesh.cloud.normals.as_mut()) {
                    n.push([values[a] as f32, values[b] as f32, values[c] as f32]);
                }
                if let (Some(i), Some(r)) = (rim, mesh.cloud.rim_px.as_mut()) {
                    // (NaN, of a float property, reads as 0: on the silhouette.)
                    r.push(values[i].round().clamp(0.0, 255.0) as u8);
                }
            } else if el.name == "face" && list.len() >= 3 {
                let nv = mesh.cloud.points.len() as f64;
                if list.iter().any(|&i| i < 0.0 || i >= nv) {
                    return Err(body_err(BodyError::Invalid(format!("face refers to a vertex outside 0…{}", nv as usize - 1))));
                }
                for k in 1..list.len() - 1 {
                    mesh.triangles.push([list[0] as u32, list[k] as u32, list[k + 1] as u32]);
                }
            }
        }
    }
    Ok(mesh)
}

/// The body of a PLY file, read value by value in either encoding.
struct Source<'a> {
    body: &'a [u8],
    pos: usize,
    format: Format,
    /// ASCII: the whitespace-separated words of the current line.
    words: Vec<&'a str>,
    word: usize,
}

impl<'a> Source<'a> {
    fn new(body: &'a [u8], format: Format) -> Self {
        Source { body, pos: 0, format, words: Vec::new(), word: 0 }
    }

    fn start_record(&mut self) -> Result<(), BodyError> {
        if self.format != Format::Ascii {
            return Ok(());
        }
        // One element per line; blank lines are skipped.
        loop {
            if self.pos >= self.body.len() {
                return Err(BodyError::EndsEarly);
            }
            let end = self.body[self.pos..].iter().position(|&c| c == b'\n').map_or(self.body.len(), |e| self.pos + e);
            let line = std::str::from_utf8(&self.body[self.pos..end]).map_err(|_| BodyError::NotText)?;
            self.pos = end + 1;
            self.words = line.split_whitespace().collect();
            self.word = 0;
            if !self.words.is_empty() {
                return Ok(());
            }
        }
    }

    fn scalar(&mut self, ty: Scalar) -> Result<f64, BodyError> {
        match self.format {
            Format::Ascii => {
                let w = self.words.get(self.word).ok_or(BodyError::FewValues)?;
                self.word += 1;
                w.parse::<f64>().map_err(|_| BodyError::NotNumber(w.to_string()))
            }
            Format::Binary { big } => {
                let n = ty.size();
                if self.pos + n > self.body.len() {
                    return Err(BodyError::EndsEarly);
                }
                let v = ty.decode(&self.body[self.pos..], big);
                self.pos += n;
                Ok(v)
            }
        }
    }
}

/// Writes a binary little-endian PLY: `x y z` float, `nx ny nz` float when the cloud has
/// normals, `red green blue` uchar, and `rim_px` uchar when it has them (a view's points:
/// how far inside the silhouette their pixels lay, [`PointCloud::rim_px`]).
pub fn write_ply(path: &Path, cloud: &PointCloud) -> Result<(), PlyError> {
    write_ply_with_faces(path, cloud, &[])
}

/// Writes a binary little-endian mesh PLY: the vertices as [`write_ply`] does, then
/// `element face` with `property list uchar int vertex_indices`.
pub fn write_mesh_ply(path: &Path, mesh: &Mesh) -> Result<(), PlyError> {
    write_ply_with_faces(path, &mesh.cloud, &mesh.triangles)
}

fn write_ply_with_faces(path: &Path, cloud: &PointCloud, triangles: &[[u32; 3]]) -> Result<(), PlyError> {
    let io = |source| PlyError::Io { path: path.to_path_buf(), source };
    let mut out = Vec::with_capacity(64 * 4 + cloud.len() * 27);
    let with_normals = cloud.normals.as_ref().is_some_and(|n| n.len() == cloud.len());
    let rim = cloud.rim_px.as_ref().filter(|r| r.len() == cloud.len());
    write!(out, "ply\nformat binary_little_endian 1.0\ncomment written by spinscan {}\nelement vertex {}\n", env!("CARGO_PKG_VERSION"), cloud.len()).unwrap();
    out.extend_from_slice(b"property float x\nproperty float y\nproperty float z\n");
    if with_normals {
        out.extend_from_slice(b"property float nx\nproperty float ny\nproperty float nz\n");
    }
    out.extend_from_slice(b"property uchar red\nproperty uchar green\nproperty uchar blue\n");
    if rim.is_some() {
        out.extend_from_slice(b"property uchar rim_px\n");
    }
    if !triangles.is_empty() {
        write!(out, "element face {}\nproperty list uchar int vertex_indices\n", triangles.len()).unwrap();
    }
    out.extend_from_slice(b"end_header\n");
    for (i, p) in cloud.points.iter().enumerate() {
        for v in p {
            out.extend_from_slice(&v.to_le_bytes());
        }
        if with_normals {
            for v in &cloud.normals.as_ref().unwrap()[i] {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out.extend_from_slice(&cloud.colors.get(i).copied().unwrap_or([200, 200, 200]));
        if let Some(r) = rim {
            out.push(r[i]);
        }
    }
    for t in triangles {
        out.push(3);
        for &v in t {
            out.extend_from_slice(&(v as i32).to_le_bytes());
        }
    }
    super::write_atomic(path, &out).map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("spinscan-ply-{}-{name}", std::process::id()))
    }

    #[test]
    fn binary_round_trip_with_normals() {
        let cloud = PointCloud {
            points: vec![[1.0, 2.0, 3.0], [-4.5, 0.25, 1e3]],
            colors: vec![[1, 2, 3], [250, 128, 0]],
            normals: Some(vec![[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
            rim_px: Some(vec![3, 255]),
        };
        let p = tmp("rt.ply");
        write_ply(&p, &cloud).unwrap();
        let back = read_ply(&p).unwrap();
        assert_eq!(back.cloud, cloud);
        std::fs::remove_file(p).unwrap();
    }

    #[test]
    fn mesh_round_trip() {
        let mesh = Mesh {
            cloud: PointCloud { points: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], colors: vec![[9, 9, 9]; 3], normals: None, rim_px: None },
            triangles: vec![[0, 1, 2]],
        };
        let p = tmp("mesh.ply");
        write_mesh_ply(&p, &mesh).unwrap();
        assert_eq!(read_ply(&p).unwrap(), mesh);
        std::fs::remove_file(p).unwrap();
    }

    #[test]
    fn a_second_vertex_element_is_refused() {
        // Found by `cargo fuzz run ply`: the vertices' properties were looked up in the first
        // `vertex` element and read from the second (an index out of bounds).
        let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement vertex 1\nproperty float x\nend_header\n0 0 0\n1\n";
        let err = read_ply_from(text.as_bytes(), Path::new("two.ply")).unwrap_err().to_string();
        assert!(err.contains("two.ply") && err.contains("second `vertex` element"), "{err}");
    }

    #[test]
    fn ascii_crlf_doubles_extra_elements_and_faces() {
        let text = "ply\r\nformat ascii 1.0\r\ncomment made by hand\r\nobj_info grid\r\nelement vertex 4\r\nproperty double x\r\nproperty double y\r\nproperty double z\r\nelement range_grid 2\r\nproperty list uchar int vertex_indices\r\nelement face 1\r\nproperty list uchar int vertex_indices\r\nend_header\r\n0 0 0\r\n1 0 0\r\n1 1 0\r\n0 1 0.5\r\n1 0\r\n0\r\n4 0 1 2 3\r\n";
        let p = tmp("ascii.ply");
        std::fs::write(&p, text).unwrap();
        let m = read_ply(&p).unwrap();
        assert_eq!(m.cloud.points.len(), 4);
        assert_eq!(m.cloud.points[3], [0.0, 1.0, 0.5]);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        std::fs::remove_file(p).unwrap();
    }

    #[test]
    fn truncated_binary_names_the_element() {
        let p = tmp("trunc.ply");
        std::fs::write(&p, b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0\0\0\0\0\0\0\0\0\0\0").unwrap();
        let e = read_ply(&p).unwrap_err().to_string();
        assert!(e.contains("`vertex` #1") && e.contains("ends early"), "{e}");
        std::fs::remove_file(p).unwrap();
    }
}
