//! ViPE's output folder (nv-tlabs/vipe, `vipe/utils/io.py`: `ArtifactPath` and the
//! `save_*_artifacts` functions), for one video `NAME`:
//!
//! - `rgb/NAME.mp4`: the frames;
//! - `pose/NAME.npz`: `data` (N, 4, 4) **world_from_camera** ("OpenCV cam2world", ViPE's own
//!   comment), `inds` (N,) the frame of each pose;
//! - `intrinsics/NAME.npz`: `data` (N, 4) `[fx, fy, cx, cy]` in pixels of the frames, `inds`;
//!   `intrinsics/NAME_camera.txt` (optional): `FRAME: TYPE` per line; only `PINHOLE` is read, the
//!   other models ViPE estimates (wide-angle `MEI`, `PANORAMA`) are refused by name;
//! - `depth/NAME.zip`: one OpenEXR per frame, `FFFFF.exr`, channel `Z` (half float): metric
//!   z-depth in metres.
//!
//! A folder with several videos is read one video at a time, named by its `pose/NAME.npz` or
//! `rgb/NAME.mp4` ([`vipe_artifact_of_file`]). Every frame must have its pose, intrinsics and depth (`inds` = 0, 1, ..., N − 1): a frame
//! ViPE skipped is an error, never given an invented pose. Not read: `mask/NAME.zip` (instance
//! masks), `flow/`, `vipe/NAME_info.pkl` (a pickle), the visualisations.

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::npy::{Axis, MAX_SIDE_PX, NpzReader, read_zip_member};
use crate::io::tool_output::{ToolOutput, check_depth_sign, check_frame_indices, with_video};
use foundation::camera::{checked_intrinsics, checked_pose, mat4_to_row_major};

/// Room for an EXR file's header and attributes beyond its samples and line offsets.
const EXR_HEADER_BYTES: usize = 1 << 20;

/// Largest EXR file of one channel of `width × height` 32-bit samples: the samples stored
/// uncompressed (OpenEXR stores a block raw when compressing would enlarge it), an 8-byte offset
/// per scan line, and [`EXR_HEADER_BYTES`]. ViPE's maps have one channel, `Z`.
fn exr_member_bound(width: usize, height: usize) -> u64 {
    (width * height * 4 + height * 8 + EXR_HEADER_BYTES) as u64
}

/// The camera model name ViPE writes for a pinhole camera (`CameraType.PINHOLE.name`).
const PINHOLE: &str = "PINHOLE";

/// The files of one ViPE artifact.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct VipeArtifact {
    /// ViPE's output root.
    pub root: PathBuf,
    /// The artifact (video) name.
    pub name: String,
}

impl VipeArtifact {
    fn file(&self, folder: &str, suffix: &str) -> PathBuf {
        self.root.join(folder).join(format!("{}{suffix}", self.name))
    }
}

/// The artifacts under ViPE's output root `root` (one per `pose/*.npz`), sorted by name.
pub fn vipe_artifacts(root: &Path) -> Result<Vec<VipeArtifact>> {
    let pose_dir = root.join("pose");
    let entries = std::fs::read_dir(&pose_dir).map_err(|e| Error::io(&pose_dir, e))?;
    let mut names: Vec<String> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(".npz")).map(str::to_owned))
        .collect();
    names.sort();
    Ok(names.into_iter().map(|name| VipeArtifact { root: root.to_owned(), name }).collect())
}

/// The artifact a file of ViPE's output names (`ROOT/pose/NAME.npz` or `ROOT/rgb/NAME.mp4`): how
/// one video of an output folder holding several is chosen.
pub fn vipe_artifact_of_file(path: &Path) -> Option<VipeArtifact> {
    let folder = path.parent()?;
    let kind = folder.file_name()?.to_str()?;
    let extension = path.extension()?.to_str()?;
    if !matches!((kind, extension), ("pose", "npz") | ("rgb", "mp4")) {
        return None;
    }
    let root = folder.parent()?;
    let name = path.file_stem()?.to_str()?.to_owned();
    (root.join("pose").is_dir() && root.join("intrinsics").is_dir())
        .then(|| VipeArtifact { root: root.to_owned(), name })
}

/// Reads the artifact, decoding `rgb/NAME.mp4`.
pub fn read_vipe(artifact: &VipeArtifact) -> Result<ToolOutput> {
    with_video(artifact.file("rgb", ".mp4"), || read_vipe_reconstruction(artifact))
}

/// The artifact's reconstruction (no frames).
pub fn read_vipe_reconstruction(artifact: &VipeArtifact) -> Result<ToolOutput> {
    let pose_path = artifact.file("pose", ".npz");
    let mut poses = NpzReader::open(&pose_path)?;
    let header = poses.header("data", Some(&[Axis::Any, Axis::Is(4), Axis::Is(4)]))?;
    let frames = header.shape[0];
    if frames == 0 {
        return Err(Error::array(&pose_path, Some("data.npy"), "no poses"));
    }
    let n = Axis::Is(frames);
    let inds = poses.read_f64("inds", &[n])?;
    check_frame_indices(&pose_path, "inds", &inds.data)?;
    let pose_data = poses.read_f64("data", &[n, Axis::Is(4), Axis::Is(4)])?;
    // Checked here, at the door, so that errors use ViPE's own names (`data[3]` of pose/NAME.npz).
    let world_from_camera = pose_data
        .data
        .chunks_exact(16)
        .enumerate()
        .map(|(i, m)| Ok(mat4_to_row_major(&checked_pose(&pose_path, &format!("data[{i}]"), m)?)))
        .collect::<Result<Vec<_>>>()?;

    let intrinsics_path = artifact.file("intrinsics", ".npz");
    check_camera_types(&artifact.file("intrinsics", "_camera.txt"))?;
    let mut archive = NpzReader::open(&intrinsics_path)?;
    let header = archive.header("data", Some(&[n, Axis::Any]))?;
    if header.shape[1] != 4 {
        return Err(Error::array(
            &intrinsics_path,
            Some("data.npy"),
            format!(
                "{} values per frame: a pinhole camera has 4 ([fx, fy, cx, cy]); other camera models are not read",
                header.shape[1]
            ),
        ));
    }
    let inds = archive.read_f64("inds", &[n])?;
    check_frame_indices(&intrinsics_path, "inds", &inds.data)?;
    let values = archive.read_f64("data", &[n, Axis::Is(4)])?;
    let intrinsics = values
        .data
        .chunks_exact(4)
        .enumerate()
        .map(|(i, k)| {
            let row_major = [k[0], 0.0, k[2], 0.0, k[1], k[3], 0.0, 0.0, 1.0];
            checked_intrinsics(&intrinsics_path, &format!("data[{i}]"), &row_major)?;
            Ok(row_major)
        })
        .collect::<Result<Vec<_>>>()?;

    let depth_path = artifact.file("depth", ".zip");
    let (depth_size, depth) = read_depth_zip(&depth_path, frames)?;
    let (width, height) = depth_size;
    Ok(ToolOutput {
        frames: None,
        depth_path,
        depth_size,
        depth,
        intrinsics_path,
        // ViPE estimates K on the frames it writes to rgb/, which are the depth's size.
        intrinsics_size: (width as u32, height as u32),
        intrinsics,
        poses_path: pose_path,
        world_from_camera,
    })
}

/// Refuses any camera model other than a pinhole in `NAME_camera.txt` (absent: pinhole, as ViPE
/// assumes when reading).
fn check_camera_types(path: &Path) -> Result<()> {
    if !path.is_file() {
        return Ok(());
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    for (line_number, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let kind = line.split_once(':').map(|(_, kind)| kind.trim());
        if kind != Some(PINHOLE) {
            return Err(Error::invalid(
                path,
                format!("line {}", line_number + 1),
                format!(
                    "camera model {:?}: only {PINHOLE} is read (run ViPE with a pinhole camera, or undistort first)",
                    kind.unwrap_or(line)
                ),
            ));
        }
    }
    Ok(())
}

/// A depth map's width and height.
type MapSize = (usize, usize);

/// The per-frame EXR maps of a ViPE depth zip, in frame order: members must be `00000.exr`,
/// `00001.exr`, ... (one per frame, none missing) and all of one size.
fn read_depth_zip(path: &Path, frames: usize) -> Result<(MapSize, Vec<Vec<f32>>)> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut archive = zip::ZipArchive::new(std::io::BufReader::new(file))
        .map_err(|e| Error::invalid(path, "zip", format!("not a readable zip archive: {e}")))?;
    let mut names: Vec<String> = archive.file_names().filter(|n| n.ends_with(".exr")).map(str::to_owned).collect();
    names.sort();
    let indices: Vec<f64> =
        names.iter().map(|n| n.trim_end_matches(".exr").parse::<u32>().map_or(f64::NAN, f64::from)).collect();
    check_frame_indices(path, "members", &indices)?;
    if names.len() != frames {
        return Err(Error::invalid(
            path,
            "members",
            format!("{} depth maps for {frames} poses in pose/: every frame needs one", names.len()),
        ));
    }
    let mut size = None;
    let mut maps = Vec::with_capacity(frames);
    for (i, name) in names.iter().enumerate() {
        let mut member = archive
            .by_name(name)
            .map_err(|e| Error::invalid(path, name.as_str(), format!("unreadable member: {e}")))?;
        // The first map may be of any size up to the side limit; the others are the first's size.
        let (bound, what) = match size {
            None => {
                (exr_member_bound(MAX_SIDE_PX, MAX_SIDE_PX), format!("any depth map up to {MAX_SIDE_PX} px a side"))
            }
            Some((w, h)) => (exr_member_bound(w, h), format!("a {w}x{h} depth map (the first map's size)")),
        };
        if member.size() > bound {
            return Err(Error::invalid(
                path,
                name.as_str(),
                format!("declares {} bytes, more than {what} can take ({bound})", member.size()),
            ));
        }
        let bytes = read_zip_member(path, &mut member)?;
        let context = format!("{}: {name}", path.display());
        let map = match size {
            None => crate::io::depth_exr::decode_depth_exr(&bytes, &context)?,
            Some((w, h)) => crate::io::depth_exr::decode_depth_exr_of_size(&bytes, &context, w, h)?,
        };
        size = Some((map.width, map.height));
        check_depth_sign(path, "depth", i, &map.values)?;
        maps.push(map.values);
    }
    Ok((size.expect("at least one frame"), maps))
}
