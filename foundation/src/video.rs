//! Video decoding and encoding with FFmpeg (ffmpeg-next): any container/codec FFmpeg reads in,
//! H.264 (libx264, yuv420p, MP4) out, frames as RGB u8 in memory.

use std::path::Path;
use std::sync::Once;

use ffmpeg::format::Pixel;
use ffmpeg::software::scaling::{context::Context as Scaler, flag::Flags};
use ffmpeg::util::frame::video::Video as VideoFrame;
use ffmpeg_next as ffmpeg;
use image::RgbImage;

use crate::error::{Error, Result};

/// libx264 constant-rate factor for written videos: visually lossless, so pairs generated from an
/// encoded video match those generated from its frames closely.
const X264_CRF: &str = "17";
/// libx264 speed preset: a balance of encode time and size for short clips.
const X264_PRESET: &str = "medium";
/// libx264 frame threads, fixed. x264's bitstream depends on its thread count, and its default
/// (`threads=0`: 1.5 × the CPUs the calling thread may run on) changes with the machine and the
/// process's CPU affinity, so the same frames encoded under `taskset -c 0` and on all CPUs gave
/// other `.mp4` bytes (and recorded digests). Four keeps encoding parallel on any machine; the
/// bytes are x264's for four threads everywhere.
const X264_THREADS: &str = "4";

/// x264's SIMD feature names (its `asm` option; the names of x264's `x264_cpu_names` table, each
/// switching on a cumulative set of flags) that this CPU offers, up to AVX2 and never AVX-512.
///
/// x264's AVX-512 code lets memory that x264 allocated without initialising reach the bitstream:
/// the same frames, every plane's row padding zeroed, gave other P/B-frame bytes under other
/// glibc `MALLOC_PERTURB_` values (also with `ffmpeg -c:v libx264`, so not our frames), but not
/// with `mbtree=0`, `bframes=0` or any SIMD level up to AVX2. x264's AVX-512 macroblock-tree
/// propagation (`mbtree_propagate_list_internal`) works on 8 macroblocks a step without
/// stopping at the row's end, where the C and AVX2 versions stop, so it reads costs and vectors
/// past the last row. A resumed trainer job, whose heap had another history, so wrote another
/// `.mp4` than an uninterrupted one. Without AVX-512 the bytes are those of the AVX-512 encode on
/// a fresh heap: x264's SIMD code is otherwise bit-exact with its C code (its `checkasm`), so
/// the cap costs speed, not bytes. Naming only what the CPU has keeps x264 from instructions it
/// lacks; it matches x264's own detection less `AVX512` on current CPUs (speed hints such as
/// `SlowShuffle` are left out, so older CPUs may encode a little slower).
#[cfg(target_arch = "x86_64")]
fn x264_simd_without_avx512() -> String {
    let sse3 = is_x86_feature_detected!("sse3");
    let ssse3 = sse3 && is_x86_feature_detected!("ssse3");
    let sse41 = ssse3 && is_x86_feature_detected!("sse4.1");
    let sse42 = sse41 && is_x86_feature_detected!("sse4.2");
    let avx = sse42 && is_x86_feature_detected!("avx");
    let fma3 = avx && is_x86_feature_detected!("fma");
    let lzcnt = is_x86_feature_detected!("lzcnt");
    let bmi2 = avx && lzcnt && is_x86_feature_detected!("bmi1") && is_x86_feature_detected!("bmi2");
    let avx2 = fma3 && bmi2 && is_x86_feature_detected!("avx2");
    // SSE2 is part of every x86-64 CPU; x264 marks SSE2 fast on CPUs with SSSE3.
    let names = [
        ("SSE2", true),
        ("SSE2Fast", ssse3),
        ("SSE3", sse3),
        ("SSSE3", ssse3),
        ("SSE4.1", sse41),
        ("SSE4.2", sse42),
        ("AVX", avx),
        ("FMA3", fma3),
        ("LZCNT", lzcnt),
        ("BMI2", bmi2),
        ("AVX2", avx2),
    ];
    names.iter().filter(|(_, has)| *has).map(|(name, _)| *name).collect::<Vec<_>>().join(",")
}

/// A decoded video: frames in display order and the stream's frame rate.
#[derive(Debug, Clone)]
pub struct Video {
    /// Frames per second (average frame rate of the stream; 0 if the container does not say).
    pub fps: f64,
    /// RGB frames, all of the same size.
    pub frames: Vec<RgbImage>,
}

fn init() {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        // Initialisation only registers codecs; failure would surface at the first open anyway.
        let _ = ffmpeg::init();
        ffmpeg::util::log::set_level(ffmpeg::util::log::Level::Error);
    });
}

fn video_error(path: &Path, what: &str, error: impl std::fmt::Display) -> Error {
    Error::Video { path: path.to_owned(), reason: format!("{what}: {error}") }
}

/// Whether FFmpeg's demuxer `name` reads single images: `image2` (files by pattern) and the
/// `*_pipe` family (`png_pipe`, `jpeg_pipe`, `webp_pipe`, ...), which it picks by content when a
/// still image is given any name, e.g. a PNG renamed to `.mp4`.
fn is_still_image_demuxer(name: &str) -> bool {
    name.split(',').any(|n| n == "image2" || n.ends_with("_pipe"))
}

/// Decodes every frame of the best video stream of `path` to RGB. A still image (whatever its
/// extension) or a stream whose frame size changes is an error naming the file.
pub fn decode_video(path: &Path) -> Result<Video> {
    init();
    if !path.is_file() {
        return Err(Error::io(path, std::io::Error::new(std::io::ErrorKind::NotFound, "video file not found")));
    }
    let mut input = ffmpeg::format::input(path).map_err(|e| video_error(path, "cannot open container", e))?;
    let demuxer = input.format().name().to_owned();
    if is_still_image_demuxer(&demuxer) {
        return Err(video_error(
            path,
            "not a video",
            format!("FFmpeg reads this file as a still image (demuxer `{demuxer}`), whatever its extension"),
        ));
    }
    let stream = input
        .streams()
        .best(ffmpeg::media::Type::Video)
        .ok_or_else(|| video_error(path, "no video stream", "the file holds no video"))?;
    let stream_index = stream.index();
    let rate = stream.avg_frame_rate();
    let fps = if rate.denominator() != 0 { f64::from(rate) } else { 0.0 };
    let mut context = ffmpeg::codec::context::Context::from_parameters(stream.parameters())
        .map_err(|e| video_error(path, "unsupported codec parameters", e))?;
    context.set_threading(ffmpeg::threading::Config {
        kind: ffmpeg::threading::Type::Frame,
        count: 0,
        ..Default::default()
    });
    let mut decoder = context.decoder().video().map_err(|e| video_error(path, "cannot open decoder", e))?;

    let mut frames = Vec::new();
    let mut scaler: Option<Scaler> = None;
    // The RGB conversion's output, one frame reused for all: a fresh frame per picture is a fresh
    // megabyte whose pages the kernel clears and maps, on the decode's critical path.
    let mut rgb = VideoFrame::empty();
    let mut receive = |decoder: &mut ffmpeg::decoder::Video, frames: &mut Vec<RgbImage>| -> Result<()> {
        let mut decoded = VideoFrame::empty();
        while decoder.receive_frame(&mut decoded).is_ok() {
            let (width, height) = (decoded.width(), decoded.height());
            if width == 0 || height == 0 {
                return Err(video_error(path, "decoded frame", "zero-size frame"));
            }
            // A stream whose size changes mid-way would give frames that no depth map or K fits.
            if let Some(first) = frames.first() {
                let (first_w, first_h) = first.dimensions();
                if (width, height) != (first_w, first_h) {
                    return Err(video_error(
                        path,
                        &format!("frame {}", frames.len()),
                        format!("size {width}x{height} differs from frame 0's {first_w}x{first_h}"),
                    ));
                }
            }
            if scaler.is_none() {
                let created =
                    Scaler::get(decoded.format(), width, height, Pixel::RGB24, width, height, Flags::BILINEAR)
                        .map_err(|e| video_error(path, "cannot convert to RGB", e))?;
                scaler = Some(created);
            }
            scaler
                .as_mut()
                .expect("scaler created above")
                .run(&decoded, &mut rgb)
                .map_err(|e| video_error(path, "RGB conversion", e))?;
            frames.push(frame_to_image(&rgb));
        }
        Ok(())
    };
    for (stream, packet) in input.packets() {
        if stream.index() == stream_index {
            decoder
                .send_packet(&packet)
                .map_err(|e| video_error(path, &format!("decoding frame {}", frames.len()), e))?;
            receive(&mut decoder, &mut frames)?;
        }
    }
    decoder.send_eof().map_err(|e| video_error(path, "flushing decoder", e))?;
    receive(&mut decoder, &mut frames)?;
    if frames.is_empty() {
        return Err(video_error(path, "no frames", "the video stream decoded to zero frames"));
    }
    Ok(Video { fps, frames })
}

fn frame_to_image(frame: &VideoFrame) -> RgbImage {
    let (width, height) = (frame.width() as usize, frame.height() as usize);
    let stride = frame.stride(0);
    let data = frame.data(0);
    let mut pixels = Vec::with_capacity(width * height * 3);
    for row in 0..height {
        pixels.extend_from_slice(&data[row * stride..row * stride + width * 3]);
    }
    RgbImage::from_raw(width as u32, height as u32, pixels).expect("buffer sized to the frame")
}

/// Encodes `frames` as H.264 (yuv420p) at `fps` into `path` (container from the extension,
/// normally `.mp4`). Frame sizes must be equal and even (4:2:0 chroma needs even sizes).
pub fn encode_video(path: &Path, frames: &[RgbImage], fps: f64) -> Result<()> {
    init();
    let first = frames.first().ok_or_else(|| Error::parameter("frames", "cannot encode a video of zero frames"))?;
    let (width, height) = first.dimensions();
    if !width.is_multiple_of(2) || !height.is_multiple_of(2) || width == 0 || height == 0 {
        return Err(Error::parameter(
            "size",
            format!("H.264 4:2:0 needs even, non-zero frame sizes, got {width}x{height}"),
        ));
    }
    if let Some(i) = frames.iter().position(|f| f.dimensions() != (width, height)) {
        return Err(Error::parameter(
            "frames",
            format!("frame {i} is {:?}, frame 0 is {width}x{height}", frames[i].dimensions()),
        ));
    }
    if !(fps.is_finite() && fps > 0.0) {
        return Err(Error::parameter("fps", format!("must be a positive number, got {fps}")));
    }
    let rate = ffmpeg::Rational::from(fps);
    let time_base = rate.invert();

    let mut output = ffmpeg::format::output(path).map_err(|e| video_error(path, "cannot create container", e))?;
    let global_header = output.format().flags().contains(ffmpeg::format::Flags::GLOBAL_HEADER);
    let codec = ffmpeg::encoder::find_by_name("libx264")
        .or_else(|| ffmpeg::encoder::find(ffmpeg::codec::Id::H264))
        .ok_or_else(|| video_error(path, "no H.264 encoder", "FFmpeg was built without libx264"))?;
    let mut stream = output.add_stream(codec).map_err(|e| video_error(path, "cannot add stream", e))?;
    let stream_index = stream.index();
    let mut encoder = ffmpeg::codec::context::Context::new_with_codec(codec)
        .encoder()
        .video()
        .map_err(|e| video_error(path, "cannot create encoder", e))?;
    encoder.set_width(width);
    encoder.set_height(height);
    encoder.set_format(Pixel::YUV420P);
    encoder.set_frame_rate(Some(rate));
    encoder.set_time_base(time_base);
    if global_header {
        encoder.set_flags(ffmpeg::codec::Flags::GLOBAL_HEADER);
    }
    let mut options = ffmpeg::Dictionary::new();
    options.set("crf", X264_CRF);
    options.set("preset", X264_PRESET);
    options.set("threads", X264_THREADS);
    #[cfg(target_arch = "x86_64")]
    options.set("x264-params", &format!("asm={}", x264_simd_without_avx512()));
    let mut encoder = encoder.open_with(options).map_err(|e| video_error(path, "cannot open H.264 encoder", e))?;
    stream.set_parameters(&encoder);
    stream.set_time_base(time_base);
    stream.set_rate(rate);
    stream.set_avg_frame_rate(rate);
    output.write_header().map_err(|e| video_error(path, "writing header", e))?;
    let stream_time_base = output.stream(stream_index).expect("stream added above").time_base();

    let mut scaler = Scaler::get(Pixel::RGB24, width, height, Pixel::YUV420P, width, height, Flags::BILINEAR)
        .map_err(|e| video_error(path, "cannot convert from RGB", e))?;
    let drain = |encoder: &mut ffmpeg::encoder::Video, output: &mut ffmpeg::format::context::Output| -> Result<()> {
        let mut packet = ffmpeg::Packet::empty();
        while encoder.receive_packet(&mut packet).is_ok() {
            packet.set_stream(stream_index);
            packet.rescale_ts(time_base, stream_time_base);
            packet.write_interleaved(output).map_err(|e| video_error(path, "writing packet", e))?;
        }
        Ok(())
    };
    for (index, image) in frames.iter().enumerate() {
        let mut rgb = VideoFrame::new(Pixel::RGB24, width, height);
        let stride = rgb.stride(0);
        let row_bytes = width as usize * 3;
        for (row, pixels) in image.as_raw().chunks_exact(row_bytes).enumerate() {
            rgb.data_mut(0)[row * stride..row * stride + row_bytes].copy_from_slice(pixels);
        }
        let mut yuv = VideoFrame::empty();
        scaler.run(&rgb, &mut yuv).map_err(|e| video_error(path, "RGB to YUV conversion", e))?;
        yuv.set_pts(Some(index as i64));
        encoder.send_frame(&yuv).map_err(|e| video_error(path, &format!("encoding frame {index}"), e))?;
        drain(&mut encoder, &mut output)?;
    }
    encoder.send_eof().map_err(|e| video_error(path, "flushing encoder", e))?;
    drain(&mut encoder, &mut output)?;
    output.write_trailer().map_err(|e| video_error(path, "writing trailer", e))?;
    Ok(())
}
