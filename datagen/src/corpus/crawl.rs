//! Finding the videos of a dataset tree (DESIGN §3): SA-V, TAO, YouTube-VOS, DAVIS 2017, and a
//! plain tree of sequence folders, each with where its frames, dynamic-object annotations and
//! reconstruction are. Listing is deterministic (sorted by key) and reads no pixels.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::annotations::TrackBox;
use crate::error::{Error, Result};

/// The dataset layouts the crawler knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DatasetKind {
    /// SA-V: `sav_XXX/{id}.mp4` + `{id}_manual.json` / `{id}_auto.json` (RLE masklets, every 4th frame).
    Sav,
    /// TAO: `frames/{split}/{source}/{video}/frame%04d.jpg` (from 1) + COCO-style JSON with boxes.
    Tao,
    /// YouTube-VOS: `JPEGImages/{vid}/{5 digits}.jpg` + palette PNGs in `Annotations/{vid}/`.
    Ytvos,
    /// DAVIS 2017: `JPEGImages/480p/{seq}/%05d.jpg` + `Annotations/480p/{seq}/%05d.png`.
    Davis,
    /// A tree of sequence folders in the cog-nvs, MegaSAM or generic layout.
    Sequences,
}

impl DatasetKind {
    /// The name used in ids and shard columns.
    pub fn name(self) -> &'static str {
        match self {
            Self::Sav => "sav",
            Self::Tao => "tao",
            Self::Ytvos => "ytvos",
            Self::Davis => "davis",
            Self::Sequences => "sequences",
        }
    }
}

/// One dataset tree to crawl.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceConfig {
    /// Layout of the tree.
    pub dataset: DatasetKind,
    /// Root folder of the tree.
    pub root: PathBuf,
    /// Where each video's reconstruction is: a path template with `{root}`, `{dataset}`,
    /// `{video_id}` and `{name}` (the last component of the video id), naming a sequence folder
    /// (cog-nvs or generic layout) or a MegaSAM `.npz`. Unset: no reconstructions (every video
    /// is reported as skipped) except for `sequences`, whose folders hold their own.
    #[serde(default)]
    pub reconstructions: Option<String>,
    /// TAO: the annotation JSON (default `{root}/annotations/{split}.json`).
    #[serde(default)]
    pub annotations: Option<PathBuf>,
    /// Split: TAO `train`/`validation`/`test` (default `train`); DAVIS an `ImageSets/2017/{split}.txt`
    /// list (default: every sequence).
    #[serde(default)]
    pub split: Option<String>,
}

/// Where a video's frames are.
#[derive(Debug, Clone, PartialEq)]
pub enum FrameSource {
    /// A video file, decoded with FFmpeg.
    Video(PathBuf),
    /// Image files in frame order.
    Images(Vec<PathBuf>),
    /// A sequence folder that holds its own frames and reconstruction.
    Sequence(PathBuf),
}

/// Where a video's dynamic-object annotations are.
#[derive(Debug, Clone, PartialEq)]
pub enum MaskSource {
    /// None.
    None,
    /// An SA-V annotation JSON.
    Sav(PathBuf),
    /// Id PNGs (palette or greyscale), matched to frames by file stem.
    IdPngs(PathBuf),
    /// TAO boxes with the frame size they are given in.
    Boxes {
        /// The boxes of every track.
        boxes: Vec<TrackBox>,
        /// Frame width the boxes refer to.
        width: u32,
        /// Frame height the boxes refer to.
        height: u32,
    },
}

/// One video found by the crawler.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoEntry {
    /// Dataset layout it came from.
    pub dataset: DatasetKind,
    /// Id within the dataset (a path-like string for TAO).
    pub video_id: String,
    /// Its frames.
    pub frames: FrameSource,
    /// Its dynamic-object annotations.
    pub masks: MaskSource,
    /// Its reconstruction, if one was found.
    pub reconstruction: Option<PathBuf>,
}

impl VideoEntry {
    /// Stable key of the input across runs and machines: `{dataset}/{video_id}`.
    pub fn key(&self) -> String {
        format!("{}/{}", self.dataset.name(), self.video_id)
    }
}

fn sorted_dir(path: &Path) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(path).map_err(|e| Error::io(path, e))?;
    let mut paths: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    Ok(paths)
}

fn has_extension(path: &Path, extensions: &[&str]) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| extensions.iter().any(|x| e.eq_ignore_ascii_case(x)))
}

fn images_in(dir: &Path) -> Result<Vec<PathBuf>> {
    Ok(sorted_dir(dir)?.into_iter().filter(|p| has_extension(p, &["jpg", "jpeg", "png"])).collect())
}

fn file_name(path: &Path) -> String {
    path.file_name().unwrap_or_default().to_string_lossy().into_owned()
}

/// Expands the reconstruction template for one video and returns it if it exists.
fn locate_reconstruction(source: &SourceConfig, video_id: &str) -> Option<PathBuf> {
    let template = source.reconstructions.as_ref()?;
    let name = video_id.rsplit('/').next().unwrap_or(video_id);
    let path = template
        .replace("{root}", &source.root.to_string_lossy())
        .replace("{dataset}", source.dataset.name())
        .replace("{video_id}", video_id)
        .replace("{name}", name);
    let path = PathBuf::from(path);
    path.exists().then_some(path)
}

/// Lists the videos of `source`, sorted by key.
pub fn crawl(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    if !source.root.is_dir() {
        return Err(Error::io(
            &source.root,
            std::io::Error::new(std::io::ErrorKind::NotFound, "dataset root is not a folder"),
        ));
    }
    let mut entries = match source.dataset {
        DatasetKind::Sav => crawl_sav(source)?,
        DatasetKind::Tao => crawl_tao(source)?,
        DatasetKind::Ytvos => {
            crawl_palette_dataset(source, &source.root.join("JPEGImages"), &source.root.join("Annotations"), None)?
        }
        DatasetKind::Davis => {
            let list = match &source.split {
                Some(split) => {
                    let path = source.root.join("ImageSets/2017").join(format!("{split}.txt"));
                    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
                    Some(text.lines().map(str::trim).filter(|l| !l.is_empty()).map(str::to_owned).collect())
                }
                None => None,
            };
            crawl_palette_dataset(
                source,
                &source.root.join("JPEGImages/480p"),
                &source.root.join("Annotations/480p"),
                list,
            )?
        }
        DatasetKind::Sequences => crawl_sequences(source)?,
    };
    entries.sort_by_key(VideoEntry::key);
    Ok(entries)
}

fn crawl_sav(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    // Videos sit in `sav_XXX/` chunk folders, or directly in the root.
    let mut folders = vec![source.root.clone()];
    folders.extend(sorted_dir(&source.root)?.into_iter().filter(|p| p.is_dir()));
    let mut entries = Vec::new();
    for folder in folders {
        for video in sorted_dir(&folder)?.into_iter().filter(|p| has_extension(p, &["mp4"])) {
            let id = video.file_stem().unwrap_or_default().to_string_lossy().into_owned();
            let manual = folder.join(format!("{id}_manual.json"));
            let auto = folder.join(format!("{id}_auto.json"));
            let masks = if manual.is_file() {
                MaskSource::Sav(manual)
            } else if auto.is_file() {
                MaskSource::Sav(auto)
            } else {
                MaskSource::None
            };
            let reconstruction = locate_reconstruction(source, &id);
            entries.push(VideoEntry {
                dataset: DatasetKind::Sav,
                video_id: id,
                frames: FrameSource::Video(video),
                masks,
                reconstruction,
            });
        }
    }
    Ok(entries)
}

fn crawl_palette_dataset(
    source: &SourceConfig,
    images: &Path,
    annotations: &Path,
    only: Option<Vec<String>>,
) -> Result<Vec<VideoEntry>> {
    let mut entries = Vec::new();
    for folder in sorted_dir(images)?.into_iter().filter(|p| p.is_dir()) {
        let id = file_name(&folder);
        if only.as_ref().is_some_and(|list| !list.contains(&id)) {
            continue;
        }
        let frames = images_in(&folder)?;
        if frames.is_empty() {
            continue;
        }
        let mask_dir = annotations.join(&id);
        let masks = if mask_dir.is_dir() { MaskSource::IdPngs(mask_dir) } else { MaskSource::None };
        let reconstruction = locate_reconstruction(source, &id);
        entries.push(VideoEntry {
            dataset: source.dataset,
            video_id: id,
            frames: FrameSource::Images(frames),
            masks,
            reconstruction,
        });
    }
    Ok(entries)
}

#[derive(Deserialize)]
struct TaoFile {
    videos: Vec<TaoVideo>,
    images: Vec<TaoImage>,
    #[serde(default)]
    annotations: Vec<TaoAnnotation>,
}

#[derive(Deserialize)]
struct TaoVideo {
    id: u64,
    name: String,
    #[serde(default)]
    width: Option<u32>,
    #[serde(default)]
    height: Option<u32>,
}

#[derive(Deserialize)]
struct TaoImage {
    id: u64,
    video_id: u64,
    file_name: String,
    #[serde(default)]
    width: Option<u32>,
    #[serde(default)]
    height: Option<u32>,
}

#[derive(Deserialize)]
struct TaoAnnotation {
    image_id: u64,
    bbox: [f64; 4],
    #[serde(default)]
    track_id: u64,
}

/// TAO frame files are `frame%04d.jpg`, numbered from 1; returns the 0-based frame index.
fn tao_frame_index(file_name: &str) -> Option<usize> {
    let stem = Path::new(file_name).file_stem()?.to_str()?;
    stem.strip_prefix("frame")?.parse::<usize>().ok()?.checked_sub(1)
}

fn crawl_tao(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    let split = source.split.as_deref().unwrap_or("train");
    let path =
        source.annotations.clone().unwrap_or_else(|| source.root.join("annotations").join(format!("{split}.json")));
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let file: TaoFile =
        serde_json::from_str(&text).map_err(|e| Error::invalid(&path, "videos", format!("invalid TAO JSON: {e}")))?;
    let images: BTreeMap<u64, &TaoImage> = file.images.iter().map(|i| (i.id, i)).collect();
    let mut boxes: BTreeMap<u64, Vec<TrackBox>> = BTreeMap::new();
    for annotation in &file.annotations {
        let image = images.get(&annotation.image_id).ok_or_else(|| {
            Error::invalid(&path, "annotations.image_id", format!("image {} is not listed", annotation.image_id))
        })?;
        let frame = tao_frame_index(&image.file_name).ok_or_else(|| {
            Error::invalid(&path, "images.file_name", format!("`{}` is not frameNNNN.jpg", image.file_name))
        })?;
        boxes.entry(image.video_id).or_default().push(TrackBox {
            frame,
            track: annotation.track_id,
            bbox: annotation.bbox,
        });
    }
    let mut entries = Vec::new();
    for video in &file.videos {
        let folder = source.root.join("frames").join(&video.name);
        if !folder.is_dir() {
            continue;
        }
        let frames = images_in(&folder)?;
        let size = file.images.iter().find(|i| i.video_id == video.id).and_then(|i| Some((i.width?, i.height?)));
        let (width, height) = match (video.width.zip(video.height), size) {
            (Some(size), _) | (None, Some(size)) => size,
            (None, None) => (0, 0),
        };
        let masks = match boxes.remove(&video.id) {
            Some(boxes) if width > 0 && height > 0 => MaskSource::Boxes { boxes, width, height },
            _ => MaskSource::None,
        };
        let reconstruction = locate_reconstruction(source, &video.name);
        entries.push(VideoEntry {
            dataset: DatasetKind::Tao,
            video_id: video.name.clone(),
            frames: FrameSource::Images(frames),
            masks,
            reconstruction,
        });
    }
    Ok(entries)
}

/// Whether `dir` looks like a sequence folder (DESIGN §3: cog-nvs, MegaSAM or generic layout).
pub fn is_sequence_folder(dir: &Path) -> bool {
    dir.join("gt_rgb.mp4").is_file()
        || dir.join("cam_info").is_dir()
        || (dir.join("frames").is_dir() && dir.join("depth").is_dir())
        || std::fs::read_dir(dir)
            .map(|entries| entries.filter_map(|e| e.ok()).any(|e| file_name(&e.path()).ends_with("_sgd_cvd_hr.npz")))
            .unwrap_or(false)
}

fn crawl_sequences(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    let mut entries = Vec::new();
    let mut pending = vec![source.root.clone()];
    while let Some(dir) = pending.pop() {
        if is_sequence_folder(&dir) {
            let id = dir.strip_prefix(&source.root).unwrap_or(&dir).to_string_lossy().into_owned();
            let id = if id.is_empty() { file_name(&dir) } else { id };
            let masks =
                if dir.join("masks").is_dir() { MaskSource::IdPngs(dir.join("masks")) } else { MaskSource::None };
            let reconstruction = locate_reconstruction(source, &id).or_else(|| Some(dir.clone()));
            entries.push(VideoEntry {
                dataset: DatasetKind::Sequences,
                video_id: id,
                frames: FrameSource::Sequence(dir),
                masks,
                reconstruction,
            });
        } else {
            pending.extend(sorted_dir(&dir)?.into_iter().filter(|p| p.is_dir()));
        }
    }
    Ok(entries)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn touch(path: &Path) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, b"x").unwrap();
    }

    #[test]
    fn sav_tree_with_manual_auto_and_missing_annotations() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("sav_train");
        touch(&root.join("sav_000/sav_000001.mp4"));
        touch(&root.join("sav_000/sav_000001_manual.json"));
        touch(&root.join("sav_000/sav_000001_auto.json"));
        touch(&root.join("sav_001/sav_000002.mp4"));
        touch(&root.join("sav_001/sav_000002_auto.json"));
        touch(&root.join("sav_001/sav_000003.mp4"));
        std::fs::create_dir_all(dir.path().join("recon/sav_000002")).unwrap();
        let source = SourceConfig {
            dataset: DatasetKind::Sav,
            root: root.clone(),
            reconstructions: Some(format!("{}/recon/{{video_id}}", dir.path().display())),
            annotations: None,
            split: None,
        };
        let entries = crawl(&source).unwrap();
        let keys: Vec<String> = entries.iter().map(VideoEntry::key).collect();
        assert_eq!(keys, ["sav/sav_000001", "sav/sav_000002", "sav/sav_000003"]);
        assert_eq!(entries[0].masks, MaskSource::Sav(root.join("sav_000/sav_000001_manual.json")), "manual preferred");
        assert_eq!(entries[1].masks, MaskSource::Sav(root.join("sav_001/sav_000002_auto.json")));
        assert_eq!(entries[2].masks, MaskSource::None);
        assert_eq!(entries[0].reconstruction, None);
        assert_eq!(entries[1].reconstruction, Some(dir.path().join("recon/sav_000002")));
    }

    #[test]
    fn davis_split_list_and_ytvos_annotations() {
        let dir = tempfile::tempdir().unwrap();
        for seq in ["bear", "camel", "dog"] {
            touch(&dir.path().join(format!("davis/JPEGImages/480p/{seq}/00000.jpg")));
            touch(&dir.path().join(format!("davis/JPEGImages/480p/{seq}/00001.jpg")));
            touch(&dir.path().join(format!("davis/Annotations/480p/{seq}/00000.png")));
        }
        std::fs::create_dir_all(dir.path().join("davis/ImageSets/2017")).unwrap();
        std::fs::write(dir.path().join("davis/ImageSets/2017/val.txt"), "dog\nbear\n").unwrap();
        let davis = SourceConfig {
            dataset: DatasetKind::Davis,
            root: dir.path().join("davis"),
            reconstructions: None,
            annotations: None,
            split: Some("val".into()),
        };
        let entries = crawl(&davis).unwrap();
        assert_eq!(entries.iter().map(VideoEntry::key).collect::<Vec<_>>(), ["davis/bear", "davis/dog"]);
        assert!(matches!(&entries[0].frames, FrameSource::Images(f) if f.len() == 2));

        touch(&dir.path().join("yt/JPEGImages/0a1b/00000.jpg"));
        touch(&dir.path().join("yt/JPEGImages/0a1b/00005.jpg"));
        let ytvos = SourceConfig {
            dataset: DatasetKind::Ytvos,
            root: dir.path().join("yt"),
            reconstructions: None,
            annotations: None,
            split: None,
        };
        let entries = crawl(&ytvos).unwrap();
        assert_eq!(entries[0].masks, MaskSource::None);
    }

    #[test]
    fn tao_boxes_per_video_from_one_json() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        touch(&root.join("frames/train/ArgoVerse/vid1/frame0001.jpg"));
        touch(&root.join("frames/train/ArgoVerse/vid1/frame0031.jpg"));
        let json = serde_json::json!({
            "videos": [{"id": 1, "name": "train/ArgoVerse/vid1", "width": 64, "height": 48}, {"id": 2, "name": "train/x/missing"}],
            "images": [{"id": 10, "video_id": 1, "file_name": "train/ArgoVerse/vid1/frame0031.jpg", "width": 64, "height": 48}],
            "annotations": [{"image_id": 10, "bbox": [1.0, 2.0, 3.0, 4.0], "track_id": 5, "category_id": 1}]
        });
        touch(&root.join("annotations/train.json"));
        std::fs::write(root.join("annotations/train.json"), json.to_string()).unwrap();
        let source = SourceConfig {
            dataset: DatasetKind::Tao,
            root: root.to_owned(),
            reconstructions: None,
            annotations: None,
            split: None,
        };
        let entries = crawl(&source).unwrap();
        assert_eq!(entries.len(), 1, "videos without frames on disk are not listed");
        let MaskSource::Boxes { boxes, width, height } = &entries[0].masks else { panic!("boxes expected") };
        assert_eq!((boxes[0].frame, boxes[0].track, *width, *height), (30, 5, 64, 48));
    }

    #[test]
    fn sequence_tree_finds_nested_folders() {
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("a/gt_rgb.mp4"));
        touch(&dir.path().join("group/b/scene_sgd_cvd_hr.npz"));
        touch(&dir.path().join("group/c/frames/00000.png"));
        touch(&dir.path().join("group/c/depth/00000.exr"));
        touch(&dir.path().join("group/not_a_sequence/readme.txt"));
        let source = SourceConfig {
            dataset: DatasetKind::Sequences,
            root: dir.path().to_owned(),
            reconstructions: None,
            annotations: None,
            split: None,
        };
        let keys: Vec<String> = crawl(&source).unwrap().iter().map(VideoEntry::key).collect();
        assert_eq!(keys, ["sequences/a", "sequences/group/b", "sequences/group/c"]);
    }

    #[test]
    fn missing_root_is_an_error_naming_it() {
        let source = SourceConfig {
            dataset: DatasetKind::Sav,
            root: "/no/such/root".into(),
            reconstructions: None,
            annotations: None,
            split: None,
        };
        assert!(crawl(&source).unwrap_err().to_string().contains("/no/such/root"));
    }
}
