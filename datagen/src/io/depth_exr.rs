//! Depth maps as OpenEXR: one 32-bit float channel `Z` per image, lossless ZIP compression in
//! blocks of 16 scanlines. This is the encoding of the shard's `depth` column and of the
//! generic input layout's `depth/*.exr` files ([`crate::io::sequence`]).
//!
//! Files are read with the exr crate (any compression, any channel layout). They are written by
//! the small single-channel ZIP writer below, which produces the same standard files in less time
//! than the exr crate's writer (whose zlib level is not configurable): depth encoding is a visible
//! share of `datagen pairs`.
//!
//! A header is checked before anything is decoded (the decoder allocates a whole data window up
//! front): at most [`MAX_SIDE_PX`] a side, the size the caller expects where it knows one (the
//! frames, the first map of a folder), and only the depth channel is ever allocated.

use std::io::{Cursor, Write};

use exr::prelude::*;
use flate2::Compression as ZlibLevel;
use flate2::write::ZlibEncoder;

use crate::error::{Error, Result};
use crate::io::npy::MAX_SIDE_PX;
use foundation::depth::DepthMap;

/// Name of the depth channel written; also preferred when reading a multi-channel file.
pub const DEPTH_CHANNEL: &str = "Z";

/// Scanlines per ZIP block, fixed by the format for ZIP (as opposed to ZIPS, one line).
const ZIP_LINES: usize = 16;

/// zlib level: 1, the fastest. On the benchmark clip of `scripts/bench_pairs_vs.sh` it spends
/// markedly less encoding CPU than level 3 for a somewhat larger shard; level 3 matches the exr
/// crate's output, and higher levels shrink it little more for much more time.
const ZLIB_LEVEL: u32 = 1;

/// Appends a header attribute: name, type name, byte size, value.
fn attribute(out: &mut Vec<u8>, name: &str, kind: &str, value: &[u8]) {
    for text in [name, kind] {
        out.extend_from_slice(text.as_bytes());
        out.push(0);
    }
    out.extend_from_slice(&(value.len() as i32).to_le_bytes());
    out.extend_from_slice(value);
}

/// Appends a ZIP block's payload to `out`: the scanlines' bytes split into even and odd
/// positions, delta-coded (the OpenEXR predictor), zlib-compressed; stored raw when compression
/// does not shrink them. `zlib` is reset after each block, so its state (hundreds of KB) is
/// allocated once per file; `compressed` is reused the same way.
fn zip_block(
    raw: &[u8],
    scratch: &mut Vec<u8>,
    zlib: &mut ZlibEncoder<Vec<u8>>,
    compressed: &mut Vec<u8>,
    out: &mut Vec<u8>,
) {
    scratch.clear();
    scratch.extend(raw.iter().step_by(2));
    scratch.extend(raw.iter().skip(1).step_by(2));
    let mut previous = scratch.first().copied().unwrap_or(0);
    for byte in scratch.iter_mut().skip(1) {
        let current = *byte;
        *byte = current.wrapping_sub(previous).wrapping_add(128);
        previous = current;
    }
    zlib.write_all(scratch).expect("compression into memory");
    compressed.clear();
    *compressed = zlib.reset(std::mem::take(compressed)).expect("compression into memory");
    let payload = if compressed.len() < raw.len() { compressed.as_slice() } else { raw };
    out.extend_from_slice(&(payload.len() as i32).to_le_bytes());
    out.extend_from_slice(payload);
}

/// Encodes `depth` as an EXR file in memory (single part, scanlines, increasing line order).
pub fn encode_depth_exr(depth: &DepthMap) -> Result<Vec<u8>> {
    let (width, height) = (depth.width, depth.height);
    assert_eq!(depth.values.len(), width * height, "depth raster size");
    if width == 0 || height == 0 || width > i32::MAX as usize || height > i32::MAX as usize {
        return Err(Error::Image {
            context: "depth EXR".into(),
            reason: format!("cannot encode a {width}×{height} depth map"),
        });
    }
    // Magic number, then version 2 with no flags (single-part scanline file, short names).
    let mut out = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
    let mut channels = Vec::new();
    channels.extend_from_slice(DEPTH_CHANNEL.as_bytes());
    channels.push(0);
    // Pixel type FLOAT (2), not perceptually linear, three reserved bytes, sampling 1 × 1.
    channels.extend_from_slice(&2i32.to_le_bytes());
    channels.extend_from_slice(&[0, 0, 0, 0]);
    channels.extend_from_slice(&1i32.to_le_bytes());
    channels.extend_from_slice(&1i32.to_le_bytes());
    channels.push(0);
    attribute(&mut out, "channels", "chlist", &channels);
    attribute(&mut out, "compression", "compression", &[3]); // ZIP_COMPRESSION
    let window: Vec<u8> =
        [0, 0, width as i32 - 1, height as i32 - 1].iter().flat_map(|v: &i32| v.to_le_bytes()).collect();
    attribute(&mut out, "dataWindow", "box2i", &window);
    attribute(&mut out, "displayWindow", "box2i", &window);
    attribute(&mut out, "lineOrder", "lineOrder", &[0]); // INCREASING_Y
    attribute(&mut out, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    attribute(&mut out, "screenWindowCenter", "v2f", &[0u8; 8]);
    attribute(&mut out, "screenWindowWidth", "float", &1f32.to_le_bytes());
    out.push(0);

    let blocks = height.div_ceil(ZIP_LINES);
    let table = out.len();
    out.resize(table + 8 * blocks, 0);
    // Room for the worst case (every block stored raw), so the file is never moved as it grows.
    out.reserve(blocks * 8 + 4 * width * height);
    let (mut raw, mut scratch, mut compressed) = (Vec::new(), Vec::new(), Vec::new());
    let mut zlib = ZlibEncoder::new(Vec::new(), ZlibLevel::new(ZLIB_LEVEL));
    for (block, rows) in depth.values.chunks(ZIP_LINES * width).enumerate() {
        raw.clear();
        raw.extend(rows.iter().flat_map(|v| v.to_le_bytes()));
        let offset = out.len() as u64;
        out[table + 8 * block..table + 8 * block + 8].copy_from_slice(&offset.to_le_bytes());
        out.extend_from_slice(&((block * ZIP_LINES) as i32).to_le_bytes());
        zip_block(&raw, &mut scratch, &mut zlib, &mut compressed, &mut out);
    }
    Ok(out)
}

/// Bytes each block of an EXR part needs at least: its entry in the offset table (a u64).
const OFFSET_TABLE_ENTRY_BYTES: usize = 8;

fn image_error(context: &str, reason: impl Into<String>) -> Error {
    Error::Image { context: context.to_owned(), reason: reason.into() }
}

/// What an EXR header declares, checked before anything is decoded: the first part's size and
/// the name of its depth channel.
struct DepthHeader {
    width: usize,
    height: usize,
    channel: Text,
}

/// Reads and checks the header: every part's data window within [`MAX_SIDE_PX`] a side (the
/// decoder allocates the whole window up front, so a 200-byte file declaring 100000×100000
/// pixels would otherwise ask for 40 GB), no more blocks than the file has room to index, and a
/// depth channel in the first part.
fn read_header(bytes: &[u8], context: &str) -> Result<DepthHeader> {
    let meta = MetaData::read_from_buffered(Cursor::new(bytes), false)
        .map_err(|e| image_error(context, format!("invalid EXR header: {e}")))?;
    for header in meta.headers.iter() {
        let Vec2(width, height) = header.layer_size;
        if width > MAX_SIDE_PX || height > MAX_SIDE_PX {
            return Err(image_error(
                context,
                format!(
                    "header field `dataWindow` declares {width}x{height} pixels; depth maps are read up to {MAX_SIDE_PX} px a side"
                ),
            ));
        }
        if header.chunk_count.saturating_mul(OFFSET_TABLE_ENTRY_BYTES) > bytes.len() {
            return Err(image_error(
                context,
                format!(
                    "header declares {} blocks, more than the {}-byte file can hold (truncated?)",
                    header.chunk_count,
                    bytes.len()
                ),
            ));
        }
    }
    let first = meta.headers.first().ok_or_else(|| image_error(context, "no image part in the file"))?;
    let channels = &first.channels.list;
    let channel = channels
        .iter()
        .find(|c| c.name.eq(DEPTH_CHANNEL))
        .or_else(|| if channels.len() == 1 { channels.first() } else { None })
        .ok_or_else(|| {
            image_error(
                context,
                format!("expected one float channel or a `{DEPTH_CHANNEL}` channel, found {} channels", channels.len()),
            )
        })?;
    let Vec2(width, height) = first.layer_size;
    Ok(DepthHeader { width, height, channel: channel.name.clone() })
}

/// The width and height an EXR depth map declares, from its header alone (checked as
/// [`decode_depth_exr`] does), so that a folder of maps can be compared before any is decoded.
pub fn depth_exr_size(bytes: &[u8], context: &str) -> Result<(usize, usize)> {
    let header = read_header(bytes, context)?;
    Ok((header.width, header.height))
}

/// Decodes an EXR holding one float channel (or a `Z` channel among several), of any size up to
/// [`MAX_SIDE_PX`] a side. `context` names the source (a file path or a shard field) in errors.
pub fn decode_depth_exr(bytes: &[u8], context: &str) -> Result<DepthMap> {
    decode_checked(bytes, context, read_header(bytes, context)?)
}

/// Decodes an EXR depth map (see [`decode_depth_exr`]) that must be `width × height`, the size
/// of the frames or sibling maps it belongs to; a header declaring another size is an error
/// before anything is decoded.
pub fn decode_depth_exr_of_size(bytes: &[u8], context: &str, width: usize, height: usize) -> Result<DepthMap> {
    let header = read_header(bytes, context)?;
    if (header.width, header.height) != (width, height) {
        return Err(image_error(
            context,
            format!(
                "header field `dataWindow` declares {}x{} pixels, expected {width}x{height}",
                header.width, header.height
            ),
        ));
    }
    decode_checked(bytes, context, header)
}

/// Decodes only the depth channel, into a buffer of the checked size (other channels are never
/// allocated, however many the file has).
fn decode_checked(bytes: &[u8], context: &str, header: DepthHeader) -> Result<DepthMap> {
    let DepthHeader { width, height, channel } = header;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .specific_channels()
        .required(channel)
        .collect_pixels(
            |resolution, _| DepthMap {
                width: resolution.width(),
                height: resolution.height(),
                values: vec![0.0; resolution.area()],
            },
            |depth: &mut DepthMap, position, (z,): (f32,)| {
                depth.values[position.y() * depth.width + position.x()] = z;
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| image_error(context, e.to_string()))?;
    let depth = image.layer_data.channel_data.pixels;
    if (depth.width, depth.height) != (width, height) {
        return Err(image_error(
            context,
            format!("decoded {}x{} pixels, the header declares {width}x{height}", depth.width, depth.height),
        ));
    }
    Ok(depth)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_round_trips_bit_exactly_including_invalid_values() {
        let (width, height) = (7, 5);
        let mut values: Vec<f32> = (0..width * height).map(|i| 0.1 + i as f32 * 1.37).collect();
        values[3] = f32::NAN;
        values[4] = f32::INFINITY;
        values[5] = 0.0;
        values[6] = -1.0;
        let depth = DepthMap { width, height, values };
        let decoded = decode_depth_exr(&encode_depth_exr(&depth).unwrap(), "test").unwrap();
        assert_eq!((decoded.width, decoded.height), (width, height));
        assert_eq!(bits(&decoded.values), bits(&depth.values));
    }

    fn bits(values: &[f32]) -> Vec<u32> {
        values.iter().map(|x| x.to_bits()).collect()
    }

    /// A smooth surface with a step, like a depth map.
    fn smooth_depth(width: usize, height: usize) -> DepthMap {
        let values = (0..width * height)
            .map(|i| {
                let (u, v) = ((i % width) as f32, (i / width) as f32);
                if u > width as f32 / 2.0 { 2.0 + 0.001 * v } else { 5.0 + 0.01 * u + 0.002 * v * v / height as f32 }
            })
            .collect();
        DepthMap { width, height, values }
    }

    /// The same image through the exr crate's own writer, the reference for the format.
    fn encode_with_exr_crate(depth: &DepthMap) -> Vec<u8> {
        let channel = AnyChannel::new(DEPTH_CHANNEL, FlatSamples::F32(depth.values.clone()));
        let encoding =
            Encoding { compression: Compression::ZIP16, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
        let layer = Layer::new(
            (depth.width, depth.height),
            LayerAttributes::default(),
            encoding,
            AnyChannels::sort(SmallVec::from_vec(vec![channel])),
        );
        let mut bytes = Vec::new();
        Image::from_layer(layer).write().to_buffered(Cursor::new(&mut bytes)).unwrap();
        bytes
    }

    #[test]
    fn several_blocks_with_a_partial_last_one_round_trip() {
        // 37 rows: blocks of 16, 16 and 5 lines.
        let depth = smooth_depth(53, 37);
        let bytes = encode_depth_exr(&depth).unwrap();
        let decoded = decode_depth_exr(&bytes, "test").unwrap();
        assert_eq!((decoded.width, decoded.height), (53, 37));
        assert_eq!(bits(&decoded.values), bits(&depth.values));
        // Size on par with the exr crate's ZIP writer.
        let reference = encode_with_exr_crate(&depth).len();
        assert!(bytes.len() * 100 <= reference * 105, "{} bytes against the exr crate's {reference}", bytes.len());
    }

    #[test]
    fn incompressible_blocks_are_stored_raw_and_round_trip() {
        // Arbitrary bit patterns (NaN payloads, subnormals, negative zero) do not compress.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let values = (0..31 * 20)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                f32::from_bits(state as u32)
            })
            .collect();
        let depth = DepthMap { width: 31, height: 20, values };
        let bytes = encode_depth_exr(&depth).unwrap();
        assert!(bytes.len() > 4 * 31 * 20, "raw blocks, so at least the raw size");
        let decoded = decode_depth_exr(&bytes, "test").unwrap();
        assert_eq!(bits(&decoded.values), bits(&depth.values));
    }

    #[test]
    fn the_exr_crate_writer_and_ours_encode_the_same_values() {
        let depth = smooth_depth(40, 18);
        let ours = decode_depth_exr(&encode_depth_exr(&depth).unwrap(), "ours").unwrap();
        let theirs = decode_depth_exr(&encode_with_exr_crate(&depth), "exr crate").unwrap();
        assert_eq!(ours, theirs);
    }

    /// `depth` encoded, then its `dataWindow` rewritten to declare `width × height`.
    fn declaring(depth: &DepthMap, width: i32, height: i32) -> Vec<u8> {
        let mut bytes = encode_depth_exr(depth).unwrap();
        let name = b"dataWindow\0box2i\0";
        let value = bytes.windows(name.len()).position(|w| w == name).unwrap() + name.len() + 4;
        bytes[value + 8..value + 12].copy_from_slice(&(width - 1).to_le_bytes());
        bytes[value + 12..value + 16].copy_from_slice(&(height - 1).to_le_bytes());
        bytes
    }

    #[test]
    fn data_window_is_checked_before_decoding() {
        let depth = smooth_depth(12, 5);
        let huge = declaring(&depth, 100_000, 5);
        let error = decode_depth_exr(&huge, "d.exr").unwrap_err().to_string();
        assert!(error.contains("d.exr") && error.contains("dataWindow") && error.contains("100000x5"), "{error}");
        let bytes = encode_depth_exr(&depth).unwrap();
        assert_eq!(depth_exr_size(&bytes, "d.exr").unwrap(), (12, 5));
        assert_eq!(decode_depth_exr_of_size(&bytes, "d.exr", 12, 5).unwrap(), depth);
        let error = decode_depth_exr_of_size(&bytes, "d.exr", 12, 6).unwrap_err().to_string();
        assert!(error.contains("12x5") && error.contains("expected 12x6"), "{error}");
    }

    #[test]
    fn more_blocks_than_the_file_can_index_is_an_error() {
        // 16384 rows need 1024 ZIP blocks, 8 KiB of offset table, in a file of a few hundred bytes.
        let error = decode_depth_exr(&declaring(&smooth_depth(4, 4), 4, 16_384), "d.exr").unwrap_err().to_string();
        assert!(error.contains("1024 blocks"), "{error}");
    }

    #[test]
    fn only_the_depth_channel_is_read_from_a_multi_channel_file() {
        let depth = smooth_depth(9, 7);
        let channels = vec![
            AnyChannel::new("G", FlatSamples::F32(vec![7.0; 63])),
            AnyChannel::new(DEPTH_CHANNEL, FlatSamples::F32(depth.values.clone())),
            AnyChannel::new("R", FlatSamples::F16(vec![f16::ONE; 63])),
        ];
        let layer = Layer::new(
            (9, 7),
            LayerAttributes::default(),
            Encoding::FAST_LOSSLESS,
            AnyChannels::sort(SmallVec::from_vec(channels)),
        );
        let mut bytes = Vec::new();
        Image::from_layer(layer).write().to_buffered(Cursor::new(&mut bytes)).unwrap();
        assert_eq!(decode_depth_exr(&bytes, "multi").unwrap(), depth);
    }

    #[test]
    fn garbage_is_an_error_naming_the_context() {
        let error = decode_depth_exr(b"not an exr", "depth/00003.exr").unwrap_err().to_string();
        assert!(error.contains("depth/00003.exr"), "{error}");
    }
}
