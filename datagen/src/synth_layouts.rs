//! `datagen synth --cameras N --format dycheck|kubric4d`: the synthetic scene of
//! [`crate::synth`] written in the benchmark datasets' own layouts and conventions, with exact
//! ground truth, so the readers of [`crate::io::dycheck`] and [`crate::io::kubric4d`] are tested
//! on files as those datasets ship them.
//!
//! - **DyCheck** ([`write_dycheck`]): camera 0 is the moving source camera (DyCheck's handheld
//!   training iPhone, with depth), cameras 1.. are static (the rig's poses at frame 0, DyCheck's
//!   tripod test iPhones) and film every instant but frame 1 (DyCheck drops the test frames it
//!   cannot synchronise). Files at 1x (the render's size) and 2x (2 × 2 area averages, as
//!   DyCheck's processor makes them; `extra.json` `factor` 2): `camera/<c>_<t:05>.json`
//!   (orientation camera_from_world, pixel-corner principal point), `rgb/{1x,2x}/` RGBA PNG,
//!   `depth/{1x,2x}/` (H, W, 1) float32 `.npy` for camera 0, `covisible/{1x,2x}/val/` masks from
//!   the exact scene (a held-out pixel is co-visible when camera 0 sees its surface point at the
//!   same instant; at 2x when all four 1x pixels are), `splits/`, `dataset.json`,
//!   `metadata.json`, `scene.json`, `extra.json`.
//! - **Kubric-4D** ([`write_kubric4d`]): every rig camera is a view `v`, with Kubric's world
//!   (Z up: synth (x, y, z) is Kubric (x, −z, y), [`KUBRIC_FROM_SYNTH`]), Blender camera axes,
//!   (w, x, y, z) quaternions, a normalised K with Kubric's signs, float32 TIFF depth holding the
//!   distance to the camera centre, RGBA PNG frames and palette segmentation PNGs of the
//!   moving-object ids.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};
use image::{GrayImage, RgbaImage};

use crate::error::{Error, Result};
use crate::synth::{
    CameraRig, LOOK_AT, ROOM_BACK, ROOM_FRONT, ROOM_HALF_WIDTH, SynthConfig, SynthScene, WALL_HEIGHT,
    ground_truth_covisibility, save_png, write_multiview,
};

/// The layouts `datagen synth --cameras N --format` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SynthFormat {
    /// `generic`: one generic sequence folder per camera ([`write_multiview`]).
    Generic,
    /// `dycheck`: DyCheck iPhone ([`write_dycheck`]).
    Dycheck,
    /// `kubric4d`: Kubric-4D as GCD ships it ([`write_kubric4d`]).
    Kubric4d,
}

impl std::str::FromStr for SynthFormat {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "generic" => Ok(Self::Generic),
            "dycheck" => Ok(Self::Dycheck),
            "kubric4d" => Ok(Self::Kubric4d),
            _ => Err(format!("unknown format `{s}`; one of: generic, dycheck, kubric4d")),
        }
    }
}

/// Writes the multi-camera scene in `format` to `out`.
pub fn write_multiview_as(
    config: &SynthConfig,
    rig: &CameraRig,
    format: SynthFormat,
    out: &Path,
    progress: impl FnMut(u32),
) -> Result<PathBuf> {
    match format {
        SynthFormat::Generic => write_multiview(config, rig, out, progress),
        SynthFormat::Dycheck => write_dycheck(config, rig, out, progress),
        SynthFormat::Kubric4d => write_kubric4d(config, rig, out, progress),
    }
}

/// DyCheck's resolution factor of the benchmark (`extra.json` `factor`, iPhone's `DEFAULT_FACTOR`).
pub const DYCHECK_FACTOR: u32 = 2;

/// The frame held-out DyCheck cameras skip, as DyCheck drops unsynchronised test frames.
pub const DYCHECK_DROPPED_FRAME: u32 = 1;

/// Pose of DyCheck camera `camera` at `frame`: the source path for camera 0, the rig's pose at
/// frame 0 for the static held-out cameras.
pub fn dycheck_world_from_camera(scene: &SynthScene, rig: &CameraRig, camera: u32, frame: u32) -> DMat4 {
    if camera == 0 { scene.world_from_camera(frame) } else { scene.rig_world_from_camera(0, rig, camera) }
}

/// The frames DyCheck camera `camera` films.
pub fn dycheck_frames(config: &SynthConfig, camera: u32) -> Vec<u32> {
    (0..config.frames).filter(|&t| camera == 0 || t != DYCHECK_DROPPED_FRAME || config.frames < 3).collect()
}

/// Renders the scene from `rig` and writes it in DyCheck's iPhone layout (module docs).
pub fn write_dycheck(
    config: &SynthConfig,
    rig: &CameraRig,
    out: &Path,
    mut progress: impl FnMut(u32),
) -> Result<PathBuf> {
    rig.validate()?;
    let scene = SynthScene::new(config)?;
    let intrinsics = config.intrinsics();
    let (width, height) = (config.width as usize, config.height as usize);
    let factor = DYCHECK_FACTOR as usize;
    for sub in ["camera", "rgb/1x", "rgb/2x", "depth/1x", "depth/2x", "covisible/1x/val", "covisible/2x/val", "splits"]
    {
        let dir = out.join(sub);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }
    let name = |camera: u32, frame: u32| format!("{camera}_{frame:05}");
    let (mut train, mut val) = (Vec::new(), Vec::new());
    for frame in 0..config.frames {
        let geometry = scene.frame_geometry(frame);
        let input_pose = dycheck_world_from_camera(&scene, rig, 0, frame);
        for camera in 0..rig.cameras {
            if !dycheck_frames(config, camera).contains(&frame) {
                continue;
            }
            let item = name(camera, frame);
            let pose = dycheck_world_from_camera(&scene, rig, camera, frame);
            let rendered = scene.render_view(&geometry, &pose, &intrinsics);
            write_json(&out.join(format!("camera/{item}.json")), &dycheck_camera_json(&pose, &intrinsics, config))?;
            // Alpha: DyCheck's LiDAR coverage for the training camera, opaque for the others.
            let alpha: Vec<bool> = if camera == 0 {
                rendered.depth.iter().map(|&d| d > 0.0).collect()
            } else {
                vec![true; width * height]
            };
            let rgba = RgbaImage::from_fn(config.width, config.height, |x, y| {
                let [r, g, b] = rendered.rgb.get_pixel(x, y).0;
                image::Rgba([r, g, b, if alpha[y as usize * width + x as usize] { 255 } else { 0 }])
            });
            save_png(&rgba, &out.join(format!("rgb/1x/{item}.png")))?;
            save_png(&area_downsample_rgba(&rgba, factor), &out.join(format!("rgb/2x/{item}.png")))?;
            if camera == 0 {
                let npy = |f: &str| out.join(format!("depth/{f}/{item}.npy"));
                crate::io::npy::write_npy(&npy("1x"), &[height, width, 1], &rendered.depth)?;
                let half = area_downsample_depth(&rendered.depth, width, height, factor);
                crate::io::npy::write_npy(&npy("2x"), &[height / factor, width / factor, 1], &half)?;
                train.push((item, frame, camera));
            } else {
                let covisible = ground_truth_covisibility(&scene, frame, &rendered, &input_pose, &intrinsics);
                let full = GrayImage::from_fn(config.width, config.height, |x, y| {
                    image::Luma([if covisible[y as usize * width + x as usize] { 255 } else { 0 }])
                });
                let half = GrayImage::from_fn(config.width / 2, config.height / 2, |x, y| {
                    let all = (0..4).all(|k| full.get_pixel(2 * x + k % 2, 2 * y + k / 2).0[0] == 255);
                    image::Luma([if all { 255 } else { 0 }])
                });
                save_png(&full, &out.join(format!("covisible/1x/val/{item}.png")))?;
                save_png(&half, &out.join(format!("covisible/2x/val/{item}.png")))?;
                val.push((item, frame, camera));
            }
        }
        progress(frame + 1);
    }
    let split = |items: &[(String, u32, u32)]| {
        serde_json::json!({
            "frame_names": items.iter().map(|i| &i.0).collect::<Vec<_>>(),
            "time_ids": items.iter().map(|i| i.1).collect::<Vec<_>>(),
            "camera_ids": items.iter().map(|i| i.2).collect::<Vec<_>>(),
        })
    };
    write_json(&out.join("splits/train.json"), &split(&train))?;
    write_json(&out.join("splits/val.json"), &split(&val))?;
    let names = |items: &[(String, u32, u32)]| items.iter().map(|i| i.0.clone()).collect::<Vec<_>>();
    let ids: Vec<String> = names(&train).into_iter().chain(names(&val)).collect();
    let dataset = serde_json::json!({
        "count": ids.len(),
        "num_exemplars": train.len(),
        "ids": ids,
        "train_ids": names(&train),
        "val_ids": names(&val),
    });
    write_json(&out.join("dataset.json"), &dataset)?;
    let metadata: serde_json::Map<String, serde_json::Value> = train
        .iter()
        .chain(&val)
        .map(|(item, frame, camera)| {
            (item.clone(), serde_json::json!({"warp_id": frame, "appearance_id": frame, "camera_id": camera}))
        })
        .collect();
    write_json(&out.join("metadata.json"), &serde_json::Value::Object(metadata))?;
    // scene.json as DyCheck's processor computes it, from the room's bounding box.
    let (low, high) =
        (DVec3::new(-ROOM_HALF_WIDTH, 0.0, ROOM_FRONT), DVec3::new(ROOM_HALF_WIDTH, WALL_HEIGHT, ROOM_BACK));
    let center = (low + high) / 2.0;
    let scale = 1.0 / (high - low).length();
    let normalised = |p: DVec3| ((p - center) * scale).to_array();
    write_json(
        &out.join("scene.json"),
        &serde_json::json!({"center": center.to_array(), "scale": scale, "near": 0.05, "far": 1.25}),
    )?;
    let extra = serde_json::json!({
        "factor": DYCHECK_FACTOR,
        "fps": config.fps,
        "bbox": [normalised(low), normalised(high)],
        "lookat": normalised(LOOK_AT),
        "up": [0.0, 1.0, 0.0],
    });
    write_json(&out.join("extra.json"), &extra)?;
    Ok(out.to_owned())
}

/// A DyCheck camera JSON for a toolkit camera (1x).
fn dycheck_camera_json(world_from_camera: &DMat4, intrinsics: &DMat3, config: &SynthConfig) -> serde_json::Value {
    let camera_from_world = DMat3::from_mat4(*world_from_camera).transpose();
    let rows: Vec<[f64; 3]> = (0..3).map(|r| camera_from_world.row(r).to_array()).collect();
    let (fx, fy) = (intrinsics.x_axis.x, intrinsics.y_axis.y);
    let offset = crate::io::dycheck::PIXEL_CORNER_OFFSET;
    serde_json::json!({
        "orientation": rows,
        "position": world_from_camera.w_axis.truncate().to_array(),
        "focal_length": fx,
        "principal_point": [intrinsics.z_axis.x + offset, intrinsics.z_axis.y + offset],
        "skew": 0.0,
        "pixel_aspect_ratio": fy / fx,
        "radial_distortion": [0.0, 0.0, 0.0],
        "tangential_distortion": [0.0, 0.0],
        "image_size": [config.width, config.height],
    })
}

/// RGBA averaged over f × f blocks (rounded); alpha stays 255 only where the whole block is.
fn area_downsample_rgba(image: &RgbaImage, f: usize) -> RgbaImage {
    let f32_ = f as u32;
    RgbaImage::from_fn(image.width() / f32_, image.height() / f32_, |x, y| {
        let mut sum = [0u32; 3];
        let mut opaque = true;
        for k in 0..f32_ * f32_ {
            let p = image.get_pixel(f32_ * x + k % f32_, f32_ * y + k / f32_).0;
            for c in 0..3 {
                sum[c] += u32::from(p[c]);
            }
            opaque &= p[3] == 255;
        }
        let n = f32_ * f32_;
        let mean = sum.map(|s| ((s + n / 2) / n) as u8);
        image::Rgba([mean[0], mean[1], mean[2], if opaque { 255 } else { 0 }])
    })
}

/// Depth averaged over f × f blocks, 0 where any value of the block is 0 (DyCheck's 2x depth).
fn area_downsample_depth(depth: &[f32], width: usize, height: usize, f: usize) -> Vec<f32> {
    let (w, h) = (width / f, height / f);
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let block: Vec<f32> = (0..f * f).map(|k| depth[(y * f + k / f) * width + x * f + k % f]).collect();
            if block.iter().all(|&d| d > 0.0) {
                (block.iter().map(|&d| f64::from(d)).sum::<f64>() / (f * f) as f64) as f32
            } else {
                0.0
            }
        })
        .collect()
}

/// Kubric's world from the synthetic scene's: Kubric is Z-up, the scene y-up, so synth
/// (x, y, z) is Kubric (x, −z, y) (a rotation of +90° about x).
pub const KUBRIC_FROM_SYNTH: DMat3 =
    DMat3::from_cols(DVec3::new(1.0, 0.0, 0.0), DVec3::new(0.0, 0.0, 1.0), DVec3::new(0.0, -1.0, 0.0));

/// Kubric's sensor width in mm (GCD's `kubric_sim._setup_camera` hard-codes 32 mm).
pub const KUBRIC_SENSOR_WIDTH_MM: f64 = 32.0;

/// Renders the scene from every camera of `rig` and writes a Kubric-4D scene folder (module
/// docs); the folder's name is the scene id in the metadata file names.
pub fn write_kubric4d(
    config: &SynthConfig,
    rig: &CameraRig,
    out: &Path,
    mut progress: impl FnMut(u32),
) -> Result<PathBuf> {
    rig.validate()?;
    let scene_id = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    if scene_id.is_empty() {
        return Err(Error::parameter("out", "a Kubric-4D scene folder needs a name (its scene id)"));
    }
    let scene = SynthScene::new(config)?;
    let intrinsics = config.intrinsics();
    let width = config.width as usize;
    let (fx, fy, cx, cy) = (intrinsics.x_axis.x, intrinsics.y_axis.y, intrinsics.z_axis.x, intrinsics.z_axis.y);
    for view in 0..rig.cameras {
        let dir = crate::io::kubric4d::frames_dir(out, view);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }
    let kubric = DMat4::from_mat3(KUBRIC_FROM_SYNTH);
    let mut positions = vec![Vec::new(); rig.cameras as usize];
    let mut quaternions = vec![Vec::new(); rig.cameras as usize];
    for frame in 0..config.frames {
        let geometry = scene.frame_geometry(frame);
        for view in 0..rig.cameras {
            let pose = scene.rig_world_from_camera(frame, rig, view);
            let rendered = scene.render_view(&geometry, &pose, &intrinsics);
            let dir = crate::io::kubric4d::frames_dir(out, view);
            let rgba = RgbaImage::from_fn(config.width, config.height, |x, y| {
                let [r, g, b] = rendered.rgb.get_pixel(x, y).0;
                image::Rgba([r, g, b, 255])
            });
            save_png(&rgba, &dir.join(format!("rgba_{frame:05}.png")))?;
            // Kubric's depth: the distance to the camera centre along the pixel's ray.
            let ray_length: Vec<f32> = rendered
                .depth
                .iter()
                .enumerate()
                .map(|(i, &z)| {
                    let ray = DVec3::new(((i % width) as f64 - cx) / fx, ((i / width) as f64 - cy) / fy, 1.0);
                    (f64::from(z) * ray.length()) as f32
                })
                .collect();
            write_tiff(&dir.join(format!("depth_{frame:05}.tiff")), config.width, config.height, &ray_length)?;
            write_palette_png(&dir.join(format!("segmentation_{frame:05}.png")), &rendered.mask_ids)?;
            let in_kubric = kubric * pose;
            let opencv = DMat3::from_mat4(in_kubric);
            // OpenCV camera axes to Blender's (y up, z backward).
            let blender = DMat3::from_cols(opencv.x_axis, -opencv.y_axis, -opencv.z_axis);
            let q = DQuat::from_mat3(&blender);
            positions[view as usize].push(in_kubric.w_axis.truncate().to_array());
            quaternions[view as usize].push([q.w, q.x, q.y, q.z]);
        }
        progress(frame + 1);
    }
    let (w, h) = (config.width as f64, config.height as f64);
    let k = [[fx / w, 0.0, -(cx + 0.5) / w], [0.0, -fy / h, -(cy + 0.5) / h], [0.0, 0.0, -1.0]];
    for view in 0..rig.cameras {
        let metadata = serde_json::json!({
            "scene": {
                "resolution": [config.width, config.height],
                "num_frames": config.frames,
                "frame_rate": config.fps,
                "frame_start": 0,
                "frame_end": config.frames,
            },
            "camera": {
                "focal_length": fx / w * KUBRIC_SENSOR_WIDTH_MM,
                "sensor_width": KUBRIC_SENSOR_WIDTH_MM,
                "field_of_view": 2.0 * (0.5 * w / fx).atan(),
                "K": k,
                "positions": positions[view as usize],
                "quaternions": quaternions[view as usize],
            },
        });
        write_json(&crate::io::kubric4d::metadata_path(out, &scene_id, view), &metadata)?;
    }
    Ok(out.to_owned())
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    std::fs::write(path, serde_json::to_vec_pretty(value).expect("json")).map_err(|e| Error::io(path, e))
}

/// A one-sample float32 TIFF, as Kubric's `write_tiff` writes depth.
pub fn write_tiff(path: &Path, width: u32, height: u32, values: &[f32]) -> Result<()> {
    let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    let bad = |e: tiff::TiffError| Error::Image { context: path.display().to_string(), reason: e.to_string() };
    let mut encoder = tiff::encoder::TiffEncoder::new(std::io::BufWriter::new(file)).map_err(bad)?;
    encoder.write_image::<tiff::encoder::colortype::Gray32Float>(width, height, values).map_err(bad)
}

/// Ids as an 8-bit palette PNG, as Kubric writes segmentation (grey palette here).
fn write_palette_png(path: &Path, ids: &GrayImage) -> Result<()> {
    let file = std::fs::File::create(path).map_err(|e| Error::io(path, e))?;
    let bad = |e: png::EncodingError| Error::Image { context: path.display().to_string(), reason: e.to_string() };
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), ids.width(), ids.height());
    encoder.set_color(png::ColorType::Indexed);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_palette((0..=255u8).flat_map(|v| [v, v, v]).collect::<Vec<u8>>());
    let mut writer = encoder.write_header().map_err(bad)?;
    writer.write_image_data(ids.as_raw()).map_err(bad)
}
