//! One benchmark scene's inputs and outputs: the source video written as a generic sequence
//! folder (the split's input camera with the chosen reconstruction), one trajectory per held-out
//! camera (its poses at the source's instants), and after sampling, the predictions brought to
//! each held-out camera's intrinsics and size beside that camera's frames and co-visibility
//! masks, matched by the scene's time ids.

use std::path::{Path, PathBuf};

use datagen::io::multiview::{CameraView, MultiViewScene};
use datagen::io::sequence::Sequence;
use foundation::camera::{PinholeCamera, mat3_to_row_major, mat4_to_row_major};
use foundation::depth::DepthMap;
use glam::{DMat3, DMat4, DVec3};
use image::{GrayImage, RgbImage};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Which reconstruction the source video is rendered from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reconstruction {
    /// The dataset's own depth and cameras of the input camera.
    Dataset,
    /// A folder with one reconstruction per scene, `DIR/<scene>/`, in any layout
    /// [`datagen::io::sequence`] reads (MegaSAM's, MoSca's exported, ...), of the input camera's
    /// whole video.
    Folder(PathBuf),
}

/// The split a scene is evaluated on: the dataset's, or the one given on the command line.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct SplitOverride {
    /// The input camera (None: the dataset's; the first camera where it has no split).
    pub input: Option<String>,
    /// The held-out cameras (empty: the dataset's; every other camera where it has no split).
    pub held_out: Vec<String>,
}

/// One held-out camera's frames that the sampled window covers.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct HeldOutView {
    /// The camera's id.
    pub camera: String,
    /// The trajectory's output name in the `nvs` job (the file stem).
    pub name: String,
    /// For each source window position with a frame of this camera: (position, frame index).
    pub matches: Vec<(usize, usize)>,
}

/// What [`prepare`] wrote.
#[derive(Debug, Clone)]
pub struct PreparedScene {
    /// The source sequence folder handed to `nvs`.
    pub source: PathBuf,
    /// One trajectory file per held-out view.
    pub trajectories: Vec<PathBuf>,
    /// The held-out views.
    pub views: Vec<HeldOutView>,
    /// The source camera per window position (K and size of the predictions).
    pub source_cameras: Vec<PinholeCamera>,
    /// First frame of the window in the input camera's video.
    pub window_start: usize,
    /// Dataset units per reconstruction unit (1 for the dataset's own reconstruction).
    pub scale: f64,
}

/// Folder of the source sequence inside a scene's work folder.
const SOURCE_DIR: &str = "source";
/// Folder of the trajectory files inside a scene's work folder.
const TRAJECTORY_DIR: &str = "trajectories";

/// The input and held-out cameras of `scene` under `split`, checked to exist and to differ
/// nowhere but where the user asked (a camera may be its own target: the identity check).
pub fn cameras<'a>(scene: &'a MultiViewScene, split: &SplitOverride) -> Result<(&'a CameraView, Vec<&'a CameraView>)> {
    let input_id = match (&split.input, &scene.split) {
        (Some(id), _) => id.clone(),
        (None, Some(s)) => s.input.clone(),
        (None, None) => scene.cameras.first().map(|c| c.id.clone()).unwrap_or_default(),
    };
    let held_ids: Vec<String> = match (split.held_out.is_empty(), &scene.split) {
        (false, _) => split.held_out.clone(),
        (true, Some(s)) => s.held_out.clone(),
        (true, None) => scene.cameras.iter().map(|c| c.id.clone()).filter(|id| *id != input_id).collect(),
    };
    let find = |id: &str| {
        scene.camera(id).ok_or_else(|| {
            let known: Vec<&str> = scene.cameras.iter().map(|c| c.id.as_str()).collect();
            Error::InvalidInput {
                path: scene.path.clone(),
                what: "cameras".to_string(),
                reason: format!("no camera `{id}` in the scene (cameras: {known:?})"),
            }
        })
    };
    let input = find(&input_id)?;
    if held_ids.is_empty() {
        return Err(Error::InvalidInput {
            path: scene.path.clone(),
            what: "split".to_string(),
            reason: "no held-out camera to evaluate on".to_string(),
        });
    }
    let held = held_ids.iter().map(|id| find(id)).collect::<Result<Vec<_>>>()?;
    Ok((input, held))
}

/// Writes the scene's source sequence (the window of `frames` instants from the first one a
/// held-out camera films) and a trajectory per held-out camera under `work`.
pub fn prepare(
    scene: &MultiViewScene,
    split: &SplitOverride,
    reconstruction: &Reconstruction,
    frames: usize,
    work: &Path,
) -> Result<PreparedScene> {
    let (input, held) = cameras(scene, split)?;
    let filmed = |t: usize| held.iter().any(|c| c.time_ids.contains(&t));
    let window_start = input.time_ids.iter().position(|&t| filmed(t)).ok_or_else(|| Error::InvalidInput {
        path: scene.path.clone(),
        what: "time ids".to_string(),
        reason: format!("no instant of input camera `{}` is filmed by a held-out camera", input.id),
    })?;
    let window = window_start..(window_start + frames.max(1)).min(input.sequence.len());
    let (source, scale) = match reconstruction {
        Reconstruction::Dataset => (window_of(&input.sequence, window.clone()), 1.0),
        Reconstruction::Folder(dir) => {
            let path = dir.join(&scene.scene_id);
            let recon = datagen::io::sequence::read_sequence(&path)?;
            if recon.len() != input.sequence.len() {
                return Err(Error::InvalidInput {
                    path,
                    what: "frames".to_string(),
                    reason: format!(
                        "{} frames, but input camera `{}` of {} has {}: a reconstruction of its whole video is needed",
                        recon.len(),
                        input.id,
                        scene.path.display(),
                        input.sequence.len()
                    ),
                });
            }
            let scale = if input.has_depth { depth_scale(&input.sequence, &recon, window.clone()) } else { None };
            (window_of(&recon, window.clone()), scale.unwrap_or(1.0))
        }
    };
    let source_dir = work.join(SOURCE_DIR);
    write_generic(&source, &source_dir)?;
    let trajectory_dir = work.join(TRAJECTORY_DIR);
    std::fs::create_dir_all(&trajectory_dir).map_err(|error| Error::Io { path: trajectory_dir.clone(), error })?;
    let mut views = Vec::new();
    let mut trajectories = Vec::new();
    for camera in held {
        let poses: Vec<DMat4> = window
            .clone()
            .enumerate()
            .map(|(k, i)| {
                let novel = camera.sequence.cameras[nearest_frame(camera, input.time_ids[i])].world_from_camera;
                match reconstruction {
                    Reconstruction::Dataset => novel,
                    Reconstruction::Folder(_) => {
                        let source_from_novel = input.sequence.cameras[i].camera_from_world() * novel;
                        source.cameras[k].world_from_camera * scaled(source_from_novel, 1.0 / scale)
                    }
                }
            })
            .collect();
        let name = format!("view-{}", camera.id);
        let path = trajectory_dir.join(format!("{name}.json"));
        let rows: Vec<Vec<f64>> = poses.iter().map(|p| mat4_to_row_major(p).to_vec()).collect();
        let json = serde_json::json!({ "world_from_camera": rows });
        write_file(&path, &serde_json::to_vec_pretty(&json).expect("json"))?;
        let matches = window
            .clone()
            .enumerate()
            .filter_map(|(k, i)| camera.time_ids.iter().position(|&t| t == input.time_ids[i]).map(|j| (k, j)))
            .collect();
        views.push(HeldOutView { camera: camera.id.clone(), name, matches });
        trajectories.push(path);
    }
    Ok(PreparedScene {
        source: source_dir,
        trajectories,
        views,
        source_cameras: source.cameras.clone(),
        window_start,
        scale,
    })
}

/// The frame of `camera` at instant `time`, else at the nearest instant it films.
fn nearest_frame(camera: &CameraView, time: usize) -> usize {
    (0..camera.time_ids.len()).min_by_key(|&j| camera.time_ids[j].abs_diff(time)).unwrap_or(0)
}

/// A rigid motion with its translation multiplied by `factor` (a change of length unit).
fn scaled(motion: DMat4, factor: f64) -> DMat4 {
    let mut out = motion;
    out.w_axis = (motion.w_axis.truncate() * factor).extend(1.0);
    out
}

/// Median of the dataset's depth over the reconstruction's at the pixels both find valid in the
/// window (the reconstruction's unit in the dataset's), None when no pixel is valid in both.
fn depth_scale(dataset: &Sequence, recon: &Sequence, window: std::ops::Range<usize>) -> Option<f64> {
    let mut ratios = Vec::new();
    for i in window {
        let (a, b) = (&dataset.depth[i], &recon.depth[i]);
        for y in 0..b.height {
            for x in 0..b.width {
                let (xa, ya) = (x * a.width / b.width, y * a.height / b.height);
                let (da, db) = (a.values[ya * a.width + xa], b.values[y * b.width + x]);
                if da.is_finite() && da > 0.0 && db.is_finite() && db > 0.0 {
                    ratios.push(f64::from(da) / f64::from(db));
                }
            }
        }
    }
    ratios.sort_by(f64::total_cmp);
    ratios.get(ratios.len() / 2).copied()
}

/// The frames `window` of `sequence`.
fn window_of(sequence: &Sequence, window: std::ops::Range<usize>) -> Sequence {
    Sequence {
        source_id: sequence.source_id.clone(),
        path: sequence.path.clone(),
        fps: sequence.fps,
        frames: sequence.frames[window.clone()].to_vec(),
        depth: sequence.depth[window.clone()].to_vec(),
        cameras: sequence.cameras[window].to_vec(),
        dynamic_masks: None,
        second_depth: None,
    }
}

/// `sequence` as a generic-layout folder: `frames/%05d.png`, `depth/%05d.exr`, `cameras.json`.
fn write_generic(sequence: &Sequence, dir: &Path) -> Result<()> {
    for sub in ["frames", "depth"] {
        let path = dir.join(sub);
        std::fs::create_dir_all(&path).map_err(|error| Error::Io { path: path.clone(), error })?;
    }
    for (i, (frame, depth)) in sequence.frames.iter().zip(&sequence.depth).enumerate() {
        save(frame, &dir.join(format!("frames/{i:05}.png")))?;
        let depth = DepthMap {
            width: depth.width,
            height: depth.height,
            // The generic layout's invalid depth is 0; NaN and ±inf read back as invalid too, but
            // zeros keep the file plain.
            values: depth.values.iter().map(|&d| if d.is_finite() && d > 0.0 { d } else { 0.0 }).collect(),
        };
        write_file(&dir.join(format!("depth/{i:05}.exr")), &datagen::io::depth_exr::encode_depth_exr(&depth)?)?;
    }
    let cameras = serde_json::json!({
        "intrinsics": sequence.cameras.iter().map(|c| mat3_to_row_major(&c.intrinsics).to_vec()).collect::<Vec<_>>(),
        "world_from_camera":
            sequence.cameras.iter().map(|c| mat4_to_row_major(&c.world_from_camera).to_vec()).collect::<Vec<_>>(),
    });
    write_file(&dir.join("cameras.json"), &serde_json::to_vec_pretty(&cameras).expect("json"))
}

/// What [`write_view`] wrote for one held-out camera, and the render's accuracy there.
pub struct ViewFolders {
    /// Predictions at the held-out camera's intrinsics and size.
    pub pred: PathBuf,
    /// The held-out camera's frames.
    pub target: PathBuf,
    /// Its co-visibility masks, where the dataset ships them.
    pub mask: Option<PathBuf>,
    /// Window positions and held-out frames scored.
    pub matches: Vec<(usize, usize)>,
    /// Mean squared error of the render over the pixels it covers ([0, 1] intensities), pooled
    /// over frames and channels; None where it covers none.
    pub render_mse: Option<f64>,
    /// Share of the held-out camera's pixels the render covers.
    pub render_coverage: f64,
}

/// Writes `work/{pred,target,mask}/<camera>/%05d.png` for `view` from the `nvs` job's outputs
/// (`sampled`: the sampled frames; `render`, `holes`: the render of every window frame), each
/// frame brought from the source camera to the held-out camera, with the render's error over the
/// pixels it covers there. Only window positions below `sampled.len()` count.
pub fn write_view(
    work: &Path,
    view: &HeldOutView,
    camera: &CameraView,
    source_cameras: &[PinholeCamera],
    sampled: &[RgbImage],
    render: &[RgbImage],
    holes: &[GrayImage],
) -> Result<ViewFolders> {
    let matches: Vec<(usize, usize)> =
        view.matches.iter().copied().filter(|&(k, _)| k < sampled.len() && k < render.len()).collect();
    let folder = |kind: &str| work.join(kind).join(&view.camera);
    let (pred_dir, target_dir, mask_dir) = (folder("pred"), folder("target"), folder("mask"));
    for dir in [&pred_dir, &target_dir, &mask_dir] {
        if dir.exists() {
            std::fs::remove_dir_all(dir).map_err(|error| Error::Io { path: dir.clone(), error })?;
        }
    }
    let (mut squared, mut counted, mut pixels) = (0.0f64, 0u64, 0u64);
    for (n, &(k, j)) in matches.iter().enumerate() {
        let (from, to) = (&source_cameras[k], &camera.sequence.cameras[j]);
        let pred = to_camera_rgb(&sampled[k], from, to);
        let rendered = to_camera_rgb(&render[k], from, to);
        let covered = to_camera_coverage(&holes[k], from, to);
        let target = &camera.sequence.frames[j];
        save(&pred, &pred_dir.join(format!("{n:05}.png")))?;
        save(target, &target_dir.join(format!("{n:05}.png")))?;
        if let Some(masks) = &camera.covisible {
            save(&masks[j], &mask_dir.join(format!("{n:05}.png")))?;
        }
        for ((r, t), c) in rendered.pixels().zip(target.pixels()).zip(covered.pixels()) {
            pixels += 1;
            if c.0[0] != 0 {
                counted += 1;
                for ch in 0..3 {
                    let d = (f64::from(r.0[ch]) - f64::from(t.0[ch])) / 255.0;
                    squared += d * d;
                }
            }
        }
    }
    Ok(ViewFolders {
        pred: pred_dir,
        target: target_dir,
        mask: camera.covisible.is_some().then_some(mask_dir),
        matches,
        render_mse: (counted > 0).then(|| squared / (3 * counted) as f64),
        render_coverage: if pixels == 0 { 0.0 } else { counted as f64 / pixels as f64 },
    })
}

/// For each pixel centre of camera `to`, the pixel of camera `from` (same pose) that sees the
/// same ray: `from.K · to.K⁻¹ · (u, v, 1)`.
fn source_pixel(from: &PinholeCamera, to: &PinholeCamera) -> impl Fn(u32, u32) -> (f64, f64) {
    let homography: DMat3 = from.intrinsics * to.intrinsics.inverse();
    move |u, v| {
        let p = homography * DVec3::new(f64::from(u), f64::from(v), 1.0);
        (p.x / p.z, p.y / p.z)
    }
}

/// Whether two cameras see the same image (same size and intrinsics).
fn same_image(from: &PinholeCamera, to: &PinholeCamera) -> bool {
    (from.width, from.height) == (to.width, to.height) && from.intrinsics == to.intrinsics
}

/// `image` from camera `from` as camera `to` (same pose, other intrinsics or size) sees it:
/// bilinear between pixel centres, black outside `from`'s image.
fn to_camera_rgb(image: &RgbImage, from: &PinholeCamera, to: &PinholeCamera) -> RgbImage {
    if same_image(from, to) && image.dimensions() == (to.width, to.height) {
        return image.clone();
    }
    let at = source_pixel(from, to);
    let (w, h) = image.dimensions();
    RgbImage::from_fn(to.width, to.height, |u, v| {
        let (x, y) = at(u, v);
        if !(x >= -0.5 && y >= -0.5 && x <= f64::from(w) - 0.5 && y <= f64::from(h) - 0.5) {
            return image::Rgb([0, 0, 0]);
        }
        let (x, y) = (x.clamp(0.0, f64::from(w - 1)), y.clamp(0.0, f64::from(h - 1)));
        let (x0, y0) = (x.floor() as u32, y.floor() as u32);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = (x - f64::from(x0), y - f64::from(y0));
        let mut out = [0u8; 3];
        for (c, value) in out.iter_mut().enumerate() {
            let p = |x, y| f64::from(image.get_pixel(x, y).0[c]);
            let top = p(x0, y0) * (1.0 - fx) + p(x1, y0) * fx;
            let bottom = p(x0, y1) * (1.0 - fx) + p(x1, y1) * fx;
            *value = (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8;
        }
        image::Rgb(out)
    })
}

/// The render's covered pixels (holes 0) as camera `to` sees them: nearest pixel, uncovered
/// outside `from`'s image.
fn to_camera_coverage(holes: &GrayImage, from: &PinholeCamera, to: &PinholeCamera) -> GrayImage {
    let (w, h) = holes.dimensions();
    let at = source_pixel(from, to);
    let identity = same_image(from, to) && holes.dimensions() == (to.width, to.height);
    GrayImage::from_fn(to.width, to.height, |u, v| {
        let (x, y) = if identity { (f64::from(u), f64::from(v)) } else { at(u, v) };
        let (x, y) = (x.round(), y.round());
        let inside = x >= 0.0 && y >= 0.0 && x < f64::from(w) && y < f64::from(h);
        image::Luma([if inside && holes.get_pixel(x as u32, y as u32).0[0] == 0 { 255 } else { 0 }])
    })
}

fn save<P: image::PixelWithColorType>(image: &image::ImageBuffer<P, Vec<P::Subpixel>>, path: &Path) -> Result<()>
where
    [P::Subpixel]: image::EncodableLayout,
{
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent).map_err(|error| Error::Io { path: parent.to_path_buf(), error })?;
    }
    image.save(path).map_err(|e| Error::InvalidInput {
        path: path.to_path_buf(),
        what: "image".to_string(),
        reason: e.to_string(),
    })
}

fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|error| Error::Io { path: path.to_path_buf(), error })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(fx: f64, cx: f64, cy: f64, width: u32, height: u32) -> PinholeCamera {
        PinholeCamera {
            width,
            height,
            intrinsics: DMat3::from_cols(DVec3::new(fx, 0.0, 0.0), DVec3::new(0.0, fx, 0.0), DVec3::new(cx, cy, 1.0)),
            world_from_camera: DMat4::IDENTITY,
        }
    }

    /// The same intrinsics at half the size (K scaled about pixel centres) give the 2×2 area's
    /// corner-centre samples; identical cameras give the image back.
    #[test]
    fn prediction_is_brought_to_the_held_out_camera() {
        let image = RgbImage::from_fn(8, 6, |x, y| image::Rgb([(x * 30) as u8, (y * 40) as u8, 7]));
        let full = camera(10.0, 3.5, 2.5, 8, 6);
        assert_eq!(to_camera_rgb(&image, &full, &full), image);
        // Half size: pixel u covers full pixels 2u, 2u + 1, so its centre is 2u + 0.5.
        let half = camera(5.0, 1.5, 1.0, 4, 3);
        let small = to_camera_rgb(&image, &full, &half);
        for (u, v) in [(0, 0), (3, 2), (1, 1)] {
            let want = [((2 * u) as f64 + 0.5) * 30.0, ((2 * v) as f64 + 0.5) * 40.0];
            let got = small.get_pixel(u, v).0;
            assert!((f64::from(got[0]) - want[0]).abs() <= 0.5 && (f64::from(got[1]) - want[1]).abs() <= 0.5);
        }
        // A wider held-out camera sees beyond the source's image: black there, covered nowhere.
        let wide = camera(5.0, 3.5, 2.5, 8, 6);
        assert_eq!(to_camera_rgb(&image, &full, &wide).get_pixel(0, 0).0, [0, 0, 0]);
        let holes = GrayImage::new(8, 6);
        let covered = to_camera_coverage(&holes, &full, &wide);
        assert_eq!((covered.get_pixel(0, 0).0[0], covered.get_pixel(4, 3).0[0]), (0, 255));
    }

    /// A change of unit scales the translation only.
    #[test]
    fn scaled_motion_keeps_rotation() {
        let motion = DMat4::from_rotation_y(0.3) * DMat4::from_translation(DVec3::new(1.0, 2.0, 3.0));
        let half = scaled(motion, 0.5);
        assert_eq!(half.x_axis, motion.x_axis);
        assert!((half.w_axis.truncate() - motion.w_axis.truncate() * 0.5).length() < 1e-12);
    }
}
