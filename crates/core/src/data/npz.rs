//! A lenient `.npy` / `.npz` codec: reads what NumPy writes with `np.savez` (stored) or
//! `np.savez_compressed` (deflate), in any byte order and in C or Fortran order, and writes
//! little-endian C-ordered arrays.
//!
//! Real files carry more than springtime needs: strings, pickled objects, structured records.
//! Reading never fails on such a key: its header is parsed leniently and its raw bytes are kept
//! as an [`Unreadable`] entry, and only asking for it as numbers fails — with the file, the key
//! and the dtype. Numeric keys (float16/32/64, signed and unsigned integers of every width,
//! bool) are decoded to native little-endian C order on read.
//!
//! Errors name the file and the key so that a user's bad file is easy to find.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// The dtypes a float key converts from, for messages.
const NUMERIC: &str = "a float or integer type";
/// Element type of a numeric array.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    /// `<f2`
    F16,
    /// `<f4`
    F32,
    /// `<f8`
    F64,
    /// `|i1`
    I8,
    /// `<i2`
    I16,
    /// `<i4`
    I32,
    /// `<i8`
    I64,
    /// `|u1`
    U8,
    /// `<u2`
    U16,
    /// `<u4`
    U32,
    /// `<u8`
    U64,
    /// `|b1`
    Bool,
}

/// Each dtype with the type string springtime writes, NumPy's one-character code for it and
/// NumPy's name.
#[rustfmt::skip]
const DTYPES: [(Dtype, &str, &str, &str); 12] = [
    (Dtype::F16, "<f2", "e", "float16"), (Dtype::F32, "<f4", "f", "float32"),
    (Dtype::F64, "<f8", "d", "float64"), (Dtype::I8, "|i1", "b", "int8"),
    (Dtype::I16, "<i2", "h", "int16"), (Dtype::I32, "<i4", "i", "int32"),
    (Dtype::I64, "<i8", "q", "int64"), (Dtype::U8, "|u1", "B", "uint8"),
    (Dtype::U16, "<u2", "H", "uint16"), (Dtype::U32, "<u4", "I", "uint32"),
    (Dtype::U64, "<u8", "Q", "uint64"), (Dtype::Bool, "|b1", "?", "bool"),
];

/// What a dtype string names: a numeric type and its byte order, or why it is not one.
struct Descr {
    dtype: Dtype,
    big_endian: bool,
}

impl Dtype {
    /// Parses a NumPy type string such as `<f4`, `>i8`, `|b1`, `=u2` or `?`.
    fn parse(descr: &str) -> std::result::Result<Descr, String> {
        let (order, body) = match descr.chars().next() {
            Some(c @ ('<' | '>' | '=' | '|' | '!')) => (c, &descr[1..]),
            _ => ('=', descr),
        };
        let big_endian =
            matches!(order, '>' | '!') || (order == '=' && cfg!(target_endian = "big"));
        let Some(&(dtype, ..)) = DTYPES
            .iter()
            .find(|&&(_, written, code, _)| body == &written[1..] || body == code)
        else {
            let what = match body.chars().next() {
                Some('U') => "Unicode strings",
                Some('S' | 'a') => "byte strings",
                Some('O') => "Python objects (pickled)",
                Some('c') => "complex numbers",
                Some('M') => "datetimes",
                Some('m') => "time deltas",
                Some('V') => "raw records",
                Some('f') => "floats of an unsupported width",
                Some('i' | 'u') => "integers of an unsupported width",
                _ => "an unknown type",
            };
            return Err(format!(
                "dtype '{descr}' holds {what}, not numbers springtime can read"
            ));
        };
        Ok(Descr { dtype, big_endian })
    }

    /// This dtype's row of [`DTYPES`].
    fn row(self) -> &'static (Dtype, &'static str, &'static str, &'static str) {
        DTYPES
            .iter()
            .find(|row| row.0 == self)
            .expect("every dtype has a row")
    }

    /// The little-endian type string springtime writes.
    fn descr(self) -> &'static str {
        self.row().1
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Dtype::I8 | Dtype::U8 | Dtype::Bool => 1,
            Dtype::F16 | Dtype::I16 | Dtype::U16 => 2,
            Dtype::F32 | Dtype::I32 | Dtype::U32 => 4,
            Dtype::F64 | Dtype::I64 | Dtype::U64 => 8,
        }
    }

    /// NumPy's name of the dtype, for messages.
    pub fn name(self) -> &'static str {
        self.row().3
    }

    fn is_float(self) -> bool {
        matches!(self, Dtype::F16 | Dtype::F32 | Dtype::F64)
    }
}

/// One numeric array: dtype, shape and little-endian bytes in C order.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Element type.
    pub dtype: Dtype,
    /// Shape; empty for a scalar.
    pub shape: Vec<usize>,
    bytes: Vec<u8>,
}

/// An entry that is not a numeric array (strings, pickled objects, records, a damaged header):
/// kept as read, so that it is skipped unless springtime needs it and survives a rewrite.
#[derive(Debug, Clone, PartialEq)]
pub struct Unreadable {
    /// The dtype as the header spells it (`<U5`, `|O`, `[('a', '<f4')]`), or `?` when the header
    /// itself could not be read.
    pub descr: String,
    /// Why springtime cannot use it as numbers.
    pub reason: String,
    /// The whole `.npy` entry.
    raw: Vec<u8>,
}

macro_rules! le_values {
    ($bytes:expr, $ty:ty) => {
        $bytes
            .chunks_exact(std::mem::size_of::<$ty>())
            .map(|c| <$ty>::from_le_bytes(c.try_into().expect("chunk size")))
    };
}

/// IEEE half precision to single precision (exact).
fn f16_to_f32(h: u16) -> f32 {
    let negative = h & 0x8000 != 0;
    let exp = u32::from((h >> 10) & 0x1f);
    let mant = u32::from(h & 0x3ff);
    let magnitude = match exp {
        0 => mant as f32 * (1.0 / 16_777_216.0), // zero and subnormals: mant · 2⁻²⁴
        0x1f => f32::from_bits(0x7f80_0000 | (mant << 13)),
        _ => f32::from_bits(((exp + 112) << 23) | (mant << 13)),
    };
    if negative { -magnitude } else { magnitude }
}

/// `values` as little-endian bytes, in one allocation of the final size.
fn le_bytes<T: num_traits::ToBytes>(values: &[T]) -> Vec<u8> {
    let mut out = Vec::with_capacity(std::mem::size_of_val(values));
    for v in values {
        out.extend_from_slice(v.to_le_bytes().as_ref());
    }
    out
}

impl Array {
    /// An `f32` array.
    pub fn f32(shape: &[usize], values: &[f32]) -> Self {
        Self::from_parts(Dtype::F32, shape, le_bytes(values))
    }

    /// An `f64` array.
    pub fn f64(shape: &[usize], values: &[f64]) -> Self {
        Self::from_parts(Dtype::F64, shape, le_bytes(values))
    }

    /// An `i32` array.
    pub fn i32(shape: &[usize], values: &[i32]) -> Self {
        Self::from_parts(Dtype::I32, shape, le_bytes(values))
    }

    /// An `i64` array.
    pub fn i64(shape: &[usize], values: &[i64]) -> Self {
        Self::from_parts(Dtype::I64, shape, le_bytes(values))
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

    /// The values as `f64`, from any float or integer dtype (not bool).
    pub fn to_f64(&self) -> Option<Vec<f64>> {
        let b = &self.bytes;
        Some(match self.dtype {
            Dtype::F16 => le_values!(b, u16)
                .map(|h| f64::from(f16_to_f32(h)))
                .collect(),
            Dtype::F32 => le_values!(b, f32).map(f64::from).collect(),
            Dtype::F64 => le_values!(b, f64).collect(),
            Dtype::I8 => b.iter().map(|&v| f64::from(v as i8)).collect(),
            Dtype::I16 => le_values!(b, i16).map(f64::from).collect(),
            Dtype::I32 => le_values!(b, i32).map(f64::from).collect(),
            Dtype::I64 => le_values!(b, i64).map(|v| v as f64).collect(),
            Dtype::U8 => b.iter().map(|&v| f64::from(v)).collect(),
            Dtype::U16 => le_values!(b, u16).map(f64::from).collect(),
            Dtype::U32 => le_values!(b, u32).map(f64::from).collect(),
            Dtype::U64 => le_values!(b, u64).map(|v| v as f64).collect(),
            Dtype::Bool => return None,
        })
    }

    /// The values as `f32`, from any float or integer dtype (not bool).
    pub fn to_f32(&self) -> Option<Vec<f32>> {
        match self.dtype {
            Dtype::F32 => Some(le_values!(self.bytes, f32).collect()),
            Dtype::F16 => Some(le_values!(self.bytes, u16).map(f16_to_f32).collect()),
            _ => Some(self.to_f64()?.into_iter().map(|v| v as f32).collect()),
        }
    }

    /// The values as `i64`, from any integer dtype, or a float dtype holding whole numbers
    /// (not bool; `None` when a value does not fit).
    pub(crate) fn to_i64(&self) -> Option<Vec<i64>> {
        let b = &self.bytes;
        Some(match self.dtype {
            Dtype::I8 => b.iter().map(|&v| i64::from(v as i8)).collect(),
            Dtype::I16 => le_values!(b, i16).map(i64::from).collect(),
            Dtype::I32 => le_values!(b, i32).map(i64::from).collect(),
            Dtype::I64 => le_values!(b, i64).collect(),
            Dtype::U8 => b.iter().map(|&v| i64::from(v)).collect(),
            Dtype::U16 => le_values!(b, u16).map(i64::from).collect(),
            Dtype::U32 => le_values!(b, u32).map(i64::from).collect(),
            Dtype::U64 => le_values!(b, u64)
                .map(i64::try_from)
                .collect::<std::result::Result<_, _>>()
                .ok()?,
            Dtype::F16 | Dtype::F32 | Dtype::F64 => self
                .to_f64()?
                .into_iter()
                .map(|v| (v.fract() == 0.0 && v.abs() < 9.0e15).then_some(v as i64))
                .collect::<Option<_>>()?,
            Dtype::Bool => return None,
        })
    }

    /// The values as `bool`, from `bool` or integers (non-zero = true).
    pub(crate) fn to_bool(&self) -> Option<Vec<bool>> {
        match self.dtype {
            Dtype::Bool => Some(self.bytes.iter().map(|&v| v != 0).collect()),
            d if d.is_float() => None,
            _ => Some(self.to_i64()?.into_iter().map(|v| v != 0).collect()),
        }
    }

    /// The `.npy` header of the array: magic, version, length and the padded dictionary.
    fn npy_header(&self) -> Vec<u8> {
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
        let mut out = Vec::with_capacity(10 + header.len());
        out.extend_from_slice(b"\x93NUMPY\x01\x00");
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out
    }

    /// The whole `.npy` entry: the header, then the data.
    #[cfg(test)]
    fn to_npy(&self) -> Vec<u8> {
        let mut out = self.npy_header();
        out.extend_from_slice(&self.bytes);
        out
    }

    /// Decodes one `.npy` entry: a numeric array, or the reason it is not one (with the dtype
    /// as the header spells it).
    fn from_npy(raw: &[u8]) -> std::result::Result<Self, (String, String)> {
        let header = NpyHeader::parse(raw).map_err(|e| ("?".to_string(), e))?;
        let fail = |reason: String| (header.descr.clone(), reason);
        let Descr { dtype, big_endian } = match &header.descr_kind {
            DescrKind::Simple => Dtype::parse(&header.descr).map_err(fail)?,
            DescrKind::Structured => {
                return Err(fail(format!(
                    "structured dtype {} (records with named fields), not a plain number array",
                    header.descr
                )));
            }
        };
        let shape = header.shape.clone();
        let n: usize = shape.iter().product();
        let size = dtype.size();
        let data = &raw[header.data_start..];
        if data.len() != n * size {
            return Err(fail(format!(
                "shape {shape:?} of {} needs {} bytes, the file holds {}",
                dtype.name(),
                n * size,
                data.len()
            )));
        }
        let mut bytes = data.to_vec();
        if big_endian && size > 1 {
            for element in bytes.chunks_exact_mut(size) {
                element.reverse();
            }
        }
        if header.fortran_order && shape.len() > 1 {
            bytes = fortran_to_c(&bytes, &shape, size);
        }
        Ok(Self {
            dtype,
            shape,
            bytes,
        })
    }
}

/// Reorders the elements of a Fortran-ordered (first axis fastest) array into C order.
fn fortran_to_c(bytes: &[u8], shape: &[usize], size: usize) -> Vec<u8> {
    let rank = shape.len();
    // Fortran strides, in elements.
    let mut stride = vec![1usize; rank];
    for d in 1..rank {
        stride[d] = stride[d - 1] * shape[d - 1];
    }
    let mut out = Vec::with_capacity(bytes.len());
    let mut index = vec![0usize; rank];
    let n: usize = shape.iter().product();
    for _ in 0..n {
        let f: usize = index.iter().zip(&stride).map(|(i, s)| i * s).sum();
        out.extend_from_slice(&bytes[f * size..(f + 1) * size]);
        // Next C-order index: the last axis fastest.
        for d in (0..rank).rev() {
            index[d] += 1;
            if index[d] < shape[d] {
                break;
            }
            index[d] = 0;
        }
    }
    out
}

enum DescrKind {
    /// A type string such as `<f4`.
    Simple,
    /// A list of fields.
    Structured,
}

/// The parts of a `.npy` header that springtime reads.
struct NpyHeader {
    descr: String,
    descr_kind: DescrKind,
    fortran_order: bool,
    shape: Vec<usize>,
    data_start: usize,
}

impl NpyHeader {
    fn parse(raw: &[u8]) -> std::result::Result<Self, String> {
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
        // Version 3 allows UTF-8 field names; only the structure matters here.
        let header = String::from_utf8_lossy(header);
        let fields = dict_fields(&header);
        let descr = fields.get("descr").ok_or("header has no 'descr'")?.trim();
        let (descr, descr_kind) = if descr.starts_with('\'') || descr.starts_with('"') {
            (
                descr.trim_matches(|c| c == '\'' || c == '"').to_string(),
                DescrKind::Simple,
            )
        } else {
            (descr.to_string(), DescrKind::Structured)
        };
        let fortran_order = fields
            .get("fortran_order")
            .is_some_and(|v| v.trim() == "True");
        let shape_text = fields.get("shape").ok_or("header has no 'shape'")?;
        let inner = shape_text
            .trim()
            .strip_prefix('(')
            .and_then(|s| s.strip_suffix(')'))
            .ok_or_else(|| format!("malformed shape {shape_text}"))?;
        let shape = inner
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| s.trim_end_matches('L').parse::<usize>())
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|_| format!("malformed shape {shape_text}"))?;
        Ok(Self {
            descr,
            descr_kind,
            fortran_order,
            shape,
            data_start: start + header_len,
        })
    }
}

/// The `key: value` pairs of a NumPy header (a Python dict literal), values as raw text.
/// Lenient: nested brackets and quoted strings inside values are kept whole, unknown keys are
/// returned too, and text that does not parse ends the scan.
fn dict_fields(header: &str) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let chars: Vec<char> = header.chars().collect();
    let mut i = 0;
    let skip = |i: &mut usize, set: &[char]| {
        while *i < chars.len() && (chars[*i].is_whitespace() || set.contains(&chars[*i])) {
            *i += 1;
        }
    };
    skip(&mut i, &['{']);
    while i < chars.len() {
        skip(&mut i, &[',']);
        let Some(&quote @ ('\'' | '"')) = chars.get(i) else {
            break;
        };
        let key_start = i + 1;
        let Some(len) = chars[key_start..].iter().position(|&c| c == quote) else {
            break;
        };
        let key: String = chars[key_start..key_start + len].iter().collect();
        i = key_start + len + 1;
        skip(&mut i, &[]);
        if chars.get(i) != Some(&':') {
            break;
        }
        i += 1;
        let value_start = i;
        let mut depth = 0i32;
        let mut in_quote: Option<char> = None;
        while i < chars.len() {
            let c = chars[i];
            match in_quote {
                Some(q) if c == q => in_quote = None,
                Some(_) => {}
                None => match c {
                    '\'' | '"' => in_quote = Some(c),
                    '(' | '[' | '{' => depth += 1,
                    ')' | ']' => depth -= 1,
                    '}' if depth > 0 => depth -= 1,
                    ',' | '}' if depth == 0 => break,
                    _ => {}
                },
            }
            i += 1;
        }
        let value: String = chars[value_start..i].iter().collect();
        out.insert(key, value.trim().to_string());
    }
    out
}

/// The arrays of one `.npz` file, by key.
#[derive(Debug, Clone, Default)]
pub struct Npz {
    /// The file it came from (for messages).
    pub path: PathBuf,
    /// Numeric arrays by key (the entry name without `.npy`).
    pub arrays: BTreeMap<String, Array>,
    /// Entries that are not numeric arrays (strings, objects, records, damaged headers), by key;
    /// skipped unless asked for, and written back unchanged.
    pub unreadable: BTreeMap<String, Unreadable>,
}

impl Npz {
    /// Reads every entry of `path`. Only a file that is not a readable zip archive fails here;
    /// an entry that is not a numeric array is kept in [`Npz::unreadable`].
    pub fn read(path: &Path) -> Result<Self> {
        let file = File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
        let mut zip = zip::ZipArchive::new(BufReader::new(file))
            .with_context(|| format!("{} is not a .npz (zip) archive", path.display()))?;
        let mut arrays = BTreeMap::new();
        let mut unreadable = BTreeMap::new();
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
            // The size is the archive's claim: a damaged header may claim terabytes.
            let mut raw = Vec::with_capacity(entry.size().min(64 << 20) as usize);
            if let Err(e) = entry.read_to_end(&mut raw) {
                unreadable.insert(
                    key.to_string(),
                    Unreadable {
                        descr: "?".into(),
                        reason: format!("the zip entry cannot be read: {e}"),
                        raw: Vec::new(),
                    },
                );
                continue;
            }
            match Array::from_npy(&raw) {
                Ok(array) => {
                    arrays.insert(key.to_string(), array);
                }
                Err((descr, reason)) => {
                    unreadable.insert(key.to_string(), Unreadable { descr, reason, raw });
                }
            }
        }
        Ok(Self {
            path: path.to_path_buf(),
            arrays,
            unreadable,
        })
    }

    /// Writes the arrays to `path` atomically (a temporary file renamed into place).
    pub fn write(&self, path: &Path) -> Result<()> {
        crate::io::write_atomic(path, |file| {
            let mut zip = zip::ZipWriter::new(BufWriter::new(file));
            // Each entry as its header and its data, written one after the other (a big
            // array is not copied into one buffer first).
            let entries = self
                .arrays
                .iter()
                .map(|(key, array)| (key, array.npy_header(), &array.bytes[..]))
                .chain(
                    self.unreadable
                        .iter()
                        .filter(|(_, u)| !u.raw.is_empty())
                        .map(|(key, u)| (key, Vec::new(), &u.raw[..])),
                );
            for (key, header, data) in entries {
                let size = (header.len() + data.len()) as u64;
                let options = zip::write::SimpleFileOptions::default()
                    .compression_method(zip::CompressionMethod::Stored)
                    .large_file(size >= u32::MAX as u64);
                zip.start_file(format!("{key}.npy"), options)?;
                zip.write_all(&header)?;
                zip.write_all(data)?;
            }
            zip.finish()?.flush()?;
            Ok(())
        })
    }

    /// Adds or replaces an array.
    pub fn insert(&mut self, key: &str, array: Array) {
        self.arrays.insert(key.to_string(), array);
    }

    /// Whether `key` exists (readable or not).
    pub fn has(&self, key: &str) -> bool {
        self.arrays.contains_key(key) || self.unreadable.contains_key(key)
    }

    /// Every key of the file, sorted.
    pub fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = self
            .arrays
            .keys()
            .chain(self.unreadable.keys())
            .cloned()
            .collect();
        keys.sort();
        keys
    }

    /// The numeric array `key`; an error names the file and the key, and for an entry that is
    /// not a numeric array, its dtype and why.
    pub fn get(&self, key: &str) -> Result<&Array> {
        if let Some(a) = self.arrays.get(key) {
            return Ok(a);
        }
        if let Some(u) = self.unreadable.get(key) {
            bail!(
                "{}: key `{key}` (dtype {}) cannot be used: {}",
                self.path.display(),
                u.descr,
                u.reason
            );
        }
        bail!(
            "{}: missing key `{key}` (has: {})",
            self.path.display(),
            self.keys().join(", ")
        )
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
        self.finite(key, shape, Array::to_f32)
    }

    /// A float array as `f64`, checked against `shape` (`None` = any size) and for finiteness.
    pub fn f64(&self, key: &str, shape: &[Option<usize>]) -> Result<(Vec<f64>, Vec<usize>)> {
        self.finite(key, shape, Array::to_f64)
    }

    /// A float array as `f32`, checked against `shape` but not for finiteness (NaN may mark a
    /// value that is not there: a hidden marker's position).
    pub(crate) fn f32_any(
        &self,
        key: &str,
        shape: &[Option<usize>],
    ) -> Result<(Vec<f32>, Vec<usize>)> {
        self.converted(key, shape, Array::to_f32, NUMERIC)
    }

    /// `key` converted by `convert`, checked against `shape`; `expected` says what dtypes
    /// convert.
    fn converted<T>(
        &self,
        key: &str,
        shape: &[Option<usize>],
        convert: fn(&Array) -> Option<Vec<T>>,
        expected: &str,
    ) -> Result<(Vec<T>, Vec<usize>)> {
        let a = self.get(key)?;
        self.check_shape(key, a, shape)?;
        let v = convert(a).ok_or_else(|| {
            anyhow::anyhow!(
                "{}: key `{key}` has dtype {}, expected {expected}",
                self.path.display(),
                a.dtype.name()
            )
        })?;
        Ok((v, a.shape.clone()))
    }

    /// `key` converted by `convert`, checked against `shape` and for finiteness.
    fn finite<T: Copy + Into<f64> + std::fmt::Display>(
        &self,
        key: &str,
        shape: &[Option<usize>],
        convert: fn(&Array) -> Option<Vec<T>>,
    ) -> Result<(Vec<T>, Vec<usize>)> {
        let (v, shape) = self.converted(key, shape, convert, NUMERIC)?;
        if let Some(i) = v.iter().position(|x| !(*x).into().is_finite()) {
            bail!(
                "{}: key `{key}` holds a non-finite value ({}) at flat index {i}{}",
                self.path.display(),
                v[i],
                unravel(&shape, i)
            );
        }
        Ok((v, shape))
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
        self.converted(
            key,
            shape,
            Array::to_i64,
            "integers (an integer type, or whole floats)",
        )
    }

    /// A boolean array, checked against `shape`.
    pub fn bool(&self, key: &str, shape: &[Option<usize>]) -> Result<Vec<bool>> {
        let a = self.get(key)?;
        self.check_shape(key, a, shape)?;
        a.to_bool().ok_or_else(|| {
            anyhow::anyhow!(
                "{}: key `{key}` has dtype {}, expected bool (or 0/1 integers)",
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
