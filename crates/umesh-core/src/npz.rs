//! NumPy `.npz` archives (a zip of `.npy` arrays), read and written without numpy.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum NpzError {
    #[error("{path}: cannot read or write: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a valid .npz archive: {reason}")]
    Format { path: PathBuf, reason: String },
    #[error("{path}: array '{name}' is missing")]
    Missing { path: PathBuf, name: String },
    #[error("{path}: array '{name}': {reason}")]
    BadArray { path: PathBuf, name: String, reason: String },
}

/// Element data of an array.
#[derive(Clone, Debug, PartialEq)]
pub enum ArrayData {
    F32(Vec<f32>),
    F64(Vec<f64>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
    U32(Vec<u32>),
}

impl ArrayData {
    fn len(&self) -> usize {
        match self {
            ArrayData::F32(v) => v.len(),
            ArrayData::F64(v) => v.len(),
            ArrayData::I32(v) => v.len(),
            ArrayData::I64(v) => v.len(),
            ArrayData::U8(v) => v.len(),
            ArrayData::U32(v) => v.len(),
        }
    }
    fn descr(&self) -> &'static str {
        match self {
            ArrayData::F32(_) => "<f4",
            ArrayData::F64(_) => "<f8",
            ArrayData::I32(_) => "<i4",
            ArrayData::I64(_) => "<i8",
            ArrayData::U8(_) => "|u1",
            ArrayData::U32(_) => "<u4",
        }
    }
    /// Values as f64, whatever the stored type.
    pub fn to_f64(&self) -> Vec<f64> {
        match self {
            ArrayData::F32(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::F64(v) => v.clone(),
            ArrayData::I32(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::U8(v) => v.iter().map(|&x| x as f64).collect(),
            ArrayData::U32(v) => v.iter().map(|&x| x as f64).collect(),
        }
    }
}

/// A C-order n-dimensional array.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: ArrayData,
}

impl Array {
    pub fn new(shape: Vec<usize>, data: ArrayData) -> Self {
        debug_assert_eq!(shape.iter().product::<usize>(), data.len());
        Self { shape, data }
    }
    pub fn f32(shape: Vec<usize>, v: Vec<f32>) -> Self {
        Self::new(shape, ArrayData::F32(v))
    }
    pub fn f64(shape: Vec<usize>, v: Vec<f64>) -> Self {
        Self::new(shape, ArrayData::F64(v))
    }
    pub fn i64(shape: Vec<usize>, v: Vec<i64>) -> Self {
        Self::new(shape, ArrayData::I64(v))
    }
    pub fn scalar_f64(v: f64) -> Self {
        Self::new(vec![], ArrayData::F64(vec![v]))
    }

    /// Serialise as `.npy` version 1.0.
    pub fn to_npy(&self) -> Vec<u8> {
        let shape = match self.shape.len() {
            0 => "()".to_string(),
            1 => format!("({},)", self.shape[0]),
            _ => format!("({})", self.shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
        };
        let mut header = format!("{{'descr': '{}', 'fortran_order': False, 'shape': {shape}, }}", self.data.descr());
        // Pad so the data starts on a multiple of 64 bytes, newline-terminated.
        while (10 + header.len() + 1) % 64 != 0 {
            header.push(' ');
        }
        header.push('\n');
        let mut out = Vec::with_capacity(10 + header.len() + self.data.len() * 8);
        out.extend_from_slice(b"\x93NUMPY\x01\x00");
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        macro_rules! put {
            ($v:expr) => {
                for x in $v {
                    out.extend_from_slice(&x.to_le_bytes());
                }
            };
        }
        match &self.data {
            ArrayData::F32(v) => put!(v),
            ArrayData::F64(v) => put!(v),
            ArrayData::I32(v) => put!(v),
            ArrayData::I64(v) => put!(v),
            ArrayData::U8(v) => out.extend_from_slice(v),
            ArrayData::U32(v) => put!(v),
        }
        out
    }

    /// Parse a `.npy` (versions 1-3, C or Fortran order, either byte order).
    pub fn from_npy(bytes: &[u8]) -> Result<Self, crate::Invalid> {
        if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
            return Err(crate::Invalid::from("missing the NPY magic"));
        }
        let (hlen, hstart) = match bytes[6] {
            1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
            2 | 3 => {
                if bytes.len() < 12 {
                    return Err(crate::Invalid::from("truncated header"));
                }
                (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
            }
            v => return Err(crate::Invalid(format!("unsupported NPY version {v}"))),
        };
        let header = std::str::from_utf8(bytes.get(hstart..hstart + hlen).ok_or("truncated header")?)
            .map_err(|_| "header is not text")?;
        let field = |key: &str| -> Result<&str, crate::Invalid> {
            let i = header.find(&format!("'{key}'")).ok_or(format!("header lacks '{key}'"))?;
            Ok(header[i + key.len() + 2..].trim_start().trim_start_matches(':').trim_start())
        };
        let descr_s = field("descr")?;
        let descr = descr_s.trim_start_matches(['\'', '"']).split(['\'', '"']).next().unwrap_or("");
        let fortran = field("fortran_order")?.starts_with("True");
        let shape_s = field("shape")?;
        let close = shape_s.find(')').ok_or("bad shape")?;
        let shape: Vec<usize> = shape_s[1..close]
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| s.trim_end_matches('L').parse::<usize>().map_err(|_| format!("bad shape entry {s:?}")))
            .collect::<Result<_, _>>()?;
        let n = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or("shape overflows")?;
        let body = &bytes[hstart + hlen..];
        let (be, code) = match descr.as_bytes().first() {
            Some(b'>') => (true, &descr[1..]),
            Some(b'<') | Some(b'|') | Some(b'=') => (false, &descr[1..]),
            _ => (false, descr),
        };
        let size = match code {
            "f4" | "i4" | "u4" => 4,
            "f8" | "i8" | "u8" => 8,
            "u1" | "i1" | "b1" => 1,
            "i2" | "u2" => 2,
            _ => return Err(crate::Invalid(format!("unsupported dtype {descr}"))),
        };
        let need = n.checked_mul(size).ok_or("size overflows")?;
        if body.len() < need {
            return Err(crate::Invalid(format!("truncated data: {} bytes for {need}", body.len())));
        }
        macro_rules! get {
            ($t:ty, $s:expr) => {
                body[..need]
                    .chunks_exact($s)
                    .map(|c| {
                        let a: [u8; $s] = c.try_into().unwrap_or([0; $s]);
                        if be { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }
                    })
                    .collect::<Vec<$t>>()
            };
        }
        let mut data = match code {
            "f4" => ArrayData::F32(get!(f32, 4)),
            "f8" => ArrayData::F64(get!(f64, 8)),
            "i4" => ArrayData::I32(get!(i32, 4)),
            "u4" => ArrayData::U32(get!(u32, 4)),
            "i8" => ArrayData::I64(get!(i64, 8)),
            "u8" => ArrayData::I64(get!(u64, 8).into_iter().map(|v| v as i64).collect()),
            "i2" => ArrayData::I32(get!(i16, 2).into_iter().map(i32::from).collect()),
            "u2" => ArrayData::I32(get!(u16, 2).into_iter().map(i32::from).collect()),
            "i1" => ArrayData::I32(body[..need].iter().map(|&b| b as i8 as i32).collect()),
            _ => ArrayData::U8(body[..need].to_vec()),
        };
        if fortran && shape.len() > 1 {
            data = fortran_to_c(data, &shape);
        }
        Ok(Array { shape, data })
    }
}

fn fortran_to_c(data: ArrayData, shape: &[usize]) -> ArrayData {
    fn perm<T: Copy>(v: &[T], shape: &[usize]) -> Vec<T> {
        let n = v.len();
        let mut out = Vec::with_capacity(n);
        let nd = shape.len();
        let mut idx = vec![0usize; nd];
        for _ in 0..n {
            // idx is the C-order multi-index; its Fortran offset:
            let mut off = 0;
            let mut stride = 1;
            for d in 0..nd {
                off += idx[d] * stride;
                stride *= shape[d];
            }
            out.push(v[off]);
            for d in (0..nd).rev() {
                idx[d] += 1;
                if idx[d] < shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        out
    }
    match data {
        ArrayData::F32(v) => ArrayData::F32(perm(&v, shape)),
        ArrayData::F64(v) => ArrayData::F64(perm(&v, shape)),
        ArrayData::I32(v) => ArrayData::I32(perm(&v, shape)),
        ArrayData::I64(v) => ArrayData::I64(perm(&v, shape)),
        ArrayData::U8(v) => ArrayData::U8(perm(&v, shape)),
        ArrayData::U32(v) => ArrayData::U32(perm(&v, shape)),
    }
}

/// Serialise named arrays as an uncompressed `.npz` with fixed timestamps, so equal
/// arrays give byte-identical files.
pub fn encode_npz(arrays: &[(&str, Array)]) -> std::io::Result<Vec<u8>> {
    encode_npz_with(arrays, false)
}

/// Like [`encode_npz`]; `compressed` deflates each array (as `numpy.savez_compressed`),
/// still deterministic for a given zlib implementation.
pub fn encode_npz_with(arrays: &[(&str, Array)], compressed: bool) -> std::io::Result<Vec<u8>> {
    let mut zw = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let method = if compressed { zip::CompressionMethod::Deflated } else { zip::CompressionMethod::Stored };
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(method)
        .last_modified_time(zip::DateTime::default())
        .large_file(false);
    for (name, arr) in arrays {
        let npy = arr.to_npy();
        let opts = if npy.len() as u64 >= u32::MAX as u64 { opts.large_file(true) } else { opts };
        zw.start_file(format!("{name}.npy"), opts).map_err(std::io::Error::other)?;
        zw.write_all(&npy)?;
    }
    Ok(zw.finish().map_err(std::io::Error::other)?.into_inner())
}

pub fn write_npz(path: &Path, arrays: &[(&str, Array)]) -> Result<(), NpzError> {
    let io = |source| NpzError::Io { path: path.into(), source };
    let bytes = encode_npz(arrays).map_err(io)?;
    crate::write_atomic(path, &bytes).map_err(io)
}

/// A read `.npz`: arrays by name.
#[derive(Clone, Debug)]
pub struct Npz {
    pub path: PathBuf,
    pub arrays: std::collections::BTreeMap<String, Array>,
}

impl Npz {
    pub fn read(path: &Path) -> Result<Self, NpzError> {
        let bytes = std::fs::read(path).map_err(|source| NpzError::Io { path: path.into(), source })?;
        Self::from_bytes(path, &bytes)
    }

    pub fn from_bytes(path: &Path, bytes: &[u8]) -> Result<Self, NpzError> {
        let fmt = |reason: String| NpzError::Format { path: path.into(), reason };
        let mut za = zip::ZipArchive::new(std::io::Cursor::new(bytes)).map_err(|e| fmt(e.to_string()))?;
        let mut arrays = std::collections::BTreeMap::new();
        for i in 0..za.len() {
            let mut f = za.by_index(i).map_err(|e| fmt(e.to_string()))?;
            let name = f.name().map_err(|e| fmt(e.to_string()))?.trim_end_matches(".npy").to_string();
            if f.size() > (8u64 << 30) {
                return Err(fmt(format!("entry {name} claims {} bytes", f.size())));
            }
            let mut buf = Vec::with_capacity(f.size() as usize);
            f.read_to_end(&mut buf).map_err(|e| fmt(format!("entry {name}: {e}")))?;
            let arr = Array::from_npy(&buf).map_err(|reason| NpzError::BadArray {
                path: path.into(),
                name: name.clone(),
                reason: reason.into(),
            })?;
            arrays.insert(name, arr);
        }
        Ok(Self { path: path.into(), arrays })
    }

    pub fn get(&self, name: &str) -> Result<&Array, NpzError> {
        self.arrays.get(name).ok_or_else(|| NpzError::Missing { path: self.path.clone(), name: name.into() })
    }

    /// An array as f64 with a checked shape; `None` entries in `shape` match any size.
    pub fn f64_with_shape(&self, name: &str, shape: &[Option<usize>]) -> Result<(Vec<usize>, Vec<f64>), NpzError> {
        let a = self.get(name)?;
        let ok = a.shape.len() == shape.len() && a.shape.iter().zip(shape).all(|(d, s)| s.is_none_or(|s| s == *d));
        if !ok {
            return Err(NpzError::BadArray {
                path: self.path.clone(),
                name: name.into(),
                reason: format!("shape {:?} does not match the expected {:?}", a.shape, shape),
            });
        }
        Ok((a.shape.clone(), a.data.to_f64()))
    }
}
