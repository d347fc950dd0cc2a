//! Depth maps as OpenEXR (exr crate): one 32-bit float channel `Z` per image, lossless ZIP
//! compression. This is the encoding of the shard's `depth` column (DESIGN §5) and of the generic
//! input layout's `depth/*.exr` files (DESIGN §3).

use std::io::Cursor;

use exr::prelude::*;

use crate::error::{Error, Result};

/// Name of the depth channel written; also preferred when reading a multi-channel file.
pub const DEPTH_CHANNEL: &str = "Z";

/// A single-channel float raster, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthMap {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `width * height` values, rows top to bottom.
    pub values: Vec<f32>,
}

/// Encodes `depth` as an EXR file in memory.
pub fn encode_depth_exr(depth: &DepthMap) -> Result<Vec<u8>> {
    assert_eq!(depth.values.len(), depth.width * depth.height, "depth raster size");
    let channel = AnyChannel::new(DEPTH_CHANNEL, FlatSamples::F32(depth.values.clone()));
    let encoding =
        Encoding { compression: Compression::ZIP16, blocks: Blocks::ScanLines, line_order: LineOrder::Increasing };
    let layer = Layer::new(
        (depth.width, depth.height),
        LayerAttributes::named("depth"),
        encoding,
        AnyChannels::sort(SmallVec::from_vec(vec![channel])),
    );
    let mut bytes = Vec::new();
    Image::from_layer(layer)
        .write()
        .to_buffered(Cursor::new(&mut bytes))
        .map_err(|e| Error::Image { context: "depth EXR".into(), reason: e.to_string() })?;
    Ok(bytes)
}

/// Decodes an EXR holding one float channel (or a `Z` channel among several). `context` names the
/// source (a file path or a shard field) in errors.
pub fn decode_depth_exr(bytes: &[u8], context: &str) -> Result<DepthMap> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))
        .map_err(|e| Error::Image { context: context.to_owned(), reason: e.to_string() })?;
    let layer = &image.layer_data;
    let channels = &layer.channel_data.list;
    let channel = channels
        .iter()
        .find(|c| c.name.eq(DEPTH_CHANNEL))
        .or_else(|| if channels.len() == 1 { channels.first() } else { None })
        .ok_or_else(|| Error::Image {
            context: context.to_owned(),
            reason: format!(
                "expected one float channel or a `{DEPTH_CHANNEL}` channel, found {} channels",
                channels.len()
            ),
        })?;
    let size = layer.size;
    Ok(DepthMap { width: size.0, height: size.1, values: channel.sample_data.values_as_f32().collect() })
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
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&decoded.values), bits(&depth.values));
    }

    #[test]
    fn garbage_is_an_error_naming_the_context() {
        let error = decode_depth_exr(b"not an exr", "depth/00003.exr").unwrap_err().to_string();
        assert!(error.contains("depth/00003.exr"), "{error}");
    }
}
