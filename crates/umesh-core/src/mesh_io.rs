//! Triangle mesh files: OBJ, PLY (ASCII and binary) and STL (ASCII and binary).

use crate::mesh::TriMesh;
use nalgebra::Vector3;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum MeshIoError {
    #[error("{path}: cannot read or write: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: unknown mesh format (use .obj, .ply or .stl)")]
    UnknownFormat { path: PathBuf },
    #[error("{path}: {reason}")]
    Parse { path: PathBuf, reason: String },
    #[error(
        "{path}: the mesh is not closed: {boundary} boundary edges, {non_manifold} non-manifold edges, {inconsistent} inconsistently oriented edges"
    )]
    Open { path: PathBuf, boundary: usize, non_manifold: usize, inconsistent: usize },
}

fn ext(path: &Path) -> String {
    path.extension().map(|e| e.to_string_lossy().to_lowercase()).unwrap_or_default()
}

/// Parse any supported file by its extension; vertex coordinates must be finite.
fn parse_file(path: &Path) -> Result<TriMesh, MeshIoError> {
    let bytes = std::fs::read(path).map_err(|source| MeshIoError::Io { path: path.into(), source })?;
    let parse = |reason: String| MeshIoError::Parse { path: path.into(), reason };
    let mesh = match ext(path).as_str() {
        "obj" => parse_obj(&String::from_utf8_lossy(&bytes)).map_err(|e| parse(e.into()))?,
        "stl" => parse_stl(&bytes).map_err(|e| parse(e.into()))?,
        "ply" => parse_ply(&bytes).map_err(|e| parse(e.into()))?,
        _ => return Err(MeshIoError::UnknownFormat { path: path.into() }),
    };
    if mesh.positions.iter().any(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(parse("a vertex coordinate is not finite".into()));
    }
    Ok(mesh)
}

pub fn read_mesh(path: &Path) -> Result<TriMesh, MeshIoError> {
    let mesh = parse_file(path)?;
    let parse = |reason: &str| MeshIoError::Parse { path: path.into(), reason: reason.into() };
    if mesh.triangles.is_empty() {
        return Err(parse("the file holds no triangles"));
    }
    let n = mesh.positions.len() as u32;
    if mesh.triangles.iter().flatten().any(|&i| i >= n) {
        return Err(parse("a face refers to a vertex that does not exist"));
    }
    Ok(mesh)
}

/// Read the vertices of a PLY, OBJ or STL file (a point cloud: faces optional).
pub fn read_point_cloud(path: &Path) -> Result<Vec<Vector3<f64>>, MeshIoError> {
    Ok(parse_file(path)?.positions)
}

/// Read a mesh that must be closed and consistently oriented (organ geometry);
/// inward-facing meshes are flipped.
pub fn read_closed_mesh(path: &Path) -> Result<TriMesh, MeshIoError> {
    let mut mesh = read_mesh(path)?;
    let t = mesh.topology();
    if !t.is_watertight() {
        return Err(MeshIoError::Open {
            path: path.into(),
            boundary: t.boundary_edges,
            non_manifold: t.non_manifold_edges,
            inconsistent: t.inconsistent_edges,
        });
    }
    if mesh.signed_volume_mm3() < 0.0 {
        for tri in &mut mesh.triangles {
            tri.swap(1, 2);
        }
    }
    Ok(mesh)
}

fn parse_obj(text: &str) -> Result<TriMesh, crate::Invalid> {
    let mut m = TriMesh::default();
    for (ln, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let v: Vec<f64> = it
                    .take(3)
                    .map(|s| s.parse::<f64>())
                    .collect::<Result<_, _>>()
                    .map_err(|e| format!("line {}: bad vertex: {e}", ln + 1))?;
                if v.len() < 3 {
                    return Err(crate::Invalid(format!("line {}: a vertex needs 3 coordinates", ln + 1)));
                }
                m.positions.push(Vector3::new(v[0], v[1], v[2]));
            }
            Some("f") => {
                let n = m.positions.len() as i64;
                let idx: Vec<u32> = it
                    .map(|s| {
                        let i: i64 = s
                            .split('/')
                            .next()
                            .unwrap_or("")
                            .parse()
                            .map_err(|_| format!("line {}: bad face index {s:?}", ln + 1))?;
                        let i = if i < 0 { n + i } else { i - 1 };
                        if i < 0 || i >= n {
                            return Err(crate::Invalid(format!("line {}: face index {s} out of range", ln + 1)));
                        }
                        Ok(i as u32)
                    })
                    .collect::<Result<_, crate::Invalid>>()?;
                if idx.len() < 3 {
                    return Err(crate::Invalid(format!("line {}: a face needs at least 3 vertices", ln + 1)));
                }
                for k in 1..idx.len() - 1 {
                    m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                }
            }
            _ => {}
        }
    }
    Ok(m)
}

/// Merge vertices with identical coordinates (STL stores triangles unshared).
fn weld(tris: Vec<[Vector3<f64>; 3]>) -> TriMesh {
    let mut m = TriMesh::default();
    let mut map: HashMap<[u64; 3], u32> = HashMap::new();
    for t in tris {
        let idx = t.map(|p| {
            *map.entry([p.x.to_bits(), p.y.to_bits(), p.z.to_bits()]).or_insert_with(|| {
                m.positions.push(p);
                (m.positions.len() - 1) as u32
            })
        });
        m.triangles.push(idx);
    }
    m
}

fn parse_stl(bytes: &[u8]) -> Result<TriMesh, crate::Invalid> {
    let is_binary = bytes.len() >= 84 && {
        let n = u32::from_le_bytes(bytes[80..84].try_into().unwrap_or_default()) as usize;
        n.checked_mul(50).and_then(|x| x.checked_add(84)) == Some(bytes.len())
    };
    if is_binary {
        let n = u32::from_le_bytes(bytes[80..84].try_into().unwrap_or_default()) as usize;
        let f = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap_or_default()) as f64;
        let tris = (0..n)
            .map(|t| {
                let o = 84 + 50 * t + 12;
                std::array::from_fn(|v| Vector3::new(f(o + 12 * v), f(o + 12 * v + 4), f(o + 12 * v + 8)))
            })
            .collect();
        return Ok(weld(tris));
    }
    let text =
        std::str::from_utf8(bytes).map_err(|_| "neither binary STL (size mismatch) nor ASCII STL".to_string())?;
    if !text.trim_start().starts_with("solid") {
        return Err(crate::Invalid::from("neither binary STL (size mismatch) nor ASCII STL"));
    }
    let mut verts = Vec::new();
    for line in text.lines() {
        let mut it = line.split_whitespace();
        if it.next() == Some("vertex") {
            let v: Vec<f64> =
                it.map(|s| s.parse::<f64>()).collect::<Result<_, _>>().map_err(|e| format!("bad vertex: {e}"))?;
            if v.len() != 3 {
                return Err(crate::Invalid::from("a vertex needs 3 coordinates"));
            }
            verts.push(Vector3::new(v[0], v[1], v[2]));
        }
    }
    if verts.len() % 3 != 0 {
        return Err(crate::Invalid::from("the number of vertices is not a multiple of 3"));
    }
    Ok(weld(verts.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()))
}

fn parse_ply(bytes: &[u8]) -> Result<TriMesh, crate::Invalid> {
    let end = bytes.windows(10).position(|w| w == b"end_header").ok_or("no end_header")?;
    let header = String::from_utf8_lossy(&bytes[..end]);
    let mut body_start = end + 10;
    while body_start < bytes.len() && bytes[body_start] != b'\n' {
        body_start += 1;
    }
    body_start += 1;
    let mut format = "";
    // (element name, count, [(property name, type, list count type)])
    let mut elements: Vec<(String, usize, Vec<(String, String, Option<String>)>)> = Vec::new();
    for line in header.lines() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.as_slice() {
            ["format", f, ..] => {
                format = if f.starts_with("ascii") {
                    "ascii"
                } else if f.contains("big") {
                    "be"
                } else {
                    "le"
                }
            }
            ["element", name, n] => {
                elements.push((name.to_string(), n.parse().map_err(|_| "bad element count")?, Vec::new()))
            }
            ["property", "list", ct, it, name] => elements.last_mut().ok_or("property before element")?.2.push((
                name.to_string(),
                it.to_string(),
                Some(ct.to_string()),
            )),
            ["property", ty, name] => {
                elements.last_mut().ok_or("property before element")?.2.push((name.to_string(), ty.to_string(), None))
            }
            _ => {}
        }
    }
    if format.is_empty() {
        return Err(crate::Invalid::from("no format line"));
    }
    let size = |t: &str| -> Result<usize, crate::Invalid> {
        Ok(match t {
            "char" | "uchar" | "int8" | "uint8" => 1,
            "short" | "ushort" | "int16" | "uint16" => 2,
            "int" | "uint" | "float" | "int32" | "uint32" | "float32" => 4,
            "double" | "float64" => 8,
            _ => return Err(crate::Invalid(format!("unknown property type {t}"))),
        })
    };
    let body = &bytes[body_start.min(bytes.len())..];
    let mut tokens = std::str::from_utf8(if format == "ascii" { body } else { b"" })
        .map_err(|_| "bad ascii body")?
        .split_whitespace();
    let mut off = 0usize;
    let mut read = |t: &str| -> Result<f64, crate::Invalid> {
        if format == "ascii" {
            return Ok(tokens.next().ok_or("the file ends early")?.parse::<f64>().map_err(|e| e.to_string())?);
        }
        let n = size(t)?;
        let b = body.get(off..off + n).ok_or("the file ends early")?;
        off += n;
        let mut a = [0u8; 8];
        a[..n].copy_from_slice(b);
        if format == "be" {
            a[..n].reverse();
        }
        Ok(match t {
            "char" | "int8" => a[0] as i8 as f64,
            "uchar" | "uint8" => a[0] as f64,
            "short" | "int16" => i16::from_le_bytes([a[0], a[1]]) as f64,
            "ushort" | "uint16" => u16::from_le_bytes([a[0], a[1]]) as f64,
            "int" | "int32" => i32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            "uint" | "uint32" => u32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            "float" | "float32" => f32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
            _ => f64::from_le_bytes(a),
        })
    };
    let mut m = TriMesh::default();
    for (name, count, props) in &elements {
        if *count > 100_000_000 {
            return Err(crate::Invalid(format!("element {name} claims {count} items")));
        }
        for _ in 0..*count {
            let mut xyz = [0.0; 3];
            for (pname, ty, list) in props {
                if let Some(ct) = list {
                    let n = read(ct)? as usize;
                    if n > 1000 {
                        return Err(crate::Invalid::from("a face with more than 1000 vertices"));
                    }
                    let idx: Vec<u32> = (0..n).map(|_| read(ty).map(|v| v as u32)).collect::<Result<_, _>>()?;
                    if name == "face" && (pname == "vertex_indices" || pname == "vertex_index") && n >= 3 {
                        for k in 1..n - 1 {
                            m.triangles.push([idx[0], idx[k], idx[k + 1]]);
                        }
                    }
                } else {
                    let v = read(ty)?;
                    if name == "vertex" {
                        match pname.as_str() {
                            "x" => xyz[0] = v,
                            "y" => xyz[1] = v,
                            "z" => xyz[2] = v,
                            _ => {}
                        }
                    }
                }
            }
            if name == "vertex" {
                m.positions.push(Vector3::from(xyz));
            }
        }
    }
    Ok(m)
}

/// Write points as a binary PLY of vertices only (a point cloud), atomically.
pub fn write_point_cloud(path: &Path, points: &[Vector3<f64>], comment: &str) -> Result<(), MeshIoError> {
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\ncomment {}\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        comment.replace('\n', " "),
        points.len()
    )
    .into_bytes();
    for p in points {
        for v in p.iter() {
            b.extend_from_slice(&(*v as f32).to_le_bytes());
        }
    }
    crate::write_atomic(path, &b).map_err(|source| MeshIoError::Io { path: path.into(), source })
}

/// Write a mesh as OBJ, binary PLY or binary STL by extension, atomically.
pub fn write_mesh(path: &Path, mesh: &TriMesh) -> Result<(), MeshIoError> {
    let bytes = match ext(path).as_str() {
        "obj" => {
            let mut s = String::with_capacity(mesh.positions.len() * 40);
            s.push_str("# umesh surface, world RAS millimetres\n");
            for p in &mesh.positions {
                s.push_str(&format!("v {:.4} {:.4} {:.4}\n", p.x, p.y, p.z));
            }
            for t in &mesh.triangles {
                s.push_str(&format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1));
            }
            s.into_bytes()
        }
        "ply" => {
            let mut b = format!(
                "ply\nformat binary_little_endian 1.0\ncomment umesh surface, world RAS millimetres\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
                mesh.positions.len(),
                mesh.triangles.len()
            )
            .into_bytes();
            for p in &mesh.positions {
                for v in p.iter() {
                    b.extend_from_slice(&(*v as f32).to_le_bytes());
                }
            }
            for t in &mesh.triangles {
                b.push(3);
                for &i in t {
                    b.extend_from_slice(&(i as i32).to_le_bytes());
                }
            }
            b
        }
        "stl" => {
            let mut b = vec![0u8; 80];
            let title = b"umesh surface, world RAS millimetres";
            b[..title.len()].copy_from_slice(title);
            b.extend_from_slice(&(mesh.triangles.len() as u32).to_le_bytes());
            for t in 0..mesh.triangles.len() {
                let (n, _) = mesh.triangle_normal_area(t);
                for v in n.iter() {
                    b.extend_from_slice(&(*v as f32).to_le_bytes());
                }
                for &i in &mesh.triangles[t] {
                    for v in mesh.positions[i as usize].iter() {
                        b.extend_from_slice(&(*v as f32).to_le_bytes());
                    }
                }
                b.extend_from_slice(&[0, 0]);
            }
            b
        }
        _ => return Err(MeshIoError::UnknownFormat { path: path.into() }),
    };
    crate::write_atomic(path, &bytes).map_err(|source| MeshIoError::Io { path: path.into(), source })
}
