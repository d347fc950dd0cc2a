//! NumPy `.npy` arrays (and `.npz` members) in and out, through npyz: the reconstruction formats
//! [`crate::io::sequence`] reads are NumPy files (`megasam_depth.npy`, `*_sgd_cvd_hr.npz`, ...).
//!
//! Every size a file states is a claim, checked before anything is allocated for it: the header's
//! shape × item size must fit in the bytes that really follow the header (a `.npy` file's length;
//! for an `.npz` member, the uncompressed size in the zip directory, enforced by a reader that
//! stops there, because a small deflated member can inflate to gigabytes), the shape must be the
//! one the caller expects (from sibling arrays) and within [`MAX_ELEMENTS`] and [`MAX_SIDE_PX`].
//! An `.npz` member is read to its end and its CRC-32 compared with the zip directory's, so a
//! corrupted stored member is an error, not data. Errors name the file and, in an `.npz`, the
//! member (`scene.npz: member `depths.npy`: ...`).

use std::fmt;
use std::fs::File;
use std::io::{BufReader, Cursor, Read};
use std::path::{Path, PathBuf};

use npyz::{DType, NpyFile, NpyHeader, WriteOptions, WriterBuilder};

use crate::error::{Error, Result};

/// Largest image side in pixels accepted from a file (depth maps and frames in `.npy`/`.npz`
/// arrays, EXR data windows): the largest texture side of current GPUs, four times a 4K frame's
/// height and far beyond the 480×720 the model trains at. A header declaring more is broken or
/// hostile, and decoding it would allocate gigabytes for one image.
pub const MAX_SIDE_PX: usize = 16_384;

/// Largest number of values in one array read from a file: 2^31 (16 GiB once converted to `f64`).
/// That holds 3,600 frames of MegaSAM's 512×384 working resolution as `(N, H, W, 3)`, more than
/// any sequence read in one piece; a header declaring more would exhaust a workstation's memory.
pub const MAX_ELEMENTS: u64 = 1 << 31;

/// Longest `.npy` header text accepted: numpy's own limit (`numpy.lib.format._MAX_HEADER_SIZE`,
/// which `np.load` enforces unless told to trust the file).
const MAX_HEADER_BYTES: usize = 10_000;

/// The first bytes of every `.npy` file.
const MAGIC: &[u8] = b"\x93NUMPY";

/// Bytes before the header text: magic, two version bytes, then the text's length as a u16
/// (format 1.0) or a u32 (2.0 and 3.0).
const PREAMBLE_V1: usize = 10;
/// See [`PREAMBLE_V1`].
const PREAMBLE_V2: usize = 12;

/// Buffer for reading an `.npz` member's values and draining its unread rest (to reach its CRC
/// check): large enough that per-read overhead vanishes, small next to any array.
const DRAIN_BUFFER: usize = 64 * 1024;

/// The most a deflate stream can inflate: 1032 bytes out per byte in (a 258-byte match coded in
/// 2 bits; zlib's FAQ and `deflateBound`'s derivation). A zip directory declaring more for a
/// member than its compressed size allows is lying.
const MAX_DEFLATE_RATIO: u64 = 1032;

/// A dense n-dimensional array in C (row-major) order.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray<T> {
    /// Extent of each axis.
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values, last axis fastest.
    pub data: Vec<T>,
}

impl<T: Clone> NdArray<T> {
    /// The values split along the first axis, one `Vec` per index (none for a 0-d array).
    pub fn into_planes(self) -> Vec<Vec<T>> {
        let plane = self.shape.iter().skip(1).product::<usize>().max(1);
        self.data.chunks(plane).map(<[T]>::to_vec).collect()
    }
}

impl<T> NdArray<T> {
    /// Fails with an error naming `path` and `field` unless the array has `expected.len()` axes
    /// and each axis given as `Some(n)` has extent `n`.
    pub fn expect_shape(&self, path: &Path, field: &str, expected: &[Option<usize>]) -> Result<()> {
        let matches = self.shape.len() == expected.len()
            && self.shape.iter().zip(expected).all(|(&got, want)| want.is_none_or(|w| w == got));
        if matches {
            return Ok(());
        }
        let want: Vec<String> = expected.iter().map(|e| e.map_or("_".to_owned(), |n| n.to_string())).collect();
        Err(Error::invalid(path, field, format!("expected shape ({}), found {:?}", want.join(", "), self.shape)))
    }
}

/// One axis of the shape a reader expects, checked against the header before any data is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    /// Any extent (the total is still bounded by [`MAX_ELEMENTS`]).
    Any,
    /// Exactly this extent, typically a sibling array's.
    Is(usize),
    /// An image side in pixels: at most [`MAX_SIDE_PX`].
    Pixels,
}

impl Axis {
    fn admits(self, extent: usize) -> bool {
        match self {
            Self::Any => true,
            Self::Is(n) => extent == n,
            Self::Pixels => extent <= MAX_SIDE_PX,
        }
    }
}

impl fmt::Display for Axis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Any => write!(f, "_"),
            Self::Is(n) => write!(f, "{n}"),
            Self::Pixels => write!(f, "≤{MAX_SIDE_PX}"),
        }
    }
}

/// What an array's header declares, once checked against the bytes that follow it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ArrayHeader {
    /// Extent of each axis.
    pub shape: Vec<usize>,
    /// The NumPy dtype as written (`<f4`, `|u1`, `|b1`, ...).
    pub dtype: String,
}

/// The real-valued dtypes read, by their NumPy kind-and-size code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    F2,
    F4,
    F8,
    B1,
    U1,
    I1,
    U2,
    I2,
    U4,
    I4,
    U8,
    I8,
}

impl Kind {
    fn parse(descr: &str) -> Option<Self> {
        Some(match descr.trim_start_matches(['<', '>', '|', '=']) {
            "f2" => Self::F2,
            "f4" => Self::F4,
            "f8" => Self::F8,
            "b1" => Self::B1,
            "u1" => Self::U1,
            "i1" => Self::I1,
            "u2" => Self::U2,
            "i2" => Self::I2,
            "u4" => Self::U4,
            "i4" => Self::I4,
            "u8" => Self::U8,
            "i8" => Self::I8,
            _ => return None,
        })
    }

    fn item_bytes(self) -> u64 {
        match self {
            Self::B1 | Self::U1 | Self::I1 => 1,
            Self::F2 | Self::U2 | Self::I2 => 2,
            Self::F4 | Self::U4 | Self::I4 => 4,
            Self::F8 | Self::U8 | Self::I8 => 8,
        }
    }
}

/// Where an array lives, for errors: a `.npy` file, or a member of an `.npz` archive.
#[derive(Debug, Clone, Copy)]
struct Source<'a> {
    path: &'a Path,
    member: Option<&'a str>,
}

impl Source<'_> {
    fn error(self, reason: impl Into<String>) -> Error {
        Error::array(self.path, self.member, reason)
    }
}

/// A parsed header whose shape, dtype and data size have been checked.
struct Declared {
    header: NpyHeader,
    kind: Kind,
    info: ArrayHeader,
}

impl Declared {
    /// Whether the values are little-endian, the byte order [`read_little_endian`] reads.
    fn little_endian(&self) -> bool {
        matches!(self.header.dtype(), DType::Plain(t) if t.endianness() == npyz::Endianness::Little)
    }
}

/// Refuses a boolean array where measured values are read (depth maps, images): `True`/`False`
/// would become depths of 1 and 0, a plane and holes, instead of an error naming the file.
fn measured(declared: Declared, source: Source<'_>) -> Result<Declared> {
    if declared.kind == Kind::B1 {
        return Err(source.error(format!(
            "dtype {} is boolean: a mask, not measured values (depth, image): expected a float or integer dtype",
            declared.info.dtype
        )));
    }
    Ok(declared)
}

/// The error for array data that cannot be read.
fn data_error(source: Source<'_>, error: std::io::Error) -> Error {
    source.error(format!("cannot read array data (truncated or corrupt?): {error}"))
}

/// Reads and checks a `.npy` header from `reader`, which holds `available` bytes in all: the text
/// length, the dtype, the shape against `expected` and the ceilings, and the data size against
/// the bytes left after the header. Nothing larger than the (bounded) header text is allocated.
fn read_declared<R: Read>(
    reader: &mut R,
    source: Source<'_>,
    available: u64,
    expected: Option<&[Axis]>,
) -> Result<Declared> {
    let mut preamble = [0u8; PREAMBLE_V2];
    let too_short = |_| source.error("not a .npy array: shorter than the .npy preamble (truncated?)");
    reader.read_exact(&mut preamble[..PREAMBLE_V1]).map_err(too_short)?;
    if &preamble[..MAGIC.len()] != MAGIC {
        return Err(source.error("not a .npy array: no \\x93NUMPY magic at its start"));
    }
    let (preamble_len, text_len) = match preamble[MAGIC.len()] {
        1 => (PREAMBLE_V1, usize::from(u16::from_le_bytes([preamble[8], preamble[9]]))),
        2 | 3 => {
            reader.read_exact(&mut preamble[PREAMBLE_V1..]).map_err(too_short)?;
            let bytes = [preamble[8], preamble[9], preamble[10], preamble[11]];
            (PREAMBLE_V2, usize::try_from(u32::from_le_bytes(bytes)).unwrap_or(usize::MAX))
        }
        version => return Err(source.error(format!("unsupported .npy format version {version}"))),
    };
    if text_len > MAX_HEADER_BYTES {
        return Err(source.error(format!(
            "header declares {text_len} bytes of text; numpy writes and reads at most {MAX_HEADER_BYTES}"
        )));
    }
    let header_bytes = (preamble_len + text_len) as u64;
    if header_bytes > available {
        return Err(source.error(format!("truncated: the header needs {header_bytes} bytes, only {available} exist")));
    }
    let mut text = vec![0u8; text_len];
    reader.read_exact(&mut text).map_err(|e| source.error(format!("truncated header: {e}")))?;
    // npyz multiplies the extents unchecked while parsing (an overflow panic, or a wrapped
    // size), so the shape is read and bounded here first.
    let shape = HeaderText(&text).shape().map_err(|reason| source.error(format!("invalid .npy header: {reason}")))?;
    check_extents(&shape, source)?;
    let header = NpyHeader::from_reader(Cursor::new(&preamble[..preamble_len]).chain(&text[..]))
        .map_err(|e| source.error(format!("invalid .npy header: {e}")))?;
    if header.shape() != shape {
        return Err(source.error(format!("invalid .npy header: ambiguous shape {:?}", header.shape())));
    }
    check_declared(header, source, available - header_bytes, expected)
}

/// Fails unless the product of `shape`'s extents, zeros counted as one, is within
/// [`MAX_ELEMENTS`]: an empty array cannot declare other axes whose products (taken in any order
/// by the code using the shape) overflow.
fn check_extents(shape: &[u64], source: Source<'_>) -> Result<()> {
    let bound = shape.iter().try_fold(1u64, |total, &n| total.checked_mul(n.max(1)));
    if bound.is_none_or(|n| n > MAX_ELEMENTS) {
        return Err(source.error(format!(
            "header declares shape {shape:?}, more than the {MAX_ELEMENTS} values read from one array"
        )));
    }
    Ok(())
}

/// The header text of a `.npy` file, a Python dict literal such as
/// `{'descr': '<f4', 'fortran_order': False, 'shape': (3, 48, 64), }`, read strictly: string
/// keys, and values that are strings without escapes, booleans or tuples of decimal integers
/// (what numpy writes for every plain dtype; structured dtypes are not read anyway).
struct HeaderText<'a>(&'a [u8]);

impl HeaderText<'_> {
    /// The `shape` entry.
    fn shape(mut self) -> std::result::Result<Vec<u64>, String> {
        let mut shape = None;
        self.expect(b'{')?;
        while !self.eat(b'}') {
            let key = self.string()?;
            self.expect(b':')?;
            match self.peek() {
                Some(b'(') => {
                    let tuple = self.tuple()?;
                    if key == "shape" && shape.replace(tuple).is_some() {
                        return Err("two `shape` entries".to_owned());
                    }
                }
                Some(b'\'' | b'"') => {
                    self.string()?;
                }
                _ if self.word("True") || self.word("False") => {}
                _ => return Err(format!("unsupported value for `{key}` (structured dtypes are not read)")),
            }
            if !self.eat(b',') {
                self.expect(b'}')?;
                break;
            }
        }
        if !self.0.iter().all(u8::is_ascii_whitespace) {
            return Err("text after the closing brace".to_owned());
        }
        shape.ok_or_else(|| "no `shape` entry".to_owned())
    }

    fn skip_whitespace(&mut self) {
        let start = self.0.iter().position(|b| !b.is_ascii_whitespace()).unwrap_or(self.0.len());
        self.0 = &self.0[start..];
    }

    fn peek(&mut self) -> Option<u8> {
        self.skip_whitespace();
        self.0.first().copied()
    }

    fn eat(&mut self, byte: u8) -> bool {
        let found = self.peek() == Some(byte);
        if found {
            self.0 = &self.0[1..];
        }
        found
    }

    fn expect(&mut self, byte: u8) -> std::result::Result<(), String> {
        if self.eat(byte) { Ok(()) } else { Err(format!("expected `{}`", char::from(byte))) }
    }

    fn word(&mut self, word: &str) -> bool {
        let found = self.0.starts_with(word.as_bytes());
        if found {
            self.0 = &self.0[word.len()..];
        }
        found
    }

    fn string(&mut self) -> std::result::Result<String, String> {
        let quote = self.peek().filter(|q| matches!(q, b'\'' | b'"')).ok_or("expected a quoted key")?;
        let rest = &self.0[1..];
        let end = rest.iter().position(|&b| b == quote || b == b'\\').ok_or("unterminated string")?;
        if rest[end] != quote {
            return Err("escapes in strings are not read".to_owned());
        }
        let text = String::from_utf8_lossy(&rest[..end]).into_owned();
        self.0 = &rest[end + 1..];
        Ok(text)
    }

    fn tuple(&mut self) -> std::result::Result<Vec<u64>, String> {
        self.expect(b'(')?;
        let mut values = Vec::new();
        while !self.eat(b')') {
            self.skip_whitespace();
            let digits = self.0.iter().position(|b| !b.is_ascii_digit()).unwrap_or(self.0.len());
            let number = std::str::from_utf8(&self.0[..digits]).unwrap_or_default();
            values.push(number.parse::<u64>().map_err(|_| format!("extent `{number}` is not a u64"))?);
            self.0 = &self.0[digits..];
            if !self.eat(b',') {
                self.expect(b')')?;
                break;
            }
        }
        Ok(values)
    }
}

/// The checks of [`read_declared`] once the header is parsed; `data_available` bytes follow it.
fn check_declared(
    header: NpyHeader,
    source: Source<'_>,
    data_available: u64,
    expected: Option<&[Axis]>,
) -> Result<Declared> {
    if header.order() == npyz::Order::Fortran {
        return Err(source.error("Fortran-ordered arrays are not supported; save with np.ascontiguousarray"));
    }
    let dtype = match header.dtype() {
        DType::Plain(type_str) => type_str.to_string(),
        other => return Err(source.error(format!("unsupported dtype {}", other.descr()))),
    };
    let kind = Kind::parse(&dtype).ok_or_else(|| source.error(format!("unsupported dtype `{dtype}`")))?;
    let declared = header.shape();
    check_extents(declared, source)?;
    let elements: u64 = declared.iter().product();
    // Every extent is at most MAX_ELEMENTS, so it fits a usize.
    let shape: Vec<usize> = declared.iter().map(|&n| usize::try_from(n).unwrap_or(usize::MAX)).collect();
    if let Some(expected) = expected {
        let matches = shape.len() == expected.len() && shape.iter().zip(expected).all(|(&n, axis)| axis.admits(n));
        if !matches {
            let want: Vec<String> = expected.iter().map(Axis::to_string).collect();
            return Err(
                source.error(format!("header declares shape {shape:?} where ({}) is expected", want.join(", ")))
            );
        }
    }
    let data_bytes = elements * kind.item_bytes();
    if data_bytes > data_available {
        return Err(source.error(format!(
            "truncated: the header declares shape {shape:?} of `{dtype}` ({data_bytes} bytes) \
             but only {data_available} bytes follow it"
        )));
    }
    Ok(Declared { header, kind, info: ArrayHeader { shape, dtype } })
}

/// A real value type the arrays are read into: every dtype is converted through `f64` (exact for
/// every float16/32 and integer up to 2^53), then to `Self`, so `f32` arrays hold the same values
/// as `f64` ones narrowed, in half the memory.
pub trait Real: Copy {
    /// `value` as `Self` (rounded to nearest for `f32`).
    fn from_f64(value: f64) -> Self;
}

impl Real for f64 {
    fn from_f64(value: f64) -> Self {
        value
    }
}

impl Real for f32 {
    fn from_f64(value: f64) -> Self {
        value as f32
    }
}

/// Reads the data of a checked header as `T`, in C order.
fn read_values<R: Read, T: Real>(declared: Declared, reader: R, source: Source<'_>) -> Result<NdArray<T>> {
    // Little-endian floats, nearly every depth or pose array, are converted from whole blocks of
    // bytes: npyz's value-by-value reader took ~30 ns a value (0.5 s for a 49×480×720 depth).
    let little = declared.little_endian();
    let Declared { header, kind, info } = declared;
    let count = info.shape.iter().product::<usize>();
    let data: Vec<T> = match kind {
        Kind::F4 if little => read_little_endian(reader, count, |b| T::from_f64(f64::from(f32::from_le_bytes(b)))),
        Kind::F8 if little => read_little_endian(reader, count, |b| T::from_f64(f64::from_le_bytes(b))),
        kind => read_with_npyz(NpyFile::with_header(header, reader), kind)
            .map(|values| values.into_iter().map(T::from_f64).collect()),
    }
    .map_err(|e| data_error(source, e))?;
    let shape = info.shape;
    if data.len() != shape.iter().product::<usize>() {
        return Err(source.error(format!("holds {} values for shape {shape:?}", data.len())));
    }
    Ok(NdArray { shape, data })
}

/// The values of any dtype [`Kind`] names, read by npyz.
fn read_with_npyz<R: Read>(npy: NpyFile<R>, kind: Kind) -> std::io::Result<Vec<f64>> {
    match kind {
        Kind::F2 => npy.into_vec::<half::f16>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::F4 => npy.into_vec::<f32>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::F8 => npy.into_vec::<f64>(),
        Kind::U1 => npy.into_vec::<u8>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::B1 => npy.into_vec::<bool>().map(|v| v.into_iter().map(|b| f64::from(u8::from(b))).collect()),
        Kind::I1 => npy.into_vec::<i8>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::U2 => npy.into_vec::<u16>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::I2 => npy.into_vec::<i16>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::U4 => npy.into_vec::<u32>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::I4 => npy.into_vec::<i32>().map(|v| v.into_iter().map(f64::from).collect()),
        Kind::I8 => npy.into_vec::<i64>().map(|v| v.into_iter().map(|x| x as f64).collect()),
        Kind::U8 => npy.into_vec::<u64>().map(|v| v.into_iter().map(|x| x as f64).collect()),
    }
}

/// The `count` values of N bytes each that `reader` holds next, converted by `convert`; read a
/// block at a time (no second copy of the whole array).
fn read_little_endian<const N: usize, T>(
    mut reader: impl Read,
    count: usize,
    convert: impl Fn([u8; N]) -> T,
) -> std::io::Result<Vec<T>> {
    const BLOCK_VALUES: usize = 1 << 16;
    let mut values = Vec::with_capacity(count);
    let mut block = vec![0u8; BLOCK_VALUES.min(count) * N];
    while values.len() < count {
        let bytes = &mut block[..(count - values.len()).min(BLOCK_VALUES) * N];
        reader.read_exact(bytes)?;
        values.extend(bytes.chunks_exact(N).map(|c| convert(c.try_into().expect("chunks of N bytes"))));
    }
    Ok(values)
}

/// Reads any real-valued array (float16/32/64, signed or unsigned integers, bool) from a reader
/// positioned at the start of a `.npy` stream of `available` bytes, as `f64` in C order, after
/// the checks of the module docs. `path` and `member` (an `.npz` member name, or `None`) name
/// the source in errors.
pub fn read_array_f64<R: Read>(
    mut reader: R,
    available: u64,
    path: &Path,
    member: Option<&str>,
    expected: Option<&[Axis]>,
) -> Result<NdArray<f64>> {
    let source = Source { path, member };
    let declared = read_declared(&mut reader, source, available, expected)?;
    read_values(declared, reader, source)
}

fn open_npy(path: &Path) -> Result<(BufReader<File>, u64)> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let length = file.metadata().map_err(|e| Error::io(path, e))?.len();
    Ok((BufReader::new(file), length))
}

/// Reads a `.npy` file as `f64` (see [`read_array_f64`]); any shape within the ceilings.
pub fn read_npy_f64(path: &Path) -> Result<NdArray<f64>> {
    let (reader, length) = open_npy(path)?;
    read_array_f64(reader, length, path, None, None)
}

/// Reads a `.npy` file as `f64`, failing before its data is read unless the header's shape is
/// `expected`.
pub fn read_npy_f64_shaped(path: &Path, expected: &[Axis]) -> Result<NdArray<f64>> {
    let (reader, length) = open_npy(path)?;
    read_array_f64(reader, length, path, None, Some(expected))
}

/// The checked header of a `.npy` file, without reading its data.
pub fn read_npy_header(path: &Path) -> Result<ArrayHeader> {
    let (mut reader, length) = open_npy(path)?;
    Ok(read_declared(&mut reader, Source { path, member: None }, length, None)?.info)
}

/// Reads a `.npy` file as `f32` (values converted from any real dtype).
pub fn read_npy_f32(path: &Path) -> Result<NdArray<f32>> {
    let (mut reader, length) = open_npy(path)?;
    let source = Source { path, member: None };
    read_values(read_declared(&mut reader, source, length, None)?, reader, source)
}

/// A `.npy` array of at least one axis as `f32`, one `Vec` per index of its first axis (a stack
/// of depth maps: each map is kept as it is read, with no second copy of the whole stack), after
/// the header's shape is checked against `expected` (a boolean array is refused: see
/// [`measured`]). Returns the shape and the planes.
pub fn read_npy_f32_planes(path: &Path, expected: &[Axis]) -> Result<(Vec<usize>, Vec<Vec<f32>>)> {
    let (mut reader, length) = open_npy(path)?;
    let source = Source { path, member: None };
    let declared = measured(read_declared(&mut reader, source, length, Some(expected))?, source)?;
    let shape = declared.info.shape.clone();
    let (count, plane) = (shape.first().copied().unwrap_or(0), shape.iter().skip(1).product::<usize>());
    let planes = match declared.kind {
        // The common case, read plane by plane (f32 through f64 and back is the value itself, as
        // `read_values` gives it); other dtypes go through the whole-array reader.
        Kind::F4 if declared.little_endian() => (0..count)
            .map(|_| read_little_endian(&mut reader, plane, f32::from_le_bytes).map_err(|e| data_error(source, e)))
            .collect::<Result<_>>()?,
        _ => read_values::<_, f32>(declared, reader, source)?.into_planes(),
    };
    Ok((shape, planes))
}

/// An `.npz` archive, read one member at a time with the checks of the module docs.
pub struct NpzReader {
    path: PathBuf,
    archive: npyz::npz::NpzArchive<BufReader<File>>,
}

impl NpzReader {
    /// Opens the archive at `path` and reads its zip directory.
    pub fn open(path: &Path) -> Result<Self> {
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let archive = npyz::npz::NpzArchive::new(BufReader::new(file))
            .map_err(|e| Error::array(path, None, format!("not a readable .npz (zip) archive: {e}")))?;
        Ok(Self { path: path.to_owned(), archive })
    }

    /// Whether the archive has an array `name` (a member `name.npy`).
    pub fn contains(&self, name: &str) -> bool {
        self.archive.array_names().any(|n| n == name)
    }

    /// The checked header of array `name` (its shape against `expected`, the ceilings and the
    /// member's size in the zip directory), reading only the header: the member is not inflated.
    pub fn header(&mut self, name: &str, expected: Option<&[Axis]>) -> Result<ArrayHeader> {
        self.with_member(name, |member, source| {
            let size = member.size;
            Ok(read_declared(member, source, size, expected)?.info)
        })
    }

    /// Reads array `name` as `f64` (see [`read_array_f64`]), then the rest of its member, and
    /// checks the member's CRC-32 against the zip directory.
    pub fn read_f64(&mut self, name: &str, expected: &[Axis]) -> Result<NdArray<f64>> {
        self.read(name, expected, false)
    }

    /// [`Self::read_f64`] as `f32` (see [`Real`]), for measured values (depth, images): a boolean
    /// array is refused (see [`measured`]).
    pub fn read_f32(&mut self, name: &str, expected: &[Axis]) -> Result<NdArray<f32>> {
        self.read(name, expected, true)
    }

    fn read<T: Real>(&mut self, name: &str, expected: &[Axis], measurement: bool) -> Result<NdArray<T>> {
        self.with_member(name, |member, source| {
            let size = member.size;
            let declared = read_declared(member, source, size, Some(expected))?;
            let declared = if measurement { measured(declared, source)? } else { declared };
            // Buffered: values are read one at a time. What the buffer reads ahead is already
            // counted and hashed by the member reader, so `finish` goes on from there.
            let array = read_values(declared, BufReader::with_capacity(DRAIN_BUFFER, &mut *member), source)?;
            member.finish().map_err(|reason| source.error(reason))?;
            Ok(array)
        })
    }

    fn with_member<T>(
        &mut self,
        name: &str,
        read: impl FnOnce(&mut MemberReader<&mut dyn Read>, Source<'_>) -> Result<T>,
    ) -> Result<T> {
        let file_name = npyz::npz::file_name_from_array_name(name);
        let source = Source { path: &self.path, member: Some(&file_name) };
        if !self.archive.array_names().any(|n| n == name) {
            return Err(source.error("missing from the archive"));
        }
        let mut file = self
            .archive
            .zip_archive()
            .by_name(&file_name)
            .map_err(|e| source.error(format!("unreadable archive member: {e}")))?;
        check_member_size(&file, source)?;
        let (size, crc32) = (file.size(), file.crc32());
        let mut member =
            MemberReader { inner: &mut file as &mut dyn Read, size, read: 0, crc: flate2::Crc::new(), crc32 };
        read(&mut member, source)
    }
}

/// Refuses a zip member whose declared uncompressed size its compression cannot produce from its
/// compressed bytes: a stored member is its bytes, a deflated one at most [`MAX_DEFLATE_RATIO`]
/// times them. Numpy's `savez` and Python's `zipfile` as the tools use it write only these two
/// methods, so any other is refused too. Everything sized from the declared size (the array's
/// allocation, the reading bound) is then bounded by the file's real size.
fn check_member_size(file: &zip::read::ZipFile<'_>, source: Source<'_>) -> Result<()> {
    let (size, compressed) = (file.size(), file.compressed_size());
    let bound = match file.compression() {
        zip::CompressionMethod::Stored => compressed,
        zip::CompressionMethod::Deflated => compressed.saturating_mul(MAX_DEFLATE_RATIO),
        other => {
            return Err(source.error(format!(
                "compression method {other:?}: only stored and deflated members are read (as numpy and zipfile write them)"
            )));
        }
    };
    if size > bound {
        return Err(source.error(format!(
            "the zip directory declares {size} bytes, more than its {compressed} compressed bytes can hold ({}): the \
             archive lies about its size",
            if file.compression() == zip::CompressionMethod::Stored {
                "a stored member is its bytes".to_string()
            } else {
                format!("deflate inflates at most {MAX_DEFLATE_RATIO}×")
            }
        )));
    }
    Ok(())
}

/// The whole of zip member `file` of the archive `path`, checked as an `.npz` member is: its
/// declared size within what its compression allows ([`check_member_size`]), never read beyond
/// it, all of it there, and its CRC-32 the directory's. For archives of other files (ViPE's
/// depth zip of EXR maps); errors name the archive and the member.
pub fn read_zip_member(path: &Path, file: &mut zip::read::ZipFile<'_>) -> Result<Vec<u8>> {
    let name = file.name().to_owned();
    let source = Source { path, member: Some(&name) };
    check_member_size(file, source)?;
    let (size, crc32) = (file.size(), file.crc32());
    let mut member = MemberReader { inner: &mut *file as &mut dyn Read, size, read: 0, crc: flate2::Crc::new(), crc32 };
    // The declared size is bounded by the compressed bytes on disk, so reserving it is safe.
    let mut bytes = Vec::with_capacity(usize::try_from(size).unwrap_or(0));
    member.read_to_end(&mut bytes).map_err(|e| source.error(format!("unreadable member: {e}")))?;
    member.finish().map_err(|reason| source.error(reason))?;
    Ok(bytes)
}

/// A zip member's decompressed bytes, never more than the size the zip directory declares,
/// hashed on the way so that [`MemberReader::finish`] can compare the directory's CRC-32.
struct MemberReader<R> {
    inner: R,
    /// Uncompressed size from the zip directory.
    size: u64,
    /// Bytes yielded so far.
    read: u64,
    crc: flate2::Crc,
    /// CRC-32 from the zip directory.
    crc32: u32,
}

impl<R: Read> Read for MemberReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let room = usize::try_from(self.size - self.read).unwrap_or(usize::MAX);
        let len = buf.len().min(room);
        if len == 0 {
            return Ok(0);
        }
        let n = self.inner.read(&mut buf[..len])?;
        self.crc.update(&buf[..n]);
        self.read += n as u64;
        Ok(n)
    }
}

impl<R: Read> MemberReader<R> {
    /// Reads what the array did not use (bounded by the declared size), then checks that the
    /// member ends there and that its CRC-32 is the directory's. The zip crate checks CRCs only
    /// when a reader reaches the end, which reading an array's values alone never does.
    fn finish(&mut self) -> std::result::Result<(), String> {
        let mut sink = vec![0u8; DRAIN_BUFFER];
        loop {
            match self.read(&mut sink) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) => return Err(format!("unreadable after {} of its {} bytes: {e}", self.read, self.size)),
            }
        }
        if self.read < self.size {
            return Err(format!("holds {} bytes, the zip directory declares {}", self.read, self.size));
        }
        // One byte past the declared size: a member that inflates further lies about its size.
        let beyond = self.inner.read(&mut sink[..1]);
        if matches!(beyond, Ok(n) if n > 0) {
            return Err(format!("inflates beyond the {} bytes the zip directory declares", self.size));
        }
        let crc = self.crc.sum();
        if crc != self.crc32 {
            return Err(format!(
                "CRC mismatch: the data's CRC-32 is {crc:08x}, the zip directory records {:08x} (corrupt archive)",
                self.crc32
            ));
        }
        beyond.map(|_| ()).map_err(|e| format!("unreadable at its end: {e}"))
    }
}

/// Writes `data` with `shape` as a little-endian `.npy` file of `T`'s natural dtype.
pub fn write_npy<T: npyz::AutoSerialize>(path: &Path, shape: &[usize], data: &[T]) -> Result<()> {
    assert_eq!(shape.iter().product::<usize>(), data.len(), "shape and data disagree");
    let write = || -> std::io::Result<()> {
        let file = std::io::BufWriter::new(std::fs::File::create(path)?);
        let shape: Vec<u64> = shape.iter().map(|&n| n as u64).collect();
        let mut writer = WriteOptions::new().default_dtype().shape(&shape).writer(file).begin_nd()?;
        writer.extend(data.iter())?;
        writer.finish()
    };
    write().map_err(|e| Error::io(path, e))
}
#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f32_and_u8_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5 - 3.0).collect();
        write_npy(&path, &[2, 3, 4], &data).unwrap();
        let read = read_npy_f32(&path).unwrap();
        assert_eq!(read.shape, vec![2, 3, 4]);
        assert_eq!(read.data, data);
        let bytes: Vec<u8> = (0..6).collect();
        write_npy(&path, &[6], &bytes).unwrap();
        assert_eq!(read_npy_f64(&path).unwrap().data, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0]);
    }

    #[test]
    fn truncated_file_names_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("megasam_depth.npy");
        write_npy(&path, &[100], &vec![1.0f32; 100]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 40]).unwrap();
        let error = read_npy_f32(&path).unwrap_err().to_string();
        assert!(error.contains("megasam_depth.npy") && error.contains("megasam_depth"), "{error}");
    }

    #[test]
    fn declared_shape_is_checked_against_expectation_and_ceilings_before_data() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("k.npy");
        write_npy(&path, &[2, 3], &[1.0f64; 6]).unwrap();
        assert_eq!(read_npy_f64_shaped(&path, &[Axis::Is(2), Axis::Any]).unwrap().shape, vec![2, 3]);
        let error = read_npy_f64_shaped(&path, &[Axis::Is(3), Axis::Any]).unwrap_err().to_string();
        assert!(error.contains("[2, 3]") && error.contains("(3, _)"), "{error}");
        write_npy(&path, &[2, MAX_SIDE_PX + 1], &vec![0u8; 2 * (MAX_SIDE_PX + 1)]).unwrap();
        let error = read_npy_f64_shaped(&path, &[Axis::Any, Axis::Pixels]).unwrap_err().to_string();
        assert!(error.contains(&format!("≤{MAX_SIDE_PX}")), "{error}");
        assert_eq!(read_npy_header(&path).unwrap().shape, vec![2, MAX_SIDE_PX + 1]);
        // An empty array cannot declare axes whose product overflows.
        let huge = 1usize << 40;
        write_npy(&path, &[0, huge, huge], &Vec::<f32>::new()).unwrap();
        let error = read_npy_f64(&path).unwrap_err().to_string();
        assert!(error.contains("more than the"), "{error}");
    }

    #[test]
    fn header_text_is_read_strictly() {
        let shape = |text: &str| HeaderText(text.as_bytes()).shape();
        let numpy = "{'descr': '<f4', 'fortran_order': False, 'shape': (3, 48, 64), }          \n";
        assert_eq!(shape(numpy), Ok(vec![3, 48, 64]));
        assert_eq!(shape("{\"shape\": (), \"descr\": \"<f8\", \"fortran_order\": True}"), Ok(vec![]));
        assert_eq!(shape("{'descr': '|u1', 'shape': (7,)}"), Ok(vec![7]));
        // A `shape` inside a string is not the shape.
        assert_eq!(shape("{'descr': \"'shape': (1,)\", 'shape': (2, 2)}"), Ok(vec![2, 2]));
        for bad in [
            "{'descr': [('a', '<f4')], 'shape': (2,)}",
            "{'descr': '<f4', 'shape': (2, -1)}",
            "{'descr': '<f4', 'shape': (99999999999999999999,)}",
            "{'descr': '<f4', 'shape': (2,), 'shape': (3,)}",
            "{'descr': '<f\\x34', 'shape': (2,)}",
            "{'descr': '<f4'}",
            "{'descr': '<f4', 'shape': (2,)} junk",
        ] {
            assert!(shape(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn header_text_longer_than_numpy_allows_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("long.npy");
        let mut bytes = b"\x93NUMPY\x02\x00".to_vec();
        bytes.extend_from_slice(&((MAX_HEADER_BYTES + 1) as u32).to_le_bytes());
        bytes.resize(bytes.len() + MAX_HEADER_BYTES + 1, b' ');
        std::fs::write(&path, &bytes).unwrap();
        let error = read_npy_f64(&path).unwrap_err().to_string();
        assert!(error.starts_with(&format!("{}: header declares", path.display())), "{error}");
    }

    #[test]
    fn member_reader_stops_at_the_declared_size_and_checks_the_crc() {
        let data = b"0123456789";
        let mut crc = flate2::Crc::new();
        crc.update(data);
        let reader = |size, crc32| MemberReader { inner: &data[..], size, read: 0, crc: flate2::Crc::new(), crc32 };
        assert_eq!(reader(10, crc.sum()).finish(), Ok(()));
        assert!(reader(10, crc.sum() ^ 1).finish().unwrap_err().contains("CRC mismatch"));
        assert!(reader(4, crc.sum()).finish().unwrap_err().contains("inflates beyond the 4 bytes"));
        assert!(reader(12, crc.sum()).finish().unwrap_err().contains("holds 10 bytes"));
    }

    #[test]
    fn shape_check_reports_expected_and_found() {
        let array = NdArray { shape: vec![3, 4], data: vec![0.0; 12] };
        assert!(array.expect_shape("k.npy".as_ref(), "K", &[Some(3), Some(4)]).is_ok());
        let error = array.expect_shape("k.npy".as_ref(), "K", &[Some(3), Some(3)]).unwrap_err().to_string();
        assert!(error.contains("(3, 3)") && error.contains("[3, 4]"), "{error}");
    }
}
