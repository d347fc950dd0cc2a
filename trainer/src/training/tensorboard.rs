//! TensorBoard event files beside `metrics.jsonl`: scalars (loss, learning rate, …) and images
//! (validation contact sheets), readable by the `tensorboard` package's own event reader.
//!
//! An event file is a sequence of TFRecords (`u64` little-endian length, masked CRC-32C of
//! the length bytes, the payload, masked CRC-32C of the payload) whose payloads are serialized
//! `tensorboard.Event` protobufs; the first one carries only `file_version`. The two messages
//! used here are small enough to encode by hand, with field numbers from tensorboard's
//! `tensorboard/compat/proto/event.proto` and `summary.proto` (checked against the descriptors
//! of the `tensorboard` 2.21 wheel in the venv).

use std::fs::{File, OpenOptions};
use std::io::{BufWriter, ErrorKind, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use crate::error::{Error, Result};

/// The version string of the first record; `brain.Event:2` is what TensorFlow and tensorboard
/// write, and the reader parses the number after the colon.
const FILE_VERSION: &str = "brain.Event:2";

/// Field numbers of `message Event` (event.proto).
mod event_field {
    /// `double wall_time = 1`: seconds since the Unix epoch.
    pub const WALL_TIME: u32 = 1;
    /// `int64 step = 2`.
    pub const STEP: u32 = 2;
    /// `string file_version = 3` (oneof `what`).
    pub const FILE_VERSION: u32 = 3;
    /// `Summary summary = 5` (oneof `what`).
    pub const SUMMARY: u32 = 5;
}

/// Field numbers of `message Summary` and its nested messages (summary.proto).
mod summary_field {
    /// `Summary.value`: `repeated Value value = 1`.
    pub const VALUE: u32 = 1;
    /// `Summary.Value.tag`: `string tag = 1`.
    pub const TAG: u32 = 1;
    /// `Summary.Value.simple_value`: `float simple_value = 2` (oneof `value`).
    pub const SIMPLE_VALUE: u32 = 2;
    /// `Summary.Value.image`: `Image image = 4` (oneof `value`).
    pub const IMAGE: u32 = 4;
    /// `Summary.Image.height`: `int32 height = 1`.
    pub const IMAGE_HEIGHT: u32 = 1;
    /// `Summary.Image.width`: `int32 width = 2`.
    pub const IMAGE_WIDTH: u32 = 2;
    /// `Summary.Image.colorspace`: `int32 colorspace = 3`.
    pub const IMAGE_COLORSPACE: u32 = 3;
    /// `Summary.Image.encoded_image_string`: `bytes encoded_image_string = 4`.
    pub const IMAGE_ENCODED: u32 = 4;
}

/// `Summary.Image.colorspace` for RGB (summary.proto: 1 grayscale, 2 grayscale + alpha, 3 RGB,
/// 4 RGBA, 5 DIGITAL_YUV, 6 BGRA).
const COLORSPACE_RGB: i64 = 3;

/// Protobuf wire types (protobuf encoding spec).
mod wire {
    /// int32, int64, enums.
    pub const VARINT: u32 = 0;
    /// double, fixed64.
    pub const FIXED64: u32 = 1;
    /// strings, bytes, embedded messages.
    pub const LEN: u32 = 2;
    /// float, fixed32.
    pub const FIXED32: u32 = 5;
}

/// The constant added after rotating a CRC in TFRecord's "masked" CRC (TensorFlow's
/// `core/lib/hash/crc32c.h`, `kMaskDelta`), so that a CRC of data holding CRCs stays strong.
const CRC_MASK_DELTA: u32 = 0xa282_ead8;

/// The reflected CRC-32C (Castagnoli) polynomial, as TFRecord uses.
const CRC32C_POLY_REFLECTED: u32 = 0x82f6_3b78;

/// Byte-at-a-time lookup table of CRC-32C, built at compile time.
const CRC32C_TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut byte = 0;
    while byte < 256 {
        let mut crc = byte as u32;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ CRC32C_POLY_REFLECTED } else { crc >> 1 };
            bit += 1;
        }
        table[byte] = crc;
        byte += 1;
    }
    table
};

/// CRC-32C of `data` (initial value and final xor all ones, as in iSCSI and TFRecord).
fn crc32c(data: &[u8]) -> u32 {
    !data.iter().fold(!0u32, |crc, &b| CRC32C_TABLE[((crc ^ u32::from(b)) & 0xff) as usize] ^ (crc >> 8))
}

/// TFRecord's masked CRC: rotate right by 15 bits and add [`CRC_MASK_DELTA`].
fn masked_crc32c(data: &[u8]) -> u32 {
    crc32c(data).rotate_right(15).wrapping_add(CRC_MASK_DELTA)
}

/// A protobuf message being encoded field by field.
#[derive(Default)]
struct Proto(Vec<u8>);

impl Proto {
    fn varint(&mut self, mut value: u64) {
        while value >= 0x80 {
            self.0.push((value as u8) | 0x80);
            value >>= 7;
        }
        self.0.push(value as u8);
    }

    fn key(&mut self, field: u32, wire_type: u32) {
        self.varint(u64::from((field << 3) | wire_type));
    }

    /// An `int32`/`int64` field; negative values are sign-extended to 64 bits, as protobuf does.
    fn int(&mut self, field: u32, value: i64) {
        self.key(field, wire::VARINT);
        self.varint(value as u64);
    }

    fn double(&mut self, field: u32, value: f64) {
        self.key(field, wire::FIXED64);
        self.0.extend_from_slice(&value.to_le_bytes());
    }

    fn float(&mut self, field: u32, value: f32) {
        self.key(field, wire::FIXED32);
        self.0.extend_from_slice(&value.to_le_bytes());
    }

    /// A `string`, `bytes` or embedded-message field.
    fn bytes(&mut self, field: u32, value: &[u8]) {
        self.key(field, wire::LEN);
        self.varint(value.len() as u64);
        self.0.extend_from_slice(value);
    }
}

/// One `Summary.Value`: a tag and either a scalar or an encoded image.
enum SummaryValue<'a> {
    Scalar(&'a str, f32),
    Image { tag: &'a str, height: u32, width: u32, png: Vec<u8> },
}

impl SummaryValue<'_> {
    fn encode(&self) -> Vec<u8> {
        let mut value = Proto::default();
        match self {
            SummaryValue::Scalar(tag, v) => {
                value.bytes(summary_field::TAG, tag.as_bytes());
                value.float(summary_field::SIMPLE_VALUE, *v);
            }
            SummaryValue::Image { tag, height, width, png } => {
                let mut image = Proto::default();
                image.int(summary_field::IMAGE_HEIGHT, i64::from(*height));
                image.int(summary_field::IMAGE_WIDTH, i64::from(*width));
                image.int(summary_field::IMAGE_COLORSPACE, COLORSPACE_RGB);
                image.bytes(summary_field::IMAGE_ENCODED, png);
                value.bytes(summary_field::TAG, tag.as_bytes());
                value.bytes(summary_field::IMAGE, &image.0);
            }
        }
        value.0
    }
}

/// A serialized `Event` holding a `Summary` of `values` at `step`.
fn summary_event(wall_time: f64, step: i64, values: &[SummaryValue<'_>]) -> Vec<u8> {
    let mut summary = Proto::default();
    for value in values {
        summary.bytes(summary_field::VALUE, &value.encode());
    }
    let mut event = Proto::default();
    event.double(event_field::WALL_TIME, wall_time);
    event.int(event_field::STEP, step);
    event.bytes(event_field::SUMMARY, &summary.0);
    event.0
}

/// Seconds since the Unix epoch (0 if the clock is before it).
fn wall_time() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

/// The machine's host name for the file name (Linux's `/proc/sys/kernel/hostname`, then
/// `$HOSTNAME`, else `localhost`); characters that do not belong in a file name become `_`.
fn hostname() -> String {
    let name = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|s| s.trim().to_owned())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".to_owned());
    name.chars().map(|c| if c.is_ascii_alphanumeric() || "-_.".contains(c) { c } else { '_' }).collect()
}

/// Writes one TensorBoard event file. Records go through a buffer that is flushed whenever the
/// step advances, after every image, on [`EventWriter::flush`] and on drop, so a killed run
/// loses at most its last step.
pub struct EventWriter {
    path: PathBuf,
    out: BufWriter<File>,
    /// The step of the last record written, to flush when the next step begins.
    last_step: Option<i64>,
}

impl EventWriter {
    /// Creates `dir` if needed and a new event file in it named as TensorFlow names them,
    /// `events.out.tfevents.{unix seconds}.{hostname}.{pid}.{n}` (`n` from 0, raised if a file
    /// of that name exists), and writes the `file_version` record.
    pub fn create(dir: &Path) -> Result<Self> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |error| Error::Io { path, error }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let now = wall_time();
        let stem = format!("events.out.tfevents.{}.{}.{}", now as u64, hostname(), std::process::id());
        let mut n = 0u32;
        let (path, file) = loop {
            let path = dir.join(format!("{stem}.{n}"));
            match OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(file) => break (path, file),
                Err(e) if e.kind() == ErrorKind::AlreadyExists => n += 1,
                Err(e) => return Err(io(&path)(e)),
            }
        };
        let mut writer = EventWriter { path, out: BufWriter::new(file), last_step: None };
        let mut event = Proto::default();
        event.double(event_field::WALL_TIME, now);
        event.bytes(event_field::FILE_VERSION, FILE_VERSION.as_bytes());
        writer.write_record(&event.0)?;
        writer.flush()?;
        Ok(writer)
    }

    /// The event file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Records scalar `value` under `tag` (e.g. `train/loss`) at `step`.
    pub fn scalar(&mut self, tag: &str, step: i64, value: f32) -> Result<()> {
        self.scalars(step, &[(tag, value)])
    }

    /// Records several scalars at `step` in one event.
    pub fn scalars(&mut self, step: i64, values: &[(&str, f32)]) -> Result<()> {
        let values: Vec<_> = values.iter().map(|&(tag, v)| SummaryValue::Scalar(tag, v)).collect();
        self.write_event(step, &values)
    }

    /// Records `image` (PNG-encoded) under `tag` at `step`, then flushes: images are rare and
    /// large, and a contact sheet is worth keeping if the run dies next.
    pub fn image(&mut self, tag: &str, step: i64, image: &image::RgbImage) -> Result<()> {
        let mut png = Vec::new();
        image.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).map_err(|e| {
            Error::InvalidArgument { name: format!("image `{tag}`"), reason: format!("PNG encoding failed: {e}") }
        })?;
        let value = SummaryValue::Image { tag, height: image.height(), width: image.width(), png };
        self.write_event(step, &[value])?;
        self.flush()
    }

    /// Writes the buffered records to the file.
    pub fn flush(&mut self) -> Result<()> {
        self.out.flush().map_err(|error| Error::Io { path: self.path.clone(), error })
    }

    fn write_event(&mut self, step: i64, values: &[SummaryValue<'_>]) -> Result<()> {
        if self.last_step.is_some_and(|last| last != step) {
            self.flush()?;
        }
        self.last_step = Some(step);
        self.write_record(&summary_event(wall_time(), step, values))
    }

    /// Frames `data` as one TFRecord.
    fn write_record(&mut self, data: &[u8]) -> Result<()> {
        let length = (data.len() as u64).to_le_bytes();
        let mut record = Vec::with_capacity(data.len() + 16);
        record.extend_from_slice(&length);
        record.extend_from_slice(&masked_crc32c(&length).to_le_bytes());
        record.extend_from_slice(data);
        record.extend_from_slice(&masked_crc32c(data).to_le_bytes());
        self.out.write_all(&record).map_err(|error| Error::Io { path: self.path.clone(), error })
    }
}

impl Drop for EventWriter {
    fn drop(&mut self) {
        // Errors cannot be returned from drop; callers who care call `flush` first.
        let _ = self.out.flush();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The CRC-32C check value of the ASCII digits "123456789" (RFC 3720 appendix B.4 and every
    /// CRC catalogue): 0xE3069283.
    #[test]
    fn crc32c_check_value() {
        assert_eq!(crc32c(b"123456789"), 0xe306_9283);
        assert_eq!(crc32c(b""), 0);
    }

    /// RFC 3720 B.4: 32 bytes of zeros give 0x8A9136AA, 32 bytes of 0xFF give 0x62A8AB43.
    #[test]
    fn crc32c_rfc3720_vectors() {
        assert_eq!(crc32c(&[0u8; 32]), 0x8a91_36aa);
        assert_eq!(crc32c(&[0xffu8; 32]), 0x62a8_ab43);
    }

    /// Varints per the protobuf encoding guide: 1 → 01, 150 → 96 01, 300 → ac 02; −1 as int64 is
    /// ten bytes.
    #[test]
    fn varint_encoding() {
        for (value, bytes) in [(1u64, vec![0x01]), (150, vec![0x96, 0x01]), (300, vec![0xac, 0x02])] {
            let mut p = Proto::default();
            p.varint(value);
            assert_eq!(p.0, bytes, "varint {value}");
        }
        let mut p = Proto::default();
        p.int(2, -1);
        assert_eq!(p.0.len(), 1 + 10);
    }
}
