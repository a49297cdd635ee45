//! NIfTI-1 and NIfTI-2 input (`.nii`, `.nii.gz`, `.hdr`+`.img`), every real datatype,
//! both byte orders, and NIfTI-1 output.
//!
//! Read here rather than with the `nifti` crate because that crate (0.18) reads only
//! NIfTI-1 and allocates before a size check can refuse an absurd header; the
//! `nifti` crate is used in tests to cross-check this reader.

use crate::volume::Volume;
use nalgebra::{Matrix3, Matrix4, Vector3};
use std::io::Read;
use std::path::{Path, PathBuf};

/// Voxels refused by default: 1 Gi voxels (4 GiB as f32).
pub const DEFAULT_MAX_VOXELS: u64 = 1 << 30;

#[derive(Debug, thiserror::Error)]
pub enum NiftiError {
    #[error("{path}: cannot read: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a NIfTI file: {reason}")]
    NotNifti { path: PathBuf, reason: String },
    #[error("{path}: unsupported NIfTI datatype {code} ({name})")]
    UnsupportedDatatype { path: PathBuf, code: i32, name: &'static str },
    #[error("{path}: a 3-D volume is needed but the file is {dims}-D (dim = {dim:?})")]
    WrongDimensionality { path: PathBuf, dims: i64, dim: Vec<i64> },
    #[error("{path}: the header claims {voxels} voxels, more than the limit of {limit}")]
    TooLarge { path: PathBuf, voxels: u64, limit: u64 },
    #[error("{path}: truncated: the voxel data needs {expected} bytes but only {got} are there")]
    Truncated { path: PathBuf, expected: u64, got: u64 },
    #[error("{path}: invalid header: {reason}")]
    BadHeader { path: PathBuf, reason: String },
}

/// Options for reading.
#[derive(Clone, Debug)]
pub struct ReadOptions {
    /// Headers claiming more voxels are refused before anything is allocated.
    pub max_voxels: u64,
}

impl Default for ReadOptions {
    fn default() -> Self {
        Self { max_voxels: DEFAULT_MAX_VOXELS }
    }
}

/// The header fields this program uses, from either NIfTI version.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    pub version: u8,
    pub little_endian: bool,
    pub dim: [i64; 8],
    pub datatype: i32,
    pub bitpix: i32,
    pub pixdim: [f64; 8],
    pub vox_offset: u64,
    pub scl_slope: f64,
    pub scl_inter: f64,
    pub xyzt_units: i32,
    pub qform_code: i32,
    pub sform_code: i32,
    pub quatern: [f64; 3],
    pub qoffset: [f64; 3],
    pub srow: [[f64; 4]; 3],
    pub single_file: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AffineSource {
    Sform,
    Qform,
    Fallback,
}

impl Header {
    /// Millimetres per spatial unit of the file.
    fn mm_per_unit(&self) -> f64 {
        match self.xyzt_units & 7 {
            1 => 1000.0,
            3 => 0.001,
            _ => 1.0, // 2 = mm; 0 = unknown, read as mm as most tools do
        }
    }

    /// Voxel -> world (RAS mm) affine as the NIfTI standard chooses it:
    /// sform when `sform_code > 0`, else qform when `qform_code > 0`, else pixdim scaling.
    pub fn world_from_voxel(&self) -> (Matrix4<f64>, AffineSource) {
        let s = self.mm_per_unit();
        let (mut m, src) = if self.sform_code > 0 {
            let mut m = Matrix4::identity();
            for r in 0..3 {
                for c in 0..4 {
                    m[(r, c)] = self.srow[r][c];
                }
            }
            (m, AffineSource::Sform)
        } else if self.qform_code > 0 {
            (self.qform_affine(), AffineSource::Qform)
        } else {
            let d = |i: usize| if self.pixdim[i] > 0.0 { self.pixdim[i] } else { 1.0 };
            (Matrix4::new_nonuniform_scaling(&Vector3::new(d(1), d(2), d(3))), AffineSource::Fallback)
        };
        for r in 0..3 {
            for c in 0..4 {
                m[(r, c)] *= s;
            }
        }
        (m, src)
    }

    fn qform_affine(&self) -> Matrix4<f64> {
        let [b, c, d] = self.quatern;
        let a2 = 1.0 - (b * b + c * c + d * d);
        let (a, b, c, d) = if a2 < 1e-7 {
            // Rotation of 180 degrees: a = 0, renormalise (b, c, d) as nifti1_io does.
            let n = (b * b + c * c + d * d).sqrt().max(1e-12);
            (0.0, b / n, c / n, d / n)
        } else {
            (a2.sqrt(), b, c, d)
        };
        let r = Matrix3::new(
            a * a + b * b - c * c - d * d,
            2.0 * (b * c - a * d),
            2.0 * (b * d + a * c),
            2.0 * (b * c + a * d),
            a * a + c * c - b * b - d * d,
            2.0 * (c * d - a * b),
            2.0 * (b * d - a * c),
            2.0 * (c * d + a * b),
            a * a + d * d - c * c - b * b,
        );
        let qfac = if self.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let dx = if self.pixdim[1] > 0.0 { self.pixdim[1] } else { 1.0 };
        let dy = if self.pixdim[2] > 0.0 { self.pixdim[2] } else { 1.0 };
        let dz = if self.pixdim[3] > 0.0 { self.pixdim[3] } else { 1.0 };
        let lin = r * Matrix3::from_diagonal(&Vector3::new(dx, dy, dz * qfac));
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&lin);
        for i in 0..3 {
            m[(i, 3)] = self.qoffset[i];
        }
        m
    }
}

/// Bytes per voxel and a name for each datatype code; `None` for unsupported ones.
fn datatype_info(code: i32) -> Result<(usize, &'static str), &'static str> {
    Ok(match code {
        2 => (1, "uint8"),
        4 => (2, "int16"),
        8 => (4, "int32"),
        16 => (4, "float32"),
        64 => (8, "float64"),
        256 => (1, "int8"),
        512 => (2, "uint16"),
        768 => (4, "uint32"),
        1024 => (8, "int64"),
        1280 => (8, "uint64"),
        1 => return Err("binary"),
        32 => return Err("complex64"),
        128 => return Err("rgb24"),
        1536 => return Err("float128"),
        1792 => return Err("complex128"),
        2048 => return Err("complex256"),
        2304 => return Err("rgba32"),
        _ => return Err("unknown"),
    })
}

struct Cursor<'a> {
    b: &'a [u8],
    le: bool,
}

impl Cursor<'_> {
    fn arr<const N: usize>(&self, off: usize) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&self.b[off..off + N]);
        if !self.le {
            a.reverse();
        }
        a
    }
    fn i16(&self, o: usize) -> i16 {
        i16::from_le_bytes(self.arr(o))
    }
    fn i32(&self, o: usize) -> i32 {
        i32::from_le_bytes(self.arr(o))
    }
    fn i64(&self, o: usize) -> i64 {
        i64::from_le_bytes(self.arr(o))
    }
    fn f32(&self, o: usize) -> f64 {
        f32::from_le_bytes(self.arr(o)) as f64
    }
    fn f64(&self, o: usize) -> f64 {
        f64::from_le_bytes(self.arr(o))
    }
}

/// Parse a header from its first bytes (348 for NIfTI-1, 540 for NIfTI-2).
/// `need_more` is returned when `bytes` is shorter than the header size.
fn parse_header(bytes: &[u8], path: &Path) -> Result<Header, NiftiError> {
    let not = |reason: &str| NiftiError::NotNifti { path: path.into(), reason: reason.into() };
    if bytes.len() < 4 {
        return Err(not("the file is shorter than a NIfTI header"));
    }
    let size_le = i32::from_le_bytes(bytes[0..4].try_into().unwrap_or_default());
    let size_be = i32::from_be_bytes(bytes[0..4].try_into().unwrap_or_default());
    let (version, le) = match (size_le, size_be) {
        (348, _) => (1u8, true),
        (_, 348) => (1, false),
        (540, _) => (2, true),
        (_, 540) => (2, false),
        _ => return Err(not("sizeof_hdr is neither 348 (NIfTI-1) nor 540 (NIfTI-2)")),
    };
    let need = if version == 1 { 348 } else { 540 };
    if bytes.len() < need {
        return Err(not("the file ends inside the header"));
    }
    let c = Cursor { b: bytes, le };
    let h = if version == 1 {
        let magic = &bytes[344..348];
        let single_file = match magic {
            b"n+1\0" => true,
            b"ni1\0" => false,
            _ => return Err(not("bad magic (expected \"n+1\" or \"ni1\")")),
        };
        let mut dim = [0i64; 8];
        let mut pixdim = [0f64; 8];
        for i in 0..8 {
            dim[i] = c.i16(40 + 2 * i) as i64;
            pixdim[i] = c.f32(76 + 4 * i);
        }
        let mut srow = [[0f64; 4]; 3];
        for r in 0..3 {
            for k in 0..4 {
                srow[r][k] = c.f32(280 + 16 * r + 4 * k);
            }
        }
        // A NaN or infinite offset would otherwise read as 0 and be reported as such.
        let vox_offset = c.f32(108);
        if !vox_offset.is_finite() || vox_offset < 0.0 {
            return Err(not(&format!("vox_offset {vox_offset} is not a finite, non-negative byte offset")));
        }
        Header {
            version,
            little_endian: le,
            dim,
            datatype: c.i16(70) as i32,
            bitpix: c.i16(72) as i32,
            pixdim,
            vox_offset: vox_offset as u64,
            scl_slope: c.f32(112),
            scl_inter: c.f32(116),
            xyzt_units: bytes[123] as i32,
            qform_code: c.i16(252) as i32,
            sform_code: c.i16(254) as i32,
            quatern: [c.f32(256), c.f32(260), c.f32(264)],
            qoffset: [c.f32(268), c.f32(272), c.f32(276)],
            srow,
            single_file,
        }
    } else {
        let magic = &bytes[4..8];
        let single_file = match magic {
            b"n+2\0" => true,
            b"ni2\0" => false,
            _ => return Err(not("bad magic (expected \"n+2\" or \"ni2\")")),
        };
        let mut dim = [0i64; 8];
        let mut pixdim = [0f64; 8];
        for i in 0..8 {
            dim[i] = c.i64(16 + 8 * i);
            pixdim[i] = c.f64(104 + 8 * i);
        }
        let mut srow = [[0f64; 4]; 3];
        for r in 0..3 {
            for k in 0..4 {
                srow[r][k] = c.f64(400 + 32 * r + 8 * k);
            }
        }
        Header {
            version,
            little_endian: le,
            dim,
            datatype: c.i16(12) as i32,
            bitpix: c.i16(14) as i32,
            pixdim,
            vox_offset: c.i64(168).max(0) as u64,
            scl_slope: c.f64(176),
            scl_inter: c.f64(184),
            xyzt_units: c.i32(500),
            qform_code: c.i32(344),
            sform_code: c.i32(348),
            quatern: [c.f64(352), c.f64(360), c.f64(368)],
            qoffset: [c.f64(376), c.f64(384), c.f64(392)],
            srow,
            single_file,
        }
    };
    Ok(h)
}

fn open_maybe_gz(path: &Path) -> Result<Box<dyn Read>, NiftiError> {
    let io = |source| NiftiError::Io { path: path.into(), source };
    let mut f = std::fs::File::open(path).map_err(io)?;
    let mut magic = [0u8; 2];
    let n = f.read(&mut magic).map_err(io)?;
    use std::io::Seek;
    f.seek(std::io::SeekFrom::Start(0)).map_err(io)?;
    let f = std::io::BufReader::new(f);
    if n == 2 && magic == [0x1f, 0x8b] { Ok(Box::new(flate2::read::MultiGzDecoder::new(f))) } else { Ok(Box::new(f)) }
}

/// Read as many bytes as the stream gives, up to `buf.len()`.
fn read_up_to(r: &mut dyn Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Resolve the header and image paths for `.nii[.gz]`, `.hdr[.gz]` or `.img[.gz]`.
fn image_path_for(hdr_path: &Path) -> Option<PathBuf> {
    let s = hdr_path.to_string_lossy();
    for (from, tos) in [(".hdr.gz", [".img.gz", ".img"]), (".hdr", [".img", ".img.gz"])] {
        if let Some(stem) = s.strip_suffix(from) {
            for to in tos {
                let p = PathBuf::from(format!("{stem}{to}"));
                if p.exists() {
                    return Some(p);
                }
            }
            return Some(PathBuf::from(format!("{stem}{}", tos[0])));
        }
    }
    None
}

/// Read a 3-D NIfTI volume. `.img` paths are redirected to their `.hdr`.
pub fn read_volume(path: &Path, options: &ReadOptions) -> Result<Volume, NiftiError> {
    let path_s = path.to_string_lossy();
    let hdr_path = if let Some(stem) = path_s.strip_suffix(".img") {
        PathBuf::from(format!("{stem}.hdr"))
    } else if let Some(stem) = path_s.strip_suffix(".img.gz") {
        PathBuf::from(format!("{stem}.hdr.gz"))
    } else {
        path.to_path_buf()
    };
    let r = open_maybe_gz(&hdr_path)?;
    read_from(r, &hdr_path, options)
}

/// Read a single-file NIfTI (`.nii` or `.nii.gz`) held in memory; `name` is used in errors.
pub fn read_volume_bytes(name: &Path, bytes: &[u8], options: &ReadOptions) -> Result<Volume, NiftiError> {
    let r: Box<dyn Read + '_> = if bytes.starts_with(&[0x1f, 0x8b]) {
        Box::new(flate2::read::MultiGzDecoder::new(bytes))
    } else {
        Box::new(bytes)
    };
    read_from(r, name, options)
}

fn read_from(mut r: Box<dyn Read + '_>, path: &Path, options: &ReadOptions) -> Result<Volume, NiftiError> {
    let io = |source| NiftiError::Io { path: path.into(), source };
    let mut head = vec![0u8; 540];
    let got = read_up_to(&mut r, &mut head[..4]).map_err(io)?;
    if got < 4 {
        return Err(NiftiError::NotNifti {
            path: path.into(),
            reason: "the file is shorter than a NIfTI header".into(),
        });
    }
    let size = match (
        i32::from_le_bytes(head[0..4].try_into().unwrap_or_default()),
        i32::from_be_bytes(head[0..4].try_into().unwrap_or_default()),
    ) {
        (540, _) | (_, 540) => 540,
        _ => 348,
    };
    let got = 4 + read_up_to(&mut r, &mut head[4..size]).map_err(io)?;
    let h = parse_header(&head[..got], path)?;
    let bad = |reason: String| NiftiError::BadHeader { path: path.into(), reason };

    // Dimensions: 3-D, trailing singleton dimensions allowed.
    let ndim = h.dim[0];
    if !(1..=7).contains(&ndim) {
        return Err(bad(format!("dim[0] = {ndim} is not in 1..7")));
    }
    let dim: Vec<i64> = h.dim[1..=ndim as usize].to_vec();
    if dim.iter().any(|&d| d < 1) {
        return Err(bad(format!("non-positive dimension in {dim:?}")));
    }
    let extra = dim.iter().skip(3).any(|&d| d > 1);
    if ndim < 3 || extra {
        return Err(NiftiError::WrongDimensionality {
            path: path.into(),
            dims: if extra { dim.iter().rposition(|&d| d > 1).unwrap_or(0) as i64 + 1 } else { ndim },
            dim,
        });
    }
    let dims = [dim[0] as u64, dim[1] as u64, dim[2] as u64];
    let voxels = dims[0].saturating_mul(dims[1]).saturating_mul(dims[2]);
    if voxels > options.max_voxels {
        return Err(NiftiError::TooLarge { path: path.into(), voxels, limit: options.max_voxels });
    }
    let (bpv, _name) = datatype_info(h.datatype).map_err(|name| NiftiError::UnsupportedDatatype {
        path: path.into(),
        code: h.datatype,
        name,
    })?;
    if h.bitpix != 0 && h.bitpix as usize != bpv * 8 {
        return Err(bad(format!("bitpix {} does not match datatype {}", h.bitpix, h.datatype)));
    }
    let (affine, source) = h.world_from_voxel();
    // The qform and the fallback scale by pixdim: a zero, negative or non-finite voxel size is
    // an error, not 1 mm (the sform carries its own scale).
    if source != AffineSource::Sform {
        let d = [h.pixdim[1], h.pixdim[2], h.pixdim[3]];
        if !d.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(bad(format!(
                "pixdim[1..4] = {d:?}: voxel sizes must be positive and finite (no sform to take them from)"
            )));
        }
    }
    if !affine.iter().all(|v| v.is_finite()) || affine.fixed_view::<3, 3>(0, 0).determinant().abs() < 1e-12 {
        return Err(bad("the voxel-to-world affine is singular or not finite".into()));
    }
    let nbytes = voxels * bpv as u64;

    // Extensions (label names), then the voxel data.
    let label_names;
    let (mut data_reader, data_path): (Box<dyn Read + '_>, PathBuf) = if h.single_file {
        if h.vox_offset < size as u64 {
            return Err(bad(format!("vox_offset {} lies inside the header", h.vox_offset)));
        }
        let ext_len = h.vox_offset - size as u64;
        if ext_len > 64 << 20 {
            return Err(bad(format!("vox_offset {} is implausibly large", h.vox_offset)));
        }
        let mut ext = vec![0u8; ext_len as usize];
        let g = read_up_to(&mut r, &mut ext).map_err(io)?;
        if g < ext.len() {
            return Err(NiftiError::Truncated { path: path.into(), expected: nbytes, got: 0 });
        }
        label_names = parse_extensions(&ext, h.little_endian);
        (r, path.to_path_buf())
    } else {
        let mut ext = Vec::new();
        let _ = r.take(64 << 20).read_to_end(&mut ext);
        label_names = parse_extensions(&ext, h.little_endian);
        let img = image_path_for(path)
            .ok_or_else(|| bad("a header-only file (magic ni1/ni2) needs a .hdr name with an .img beside it".into()))?;
        let mut ir = open_maybe_gz(&img)?;
        let mut skip = vec![0u8; h.vox_offset.min(64 << 20) as usize];
        read_up_to(&mut ir, &mut skip).map_err(|source| NiftiError::Io { path: img.clone(), source })?;
        (ir, img)
    };
    let mut raw = Vec::new();
    raw.try_reserve_exact(nbytes as usize)
        .map_err(|_| bad(format!("cannot allocate {nbytes} bytes for the voxels")))?;
    let got = (&mut data_reader)
        .take(nbytes)
        .read_to_end(&mut raw)
        .map_err(|source| NiftiError::Io { path: data_path.clone(), source })? as u64;
    if got < nbytes {
        return Err(NiftiError::Truncated { path: data_path, expected: nbytes, got });
    }
    let data = decode(&raw, h.datatype, h.little_endian, h.scl_slope, h.scl_inter);
    let mut vol = Volume {
        dims: [dims[0] as usize, dims[1] as usize, dims[2] as usize],
        data,
        world_from_voxel: affine,
        label_names,
    };
    if vol.label_names.is_empty() {
        vol.label_names = read_sidecar_names(path);
    }
    Ok(vol)
}

/// Read only the header (for inspection and size checks).
pub fn read_header(path: &Path) -> Result<Header, NiftiError> {
    let mut r = open_maybe_gz(path)?;
    let mut head = vec![0u8; 540];
    let got = read_up_to(&mut r, &mut head).map_err(|source| NiftiError::Io { path: path.into(), source })?;
    parse_header(&head[..got], path)
}

fn decode(raw: &[u8], datatype: i32, le: bool, slope: f64, inter: f64) -> Vec<f32> {
    macro_rules! conv {
        ($t:ty, $n:expr) => {
            raw.chunks_exact($n)
                .map(|c| {
                    let mut a = [0u8; $n];
                    a.copy_from_slice(c);
                    (if le { <$t>::from_le_bytes(a) } else { <$t>::from_be_bytes(a) }) as f64
                })
                .collect::<Vec<f64>>()
        };
    }
    let vals: Vec<f64> = match datatype {
        2 => raw.iter().map(|&b| b as f64).collect(),
        256 => raw.iter().map(|&b| b as i8 as f64).collect(),
        4 => conv!(i16, 2),
        512 => conv!(u16, 2),
        8 => conv!(i32, 4),
        768 => conv!(u32, 4),
        16 => conv!(f32, 4),
        64 => conv!(f64, 8),
        1024 => conv!(i64, 8),
        1280 => conv!(u64, 8),
        _ => Vec::new(),
    };
    // The standard: slope 0 means no scaling.
    let scale = slope != 0.0 && slope.is_finite() && !(slope == 1.0 && inter == 0.0);
    vals.into_iter()
        .map(|v| if scale { (v * slope + if inter.is_finite() { inter } else { 0.0 }) as f32 } else { v as f32 })
        .collect()
}

/// Label names from NIfTI extensions: Caret/GIFTI-style XML `<Label Key="5" ...>liver</Label>`
/// (as TotalSegmentator writes) or a JSON object `{"5": "liver"}`.
fn parse_extensions(ext: &[u8], le: bool) -> std::collections::BTreeMap<i64, String> {
    let mut names = std::collections::BTreeMap::new();
    if ext.len() < 4 || ext[0] == 0 {
        return names;
    }
    let mut off = 4;
    while off + 8 <= ext.len() {
        let rd = |o: usize| {
            let a: [u8; 4] = ext[o..o + 4].try_into().unwrap_or_default();
            if le { i32::from_le_bytes(a) } else { i32::from_be_bytes(a) }
        };
        let esize = rd(off);
        if esize < 8 || off + esize as usize > ext.len() {
            break;
        }
        let body = String::from_utf8_lossy(&ext[off + 8..off + esize as usize]);
        names.extend(parse_label_text(&body));
        off += esize as usize;
    }
    names
}

/// Label names from XML label tables or a JSON object of number -> name.
pub fn parse_label_text(text: &str) -> std::collections::BTreeMap<i64, String> {
    let mut names = std::collections::BTreeMap::new();
    let trimmed = text.trim_matches(char::from(0)).trim();
    if trimmed.starts_with('{')
        && let Ok(serde_json::Value::Object(map)) = serde_json::from_str::<serde_json::Value>(trimmed)
    {
        let map = match map.get("labels") {
            Some(serde_json::Value::Object(m)) => m.clone(),
            _ => map,
        };
        for (k, v) in map {
            if let (Ok(n), Some(s)) = (k.parse::<i64>(), v.as_str()) {
                names.insert(n, s.to_string());
            }
        }
        return names;
    }
    for part in text.split("<Label ").skip(1) {
        let Some(k0) = part.find("Key=\"") else { continue };
        let rest = &part[k0 + 5..];
        let Some(k1) = rest.find('"') else { continue };
        let Ok(key) = rest[..k1].parse::<i64>() else { continue };
        let Some(gt) = part.find('>') else { continue };
        let Some(end) = part.find("</Label>") else { continue };
        if end <= gt {
            continue;
        }
        let mut name = part[gt + 1..end].trim();
        if let Some(s) = name.strip_prefix("<![CDATA[") {
            name = s.strip_suffix("]]>").unwrap_or(s);
        }
        names.insert(key, name.to_string());
    }
    names
}

/// `seg.nii.gz` -> `seg.json` (or `seg.nii.gz.json`) holding `{"5": "liver", ...}`.
fn read_sidecar_names(path: &Path) -> std::collections::BTreeMap<i64, String> {
    let s = path.to_string_lossy();
    let stem =
        s.strip_suffix(".nii.gz").or_else(|| s.strip_suffix(".nii")).or_else(|| s.strip_suffix(".hdr")).unwrap_or(&s);
    for cand in [format!("{stem}.json"), format!("{s}.json")] {
        if let Ok(text) = std::fs::read_to_string(&cand) {
            let names = parse_label_text(&text);
            if !names.is_empty() {
                return names;
            }
        }
    }
    Default::default()
}

/// Datatype used when writing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WriteType {
    U8,
    I16,
    F32,
}

/// Serialise a volume as a single-file NIfTI-1 (little endian, sform and qform set to the
/// volume's affine when it is a rotation + scaling; label names in a Caret XML extension).
pub fn encode_nifti1(vol: &Volume, ty: WriteType) -> Vec<u8> {
    let mut h = vec![0u8; 348];
    let put_i16 = |h: &mut Vec<u8>, o: usize, v: i16| h[o..o + 2].copy_from_slice(&v.to_le_bytes());
    let put_f32 = |h: &mut Vec<u8>, o: usize, v: f32| h[o..o + 4].copy_from_slice(&v.to_le_bytes());
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    h[38] = b'r';
    let dims = [3i16, vol.dims[0] as i16, vol.dims[1] as i16, vol.dims[2] as i16, 1, 1, 1, 1];
    for (i, d) in dims.iter().enumerate() {
        put_i16(&mut h, 40 + 2 * i, *d);
    }
    let (code, bitpix) = match ty {
        WriteType::U8 => (2, 8),
        WriteType::I16 => (4, 16),
        WriteType::F32 => (16, 32),
    };
    put_i16(&mut h, 70, code);
    put_i16(&mut h, 72, bitpix);
    let m = &vol.world_from_voxel;
    let lin = m.fixed_view::<3, 3>(0, 0).into_owned();
    let spacing = Vector3::new(lin.column(0).norm(), lin.column(1).norm(), lin.column(2).norm());
    let mut r = lin * Matrix3::from_diagonal(&spacing.map(|s| 1.0 / s.max(1e-12)));
    let mut qfac = 1.0f32;
    if r.determinant() < 0.0 {
        qfac = -1.0;
        r.set_column(2, &(-r.column(2)));
    }
    let pix = [qfac, spacing.x as f32, spacing.y as f32, spacing.z as f32, 1.0, 1.0, 1.0, 1.0];
    for (i, p) in pix.iter().enumerate() {
        put_f32(&mut h, 76 + 4 * i, *p);
    }
    put_f32(&mut h, 112, 1.0); // scl_slope
    h[123] = 2 | 8; // mm, seconds
    put_i16(&mut h, 252, 1); // qform_code: scanner
    put_i16(&mut h, 254, 1); // sform_code: scanner
    let q = nalgebra::UnitQuaternion::from_matrix(&r);
    let q = if q.w < 0.0 { -q.into_inner() } else { q.into_inner() };
    put_f32(&mut h, 256, q.i as f32);
    put_f32(&mut h, 260, q.j as f32);
    put_f32(&mut h, 264, q.k as f32);
    for i in 0..3 {
        put_f32(&mut h, 268 + 4 * i, m[(i, 3)] as f32);
        for c in 0..4 {
            put_f32(&mut h, 280 + 16 * i + 4 * c, m[(i, c)] as f32);
        }
    }
    h[344..348].copy_from_slice(b"n+1\0");

    let mut ext = Vec::new();
    if !vol.label_names.is_empty() {
        let mut xml = String::from(
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?><CaretExtension><VolumeInformation Index=\"0\"><LabelTable>\n",
        );
        for (k, v) in &vol.label_names {
            xml.push_str(&format!("<Label Key=\"{k}\"><![CDATA[{v}]]></Label>\n"));
        }
        xml.push_str("</LabelTable></VolumeInformation></CaretExtension>");
        let mut body = xml.into_bytes();
        while (body.len() + 8) % 16 != 0 {
            body.push(0);
        }
        ext.extend_from_slice(&((body.len() + 8) as i32).to_le_bytes());
        ext.extend_from_slice(&0i32.to_le_bytes());
        ext.extend_from_slice(&body);
    }
    let vox_offset = 348 + 4 + ext.len();
    put_f32(&mut h, 108, vox_offset as f32);
    let mut out = h;
    out.extend_from_slice(&[u8::from(!ext.is_empty()), 0, 0, 0]);
    out.extend_from_slice(&ext);
    match ty {
        WriteType::U8 => out.extend(vol.data.iter().map(|&v| v.round().clamp(0.0, 255.0) as u8)),
        WriteType::I16 => {
            for &v in &vol.data {
                out.extend_from_slice(&(v.round().clamp(-32768.0, 32767.0) as i16).to_le_bytes());
            }
        }
        WriteType::F32 => {
            for &v in &vol.data {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    out
}

/// Write a NIfTI-1 file, gzip-compressed when the name ends in `.gz`, atomically.
/// Compression is deterministic (no timestamp in the gzip header).
pub fn write_volume(path: &Path, vol: &Volume, ty: WriteType) -> std::io::Result<()> {
    let bytes = encode_nifti1(vol, ty);
    let bytes = if path.to_string_lossy().ends_with(".gz") {
        use std::io::Write;
        let mut enc = flate2::GzBuilder::new().mtime(0).write(Vec::new(), flate2::Compression::new(6));
        enc.write_all(&bytes)?;
        enc.finish()?
    } else {
        bytes
    };
    crate::write_atomic(path, &bytes)
}
