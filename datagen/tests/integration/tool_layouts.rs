//! Reconstruction tools' outputs (ViPE, VGGT, COLMAP text and binary, GEN3C, depth-only) written
//! by hand in each tool's format and convention from a synthetic scene with exact cameras and
//! depth, read back to the scene's values; their bad inputs fail naming file and field.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::io::sequence::{LayoutName, ReadOptions, read_sequence, read_sequence_as, read_sequence_with};
use datagen::synth::{SynthConfig, SynthScene};
use glam::{DMat3, DMat4, DQuat};
use image::RgbImage;
use npyz::WriterBuilder;

/// A synthetic scene's exact frames, depth and cameras.
pub struct Truth {
    pub width: usize,
    pub height: usize,
    pub frames: Vec<RgbImage>,
    pub depth: Vec<Vec<f32>>,
    /// Moving-object ids (0 static).
    pub masks: Vec<image::GrayImage>,
    pub k: DMat3,
    pub world_from_camera: Vec<DMat4>,
}

impl Truth {
    pub fn new(frames: u32) -> Self {
        Self::of(SynthConfig { width: 64, height: 48, frames, ..SynthConfig::default() })
    }

    pub fn of(config: SynthConfig) -> Self {
        let scene = SynthScene::new(&config).unwrap();
        let rendered: Vec<_> = (0..config.frames).map(|f| scene.render_frame(f)).collect();
        Self {
            width: config.width as usize,
            height: config.height as usize,
            frames: rendered.iter().map(|r| r.rgb.clone()).collect(),
            depth: rendered.iter().map(|r| r.depth.clone()).collect(),
            masks: rendered.iter().map(|r| r.mask_ids.clone()).collect(),
            k: config.intrinsics(),
            world_from_camera: (0..config.frames).map(|f| scene.world_from_camera(f)).collect(),
        }
    }

    pub fn n(&self) -> usize {
        self.frames.len()
    }

    pub fn camera_from_world(&self, i: usize) -> DMat4 {
        self.world_from_camera[i].inverse()
    }

    /// Checks a read sequence against the truth: cameras to `tolerance`, depth where the truth
    /// has a surface (relative `depth_tolerance`), exact frames when `exact_frames`.
    fn assert_read(&self, dir: &Path, layout: Option<LayoutName>, depth_tolerance: f32, exact_frames: bool) {
        let read = read_sequence_as(dir, layout).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        assert_eq!((read.len(), read.size()), (self.n(), (self.width as u32, self.height as u32)));
        for i in 0..self.n() {
            let camera = &read.cameras[i];
            assert!(camera.intrinsics.abs_diff_eq(self.k, 1e-6), "K[{i}] {} vs {}", camera.intrinsics, self.k);
            assert!(
                camera.world_from_camera.abs_diff_eq(self.world_from_camera[i], 1e-6),
                "pose[{i}] {} vs {}",
                camera.world_from_camera,
                self.world_from_camera[i]
            );
            for (got, want) in read.depth[i].values.iter().zip(&self.depth[i]) {
                if *want > 0.0 {
                    assert!((got - want).abs() <= depth_tolerance * want, "depth[{i}] {got} vs {want}");
                }
            }
            if exact_frames {
                assert_eq!(read.frames[i], self.frames[i], "frame {i}");
            }
        }
    }
}

/// One `.npz` member's values in the dtype the tool writes.
pub enum Values<'a> {
    F16(Vec<half::f16>),
    F32(Vec<f32>),
    F64(&'a [f64]),
    I64(Vec<i64>),
    Bool(Vec<bool>),
}

pub fn write_npz(path: &Path, members: Vec<(&str, Vec<u64>, Values<'_>)>) {
    let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
    let options = || zip::write::FileOptions::default();
    for (name, shape, values) in members {
        match values {
            Values::F16(v) => {
                let mut w =
                    npz.array::<half::f16>(name, options()).unwrap().default_dtype().shape(&shape).begin_nd().unwrap();
                w.extend(v.iter().copied()).unwrap();
                w.finish().unwrap();
            }
            Values::F32(v) => {
                let mut w =
                    npz.array::<f32>(name, options()).unwrap().default_dtype().shape(&shape).begin_nd().unwrap();
                w.extend(v.iter().copied()).unwrap();
                w.finish().unwrap();
            }
            Values::F64(v) => {
                let mut w =
                    npz.array::<f64>(name, options()).unwrap().default_dtype().shape(&shape).begin_nd().unwrap();
                w.extend(v.iter().copied()).unwrap();
                w.finish().unwrap();
            }
            Values::I64(v) => {
                let mut w =
                    npz.array::<i64>(name, options()).unwrap().default_dtype().shape(&shape).begin_nd().unwrap();
                w.extend(v.iter().copied()).unwrap();
                w.finish().unwrap();
            }
            Values::Bool(v) => {
                let mut w =
                    npz.array::<bool>(name, options()).unwrap().default_dtype().shape(&shape).begin_nd().unwrap();
                w.extend(v.iter().copied()).unwrap();
                w.finish().unwrap();
            }
        }
    }
}

fn row_major4(m: &DMat4) -> Vec<f64> {
    foundation::camera::mat4_to_row_major(m).to_vec()
}

fn row_major3(m: &DMat3) -> Vec<f64> {
    foundation::camera::mat3_to_row_major(m).to_vec()
}

/// VGGT's `predictions.npz` (float32, as the model computes): camera_from_world 3×4 extrinsics,
/// K, depth (S, H, W, 1), confidence, images (S, 3, H, W) in 0–1.
pub fn write_vggt(truth: &Truth, dir: &Path) -> PathBuf {
    let extrinsics: Vec<DMat4> = (0..truth.n()).map(|i| truth.camera_from_world(i)).collect();
    write_vggt_extrinsics(truth, dir, &extrinsics)
}

/// [`write_vggt`] with the given `extrinsic` matrices (a user's slip: camera-to-world saved).
pub fn write_vggt_extrinsics(truth: &Truth, dir: &Path, extrinsics: &[DMat4]) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let (n, h, w) = (truth.n() as u64, truth.height as u64, truth.width as u64);
    let extrinsic: Vec<f32> = extrinsics.iter().flat_map(|m| row_major4(m)[..12].to_vec()).map(|v| v as f32).collect();
    let intrinsic: Vec<f32> = (0..truth.n()).flat_map(|_| row_major3(&truth.k)).map(|v| v as f32).collect();
    let depth: Vec<f32> = truth.depth.concat();
    let plane = truth.width * truth.height;
    let images: Vec<f32> = truth
        .frames
        .iter()
        .flat_map(|f| (0..3).flat_map(move |c| (0..plane).map(move |p| f32::from(f.as_raw()[p * 3 + c]) / 255.0)))
        .collect();
    write_npz(
        &dir.join("predictions.npz"),
        vec![
            ("extrinsic", vec![n, 3, 4], Values::F32(extrinsic)),
            ("intrinsic", vec![n, 3, 3], Values::F32(intrinsic)),
            ("depth", vec![n, h, w, 1], Values::F32(depth)),
            ("depth_conf", vec![n, h, w], Values::F32(vec![2.0; (n * h * w) as usize])),
            ("images", vec![n, 3, h, w], Values::F32(images)),
        ],
    );
    dir.to_owned()
}

/// GEN3C's archive: rgb.mp4, depth.npz (float16), mask.npz (bool), camera.npz (w2c, intrinsics).
pub fn write_gen3c(truth: &Truth, dir: &Path) -> PathBuf {
    let w2c: Vec<DMat4> = (0..truth.n()).map(|i| truth.camera_from_world(i)).collect();
    write_gen3c_w2c(truth, dir, &w2c)
}

/// [`write_gen3c`] with the given `w2c` matrices (a user's slip: OpenGL axes).
pub fn write_gen3c_w2c(truth: &Truth, dir: &Path, w2c: &[DMat4]) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let (n, h, w) = (truth.n() as u64, truth.height as u64, truth.width as u64);
    foundation::video::encode_video(&dir.join("rgb.mp4"), &truth.frames, 24.0).unwrap();
    let depth = truth.depth.concat();
    write_npz(
        &dir.join("depth.npz"),
        vec![("depth", vec![n, h, w], Values::F16(depth.iter().map(|&d| half::f16::from_f32(d)).collect()))],
    );
    write_npz(
        &dir.join("mask.npz"),
        vec![("mask", vec![n, h, w], Values::Bool(depth.iter().map(|&d| d > 0.0).collect()))],
    );
    let w2c: Vec<f64> = w2c.iter().flat_map(row_major4).collect();
    let k: Vec<f64> = (0..truth.n()).flat_map(|_| row_major3(&truth.k)).collect();
    write_npz(
        &dir.join("camera.npz"),
        vec![("w2c", vec![n, 4, 4], Values::F64(&w2c)), ("intrinsics", vec![n, 3, 3], Values::F64(&k))],
    );
    dir.to_owned()
}

/// A one-channel half-float EXR with channel `Z`, as ViPE writes each depth frame.
fn half_exr(values: &[f32], width: usize, height: usize) -> Vec<u8> {
    use exr::prelude::*;
    let samples = FlatSamples::F16(values.iter().map(|&v| f16::from_f32(v)).collect());
    let layer = Layer::new(
        (width, height),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(vec![AnyChannel::new("Z", samples)])),
    );
    let mut bytes = Vec::new();
    Image::from_layer(layer).write().to_buffered(std::io::Cursor::new(&mut bytes)).unwrap();
    bytes
}

/// ViPE's output folder for one video `name`: rgb/, pose/ (cam2world), intrinsics/ ([fx fy cx cy]),
/// depth/ (zip of per-frame half EXR).
pub fn write_vipe(truth: &Truth, root: &Path, name: &str) -> PathBuf {
    for sub in ["rgb", "pose", "intrinsics", "depth"] {
        std::fs::create_dir_all(root.join(sub)).unwrap();
    }
    let n = truth.n() as u64;
    foundation::video::encode_video(&root.join(format!("rgb/{name}.mp4")), &truth.frames, 24.0).unwrap();
    let inds: Vec<i64> = (0..truth.n() as i64).collect();
    let poses: Vec<f64> = truth.world_from_camera.iter().flat_map(row_major4).collect();
    write_npz(
        &root.join(format!("pose/{name}.npz")),
        vec![("data", vec![n, 4, 4], Values::F64(&poses)), ("inds", vec![n], Values::I64(inds.clone()))],
    );
    let k = truth.k;
    let intrinsics: Vec<f64> = (0..truth.n()).flat_map(|_| [k.x_axis.x, k.y_axis.y, k.z_axis.x, k.z_axis.y]).collect();
    write_npz(
        &root.join(format!("intrinsics/{name}.npz")),
        vec![("data", vec![n, 4], Values::F64(&intrinsics)), ("inds", vec![n], Values::I64(inds))],
    );
    std::fs::write(
        root.join(format!("intrinsics/{name}_camera.txt")),
        (0..n).map(|i| format!("{i}: PINHOLE\n")).collect::<String>(),
    )
    .unwrap();
    let file = std::fs::File::create(root.join(format!("depth/{name}.zip"))).unwrap();
    let mut zip = zip::ZipWriter::new(file);
    for (i, depth) in truth.depth.iter().enumerate() {
        zip.start_file(format!("{i:05}.exr"), zip::write::FileOptions::default()).unwrap();
        zip.write_all(&half_exr(depth, truth.width, truth.height)).unwrap();
    }
    zip.finish().unwrap();
    root.to_owned()
}

/// The order a quaternion's components are written in.
#[derive(Clone, Copy, PartialEq)]
pub enum QuaternionOrder {
    /// COLMAP's (w, x, y, z).
    Wxyz,
    /// (x, y, z, w) (SciPy's, Eigen's storage): a user's slip when written as COLMAP's qvec.
    Xyzw,
}

/// The qvec (in `order`) and tvec of a camera_from_world.
fn qvec_tvec(camera_from_world: &DMat4, order: QuaternionOrder) -> ([f64; 4], [f64; 3]) {
    let q = DQuat::from_mat3(&DMat3::from_mat4(*camera_from_world)).normalize();
    let qvec = match order {
        QuaternionOrder::Wxyz => [q.w, q.x, q.y, q.z],
        QuaternionOrder::Xyzw => [q.x, q.y, q.z, q.w],
    };
    (qvec, camera_from_world.w_axis.truncate().to_array())
}

fn colmap_depth_map(values: &[f32], width: usize, height: usize) -> Vec<u8> {
    let mut bytes = format!("{width}&{height}&1&").into_bytes();
    bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    bytes
}

/// A COLMAP workspace: images/, sparse/0/ (text or binary, one PINHOLE camera with COLMAP's +0.5
/// pixel centres) and stereo/depth_maps/*.geometric.bin.
pub fn write_colmap(truth: &Truth, dir: &Path, binary: bool) -> PathBuf {
    write_colmap_ordered(truth, dir, binary, QuaternionOrder::Wxyz)
}

/// [`write_colmap`] with the qvecs written in `order`.
pub fn write_colmap_ordered(truth: &Truth, dir: &Path, binary: bool, order: QuaternionOrder) -> PathBuf {
    for sub in ["images", "sparse/0", "stereo/depth_maps"] {
        std::fs::create_dir_all(dir.join(sub)).unwrap();
    }
    let k = truth.k;
    let params = [k.x_axis.x, k.y_axis.y, k.z_axis.x + 0.5, k.z_axis.y + 0.5];
    let names: Vec<String> = (0..truth.n()).map(|i| format!("frame_{i:03}.png")).collect();
    for (i, name) in names.iter().enumerate() {
        truth.frames[i].save(dir.join("images").join(name)).unwrap();
        std::fs::write(
            dir.join("stereo/depth_maps").join(format!("{name}.geometric.bin")),
            colmap_depth_map(&truth.depth[i], truth.width, truth.height),
        )
        .unwrap();
    }
    let model = dir.join("sparse/0");
    if binary {
        let mut cameras = 1u64.to_le_bytes().to_vec();
        cameras.extend(1i32.to_le_bytes());
        cameras.extend(1i32.to_le_bytes()); // PINHOLE
        cameras.extend((truth.width as u64).to_le_bytes());
        cameras.extend((truth.height as u64).to_le_bytes());
        cameras.extend(params.iter().flat_map(|p| p.to_le_bytes()));
        std::fs::write(model.join("cameras.bin"), cameras).unwrap();
        let mut images = (truth.n() as u64).to_le_bytes().to_vec();
        for (i, name) in names.iter().enumerate() {
            let (q, t) = qvec_tvec(&truth.camera_from_world(i), order);
            images.extend((i as i32 + 1).to_le_bytes());
            images.extend(q.iter().chain(&t).flat_map(|v| v.to_le_bytes()));
            images.extend(1i32.to_le_bytes());
            images.extend(name.as_bytes());
            images.push(0);
            images.extend(1u64.to_le_bytes());
            images.extend(10.0f64.to_le_bytes());
            images.extend(12.0f64.to_le_bytes());
            images.extend((-1i64).to_le_bytes());
        }
        std::fs::write(model.join("images.bin"), images).unwrap();
    } else {
        let cameras = format!(
            "# Camera list with one line of data per camera:\n1 PINHOLE {} {} {} {} {} {}\n",
            truth.width, truth.height, params[0], params[1], params[2], params[3]
        );
        std::fs::write(model.join("cameras.txt"), cameras).unwrap();
        let mut images = String::from("# Image list with two lines of data per image:\n");
        for (i, name) in names.iter().enumerate() {
            let (q, t) = qvec_tvec(&truth.camera_from_world(i), order);
            images += &format!("{} {} {} {} {} {} {} {} 1 {name}\n", i + 1, q[0], q[1], q[2], q[3], t[0], t[1], t[2]);
            images += if i == 0 { "\n" } else { "10.0 12.0 -1\n" };
        }
        std::fs::write(model.join("images.txt"), images).unwrap();
    }
    dir.to_owned()
}

/// A depth-only tool's output (Video Depth Anything's `NAME_depths.npz`) with PNG frames and a
/// `cameras.json` from another tool declaring z-depth.
pub fn write_depth_only(truth: &Truth, dir: &Path) -> PathBuf {
    write_depth_only_values(truth, dir, &truth.depth)
}

/// [`write_depth_only`] with the given depth file values (a user's slip: disparity or millimetres
/// declared as z-depth in the poses' units).
pub fn write_depth_only_values(truth: &Truth, dir: &Path, depth: &[Vec<f32>]) -> PathBuf {
    std::fs::create_dir_all(dir.join("frames")).unwrap();
    for (i, frame) in truth.frames.iter().enumerate() {
        frame.save(dir.join(format!("frames/{i:05}.png"))).unwrap();
    }
    let (n, h, w) = (truth.n() as u64, truth.height as u64, truth.width as u64);
    write_npz(&dir.join("clip_depths.npz"), vec![("depths", vec![n, h, w], Values::F32(depth.concat()))]);
    write_cameras_json(truth, dir);
    dir.to_owned()
}

/// `cameras.json` with the truth's cameras, declaring z-depth.
fn write_cameras_json(truth: &Truth, dir: &Path) {
    let poses: Vec<Vec<f64>> = truth.world_from_camera.iter().map(row_major4).collect();
    let json =
        serde_json::json!({"intrinsics": row_major3(&truth.k), "world_from_camera": poses, "depth_kind": "z_depth"});
    std::fs::write(dir.join("cameras.json"), json.to_string()).unwrap();
}

fn error_of(dir: &Path, layout: Option<LayoutName>) -> String {
    read_sequence_as(dir, layout).err().map(|e| e.to_string()).unwrap_or_else(|| panic!("{} must fail", dir.display()))
}

#[test]
fn vggt_predictions_read_to_the_scene() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let seq = write_vggt(&truth, &dir.path().join("vggt"));
    // float32 extrinsics inverted in f64: ~1e-6 of the scene's few-unit translations.
    truth.assert_read(&seq, None, 1e-6, true);

    // Every finite depth is kept by default, whatever its confidence (VGGT filters by confidence
    // only to display points); the percentile option drops depth below that percentile of the
    // confidences, as VGGT's viewers do: every third pixel here at the median.
    let (n, h, w) = (truth.n() as u64, truth.height as u64, truth.width as u64);
    let plane = (h * w) as usize;
    let conf: Vec<f32> =
        (0..n as usize * plane).map(|i| if (i % plane).is_multiple_of(3) { 1.0 } else { 3.0 }).collect();
    let mut archive = datagen::io::npy::NpzReader::open(&seq.join("predictions.npz")).unwrap();
    let read_member = |archive: &mut datagen::io::npy::NpzReader, name: &str| {
        archive.read_f32(name, &[datagen::io::npy::Axis::Any; 4])
    };
    let extrinsic = archive.read_f32("extrinsic", &[datagen::io::npy::Axis::Any; 3]).unwrap().data;
    let intrinsic = archive.read_f32("intrinsic", &[datagen::io::npy::Axis::Any; 3]).unwrap().data;
    let depth = read_member(&mut archive, "depth").unwrap().data;
    let images = read_member(&mut archive, "images").unwrap().data;
    write_npz(
        &seq.join("predictions.npz"),
        vec![
            ("extrinsic", vec![n, 3, 4], Values::F32(extrinsic)),
            ("intrinsic", vec![n, 3, 3], Values::F32(intrinsic)),
            ("depth", vec![n, h, w, 1], Values::F32(depth)),
            ("depth_conf", vec![n, h, w], Values::F32(conf)),
            ("images", vec![n, 3, h, w], Values::F32(images)),
        ],
    );
    let read = read_sequence(&seq).unwrap();
    assert!(read.depth.iter().all(|d| d.values.iter().all(|v| v.is_finite())), "no depth dropped by default");
    let with = |p: f64| ReadOptions { vggt_confidence_percentile: Some(p) };
    let read = read_sequence_with(&seq, None, &with(50.0)).unwrap();
    for (i, value) in read.depth[2].values.iter().enumerate() {
        assert_eq!(value.is_nan(), i.is_multiple_of(3), "pixel {i}: {value}");
    }
    // Percentile 0 keeps everything (VGGT's conf_thres 0); ≥ keeps the values at the threshold:
    // at the 80th percentile (3.0) the 3.0s stay.
    for p in [0.0, 80.0] {
        let read = read_sequence_with(&seq, None, &with(p)).unwrap();
        assert_eq!(
            read.depth[2].values.iter().filter(|v| v.is_nan()).count(),
            if p == 0.0 { 0 } else { plane.div_ceil(3) }
        );
    }
    let error = read_sequence_with(&seq, None, &with(101.0)).unwrap_err().to_string();
    assert!(error.contains("predictions.npz") && error.contains("101"), "{error}");
}

#[test]
fn gen3c_archive_reads_to_the_scene() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let seq = write_gen3c(&truth, &dir.path().join("gen3c"));
    // float16 depth: 2^-11 relative.
    truth.assert_read(&seq, Some(LayoutName::Gen3c), 1e-3, false);
    // mask.npz false (here every 7th pixel) is invalid depth, true keeps it.
    let (n, h, w) = (truth.n() as u64, truth.height as u64, truth.width as u64);
    let mask: Vec<bool> = (0..n * h * w).map(|i| !i.is_multiple_of(7)).collect();
    write_npz(&seq.join("mask.npz"), vec![("mask", vec![n, h, w], Values::Bool(mask))]);
    let read = read_sequence(&seq).unwrap();
    for (i, value) in read.depth[1].values.iter().enumerate() {
        let flat = (h * w) as usize + i;
        assert_eq!(value.is_nan(), flat.is_multiple_of(7), "pixel {i}: {value}");
    }
}

#[test]
fn vipe_output_reads_to_the_scene() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let root = write_vipe(&truth, &dir.path().join("vipe_results"), "clip");
    truth.assert_read(&root, None, 1e-3, false);
    assert_eq!(read_sequence(&root).unwrap().source_id, "clip", "the video's name, not the output folder's");

    // A second video in the same output folder: detection lists both, naming one is still ambiguous.
    write_vipe(&truth, &root, "other");
    let error = error_of(&root, None);
    assert!(
        error.contains("pose/clip.npz") && error.contains("pose/other.npz") && error.contains("ambiguous"),
        "{error}"
    );
    let error = error_of(&root, Some(LayoutName::Vipe));
    assert!(error.contains("clip, other") && error.contains("one per folder"), "{error}");
    // One video is named by its pose file (or its rgb/NAME.mp4).
    truth.assert_read(&root.join("pose/other.npz"), None, 1e-3, false);
    let read = read_sequence_as(&root.join("rgb/clip.mp4"), Some(LayoutName::Vipe)).unwrap();
    assert_eq!(read.source_id, "clip");
}

#[test]
fn colmap_text_and_binary_models_read_to_the_scene() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let text = write_colmap(&truth, &dir.path().join("text"), false);
    truth.assert_read(&text, None, 0.0, true);
    let binary = write_colmap(&truth, &dir.path().join("binary"), true);
    truth.assert_read(&binary, Some(LayoutName::Colmap), 0.0, true);
}

#[test]
fn depth_only_output_reads_with_poses_from_cameras_json() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let seq = write_depth_only(&truth, &dir.path().join("vda"));
    truth.assert_read(&seq, None, 0.0, true);

    // Without cameras: an error, never invented poses.
    std::fs::remove_file(seq.join("cameras.json")).unwrap();
    let error = error_of(&seq, Some(LayoutName::DepthOnly));
    assert!(error.contains("cameras.json") && error.contains("none are invented"), "{error}");

    // Disparity, or depth of no declared kind, is refused naming the key.
    let json = serde_json::json!({"intrinsics": row_major3(&truth.k),
        "world_from_camera": truth.world_from_camera.iter().map(row_major4).collect::<Vec<_>>()});
    std::fs::write(seq.join("cameras.json"), json.to_string()).unwrap();
    let error = error_of(&seq, None);
    assert!(error.contains("cameras.json") && error.contains("depth_kind") && error.contains("disparity"), "{error}");
}

/// A depth video as the depth tools save it beside their input: grey levels of the depth.
fn grey_depth_video(truth: &Truth) -> Vec<RgbImage> {
    let max = truth.depth.iter().flatten().copied().fold(0.0f32, f32::max);
    truth
        .depth
        .iter()
        .map(|d| {
            let grey: Vec<u8> = d.iter().flat_map(|&v| [(255.0 * v / max) as u8; 3]).collect();
            RgbImage::from_raw(truth.width as u32, truth.height as u32, grey).unwrap()
        })
        .collect()
}

/// Mean absolute difference of two frame lists' channels (0–255).
fn mean_difference(a: &[RgbImage], b: &[RgbImage]) -> f64 {
    let (sum, count) = a.iter().zip(b).fold((0u64, 0u64), |(sum, count), (x, y)| {
        let d: u64 = x.as_raw().iter().zip(y.as_raw()).map(|(p, q)| u64::from(p.abs_diff(*q))).sum();
        (sum + d, count + x.as_raw().len() as u64)
    });
    sum as f64 / count as f64
}

/// DepthCrafter's `run.py` output for `clip.mp4`: `clip.npz` (member `depth`), `clip_depth.mp4`,
/// `clip_vis.mp4` and `clip_input.mp4` (the frames it processed); Video Depth Anything's:
/// `clip_depths.npz` (member `depths`), `clip_src.mp4`, `clip_vis.mp4`. Both train on their
/// input video, whatever sorts first; the original video beside the tool's saved input (with
/// another frame count, as DepthCrafter's `--target-fps` makes) yields to the saved input.
#[test]
fn depth_tools_folders_train_on_their_input_video() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let grey = grey_depth_video(&truth);
    let doubled: Vec<RgbImage> = truth.frames.iter().flat_map(|f| [f.clone(), f.clone()]).collect();
    let (n, h, w) = (truth.n() as u64, truth.height as u64, truth.width as u64);
    let video = |path: PathBuf, frames: &[RgbImage]| foundation::video::encode_video(&path, frames, 24.0).unwrap();

    let crafter = dir.path().join("depthcrafter");
    std::fs::create_dir_all(&crafter).unwrap();
    write_npz(&crafter.join("clip.npz"), vec![("depth", vec![n, h, w], Values::F32(truth.depth.concat()))]);
    write_cameras_json(&truth, &crafter);
    video(crafter.join("clip_depth.mp4"), &grey);
    video(crafter.join("clip_vis.mp4"), &grey);
    video(crafter.join("clip_input.mp4"), &truth.frames);
    video(crafter.join("clip.mp4"), &doubled);

    let vda = dir.path().join("vda");
    std::fs::create_dir_all(&vda).unwrap();
    write_npz(&vda.join("clip_depths.npz"), vec![("depths", vec![n, h, w], Values::F32(truth.depth.concat()))]);
    write_cameras_json(&truth, &vda);
    video(vda.join("clip_vis.mp4"), &grey);
    video(vda.join("clip_src.mp4"), &truth.frames);
    video(vda.join("clip.mp4"), &doubled);

    for (seq, input) in [(&crafter, "clip_input.mp4"), (&vda, "clip_src.mp4")] {
        let read = read_sequence(seq).unwrap_or_else(|e| panic!("{}: {e}", seq.display()));
        let expected = foundation::video::decode_video(&seq.join(input)).unwrap().frames;
        assert!(read.frames == expected, "{}: the frames are not {input}'s", seq.display());
        // What sorting would have picked instead: the depth video, far off the frames.
        assert!(mean_difference(&grey, &truth.frames) > 30.0);
    }

    // Two videos that could each be the frames: refused, naming both, never picked by sort order.
    std::fs::rename(crafter.join("clip.mp4"), crafter.join("other.mp4")).unwrap();
    let error = error_of(&crafter, None);
    assert!(error.contains("ambiguous") && error.contains("clip_input.mp4") && error.contains("other.mp4"), "{error}");
    // Only the tool's depth and visualisation videos: no frames, said so.
    for name in ["clip_input.mp4", "other.mp4"] {
        std::fs::remove_file(crafter.join(name)).unwrap();
    }
    let error = error_of(&crafter, None);
    assert!(error.contains("no input video") && error.contains("clip_depth.mp4"), "{error}");
}

#[test]
fn a_folder_with_two_tools_files_is_ambiguous_and_lists_them() {
    let truth = Truth::new(2);
    let dir = tempfile::tempdir().unwrap();
    let seq = write_vggt(&truth, &dir.path().join("both"));
    write_gen3c(&truth, &seq);
    let error = error_of(&seq, None);
    assert!(
        error.contains("ambiguous") && error.contains("vggt") && error.contains("gen3c") && error.contains("--layout"),
        "{error}"
    );
    // Naming the layout resolves it.
    truth.assert_read(&seq, Some(LayoutName::Vggt), 1e-6, true);
}

#[test]
fn tool_files_with_bad_content_fail_naming_file_and_field() {
    let truth = Truth::new(2);
    let dir = tempfile::tempdir().unwrap();
    let (n, h, w) = (2u64, truth.height as u64, truth.width as u64);

    // VGGT: a scaled (non-rigid) extrinsic; a NaN confidence.
    let vggt = write_vggt(&truth, &dir.path().join("vggt"));
    let mut extrinsic: Vec<f32> =
        (0..2).flat_map(|i| row_major4(&truth.camera_from_world(i))[..12].to_vec()).map(|v| v as f32).collect();
    for v in &mut extrinsic[12..] {
        *v *= 2.0;
    }
    let depth = truth.depth.concat();
    let images = vec![0.5f32; (n * 3 * h * w) as usize];
    let k: Vec<f32> = (0..2).flat_map(|_| row_major3(&truth.k)).map(|v| v as f32).collect();
    let predictions = |extrinsic: Vec<f32>, conf: Vec<f32>| {
        write_npz(
            &vggt.join("predictions.npz"),
            vec![
                ("extrinsic", vec![n, 3, 4], Values::F32(extrinsic)),
                ("intrinsic", vec![n, 3, 3], Values::F32(k.clone())),
                ("depth", vec![n, h, w, 1], Values::F32(depth.clone())),
                ("depth_conf", vec![n, h, w], Values::F32(conf)),
                ("images", vec![n, 3, h, w], Values::F32(images.clone())),
            ],
        )
    };
    predictions(extrinsic, vec![2.0; depth.len()]);
    let error = error_of(&vggt, None);
    assert!(error.contains("predictions.npz") && error.contains("extrinsic[1]") && error.contains("rigid"), "{error}");
    let good: Vec<f32> =
        (0..2).flat_map(|i| row_major4(&truth.camera_from_world(i))[..12].to_vec()).map(|v| v as f32).collect();
    let mut conf = vec![2.0; depth.len()];
    conf[(h * w) as usize + 5] = f32::NAN;
    predictions(good, conf);
    let filtered = ReadOptions { vggt_confidence_percentile: Some(50.0) };
    let error = read_sequence_with(&vggt, None, &filtered).unwrap_err().to_string();
    assert!(error.contains("depth_conf[1]") && error.contains("non-finite confidence"), "{error}");

    // GEN3C: OpenGL-style depth (negative z); a mask of another resolution than the depth.
    let gen3c = write_gen3c(&truth, &dir.path().join("gen3c"));
    let negative: Vec<half::f16> = depth.iter().map(|&d| half::f16::from_f32(-d)).collect();
    write_npz(&gen3c.join("depth.npz"), vec![("depth", vec![n, h, w], Values::F16(negative))]);
    let error = error_of(&gen3c, None);
    assert!(error.contains("depth.npz") && error.contains("depth[0]") && error.contains("OpenGL"), "{error}");
    write_gen3c(&truth, &gen3c);
    write_npz(
        &gen3c.join("mask.npz"),
        vec![("mask", vec![n, h / 2, w / 2], Values::Bool(vec![true; (n * h * w / 4) as usize]))],
    );
    let error = error_of(&gen3c, None);
    assert!(error.contains("mask.npz") && error.contains("mask.npy"), "{error}");

    // ViPE: one depth frame of another resolution; a pose missing for frame 1; a fisheye camera.
    let vipe = write_vipe(&truth, &dir.path().join("vipe"), "clip");
    let file = std::fs::File::create(vipe.join("depth/clip.zip")).unwrap();
    let mut zip = zip::ZipWriter::new(file);
    zip.start_file("00000.exr", zip::write::FileOptions::default()).unwrap();
    zip.write_all(&half_exr(&truth.depth[0], truth.width, truth.height)).unwrap();
    zip.start_file("00001.exr", zip::write::FileOptions::default()).unwrap();
    zip.write_all(&half_exr(&vec![1.0; 32 * 24], 32, 24)).unwrap();
    zip.finish().unwrap();
    let error = error_of(&vipe, None);
    assert!(error.contains("clip.zip") && error.contains("00001.exr"), "{error}");
    write_vipe(&truth, &vipe, "clip");
    let poses: Vec<f64> = row_major4(&truth.world_from_camera[0]).repeat(2);
    write_npz(
        &vipe.join("pose/clip.npz"),
        vec![("data", vec![2, 4, 4], Values::F64(&poses)), ("inds", vec![2], Values::I64(vec![0, 2]))],
    );
    let error = error_of(&vipe, None);
    assert!(error.contains("pose/clip.npz") && error.contains("inds") && error.contains("frame 2"), "{error}");
    write_vipe(&truth, &vipe, "clip");
    std::fs::write(vipe.join("intrinsics/clip_camera.txt"), "0: PINHOLE\n1: MEI\n").unwrap();
    let error = error_of(&vipe, None);
    assert!(error.contains("clip_camera.txt") && error.contains("line 2") && error.contains("MEI"), "{error}");

    // COLMAP: a frame the model does not have; a distorted camera model.
    let colmap = write_colmap(&truth, &dir.path().join("colmap"), false);
    truth.frames[0].save(colmap.join("images/extra.png")).unwrap();
    let error = error_of(&colmap, None);
    assert!(error.contains("sparse/0") && error.contains("extra.png") && error.contains("not registered"), "{error}");
    std::fs::remove_file(colmap.join("images/extra.png")).unwrap();
    std::fs::write(colmap.join("sparse/0/cameras.txt"), "1 SIMPLE_RADIAL 64 48 60 32 24 0.05\n").unwrap();
    let error = error_of(&colmap, None);
    assert!(
        error.contains("cameras.txt")
            && error.contains("camera 1")
            && error.contains("SIMPLE_RADIAL")
            && error.contains("image_undistorter"),
        "{error}"
    );
    std::fs::write(colmap.join("sparse/0/cameras.txt"), "1 OPENCV_FISHEYE 64 48 60 60 32 24 0 0 0 0\n").unwrap();
    let error = error_of(&colmap, None);
    assert!(error.contains("OPENCV_FISHEYE") && error.contains("not read"), "{error}");
}

#[test]
fn pairs_from_each_tool_in_one_command_and_nothing_written_on_bad_input() {
    let truth = Truth::new(3);
    let dir = tempfile::tempdir().unwrap();
    let tools: [(&str, PathBuf); 5] = [
        ("vipe", write_vipe(&truth, &dir.path().join("vipe"), "clip")),
        ("vggt", write_vggt(&truth, &dir.path().join("vggt"))),
        ("colmap", write_colmap(&truth, &dir.path().join("colmap"), true)),
        ("gen3c", write_gen3c(&truth, &dir.path().join("gen3c"))),
        ("depth-only", write_depth_only(&truth, &dir.path().join("depth_only"))),
    ];
    for (layout, seq) in &tools {
        let out = dir.path().join(format!("out_{layout}"));
        let output = Command::new(env!("CARGO_BIN_EXE_datagen"))
            .args(["pairs", seq.to_str().unwrap(), "--out", out.to_str().unwrap(), "--layout", layout])
            .output()
            .unwrap();
        assert!(output.status.success(), "{layout}: {}", String::from_utf8_lossy(&output.stderr));
        let shards: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.path().extension().is_some_and(|x| x == "parquet"))
            .collect();
        assert_eq!(shards.len(), 1, "{layout}");
    }
    // A non-rigid pose: the command fails naming file and field, and writes nothing.
    let gen3c = &tools[3].1;
    let mut w2c: Vec<f64> = (0..3).flat_map(|i| row_major4(&truth.camera_from_world(i))).collect();
    w2c[16] = 1.5;
    let k: Vec<f64> = (0..3).flat_map(|_| row_major3(&truth.k)).collect();
    write_npz(
        &gen3c.join("camera.npz"),
        vec![("w2c", vec![3, 4, 4], Values::F64(&w2c)), ("intrinsics", vec![3, 3, 3], Values::F64(&k))],
    );
    let out = dir.path().join("out_bad");
    let output = Command::new(env!("CARGO_BIN_EXE_datagen"))
        .args(["pairs", gen3c.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("camera.npz") && stderr.contains("w2c[1]"), "{stderr}");
    assert!(!out.exists() || std::fs::read_dir(&out).unwrap().next().is_none(), "nothing written");
}
