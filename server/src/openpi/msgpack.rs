//! The msgpack subset openpi speaks, with openpi's numpy extension (`openpi_client.msgpack_numpy`).
//!
//! Decoding is zero-copy (strings and binaries borrow the frame) and bounded: at most
//! [`MAX_DEPTH`] levels of nesting and `max_nodes` values in all, so a small frame that declares a
//! huge array of one-byte values cannot make the server allocate a tree many times its size. The
//! whole frame must be one value.
//!
//! numpy arrays travel as maps `{b"__ndarray__": True, b"data": <bin>, b"dtype": "<f4", b"shape":
//! [..]}` and numpy scalars as `{b"__npgeneric__": True, b"data": <value>, b"dtype": ".."}`; the
//! Python packer writes those keys as msgpack `bin` (they are `bytes`), and the Python unpacker
//! only recognises them as `bin`, so [`Writer::ndarray`] writes them so too. Readers here accept
//! keys as `str` or `bin`.

use std::fmt;

/// Deepest nesting a frame may have (openpi observations are two or three levels deep).
pub const MAX_DEPTH: usize = 32;

/// A decoded msgpack value, borrowing strings and binaries from the frame.
#[derive(Clone, Debug, PartialEq)]
pub enum Value<'a> {
    /// `nil`.
    Nil,
    /// `true`/`false`.
    Bool(bool),
    /// A non-negative integer.
    UInt(u64),
    /// A negative integer.
    Int(i64),
    /// `float 32` or `float 64`.
    Float(f64),
    /// `str`, valid UTF-8.
    Str(&'a str),
    /// `bin`.
    Bin(&'a [u8]),
    /// `array`.
    Array(Vec<Value<'a>>),
    /// `map`, in frame order.
    Map(Vec<(Value<'a>, Value<'a>)>),
    /// `ext` (type, data); openpi does not use it.
    Ext(i8, &'a [u8]),
}

impl<'a> Value<'a> {
    /// The text of a `str`, or of a `bin` that is UTF-8 (the numpy extension's keys are `bin`).
    pub fn as_text(&self) -> Option<&'a str> {
        match *self {
            Value::Str(s) => Some(s),
            Value::Bin(b) => std::str::from_utf8(b).ok(),
            _ => None,
        }
    }

    /// The value under `key` of a map (keys compared as text).
    pub fn get(&self, key: &str) -> Option<&Value<'a>> {
        match self {
            Value::Map(entries) => entries
                .iter()
                .find(|(k, _)| k.as_text() == Some(key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    /// A short name of the value's type, for error messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Value::Nil => "nil",
            Value::Bool(_) => "bool",
            Value::UInt(_) | Value::Int(_) => "int",
            Value::Float(_) => "float",
            Value::Str(_) => "str",
            Value::Bin(_) => "bin",
            Value::Array(_) => "array",
            Value::Map(_) => "map",
            Value::Ext(..) => "ext",
        }
    }
}

/// Why a frame is not one msgpack value within the bounds.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// The frame ended inside a value.
    #[error("not msgpack: the frame ends inside a value (at byte {0})")]
    Truncated(usize),
    /// A byte that starts no msgpack value (0xc1).
    #[error("not msgpack: invalid marker 0x{marker:02x} at byte {at}")]
    InvalidMarker {
        /// The byte.
        marker: u8,
        /// Its offset.
        at: usize,
    },
    /// A `str` that is not UTF-8.
    #[error("not msgpack: a str at byte {0} is not UTF-8")]
    NotUtf8(usize),
    /// Bytes after the value.
    #[error("not msgpack: {0} bytes after the value")]
    Trailing(usize),
    /// Nested deeper than [`MAX_DEPTH`].
    #[error("msgpack nested deeper than {MAX_DEPTH} levels")]
    TooDeep,
    /// More values than allowed.
    #[error("msgpack frame holds more than {0} values")]
    TooManyValues(usize),
}

/// Decodes `frame` as exactly one msgpack value of at most `max_nodes` values in all.
pub fn decode(frame: &[u8], max_nodes: usize) -> Result<Value<'_>, DecodeError> {
    let mut reader = Reader {
        bytes: frame,
        at: 0,
        nodes: 0,
        max_nodes,
    };
    let value = reader.value(0)?;
    if reader.at != frame.len() {
        return Err(DecodeError::Trailing(frame.len() - reader.at));
    }
    Ok(value)
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    nodes: usize,
    max_nodes: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&end| end <= self.bytes.len())
            .ok_or(DecodeError::Truncated(self.bytes.len()))?;
        let slice = &self.bytes[self.at..end];
        self.at = end;
        Ok(slice)
    }

    fn be<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    fn len(&mut self, bytes: usize) -> Result<usize, DecodeError> {
        Ok(match bytes {
            1 => usize::from(self.be::<1>()?[0]),
            2 => usize::from(u16::from_be_bytes(self.be()?)),
            _ => u32::from_be_bytes(self.be()?) as usize,
        })
    }

    fn str(&mut self, len: usize) -> Result<Value<'a>, DecodeError> {
        let start = self.at;
        let bytes = self.take(len)?;
        std::str::from_utf8(bytes)
            .map(Value::Str)
            .map_err(|_| DecodeError::NotUtf8(start))
    }

    fn array(&mut self, len: usize, depth: usize) -> Result<Value<'a>, DecodeError> {
        // Each element is at least one byte: a length past the frame's end is truncated, and
        // the preallocation is bounded by the frame.
        if len > self.bytes.len() - self.at {
            return Err(DecodeError::Truncated(self.bytes.len()));
        }
        let mut items = Vec::with_capacity(len);
        for _ in 0..len {
            items.push(self.value(depth + 1)?);
        }
        Ok(Value::Array(items))
    }

    fn map(&mut self, len: usize, depth: usize) -> Result<Value<'a>, DecodeError> {
        if len.saturating_mul(2) > self.bytes.len() - self.at {
            return Err(DecodeError::Truncated(self.bytes.len()));
        }
        let mut entries = Vec::with_capacity(len);
        for _ in 0..len {
            let key = self.value(depth + 1)?;
            let value = self.value(depth + 1)?;
            entries.push((key, value));
        }
        Ok(Value::Map(entries))
    }

    fn ext(&mut self, len: usize) -> Result<Value<'a>, DecodeError> {
        let kind = i8::from_be_bytes(self.be()?);
        Ok(Value::Ext(kind, self.take(len)?))
    }

    fn value(&mut self, depth: usize) -> Result<Value<'a>, DecodeError> {
        if depth > MAX_DEPTH {
            return Err(DecodeError::TooDeep);
        }
        self.nodes += 1;
        if self.nodes > self.max_nodes {
            return Err(DecodeError::TooManyValues(self.max_nodes));
        }
        let at = self.at;
        let marker = self.be::<1>()?[0];
        Ok(match marker {
            0x00..=0x7f => Value::UInt(u64::from(marker)),
            0x80..=0x8f => return self.map(usize::from(marker & 0x0f), depth),
            0x90..=0x9f => return self.array(usize::from(marker & 0x0f), depth),
            0xa0..=0xbf => return self.str(usize::from(marker & 0x1f)),
            0xc0 => Value::Nil,
            0xc2 => Value::Bool(false),
            0xc3 => Value::Bool(true),
            0xc4..=0xc6 => {
                let len = self.len(1 << (marker - 0xc4))?;
                Value::Bin(self.take(len)?)
            }
            0xc7..=0xc9 => {
                let len = self.len(1 << (marker - 0xc7))?;
                return self.ext(len);
            }
            0xca => Value::Float(f64::from(f32::from_be_bytes(self.be()?))),
            0xcb => Value::Float(f64::from_be_bytes(self.be()?)),
            0xcc => Value::UInt(u64::from(self.be::<1>()?[0])),
            0xcd => Value::UInt(u64::from(u16::from_be_bytes(self.be()?))),
            0xce => Value::UInt(u64::from(u32::from_be_bytes(self.be()?))),
            0xcf => Value::UInt(u64::from_be_bytes(self.be()?)),
            0xd0 => int(i64::from(i8::from_be_bytes(self.be()?))),
            0xd1 => int(i64::from(i16::from_be_bytes(self.be()?))),
            0xd2 => int(i64::from(i32::from_be_bytes(self.be()?))),
            0xd3 => int(i64::from_be_bytes(self.be()?)),
            0xd4..=0xd8 => return self.ext(1 << (marker - 0xd4)),
            0xd9..=0xdb => {
                let len = self.len(1 << (marker - 0xd9))?;
                return self.str(len);
            }
            0xdc | 0xdd => {
                let len = self.len(if marker == 0xdc { 2 } else { 4 })?;
                return self.array(len, depth);
            }
            0xde | 0xdf => {
                let len = self.len(if marker == 0xde { 2 } else { 4 })?;
                return self.map(len, depth);
            }
            0xe0..=0xff => Value::Int(i64::from(marker as i8)),
            0xc1 => return Err(DecodeError::InvalidMarker { marker, at }),
        })
    }
}

/// Signed integers that are not negative are `UInt`, so one comparison covers both encodings.
fn int(v: i64) -> Value<'static> {
    match u64::try_from(v) {
        Ok(u) => Value::UInt(u),
        Err(_) => Value::Int(v),
    }
}

/// A numpy dtype as `dtype.str` spells it (`<f4`, `|u1`, ...): byte order, kind, item size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DType {
    /// Little-endian (`<`, or `|` for one-byte types).
    pub little_endian: bool,
    /// `f` float, `i` signed, `u` unsigned, `b` bool.
    pub kind: char,
    /// Bytes per item.
    pub size: usize,
}

impl DType {
    /// Parses `dtype.str`; only numeric and bool dtypes are accepted.
    pub fn parse(s: &str) -> Option<DType> {
        let mut chars = s.chars();
        let order = chars.next()?;
        let kind = chars.next()?;
        let size: usize = chars.as_str().parse().ok()?;
        let little_endian = match order {
            '<' | '|' | '=' => true,
            '>' => false,
            _ => return None,
        };
        let ok = match kind {
            'f' => matches!(size, 2 | 4 | 8),
            'i' | 'u' => matches!(size, 1 | 2 | 4 | 8),
            'b' => size == 1,
            _ => false,
        };
        ok.then_some(DType {
            little_endian,
            kind,
            size,
        })
    }

    /// Reads item `bytes` (exactly `size` of them) as a number.
    pub(crate) fn read(&self, bytes: &[u8]) -> f64 {
        let mut b = [0u8; 8];
        b[..self.size].copy_from_slice(bytes);
        if !self.little_endian {
            b[..self.size].reverse();
        }
        match (self.kind, self.size) {
            ('f', 2) => f64::from(half_to_f32(u16::from_le_bytes([b[0], b[1]]))),
            ('f', 4) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            ('f', _) => f64::from_le_bytes(b),
            ('i', n) => {
                // Sign-extend the n-byte little-endian integer.
                let shift = 64 - 8 * n as u32;
                ((i64::from_le_bytes(b) << shift) >> shift) as f64
            }
            _ => u64::from_le_bytes(b) as f64,
        }
    }
}

impl fmt::Display for DType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let order = if self.size == 1 {
            '|'
        } else if self.little_endian {
            '<'
        } else {
            '>'
        };
        write!(f, "{order}{}{}", self.kind, self.size)
    }
}

/// IEEE half precision to `f32`.
fn half_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = i32::from((h >> 10) & 0x1f);
    let frac = f32::from(h & 0x3ff);
    match exp {
        0 => sign * frac * 2f32.powi(-24),
        31 if frac == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        _ => sign * (1.0 + frac / 1024.0) * 2f32.powi(exp - 15),
    }
}

/// A numpy array from a frame, its data borrowed.
#[derive(Clone, Debug, PartialEq)]
pub struct NdArray<'a> {
    /// Element type.
    pub dtype: DType,
    /// Dimensions (empty for a scalar).
    pub shape: Vec<usize>,
    /// Raw bytes, C order, `shape.product() * dtype.size` of them.
    pub data: &'a [u8],
}

/// Why a value is not a numeric numpy array.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ArrayError {
    /// Not an `__ndarray__` map (or a number, or a numpy scalar).
    #[error("expected a numpy array, got a msgpack {0}")]
    NotAnArray(&'static str),
    /// A field of the `__ndarray__` map is missing or mistyped.
    #[error("numpy array: `{0}` is missing or of the wrong type")]
    Field(&'static str),
    /// A dtype that is not numeric.
    #[error("numpy dtype `{0}` is not supported (numeric and bool dtypes only)")]
    DType(String),
    /// `data` does not hold `shape` items.
    #[error("numpy array: shape {shape:?} of {dtype} needs {expected} bytes, data has {actual}")]
    Length {
        /// The shape.
        shape: Vec<usize>,
        /// The dtype.
        dtype: String,
        /// Bytes the shape needs.
        expected: usize,
        /// Bytes present.
        actual: usize,
    },
}

impl<'a> NdArray<'a> {
    /// Reads an `__ndarray__` map. Numbers and numpy scalars are not arrays here; see
    /// [`numbers`] for a reader that takes them too.
    pub fn from_value(value: &Value<'a>) -> Result<NdArray<'a>, ArrayError> {
        if value.get("__ndarray__").is_none() {
            return Err(ArrayError::NotAnArray(value.kind()));
        }
        let data = match value.get("data") {
            Some(Value::Bin(b)) => *b,
            _ => return Err(ArrayError::Field("data")),
        };
        let dtype_text = value
            .get("dtype")
            .and_then(Value::as_text)
            .ok_or(ArrayError::Field("dtype"))?;
        let dtype =
            DType::parse(dtype_text).ok_or_else(|| ArrayError::DType(dtype_text.to_string()))?;
        let shape = match value.get("shape") {
            Some(Value::Array(dims)) => dims
                .iter()
                .map(|d| match d {
                    Value::UInt(n) => usize::try_from(*n).ok(),
                    _ => None,
                })
                .collect::<Option<Vec<usize>>>()
                .ok_or(ArrayError::Field("shape"))?,
            _ => return Err(ArrayError::Field("shape")),
        };
        let expected = shape
            .iter()
            .try_fold(dtype.size, |acc, &d| acc.checked_mul(d))
            .unwrap_or(usize::MAX);
        if expected != data.len() {
            return Err(ArrayError::Length {
                shape,
                dtype: dtype.to_string(),
                expected,
                actual: data.len(),
            });
        }
        Ok(NdArray { dtype, shape, data })
    }

    /// Number of items.
    pub fn len(&self) -> usize {
        self.data.len() / self.dtype.size
    }

    /// Whether it holds no items.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// Every item as `f32`, C order.
    pub fn to_f32(&self) -> Vec<f32> {
        self.data
            .chunks_exact(self.dtype.size)
            .map(|item| self.dtype.read(item) as f32)
            .collect()
    }
}

/// The numbers of a numpy array, a numpy scalar, a plain number or a list of plain numbers,
/// flattened to `f32` (openpi clients send states as arrays of any float dtype, and sometimes a
/// gripper position as a scalar).
pub fn numbers(value: &Value<'_>) -> Result<Vec<f32>, ArrayError> {
    let scalar = |v: &Value<'_>| match *v {
        Value::UInt(n) => Some(n as f32),
        Value::Int(n) => Some(n as f32),
        Value::Float(x) => Some(x as f32),
        Value::Bool(b) => Some(if b { 1.0 } else { 0.0 }),
        _ => None,
    };
    if let Some(x) = scalar(value) {
        return Ok(vec![x]);
    }
    if value.get("__npgeneric__").is_some() {
        return value
            .get("data")
            .and_then(scalar)
            .map(|x| vec![x])
            .ok_or(ArrayError::Field("data"));
    }
    if let Value::Array(items) = value {
        return items
            .iter()
            .map(|v| scalar(v).ok_or(ArrayError::NotAnArray(v.kind())))
            .collect();
    }
    Ok(NdArray::from_value(value)?.to_f32())
}

/// How many numbers [`numbers`] would read from `value`, without reading them: a bound a caller
/// checks before it allocates.
pub fn number_count(value: &Value<'_>) -> Result<usize, ArrayError> {
    match value {
        Value::UInt(_) | Value::Int(_) | Value::Float(_) | Value::Bool(_) => Ok(1),
        _ if value.get("__npgeneric__").is_some() => Ok(1),
        Value::Array(items) => Ok(items.len()),
        _ => {
            let array = NdArray::from_value(value)?;
            Ok(array.data.len() / array.dtype.size)
        }
    }
}

/// Builds one msgpack frame (the subset the replies need).
#[derive(Debug, Default)]
pub struct Writer {
    buf: Vec<u8>,
}

impl Writer {
    /// An empty frame.
    pub fn new() -> Writer {
        Writer::default()
    }

    /// The frame's bytes.
    pub fn finish(self) -> Vec<u8> {
        self.buf
    }

    fn header(&mut self, len: usize, fix: (u8, usize), m16: u8, m32: u8) {
        if len < fix.1 {
            self.buf.push(fix.0 | len as u8);
        } else if let Ok(n) = u16::try_from(len) {
            self.buf.push(m16);
            self.buf.extend_from_slice(&n.to_be_bytes());
        } else {
            self.buf.push(m32);
            self.buf
                .extend_from_slice(&u32::try_from(len).unwrap_or(u32::MAX).to_be_bytes());
        }
    }

    /// A map header of `len` entries; the caller writes `len` key/value pairs.
    pub fn map(&mut self, len: usize) -> &mut Self {
        self.header(len, (0x80, 16), 0xde, 0xdf);
        self
    }

    /// An array header of `len` items.
    pub fn array(&mut self, len: usize) -> &mut Self {
        self.header(len, (0x90, 16), 0xdc, 0xdd);
        self
    }

    /// A `str`.
    pub fn str(&mut self, s: &str) -> &mut Self {
        if s.len() < 32 {
            self.buf.push(0xa0 | s.len() as u8);
        } else if let Ok(n) = u8::try_from(s.len()) {
            self.buf.extend_from_slice(&[0xd9, n]);
        } else {
            self.header(s.len(), (0, 0), 0xda, 0xdb);
        }
        self.buf.extend_from_slice(s.as_bytes());
        self
    }

    /// A `bin`.
    pub fn bin(&mut self, b: &[u8]) -> &mut Self {
        if let Ok(n) = u8::try_from(b.len()) {
            self.buf.extend_from_slice(&[0xc4, n]);
        } else {
            self.header(b.len(), (0, 0), 0xc5, 0xc6);
        }
        self.buf.extend_from_slice(b);
        self
    }

    /// A non-negative integer.
    pub fn uint(&mut self, v: u64) -> &mut Self {
        if v < 128 {
            self.buf.push(v as u8);
        } else {
            self.buf.push(0xcf);
            self.buf.extend_from_slice(&v.to_be_bytes());
        }
        self
    }

    /// A `float 64`.
    pub fn float(&mut self, v: f64) -> &mut Self {
        self.buf.push(0xcb);
        self.buf.extend_from_slice(&v.to_be_bytes());
        self
    }

    /// A bool.
    pub fn bool(&mut self, v: bool) -> &mut Self {
        self.buf.push(if v { 0xc3 } else { 0xc2 });
        self
    }

    /// A negative integer (`int 64`).
    pub fn int(&mut self, v: i64) -> &mut Self {
        self.buf.push(0xd3);
        self.buf.extend_from_slice(&v.to_be_bytes());
        self
    }

    /// An `ext` of type `kind`.
    pub fn ext(&mut self, kind: i8, data: &[u8]) -> &mut Self {
        match data.len() {
            1 => self.buf.push(0xd4),
            2 => self.buf.push(0xd5),
            4 => self.buf.push(0xd6),
            8 => self.buf.push(0xd7),
            16 => self.buf.push(0xd8),
            len => self.header(len, (0, 0), 0xc8, 0xc9),
        }
        self.buf.extend_from_slice(&kind.to_be_bytes());
        self.buf.extend_from_slice(data);
        self
    }

    /// Any decoded value, recursively: what [`decode`] reads back as the same value.
    pub fn value(&mut self, value: &Value<'_>) -> &mut Self {
        match value {
            Value::Nil => self.buf.push(0xc0),
            Value::Bool(b) => {
                self.bool(*b);
            }
            Value::UInt(v) => {
                self.uint(*v);
            }
            Value::Int(v) => {
                self.int(*v);
            }
            Value::Float(v) => {
                self.float(*v);
            }
            Value::Str(s) => {
                self.str(s);
            }
            Value::Bin(b) => {
                self.bin(b);
            }
            Value::Array(items) => {
                self.array(items.len());
                for item in items {
                    self.value(item);
                }
            }
            Value::Map(entries) => {
                self.map(entries.len());
                for (key, item) in entries {
                    self.value(key).value(item);
                }
            }
            Value::Ext(kind, data) => {
                self.ext(*kind, data);
            }
        }
        self
    }

    /// A numpy `float32` array of `shape` (C order), as openpi's `msgpack_numpy` writes it.
    pub fn ndarray_f32(&mut self, shape: &[usize], values: &[f32]) -> &mut Self {
        let mut data = Vec::with_capacity(values.len() * 4);
        for v in values {
            data.extend_from_slice(&v.to_le_bytes());
        }
        self.ndarray_raw(shape, "<f4", &data)
    }

    /// A numpy array of little-endian `data` with `dtype` (`dtype.str`) and `shape`.
    pub fn ndarray_raw(&mut self, shape: &[usize], dtype: &str, data: &[u8]) -> &mut Self {
        self.map(4);
        self.bin(b"__ndarray__").bool(true);
        self.bin(b"data").bin(data);
        self.bin(b"dtype").str(dtype);
        self.bin(b"shape").array(shape.len());
        for &d in shape {
            self.uint(d as u64);
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_what_the_writer_writes() {
        let mut w = Writer::new();
        w.map(3);
        w.str("actions")
            .ndarray_f32(&[2, 2], &[1.0, -2.0, 0.5, 3.0]);
        w.str("name").str(&"x".repeat(40));
        w.str("n").uint(300);
        let frame = w.finish();
        let value = decode(&frame, 100).unwrap();
        let actions = NdArray::from_value(value.get("actions").unwrap()).unwrap();
        assert_eq!(actions.shape, [2, 2]);
        assert_eq!(actions.dtype.to_string(), "<f4");
        assert_eq!(actions.to_f32(), [1.0, -2.0, 0.5, 3.0]);
        assert_eq!(value.get("name").unwrap().as_text().unwrap().len(), 40);
        assert_eq!(value.get("n"), Some(&Value::UInt(300)));
    }

    /// Bytes as Python's `msgpack_numpy.packb({"s": np.array([1.5, -2], "<f8"), "p": "go"})`
    /// writes them (keys of the array map as `bin`, shape as an array).
    #[test]
    fn reads_the_python_packers_numpy_arrays() {
        let mut frame = vec![0x82, 0xa1, b's', 0x84];
        frame.extend_from_slice(&[0xc4, 11]);
        frame.extend_from_slice(b"__ndarray__");
        frame.push(0xc3);
        frame.extend_from_slice(&[0xc4, 4]);
        frame.extend_from_slice(b"data");
        frame.extend_from_slice(&[0xc4, 16]);
        frame.extend_from_slice(&1.5f64.to_le_bytes());
        frame.extend_from_slice(&(-2.0f64).to_le_bytes());
        frame.extend_from_slice(&[0xc4, 5]);
        frame.extend_from_slice(b"dtype");
        frame.extend_from_slice(&[0xa3, b'<', b'f', b'8']);
        frame.extend_from_slice(&[0xc4, 5]);
        frame.extend_from_slice(b"shape");
        frame.extend_from_slice(&[0x91, 0x02]);
        frame.extend_from_slice(&[0xa1, b'p', 0xa2, b'g', b'o']);
        let value = decode(&frame, 100).unwrap();
        assert_eq!(numbers(value.get("s").unwrap()).unwrap(), [1.5, -2.0]);
        assert_eq!(value.get("p").unwrap().as_text(), Some("go"));
    }

    #[test]
    fn dtypes_convert_like_numpy() {
        let le = |s: &str, bytes: &[u8]| DType::parse(s).unwrap().read(bytes);
        assert_eq!(le("|u1", &[200]), 200.0);
        assert_eq!(le("|i1", &[0xff]), -1.0);
        assert_eq!(le("<i2", &(-300i16).to_le_bytes()), -300.0);
        assert_eq!(le(">i4", &(-7i32).to_be_bytes()), -7.0);
        assert_eq!(le("<u8", &(1u64 << 40).to_le_bytes()), (1u64 << 40) as f64);
        assert_eq!(le("<f2", &0x3c00u16.to_le_bytes()), 1.0);
        assert_eq!(le("<f2", &0xc000u16.to_le_bytes()), -2.0);
        assert_eq!(le(">f4", &0.25f32.to_be_bytes()), 0.25);
        assert_eq!(le("|b1", &[1]), 1.0);
        for bad in ["<U5", "|O", "<c8", "f4", "<f3", "", "<V8"] {
            assert_eq!(DType::parse(bad), None, "{bad}");
        }
    }

    #[test]
    fn refuses_garbage_and_bounds_what_it_builds() {
        assert!(matches!(
            decode(b"\xc1", 10),
            Err(DecodeError::InvalidMarker { .. })
        ));
        assert_eq!(decode(b"\x92\x01", 10), Err(DecodeError::Truncated(2)));
        assert_eq!(decode(b"\x01\x02", 10), Err(DecodeError::Trailing(1)));
        assert!(matches!(
            decode(b"\xa2\xff\xfe", 10),
            Err(DecodeError::NotUtf8(_))
        ));
        // An array that claims four billion items in a five-byte frame allocates nothing.
        assert!(matches!(
            decode(b"\xdd\xff\xff\xff\xff", 10),
            Err(DecodeError::Truncated(_))
        ));
        // A thousand one-byte values against a budget of 100.
        let mut many = vec![0xdc, 0x03, 0xe8];
        many.extend(std::iter::repeat_n(0xc0, 1000));
        assert_eq!(decode(&many, 100), Err(DecodeError::TooManyValues(100)));
        assert!(decode(&many, 2000).is_ok());
        let deep = vec![0x91; MAX_DEPTH + 2];
        assert_eq!(decode(&deep, 1000), Err(DecodeError::TooDeep));
    }

    #[test]
    fn arrays_must_hold_what_their_shape_says() {
        let mut w = Writer::new();
        w.ndarray_raw(&[2, 3], "<f4", &[0; 20]);
        let frame = w.finish();
        let value = decode(&frame, 100).unwrap();
        assert!(matches!(
            NdArray::from_value(&value),
            Err(ArrayError::Length {
                expected: 24,
                actual: 20,
                ..
            })
        ));
        let mut w = Writer::new();
        w.ndarray_raw(&[1], "|O", &[0; 8]);
        let frame = w.finish();
        assert!(matches!(
            NdArray::from_value(&decode(&frame, 100).unwrap()),
            Err(ArrayError::DType(_))
        ));
        assert!(matches!(
            numbers(&Value::Str("x")),
            Err(ArrayError::NotAnArray("str"))
        ));
    }
}
