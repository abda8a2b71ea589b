//! A small `.npy` / `.npz` codec: the arrays NumPy writes with `np.savez` (stored) or
//! `np.savez_compressed` (deflate), little-endian numeric and bool dtypes, C order.
//!
//! Errors name the file and the key so that a user's bad file is easy to find.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// Element type of an array.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    /// `<f4`
    F32,
    /// `<f8`
    F64,
    /// `<i4`
    I32,
    /// `<i8`
    I64,
    /// `|u1`
    U8,
    /// `|b1`
    Bool,
}

impl Dtype {
    fn from_descr(descr: &str) -> Option<Self> {
        Some(match descr {
            "<f4" | "=f4" => Dtype::F32,
            "<f8" | "=f8" => Dtype::F64,
            "<i4" | "=i4" => Dtype::I32,
            "<i8" | "=i8" => Dtype::I64,
            "|u1" | "<u1" => Dtype::U8,
            "|b1" | "<b1" => Dtype::Bool,
            _ => return None,
        })
    }

    fn descr(self) -> &'static str {
        match self {
            Dtype::F32 => "<f4",
            Dtype::F64 => "<f8",
            Dtype::I32 => "<i4",
            Dtype::I64 => "<i8",
            Dtype::U8 => "|u1",
            Dtype::Bool => "|b1",
        }
    }

    fn size(self) -> usize {
        match self {
            Dtype::F32 | Dtype::I32 => 4,
            Dtype::F64 | Dtype::I64 => 8,
            Dtype::U8 | Dtype::Bool => 1,
        }
    }

    /// NumPy's name of the dtype, for messages.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::F32 => "float32",
            Dtype::F64 => "float64",
            Dtype::I32 => "int32",
            Dtype::I64 => "int64",
            Dtype::U8 => "uint8",
            Dtype::Bool => "bool",
        }
    }
}

/// One array: dtype, shape and little-endian bytes in C order.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Element type.
    pub dtype: Dtype,
    /// Shape; empty for a scalar.
    pub shape: Vec<usize>,
    bytes: Vec<u8>,
}

macro_rules! le_values {
    ($bytes:expr, $ty:ty) => {
        $bytes
            .chunks_exact(std::mem::size_of::<$ty>())
            .map(|c| <$ty>::from_le_bytes(c.try_into().expect("chunk size")))
    };
}

impl Array {
    /// An `f32` array.
    pub fn f32(shape: &[usize], values: &[f32]) -> Self {
        Self::from_parts(
            Dtype::F32,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    /// An `f64` array.
    pub fn f64(shape: &[usize], values: &[f64]) -> Self {
        Self::from_parts(
            Dtype::F64,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    /// An `i32` array.
    pub fn i32(shape: &[usize], values: &[i32]) -> Self {
        Self::from_parts(
            Dtype::I32,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    /// An `i64` array.
    pub fn i64(shape: &[usize], values: &[i64]) -> Self {
        Self::from_parts(
            Dtype::I64,
            shape,
            values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        )
    }

    /// A `bool` array.
    pub fn bool(shape: &[usize], values: &[bool]) -> Self {
        Self::from_parts(
            Dtype::Bool,
            shape,
            values.iter().map(|&v| v as u8).collect(),
        )
    }

    /// A 0-d `f64` scalar.
    pub fn scalar(value: f64) -> Self {
        Self::f64(&[], &[value])
    }

    fn from_parts(dtype: Dtype, shape: &[usize], bytes: Vec<u8>) -> Self {
        let n: usize = shape.iter().product();
        assert_eq!(
            n * dtype.size(),
            bytes.len(),
            "array shape and data disagree"
        );
        Self {
            dtype,
            shape: shape.to_vec(),
            bytes,
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    /// Whether the array has no element.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The values as `f64`, from any float or integer dtype.
    pub fn to_f64(&self) -> Option<Vec<f64>> {
        Some(match self.dtype {
            Dtype::F32 => le_values!(self.bytes, f32).map(f64::from).collect(),
            Dtype::F64 => le_values!(self.bytes, f64).collect(),
            Dtype::I32 => le_values!(self.bytes, i32).map(f64::from).collect(),
            Dtype::I64 => le_values!(self.bytes, i64).map(|v| v as f64).collect(),
            Dtype::U8 | Dtype::Bool => return None,
        })
    }

    /// The values as `f32`, from `f32` or `f64`.
    pub fn to_f32(&self) -> Option<Vec<f32>> {
        Some(match self.dtype {
            Dtype::F32 => le_values!(self.bytes, f32).collect(),
            Dtype::F64 => le_values!(self.bytes, f64).map(|v| v as f32).collect(),
            _ => return None,
        })
    }

    /// The values as `i64`, from any integer dtype.
    pub fn to_i64(&self) -> Option<Vec<i64>> {
        Some(match self.dtype {
            Dtype::I32 => le_values!(self.bytes, i32).map(i64::from).collect(),
            Dtype::I64 => le_values!(self.bytes, i64).collect(),
            Dtype::U8 => self.bytes.iter().map(|&v| i64::from(v)).collect(),
            _ => return None,
        })
    }

    /// The values as `bool`, from `bool` or 0/1 integers.
    pub fn to_bool(&self) -> Option<Vec<bool>> {
        match self.dtype {
            Dtype::Bool | Dtype::U8 => Some(self.bytes.iter().map(|&v| v != 0).collect()),
            Dtype::I32 | Dtype::I64 => Some(self.to_i64()?.into_iter().map(|v| v != 0).collect()),
            _ => None,
        }
    }

    fn to_npy(&self) -> Vec<u8> {
        let shape = match self.shape.len() {
            0 => "()".to_string(),
            1 => format!("({},)", self.shape[0]),
            _ => format!(
                "({})",
                self.shape
                    .iter()
                    .map(|d| d.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        };
        let mut header = format!(
            "{{'descr': '{}', 'fortran_order': False, 'shape': {}, }}",
            self.dtype.descr(),
            shape
        );
        // Magic (6) + version (2) + length (2) + header, padded with spaces and a newline to a
        // multiple of 64 bytes.
        let unpadded = 10 + header.len() + 1;
        header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
        header.push('\n');
        let mut out = Vec::with_capacity(10 + header.len() + self.bytes.len());
        out.extend_from_slice(b"\x93NUMPY\x01\x00");
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(&self.bytes);
        out
    }

    fn from_npy(raw: &[u8]) -> std::result::Result<Self, String> {
        if raw.len() < 10 || &raw[..6] != b"\x93NUMPY" {
            return Err("not a .npy array (bad magic)".into());
        }
        let (header_len, start) = match raw[6] {
            1 => (u16::from_le_bytes([raw[8], raw[9]]) as usize, 10),
            2 | 3 => {
                if raw.len() < 12 {
                    return Err("truncated .npy header".into());
                }
                (
                    u32::from_le_bytes([raw[8], raw[9], raw[10], raw[11]]) as usize,
                    12,
                )
            }
            v => return Err(format!("unsupported .npy version {v}")),
        };
        let header = raw
            .get(start..start + header_len)
            .ok_or("truncated .npy header")?;
        let header = std::str::from_utf8(header).map_err(|_| "non-UTF-8 .npy header")?;
        let descr = dict_value(header, "descr").ok_or("header has no 'descr'")?;
        let descr = descr.trim_matches(|c| c == '\'' || c == '"');
        let dtype = Dtype::from_descr(descr).ok_or_else(|| {
            format!(
                "unsupported dtype '{descr}' (use little-endian float32/float64/int32/int64/bool)"
            )
        })?;
        if dict_value(header, "fortran_order").is_some_and(|v| v.starts_with("True")) {
            return Err(
                "Fortran-ordered arrays are not supported (save a C-contiguous array)".into(),
            );
        }
        let shape_text = dict_value(header, "shape").ok_or("header has no 'shape'")?;
        let inner = shape_text
            .trim()
            .strip_prefix('(')
            .and_then(|s| s.split(')').next())
            .ok_or("malformed 'shape'")?;
        let shape = inner
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| s.trim_end_matches('L').parse::<usize>())
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|_| format!("malformed shape {shape_text}"))?;
        let n: usize = shape.iter().product();
        let data = &raw[start + header_len..];
        if data.len() != n * dtype.size() {
            return Err(format!(
                "shape {shape:?} of {} needs {} bytes, the file holds {}",
                dtype.name(),
                n * dtype.size(),
                data.len()
            ));
        }
        Ok(Self {
            dtype,
            shape,
            bytes: data.to_vec(),
        })
    }
}

/// The text after `'key':` in a NumPy header dict, up to the next top-level comma.
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let pat_single = format!("'{key}':");
    let pat_double = format!("\"{key}\":");
    let at = header
        .find(&pat_single)
        .map(|i| i + pat_single.len())
        .or_else(|| header.find(&pat_double).map(|i| i + pat_double.len()))?;
    let rest = header[at..].trim_start();
    if rest.starts_with('(') {
        return Some(&rest[..rest.find(')')? + 1]);
    }
    Some(rest.split(',').next()?.trim())
}

/// The arrays of one `.npz` file, by key.
#[derive(Debug, Clone, Default)]
pub struct Npz {
    /// The file it came from (for messages).
    pub path: PathBuf,
    /// Arrays by key (the entry name without `.npy`).
    pub arrays: BTreeMap<String, Array>,
}

impl Npz {
    /// Reads every array of `path`.
    pub fn read(path: &Path) -> Result<Self> {
        let file = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
        let mut zip = zip::ZipArchive::new(BufReader::new(file))
            .with_context(|| format!("{} is not a .npz (zip) archive", path.display()))?;
        let mut arrays = BTreeMap::new();
        for i in 0..zip.len() {
            let mut entry = zip
                .by_index(i)
                .with_context(|| format!("{}: unreadable zip entry {i}", path.display()))?;
            let name = entry
                .name()
                .with_context(|| format!("{}: zip entry {i} has a bad name", path.display()))?
                .to_string();
            let Some(key) = name.strip_suffix(".npy") else {
                continue;
            };
            let mut raw = Vec::with_capacity(entry.size() as usize);
            entry
                .read_to_end(&mut raw)
                .with_context(|| format!("{}: cannot read key `{key}`", path.display()))?;
            let array = Array::from_npy(&raw)
                .map_err(|e| anyhow::anyhow!("{}: key `{key}`: {e}", path.display()))?;
            arrays.insert(key.to_string(), array);
        }
        Ok(Self {
            path: path.to_path_buf(),
            arrays,
        })
    }

    /// Writes the arrays to `path` atomically (a temporary file renamed into place).
    pub fn write(&self, path: &Path) -> Result<()> {
        crate::io::write_atomic(path, |file| {
            let mut zip = zip::ZipWriter::new(BufWriter::new(file));
            for (key, array) in &self.arrays {
                let npy = array.to_npy();
                let options = zip::write::SimpleFileOptions::default()
                    .compression_method(zip::CompressionMethod::Stored)
                    .large_file(npy.len() as u64 >= u32::MAX as u64);
                zip.start_file(format!("{key}.npy"), options)?;
                zip.write_all(&npy)?;
            }
            zip.finish()?.flush()?;
            Ok(())
        })
    }

    /// Adds or replaces an array.
    pub fn insert(&mut self, key: &str, array: Array) {
        self.arrays.insert(key.to_string(), array);
    }

    /// Whether `key` exists.
    pub fn has(&self, key: &str) -> bool {
        self.arrays.contains_key(key)
    }

    fn get(&self, key: &str) -> Result<&Array> {
        self.arrays.get(key).ok_or_else(|| {
            anyhow::anyhow!(
                "{}: missing key `{key}` (has: {})",
                self.path.display(),
                self.arrays.keys().cloned().collect::<Vec<_>>().join(", ")
            )
        })
    }

    fn check_shape(&self, key: &str, array: &Array, expect: &[Option<usize>]) -> Result<()> {
        let ok = array.shape.len() == expect.len()
            && array
                .shape
                .iter()
                .zip(expect)
                .all(|(&d, e)| e.is_none_or(|e| e == d));
        if !ok {
            let want: Vec<String> = expect
                .iter()
                .map(|e| e.map_or("*".to_string(), |d| d.to_string()))
                .collect();
            bail!(
                "{}: key `{key}` has shape {:?}, expected [{}]",
                self.path.display(),
                array.shape,
                want.join(", ")
            );
        }
        Ok(())
    }

    /// A float array as `f32`, checked against `shape` (`None` = any size) and for finiteness.
    pub fn f32(&self, key: &str, shape: &[Option<usize>]) -> Result<(Vec<f32>, Vec<usize>)> {
        let a = self.get(key)?;
        self.check_shape(key, a, shape)?;
        let v = a.to_f32().ok_or_else(|| {
            anyhow::anyhow!(
                "{}: key `{key}` has dtype {}, expected float32 or float64",
                self.path.display(),
                a.dtype.name()
            )
        })?;
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            bail!(
                "{}: key `{key}` holds a non-finite value ({}) at flat index {i}{}",
                self.path.display(),
                v[i],
                unravel(&a.shape, i)
            );
        }
        Ok((v, a.shape.clone()))
    }

    /// A finite scalar (0-d or one-element array of any numeric dtype).
    pub fn scalar(&self, key: &str) -> Result<f64> {
        let a = self.get(key)?;
        if a.len() != 1 || a.shape.len() > 1 {
            bail!(
                "{}: key `{key}` must be a scalar, has shape {:?}",
                self.path.display(),
                a.shape
            );
        }
        let v = a.to_f64().ok_or_else(|| {
            anyhow::anyhow!(
                "{}: key `{key}` must be numeric, has dtype {}",
                self.path.display(),
                a.dtype.name()
            )
        })?[0];
        if !v.is_finite() {
            bail!("{}: key `{key}` is not finite ({v})", self.path.display());
        }
        Ok(v)
    }

    /// An integer array, checked against `shape`.
    pub fn int(&self, key: &str, shape: &[Option<usize>]) -> Result<(Vec<i64>, Vec<usize>)> {
        let a = self.get(key)?;
        self.check_shape(key, a, shape)?;
        let v = a.to_i64().ok_or_else(|| {
            anyhow::anyhow!(
                "{}: key `{key}` has dtype {}, expected an integer type",
                self.path.display(),
                a.dtype.name()
            )
        })?;
        Ok((v, a.shape.clone()))
    }

    /// A boolean array, checked against `shape`.
    pub fn bool(&self, key: &str, shape: &[Option<usize>]) -> Result<Vec<bool>> {
        let a = self.get(key)?;
        self.check_shape(key, a, shape)?;
        a.to_bool().ok_or_else(|| {
            anyhow::anyhow!(
                "{}: key `{key}` has dtype {}, expected bool",
                self.path.display(),
                a.dtype.name()
            )
        })
    }
}

/// ` (index [i, j, k])` for a flat index into `shape`.
fn unravel(shape: &[usize], mut flat: usize) -> String {
    if shape.len() < 2 {
        return String::new();
    }
    let mut idx = vec![0; shape.len()];
    for (d, &n) in shape.iter().enumerate().rev() {
        idx[d] = flat % n;
        flat /= n;
    }
    format!(" (index {idx:?})")
}

/// Writes `bytes` to `w`; used by tests that build malformed files.
#[doc(hidden)]
pub fn npy_bytes(array: &Array) -> Vec<u8> {
    array.to_npy()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_every_dtype_and_shape() {
        let dir = std::env::temp_dir().join(format!("springtime-npz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.npz");
        let mut npz = Npz::default();
        npz.insert("x", Array::f32(&[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.5]));
        npz.insert("d", Array::scalar(0.001));
        npz.insert("i", Array::i32(&[3], &[1, -2, 3]));
        npz.insert("p", Array::bool(&[2], &[true, false]));
        npz.write(&path).unwrap();
        let back = Npz::read(&path).unwrap();
        assert_eq!(back.arrays, npz.arrays);
        assert_eq!(back.f32("x", &[Some(2), None]).unwrap().0[5], 6.5);
        assert_eq!(back.scalar("d").unwrap(), 0.001);
        let err = back.f32("x", &[Some(3), None]).unwrap_err().to_string();
        assert!(err.contains("`x`") && err.contains("shape"), "{err}");
        let err = back.f32("nope", &[None]).unwrap_err().to_string();
        assert!(err.contains("missing key `nope`"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn non_finite_values_are_named() {
        let mut npz = Npz {
            path: "bad.npz".into(),
            ..Default::default()
        };
        npz.insert(
            "positions",
            Array::f32(&[1, 2, 3], &[0.0, 1.0, f32::NAN, 0.0, 0.0, 0.0]),
        );
        let err = npz
            .f32("positions", &[None, None, Some(3)])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("bad.npz") && err.contains("`positions`") && err.contains("[0, 0, 2]"),
            "{err}"
        );
    }

    #[test]
    fn header_is_64_byte_aligned_and_parses_numpy_style() {
        let a = Array::f64(&[4], &[1.0, 2.0, 3.0, 4.0]);
        let raw = a.to_npy();
        let header_len = u16::from_le_bytes([raw[8], raw[9]]) as usize;
        assert_eq!((10 + header_len) % 64, 0);
        // NumPy writes `(4,)` and a trailing space-padded dict; both forms must parse.
        assert_eq!(Array::from_npy(&raw).unwrap(), a);
    }
}
