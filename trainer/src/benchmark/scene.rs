//! One benchmark scene's inputs and outputs: the frames scored (every held-out frame at an
//! instant the input camera films, or those a DyCheck correspondence file lists), the windows of
//! the input camera's video that cover them ([`plan_windows`]), per window the source video
//! written as a generic sequence folder (the split's input camera with the chosen
//! reconstruction) and one trajectory per held-out camera (its poses at the window's instants),
//! and after sampling, the predictions brought to each held-out camera's intrinsics and size
//! beside that camera's frames and co-visibility masks, matched by the scene's time ids.

use std::path::{Path, PathBuf};

use datagen::api::FrameCorrespondence;
use datagen::api::Sequence;
use datagen::api::{CameraView, MultiViewScene};
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
    /// [`datagen::api::read_sequence`] reads (MegaSAM's, MoSca's exported, ...), of the input camera's
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

/// One held-out camera's frames scored from one window.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct HeldOutView {
    /// The camera's id.
    pub camera: String,
    /// The trajectory's output name in the window's `nvs` job (the file stem).
    pub name: String,
    /// For each window position scored with a frame of this camera: (position, frame index).
    pub matches: Vec<(usize, usize)>,
}

/// A window of the input camera's video sampled as one clip, and the instants scored from it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Window {
    /// First frame (index into the input camera's video).
    pub start: usize,
    /// One past the last frame.
    pub end: usize,
    /// The evaluated frames scored from this window (indices into the input camera's video).
    pub scored: Vec<usize>,
}

/// What [`prepare`] wrote for one window.
#[derive(Debug, Clone)]
pub struct PreparedWindow {
    /// The window.
    pub window: Window,
    /// Its work folder (`window-<start>`): the source, the trajectories and the `nvs` job.
    pub dir: PathBuf,
    /// The source sequence folder handed to `nvs`.
    pub source: PathBuf,
    /// One trajectory file per held-out view.
    pub trajectories: Vec<PathBuf>,
    /// The held-out views with a frame scored from this window.
    pub views: Vec<HeldOutView>,
    /// The source camera per window position (K and size of the predictions).
    pub source_cameras: Vec<PinholeCamera>,
}

/// What [`prepare`] wrote.
#[derive(Debug, Clone)]
pub struct PreparedScene {
    /// The windows, in order.
    pub windows: Vec<PreparedWindow>,
    /// Dataset units per reconstruction unit (1 for the dataset's own reconstruction).
    pub scale: f64,
}

/// Folder of the source sequence inside a window's work folder.
const SOURCE_DIR: &str = "source";
/// Folder of the trajectory files inside a window's work folder.
const TRAJECTORY_DIR: &str = "trajectories";

/// The work folder name of the window starting at frame `start`.
pub fn window_dir_name(start: usize) -> String {
    format!("window-{start:05}")
}

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

/// The frames of held-out `camera` that are scored: those at an instant the input camera films,
/// and with a correspondence file (`path`, read), only those it lists for the camera
/// (`<camera>_<time>.png`, the camera's id as its number), as the official `eval_metrics.py`
/// selects them. A listed frame the camera does not have at an instant the input films is
/// refused naming the file and the entry.
fn scored_frames(
    input: &CameraView,
    camera: &CameraView,
    correspondence: Option<(&Path, &FrameCorrespondence)>,
) -> Result<Vec<usize>> {
    let filmed = |j: usize| input.time_ids.contains(&camera.time_ids[j]);
    let Some((path, correspondence)) = correspondence else {
        return Ok((0..camera.time_ids.len()).filter(|&j| filmed(j)).collect());
    };
    let refuse =
        |reason: String| Error::InvalidInput { path: path.to_path_buf(), what: "correspondence".to_string(), reason };
    let number: u32 = camera.id.parse().map_err(|_| {
        refuse(format!(
            "held-out camera `{}` has no number, and correspondence files name cameras by number",
            camera.id
        ))
    })?;
    let listed = correspondence.frames(number);
    if listed.is_empty() {
        return Err(refuse(format!("no `{number}_<frame>.png` line for held-out camera `{}`", camera.id)));
    }
    let mut frames = Vec::with_capacity(listed.len());
    for time in listed {
        let j = (0..camera.time_ids.len()).find(|&j| camera.time_ids[j] == time && filmed(j)).ok_or_else(|| {
            refuse(format!(
                "`{number}_{time:05}.png`: camera `{}` has no frame at instant {time} that input camera `{}` films",
                camera.id, input.id
            ))
        })?;
        frames.push(j);
    }
    frames.sort_unstable();
    frames.dedup();
    Ok(frames)
}

/// The windows of `frames` frames of a video of `len` frames that score the `evaluated` frames
/// (sorted, distinct): each starts at the first evaluated frame not yet scored, except that one
/// that would pass the last evaluated frame is shifted back to end there (not before frame 0),
/// overlapping the window before it. A frame in two windows is scored from the earlier one
/// (the later window scores only the frames past the earlier's end).
pub fn plan_windows(evaluated: &[usize], frames: usize, len: usize) -> Vec<Window> {
    let frames = frames.max(1);
    let Some(&last) = evaluated.last() else { return Vec::new() };
    let mut windows = Vec::new();
    let mut rest = evaluated;
    while let Some(&next) = rest.first() {
        let start = next.min((last + 1).saturating_sub(frames));
        let end = (start + frames).min(len);
        let scored = rest.iter().take_while(|&&i| i < end).count();
        windows.push(Window { start, end, scored: rest[..scored].to_vec() });
        rest = &rest[scored..];
    }
    windows
}

/// Writes the scene's windows under `work`: per window (see [`plan_windows`]) over the frames
/// scored (every held-out frame at an instant the input camera films, or those the
/// correspondence file at `correspondence` lists), its source sequence and a trajectory per
/// held-out camera scored there.
pub fn prepare(
    scene: &MultiViewScene,
    split: &SplitOverride,
    reconstruction: &Reconstruction,
    frames: usize,
    correspondence: Option<&Path>,
    work: &Path,
) -> Result<PreparedScene> {
    let (input, held) = cameras(scene, split)?;
    let correspondence =
        correspondence.map(|path| datagen::api::read_correspondence(path).map(|c| (path, c))).transpose()?;
    let mut scored = Vec::with_capacity(held.len());
    for camera in &held {
        scored.push(scored_frames(input, camera, correspondence.as_ref().map(|(p, c)| (*p, c)))?);
    }
    // The input frame of each scored held-out frame (the first at its instant).
    let position = |time: usize| input.time_ids.iter().position(|&t| t == time).expect("filtered as filmed");
    let evaluated: std::collections::BTreeSet<usize> = held
        .iter()
        .zip(&scored)
        .flat_map(|(camera, frames)| frames.iter().map(|&j| position(camera.time_ids[j])))
        .collect();
    if evaluated.is_empty() {
        return Err(Error::InvalidInput {
            path: scene.path.clone(),
            what: "time ids".to_string(),
            reason: format!("no instant of input camera `{}` is filmed by a held-out camera", input.id),
        });
    }
    let evaluated: Vec<usize> = evaluated.into_iter().collect();
    let windows = plan_windows(&evaluated, frames, input.sequence.len());
    let span = windows.iter().map(|w| w.start).min().unwrap_or(0)..windows.iter().map(|w| w.end).max().unwrap_or(0);
    let (recon, scale) = match reconstruction {
        Reconstruction::Dataset => (None, 1.0),
        Reconstruction::Folder(dir) => {
            let path = dir.join(&scene.scene_id);
            let recon = datagen::api::read_sequence(&path, None)?;
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
            // One unit for the whole video: the median over every frame the windows span.
            let scale = if input.has_depth { depth_scale(&input.sequence, &recon, span) } else { None };
            (Some(recon), scale.unwrap_or(1.0))
        }
    };
    let mut prepared = Vec::with_capacity(windows.len());
    for window in windows {
        let dir = work.join(window_dir_name(window.start));
        let range = window.start..window.end;
        let source = window_of(recon.as_ref().unwrap_or(&input.sequence), range.clone());
        let source_dir = dir.join(SOURCE_DIR);
        write_generic(&source, &source_dir)?;
        let trajectory_dir = dir.join(TRAJECTORY_DIR);
        std::fs::create_dir_all(&trajectory_dir).map_err(|error| Error::Io { path: trajectory_dir.clone(), error })?;
        let (mut views, mut trajectories) = (Vec::new(), Vec::new());
        for (camera, frames) in held.iter().zip(&scored) {
            let matches: Vec<(usize, usize)> = window
                .scored
                .iter()
                .filter_map(|&i| {
                    let j = frames.iter().copied().find(|&j| camera.time_ids[j] == input.time_ids[i])?;
                    Some((i - window.start, j))
                })
                .collect();
            if matches.is_empty() {
                continue;
            }
            let poses: Vec<DMat4> = range
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
            views.push(HeldOutView { camera: camera.id.clone(), name, matches });
            trajectories.push(path);
        }
        prepared.push(PreparedWindow {
            window,
            dir,
            source: source_dir,
            trajectories,
            views,
            source_cameras: source.cameras.clone(),
        });
    }
    Ok(PreparedScene { windows: prepared, scale })
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
        write_file(&dir.join(format!("depth/{i:05}.exr")), &datagen::api::encode_depth_exr(&depth)?)?;
    }
    let cameras = serde_json::json!({
        "intrinsics": sequence.cameras.iter().map(|c| mat3_to_row_major(&c.intrinsics).to_vec()).collect::<Vec<_>>(),
        "world_from_camera":
            sequence.cameras.iter().map(|c| mat4_to_row_major(&c.world_from_camera).to_vec()).collect::<Vec<_>>(),
    });
    write_file(&dir.join("cameras.json"), &serde_json::to_vec_pretty(&cameras).expect("json"))
}

/// A held-out camera's folders of scored frames: `work/{pred,target,mask}/<camera>/%05d.png`.
pub struct ViewFolders {
    /// Predictions at the held-out camera's intrinsics and size.
    pub pred: PathBuf,
    /// The held-out camera's frames.
    pub target: PathBuf,
    /// Its co-visibility masks, where the dataset ships them.
    pub mask: Option<PathBuf>,
}

impl ViewFolders {
    /// The folders of `camera` under `work`, emptied of an earlier run's frames.
    pub fn create(work: &Path, camera: &CameraView) -> Result<Self> {
        let folder = |kind: &str| work.join(kind).join(&camera.id);
        let (pred, target, mask) = (folder("pred"), folder("target"), folder("mask"));
        for dir in [&pred, &target, &mask] {
            if dir.exists() {
                std::fs::remove_dir_all(dir).map_err(|error| Error::Io { path: dir.clone(), error })?;
            }
        }
        Ok(Self { pred, target, mask: camera.covisible.is_some().then_some(mask) })
    }
}

/// The render's error over the pixels it covers, summed over the frames written.
#[derive(Debug, Clone, Copy, Default)]
pub struct RenderError {
    /// Sum of squared errors ([0, 1] intensities) over covered pixels and channels.
    squared: f64,
    /// Covered pixels.
    covered: u64,
    /// All pixels.
    pixels: u64,
}

impl RenderError {
    /// Mean squared error over the covered pixels and channels; None where none is covered.
    pub fn mse(&self) -> Option<f64> {
        (self.covered > 0).then(|| self.squared / (3 * self.covered) as f64)
    }

    /// Share of the pixels covered.
    pub fn coverage(&self) -> f64 {
        if self.pixels == 0 { 0.0 } else { self.covered as f64 / self.pixels as f64 }
    }
}

/// One window's `nvs` outputs for a held-out view.
pub struct WindowOutputs<'a> {
    /// The source camera per window position.
    pub source_cameras: &'a [PinholeCamera],
    /// The sampled frames.
    pub sampled: &'a [RgbImage],
    /// The render of every window frame.
    pub render: &'a [RgbImage],
    /// Its holes.
    pub holes: &'a [GrayImage],
}

/// Writes `view`'s scored frames of one window into `folders`, numbered from `first`: each
/// sampled frame brought from the source camera to the held-out camera beside that camera's
/// frame (and mask), adding the render's error over the pixels it covers there to `error`.
/// Only window positions below `outputs.sampled.len()` count; returns the matches written.
pub fn write_view(
    folders: &ViewFolders,
    first: usize,
    view: &HeldOutView,
    camera: &CameraView,
    outputs: &WindowOutputs,
    error: &mut RenderError,
) -> Result<Vec<(usize, usize)>> {
    let matches: Vec<(usize, usize)> =
        view.matches.iter().copied().filter(|&(k, _)| k < outputs.sampled.len() && k < outputs.render.len()).collect();
    for (n, &(k, j)) in matches.iter().enumerate() {
        let (from, to) = (&outputs.source_cameras[k], &camera.sequence.cameras[j]);
        let pred = to_camera_rgb(&outputs.sampled[k], from, to);
        let rendered = to_camera_rgb(&outputs.render[k], from, to);
        let covered = to_camera_coverage(&outputs.holes[k], from, to);
        let target = &camera.sequence.frames[j];
        let name = format!("{:05}.png", first + n);
        save(&pred, &folders.pred.join(&name))?;
        save(target, &folders.target.join(&name))?;
        if let (Some(masks), Some(dir)) = (&camera.covisible, &folders.mask) {
            save(&masks[j], &dir.join(&name))?;
        }
        for ((r, t), c) in rendered.pixels().zip(target.pixels()).zip(covered.pixels()) {
            error.pixels += 1;
            if c.0[0] != 0 {
                error.covered += 1;
                for ch in 0..3 {
                    let d = (f64::from(r.0[ch]) - f64::from(t.0[ch])) / 255.0;
                    error.squared += d * d;
                }
            }
        }
    }
    Ok(matches)
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

    /// Windows start at the first frame not yet scored, back to back; the last is shifted back to
    /// end at the last evaluated frame, overlapping its predecessor, and scores only what that
    /// one did not; gaps of unevaluated frames are skipped; a short video is one clipped window.
    #[test]
    fn windows_cover_every_evaluated_frame_once() {
        let plan = |evaluated: &[usize], frames, len| {
            plan_windows(evaluated, frames, len).into_iter().map(|w| (w.start, w.end, w.scored)).collect::<Vec<_>>()
        };
        let all: Vec<usize> = [0].into_iter().chain(2..12).collect();
        assert_eq!(plan(&all, 5, 12), [(0, 5, vec![0, 2, 3, 4]), (5, 10, vec![5, 6, 7, 8, 9]), (7, 12, vec![10, 11])]);
        assert_eq!(plan(&[2, 3, 7, 11], 5, 20), [(2, 7, vec![2, 3]), (7, 12, vec![7, 11])]);
        assert_eq!(plan(&[1, 30, 31], 5, 40), [(1, 6, vec![1]), (27, 32, vec![30, 31])]);
        assert_eq!(plan(&[3, 4], 5, 20), [(0, 5, vec![3, 4])], "one window ends at the last evaluated frame");
        assert_eq!(plan(&[1, 2], 5, 3), [(0, 3, vec![1, 2])]);
        assert!(plan(&[], 5, 3).is_empty());
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
