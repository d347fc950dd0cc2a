//! Finding the videos of a dataset tree: SA-V, TAO, YouTube-VOS, DAVIS 2017, and a
//! plain tree of sequence folders, each with where its frames, dynamic-object annotations and
//! reconstruction are. Listing is deterministic (sorted by key) and reads no pixels.
//!
//! Input keys must be unique within a build ([`crawl_all`]): two sources listing the same key is
//! an error at start naming both, not a guess. Silently qualifying every key by its source's
//! position would make keys (and so resume, worker partition and seeds) depend on the order of
//! `[[sources]]`, and would quietly double the corpus when the same tree is listed twice (the
//! usual cause); a source that really holds other videos under the same ids gets an explicit
//! `id_prefix` instead.
//!
//! A malformed file that lists or annotates many videos at once (a TAO split's JSON, a DAVIS
//! split list) does not stop the crawl: every video that depends on it is listed with the
//! reason in [`VideoEntry::crawl_error`], so the build records them as failed and builds the
//! rest, and retries them once the file changes (it is part of their content hash).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::annotations::TrackBox;
use foundation::paths::FolderIdentity;

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
    /// A tree of synchronised multi-camera scene folders ([`crate::io::multiview`]): each scene
    /// is one input, giving monocular and multi-view pairs.
    Multiview,
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
            Self::Multiview => "multiview",
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
    /// `{video_id}` (the dataset's own id, without `id_prefix`) and `{name}` (the last component
    /// of the video id), naming a sequence folder (cog-nvs or generic layout) or a MegaSAM
    /// `.npz`; any other `{...}` is rejected when the config loads. Unset: no reconstructions
    /// (every video is reported as skipped) except for `sequences`, whose folders hold their own.
    #[serde(default)]
    pub reconstructions: Option<String>,
    /// TAO: the annotation JSON (default `{root}/annotations/{split}.json`).
    #[serde(default)]
    pub annotations: Option<PathBuf>,
    /// Split: TAO `train`/`validation`/`test` (default `train`); DAVIS an `ImageSets/2017/{split}.txt`
    /// list (default: every sequence).
    #[serde(default)]
    pub split: Option<String>,
    /// Prepended to this source's video ids (`{id_prefix}/{video_id}`, so keys read
    /// `{dataset}/{id_prefix}/{video_id}`): set it when two sources hold different videos under
    /// the same ids, which is otherwise an error at start (see the module docs).
    #[serde(default)]
    pub id_prefix: Option<String>,
}

/// The placeholders a reconstruction template may use (see [`SourceConfig::reconstructions`]).
pub const RECONSTRUCTION_PLACEHOLDERS: [&str; 4] = ["root", "dataset", "video_id", "name"];

/// Checks the string fields of a source that would otherwise fail silently at crawl time (the
/// reconstruction template, the id prefix), naming the offending key.
pub fn check_source_strings(source: &SourceConfig) -> crate::config_file::Checked {
    use crate::config_file::{KeyError, check_placeholders};
    if let Some(template) = &source.reconstructions {
        check_placeholders("reconstructions", template, &RECONSTRUCTION_PLACEHOLDERS)?;
    }
    if let Some(prefix) = &source.id_prefix {
        let bad = prefix.is_empty()
            || prefix.starts_with('/')
            || prefix.ends_with('/')
            || prefix.split('/').any(|part| part.is_empty() || part == "." || part == "..");
        if bad {
            return Err(KeyError::new(
                "id_prefix",
                format!(
                    "`{prefix}` must be non-empty path components (like `mirror` or `a/b`), no empty, `.` or `..` part"
                ),
            ));
        }
    }
    Ok(())
}

impl crate::config_file::Validate for SourceConfig {
    /// Valid: a non-empty `root` and `annotations`; `split` one non-empty name (it becomes a
    /// file name); the template and prefix as [`check_source_strings`] says.
    fn validate(&self) -> crate::config_file::Checked {
        use crate::config_file::KeyError;
        if self.root.as_os_str().is_empty() {
            return Err(KeyError::new("root", "is empty; name the dataset's root folder"));
        }
        if self.annotations.as_ref().is_some_and(|a| a.as_os_str().is_empty()) {
            return Err(KeyError::new("annotations", "is empty (leave the key out for the default)"));
        }
        if let Some(split) = &self.split
            && (split.trim().is_empty() || split.contains(['/', '\\']) || split == "." || split == "..")
        {
            return Err(KeyError::new("split", format!("`{split}` must be one split name, like `train`")));
        }
        check_source_strings(self)
    }
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
    /// A synchronised multi-camera scene folder (one sub-folder per camera).
    MultiView(PathBuf),
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
    /// Id within the build: the dataset's own id (a path-like string for TAO), after the
    /// source's `id_prefix` if it has one. Keys, clip ids and seeds derive from it.
    pub video_id: String,
    /// The dataset's own id, without `id_prefix` (what path templates expand `{video_id}` to).
    pub dataset_id: String,
    /// Its frames.
    pub frames: FrameSource,
    /// Its dynamic-object annotations.
    pub masks: MaskSource,
    /// Its reconstruction, if one was found.
    pub reconstruction: Option<PathBuf>,
    /// Files listing or annotating many videos at once that this one depends on (a TAO split's
    /// JSON, a DAVIS split list): part of its content hash, so fixing them retries it.
    pub shared_files: Vec<PathBuf>,
    /// Why this video cannot be built, found while listing it (a malformed shared annotation
    /// file, naming the file and field): the build records it as failed without processing.
    pub crawl_error: Option<String>,
}

impl VideoEntry {
    /// An entry with no shared files and no crawl error.
    fn new(
        dataset: DatasetKind,
        id: String,
        frames: FrameSource,
        masks: MaskSource,
        reconstruction: Option<PathBuf>,
    ) -> Self {
        Self {
            dataset,
            dataset_id: id.clone(),
            video_id: id,
            frames,
            masks,
            reconstruction,
            shared_files: Vec::new(),
            crawl_error: None,
        }
    }

    /// Where its frames are (a video file or a folder), for messages.
    pub fn frames_path(&self) -> &Path {
        match &self.frames {
            FrameSource::Video(path) | FrameSource::Sequence(path) | FrameSource::MultiView(path) => path,
            FrameSource::Images(paths) => paths.first().and_then(|p| p.parent()).unwrap_or(Path::new("")),
        }
    }

    /// Stable key of the input across runs and machines: `{dataset}/{video_id}`.
    pub fn key(&self) -> String {
        format!("{}/{}", self.dataset.name(), self.video_id)
    }
}

/// The entries of folder `path`, sorted by name.
pub(crate) fn sorted_dir(path: &Path) -> Result<Vec<PathBuf>> {
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
    check_source_strings(source).map_err(|e| Error::invalid(&source.root, e.key, e.reason))?;
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
        DatasetKind::Davis => crawl_davis(source)?,
        DatasetKind::Sequences => crawl_sequences(source)?,
        DatasetKind::Multiview => crawl_multiview(source)?,
    };
    if let Some(prefix) = &source.id_prefix {
        for entry in &mut entries {
            entry.video_id = format!("{prefix}/{}", entry.dataset_id);
        }
    }
    entries.sort_by_key(VideoEntry::key);
    Ok(entries)
}

/// Lists the videos of every source, in source order, checking that keys are unique within the
/// build: a key listed twice (by two sources, or twice by one) is an error naming both places.
pub fn crawl_all(sources: &[SourceConfig]) -> Result<Vec<VideoEntry>> {
    let mut seen: BTreeMap<String, (usize, PathBuf)> = BTreeMap::new();
    let mut all = Vec::new();
    for (index, source) in sources.iter().enumerate() {
        for entry in crawl(source)? {
            let key = entry.key();
            if let Some((first, first_path)) = seen.get(&key) {
                let which =
                    if *first == index { "twice by this source".to_owned() } else { format!("by sources[{first}]") };
                return Err(Error::invalid(
                    entry.frames_path(),
                    format!("sources[{index}]"),
                    format!(
                        "input key `{key}` is also listed {which} (root {}, at {}); keys must be unique \
                         within a build: remove the duplicate tree, or set `id_prefix` on one of the sources",
                        sources[*first].root.display(),
                        first_path.display()
                    ),
                ));
            }
            seen.insert(key, (index, entry.frames_path().to_owned()));
            all.push(entry);
        }
    }
    Ok(all)
}

/// DAVIS 2017: every sequence, or those of the split's `ImageSets/2017/{split}.txt`. An
/// unreadable list fails every sequence (each depends on it to know whether it is included).
fn crawl_davis(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    let images = source.root.join("JPEGImages/480p");
    let annotations = source.root.join("Annotations/480p");
    let Some(split) = &source.split else {
        return crawl_palette_dataset(source, &images, &annotations, None);
    };
    let path = source.root.join("ImageSets/2017").join(format!("{split}.txt"));
    let (list, error) = match std::fs::read_to_string(&path) {
        Ok(text) => (Some(text.lines().map(str::trim).filter(|l| !l.is_empty()).map(str::to_owned).collect()), None),
        Err(e) => (None, Some(Error::io(&path, e))),
    };
    depend_on_shared_file(crawl_palette_dataset(source, &images, &annotations, list)?, &path, error)
}

/// Makes every entry depend on the shared file `path` (a split list or annotation JSON, so it is
/// part of their content hash) and, if reading that file failed with `error`, marks every entry
/// failed with it instead of stopping the crawl; with no entry to carry it, the error stops it.
fn depend_on_shared_file(mut entries: Vec<VideoEntry>, path: &Path, error: Option<Error>) -> Result<Vec<VideoEntry>> {
    if let Some(error) = error {
        if entries.is_empty() {
            return Err(error);
        }
        let reason = error.to_string();
        for entry in &mut entries {
            entry.crawl_error = Some(reason.clone());
        }
    }
    for entry in &mut entries {
        entry.shared_files.push(path.to_owned());
    }
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
            entries.push(VideoEntry::new(DatasetKind::Sav, id, FrameSource::Video(video), masks, reconstruction));
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
        entries.push(VideoEntry::new(source.dataset, id, FrameSource::Images(frames), masks, reconstruction));
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
    match read_tao(&path) {
        Ok((file, boxes)) => depend_on_shared_file(tao_entries(source, &file, boxes)?, &path, None),
        // Every video of the split depends on this file: fail them all, build other sources.
        Err(error) => depend_on_shared_file(tao_frame_folders(source, split)?, &path, Some(error)),
    }
}

/// Parses a TAO split JSON and groups its boxes by video id.
fn read_tao(path: &Path) -> Result<(TaoFile, BTreeMap<u64, Vec<TrackBox>>)> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let file: TaoFile =
        serde_json::from_str(&text).map_err(|e| Error::invalid(path, "videos", format!("invalid TAO JSON: {e}")))?;
    // A video's name is the path of its frame folder under `frames/`.
    for (index, video) in file.videos.iter().enumerate() {
        foundation::paths::check_name(&video.name)
            .map_err(|reason| Error::invalid(path, format!("videos[{index}].name"), reason))?;
    }
    let images: BTreeMap<u64, &TaoImage> = file.images.iter().map(|i| (i.id, i)).collect();
    let mut boxes: BTreeMap<u64, Vec<TrackBox>> = BTreeMap::new();
    for (index, annotation) in file.annotations.iter().enumerate() {
        let image = images.get(&annotation.image_id).ok_or_else(|| {
            Error::invalid(
                path,
                format!("annotations[{index}].image_id"),
                format!("image {} is not listed", annotation.image_id),
            )
        })?;
        let frame = tao_frame_index(&image.file_name).ok_or_else(|| {
            Error::invalid(path, "images.file_name", format!("`{}` is not frameNNNN.jpg", image.file_name))
        })?;
        boxes.entry(image.video_id).or_default().push(TrackBox {
            frame,
            track: annotation.track_id,
            bbox: annotation.bbox,
        });
    }
    Ok((file, boxes))
}

fn tao_entries(
    source: &SourceConfig,
    file: &TaoFile,
    mut boxes: BTreeMap<u64, Vec<TrackBox>>,
) -> Result<Vec<VideoEntry>> {
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
        entries.push(VideoEntry::new(
            DatasetKind::Tao,
            video.name.clone(),
            FrameSource::Images(frames),
            masks,
            reconstruction,
        ));
    }
    Ok(entries)
}

/// The videos of a TAO split as its frame folders show them (`frames/{split}/{source}/{video}`),
/// for when its JSON cannot say.
fn tao_frame_folders(source: &SourceConfig, split: &str) -> Result<Vec<VideoEntry>> {
    let frames_root = source.root.join("frames");
    let split_dir = frames_root.join(split);
    let mut entries = Vec::new();
    if !split_dir.is_dir() {
        return Ok(entries);
    }
    for group in sorted_dir(&split_dir)?.into_iter().filter(|p| p.is_dir()) {
        for folder in sorted_dir(&group)?.into_iter().filter(|p| p.is_dir()) {
            let id = folder.strip_prefix(&frames_root).unwrap_or(&folder).to_string_lossy().into_owned();
            let reconstruction = locate_reconstruction(source, &id);
            let frames = FrameSource::Images(images_in(&folder)?);
            entries.push(VideoEntry::new(DatasetKind::Tao, id, frames, MaskSource::None, reconstruction));
        }
    }
    Ok(entries)
}

/// Whether `dir` looks like a sequence folder in the cog-nvs, MegaSAM or generic layout, or a
/// reconstruction tool's output ([`crate::io::layout`]), also where its files are incomplete
/// (`frames/` and `depth/` without `.exr` files or `cameras.json`): it is then one failed input
/// whose reader names what is missing.
pub fn is_sequence_folder(dir: &Path) -> bool {
    crate::io::layout::has_layout_files(dir)
        || crate::io::layout::cog_nvs::recognised(dir)
        || (dir.join("frames").is_dir() && dir.join("depth").is_dir())
        || crate::io::layout::megasam::archive(dir).is_ok_and(|archive| archive.is_some())
}

/// Whether `dir` is a multi-camera scene folder: not a sequence folder itself, and at least one of
/// its sub-folders is. One camera is enough to list it: a scene whose other cameras are broken is
/// then one failed input (the reader names the broken camera), not a single-camera sequence.
/// A folder in a benchmark dataset's layout (DyCheck, Kubric-4D, ParallelDomain-4D) is one too.
pub fn is_multiview_folder(dir: &Path) -> bool {
    use crate::io::layout::{MultiViewLayoutName, detect_multiview_layout};
    if detect_multiview_layout(dir).is_ok_and(|layout| layout != MultiViewLayoutName::Generic) {
        return true;
    }
    !is_sequence_folder(dir)
        && std::fs::read_dir(dir)
            .map(|entries| entries.filter_map(|e| e.ok()).any(|e| e.path().is_dir() && is_sequence_folder(&e.path())))
            .unwrap_or(false)
}

/// A tree of multi-camera scenes: every folder that [`is_multiview_folder`] is one scene (its id
/// the path below the root), found at any depth.
fn crawl_multiview(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    let mut entries = Vec::new();
    let mut tree = FolderWalk::new(&source.root);
    while let Some(dir) = tree.next() {
        if is_multiview_folder(&dir) {
            let id = dir.strip_prefix(&source.root).unwrap_or(&dir).to_string_lossy().into_owned();
            let id = if id.is_empty() { file_name(&dir) } else { id };
            let reconstruction = Some(dir.clone());
            entries.push(VideoEntry::new(
                DatasetKind::Multiview,
                id,
                FrameSource::MultiView(dir),
                MaskSource::None,
                reconstruction,
            ));
        } else if !is_sequence_folder(&dir) {
            tree.descend(&dir)?;
        }
    }
    Ok(entries)
}

/// A depth-first walk over the folders of a tree that visits each real folder once: a folder is
/// known by its [`FolderIdentity`] (links resolved), so a link back up the tree (`loop -> .`)
/// or a second name for a folder is skipped, never walked again (which would list one scene
/// once per spelling, and loop until the OS refuses the path).
struct FolderWalk {
    pending: Vec<PathBuf>,
    visited: std::collections::BTreeSet<FolderIdentity>,
}

impl FolderWalk {
    fn new(root: &Path) -> Self {
        Self { pending: vec![root.to_owned()], visited: Default::default() }
    }

    /// The next folder not visited under another name.
    fn next(&mut self) -> Option<PathBuf> {
        while let Some(dir) = self.pending.pop() {
            if self.visited.insert(FolderIdentity::of(&dir)) {
                return Some(dir);
            }
        }
        None
    }

    /// Queues the sub-folders of `dir`: real folders in sorted order, then links, so that a
    /// folder reachable under its own name and through a sibling link keeps its own name.
    fn descend(&mut self, dir: &Path) -> Result<()> {
        let (links, real): (Vec<PathBuf>, Vec<PathBuf>) =
            sorted_dir(dir)?.into_iter().filter(|p| p.is_dir()).partition(|p| p.is_symlink());
        // Reversed so that popping from the end walks them in that order.
        self.pending.extend(real.into_iter().chain(links).rev());
        Ok(())
    }
}

fn crawl_sequences(source: &SourceConfig) -> Result<Vec<VideoEntry>> {
    let mut entries = Vec::new();
    let mut tree = FolderWalk::new(&source.root);
    while let Some(dir) = tree.next() {
        if is_sequence_folder(&dir) {
            let id = dir.strip_prefix(&source.root).unwrap_or(&dir).to_string_lossy().into_owned();
            let id = if id.is_empty() { file_name(&dir) } else { id };
            let masks =
                if dir.join("masks").is_dir() { MaskSource::IdPngs(dir.join("masks")) } else { MaskSource::None };
            let reconstruction = locate_reconstruction(source, &id).or_else(|| Some(dir.clone()));
            entries.push(VideoEntry::new(
                DatasetKind::Sequences,
                id,
                FrameSource::Sequence(dir),
                masks,
                reconstruction,
            ));
        } else {
            tree.descend(&dir)?;
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
            id_prefix: None,
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
            id_prefix: None,
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
            id_prefix: None,
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
            id_prefix: None,
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
            id_prefix: None,
        };
        let keys: Vec<String> = crawl(&source).unwrap().iter().map(VideoEntry::key).collect();
        assert_eq!(keys, ["sequences/a", "sequences/group/b", "sequences/group/c"]);
    }

    #[test]
    fn multiview_tree_lists_each_scene_folder_once() {
        let dir = tempfile::tempdir().unwrap();
        touch(&dir.path().join("s1/cam0/gt_rgb.mp4"));
        touch(&dir.path().join("s1/cam1/gt_rgb.mp4"));
        // A scene with one readable camera is still one scene (its reader names the broken one).
        touch(&dir.path().join("group/s2/cam0/frames/00000.png"));
        touch(&dir.path().join("group/s2/cam0/depth/00000.exr"));
        touch(&dir.path().join("group/s2/cam1/readme.txt"));
        touch(&dir.path().join("notes/readme.txt"));
        let source = SourceConfig {
            dataset: DatasetKind::Multiview,
            root: dir.path().to_owned(),
            reconstructions: None,
            annotations: None,
            split: None,
            id_prefix: None,
        };
        let entries = crawl(&source).unwrap();
        let keys: Vec<String> = entries.iter().map(VideoEntry::key).collect();
        assert_eq!(keys, ["multiview/group/s2", "multiview/s1"]);
        assert_eq!(entries[1].frames, FrameSource::MultiView(dir.path().join("s1")));
    }

    #[test]
    fn missing_root_is_an_error_naming_it() {
        let source = SourceConfig {
            dataset: DatasetKind::Sav,
            root: "/no/such/root".into(),
            reconstructions: None,
            annotations: None,
            split: None,
            id_prefix: None,
        };
        assert!(crawl(&source).unwrap_err().to_string().contains("/no/such/root"));
    }
}
