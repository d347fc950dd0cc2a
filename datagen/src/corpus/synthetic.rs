//! A small corpus of synthetic videos laid out as every dataset tree the crawler knows (SA-V,
//! TAO, YouTube-VOS, DAVIS 2017, sequence folders), each video with its reconstruction (cog-nvs
//! `cam_info/*.npy`) and annotations in the dataset's own format, plus a corpus config pointing at
//! all of it: `datagen synth-corpus`, for trying `datagen build` and for its throughput benchmark.
//!
//! Annotations follow each dataset's conventions: SA-V compressed-RLE masklets on every 4th
//! frame, YouTube-VOS id PNGs on every 5th frame, DAVIS id PNGs on every frame, TAO boxes (the
//! objects' bounding boxes) in a COCO-style JSON; frames of the image datasets are JPEGs.

use std::path::{Path, PathBuf};

use image::GrayImage;

use crate::error::{Error, Result};
use crate::io::rle::{encode_counts, mask_runs};
use crate::synth::{SynthConfig, write_sequence};

/// SA-V annotates every 4th frame (6 fps of 24 fps video).
const SAV_ANNOTATION_STEP: usize = 4;
/// YouTube-VOS annotates every 5th frame.
const YTVOS_ANNOTATION_STEP: usize = 5;
/// JPEG quality of the image datasets' frames.
const JPEG_QUALITY: u8 = 95;

/// What [`write_synthetic_corpus`] wrote.
#[derive(Debug, Clone)]
pub struct SyntheticCorpus {
    /// The corpus config (`corpus.toml`) for `datagen build`.
    pub config: PathBuf,
    /// Videos written per layout.
    pub videos_per_layout: usize,
}

/// Writes `videos_per_layout` synthetic videos per layout under `root` (scene seeds `0..`, one
/// scene per video) and `root/corpus.toml` building them into `out`.
pub fn write_synthetic_corpus(
    root: &Path,
    out: &Path,
    videos_per_layout: usize,
    synth: &SynthConfig,
) -> Result<SyntheticCorpus> {
    let mut seed = synth.seed;
    let mut next_scene = |name: &str| -> Result<PathBuf> {
        let dir = root.join("scenes").join(name);
        write_sequence(&SynthConfig { seed, ..synth.clone() }, &dir, |_| {})?;
        seed += 1;
        Ok(dir)
    };
    for i in 0..videos_per_layout {
        // Sequence folders: the scene itself.
        let scene = next_scene(&format!("seq_{i:04}"))?;
        copy_dir(&scene, &root.join("sequences").join(format!("seq_{i:04}")))?;

        // SA-V: mp4 + masklet JSON; reconstruction keyed by video id.
        let id = format!("sav_{i:06}");
        let scene = next_scene(&id)?;
        let folder = root.join("sav/sav_000");
        mkdir(&folder)?;
        copy(&scene.join("gt_rgb.mp4"), &folder.join(format!("{id}.mp4")))?;
        write_sav_annotation(&scene, &folder.join(format!("{id}_manual.json")), &id)?;
        copy_dir(&scene.join("cam_info"), &root.join("recon/sav").join(&id).join("cam_info"))?;

        // YouTube-VOS: JPEG frames, id PNGs on every 5th frame.
        let id = format!("ytvos{i:04}");
        let scene = next_scene(&id)?;
        write_jpegs(&scene, &root.join("ytvos/JPEGImages").join(&id), |f| format!("{f:05}.jpg"))?;
        copy_masks(&scene, &root.join("ytvos/Annotations").join(&id), YTVOS_ANNOTATION_STEP)?;
        copy_dir(&scene.join("cam_info"), &root.join("recon/ytvos").join(&id).join("cam_info"))?;

        // DAVIS 2017: JPEG frames, id PNGs on every frame, listed in ImageSets.
        let id = format!("davis-{i:04}");
        let scene = next_scene(&id)?;
        write_jpegs(&scene, &root.join("davis/JPEGImages/480p").join(&id), |f| format!("{f:05}.jpg"))?;
        copy_masks(&scene, &root.join("davis/Annotations/480p").join(&id), 1)?;
        copy_dir(&scene.join("cam_info"), &root.join("recon/davis").join(&id).join("cam_info"))?;
    }
    let davis_list: String = (0..videos_per_layout).map(|i| format!("davis-{i:04}\n")).collect();
    mkdir(&root.join("davis/ImageSets/2017"))?;
    write(&root.join("davis/ImageSets/2017/train.txt"), davis_list.as_bytes())?;
    write_tao(root, videos_per_layout, &mut next_scene)?;

    let config = root.join("corpus.toml");
    let r = root.display();
    let text = format!(
        "# A synthetic corpus in every dataset layout (datagen synth-corpus).\nseed = 0\ntrajectories = 2\n\n\
         [[sources]]\ndataset = \"sequences\"\nroot = \"{r}/sequences\"\n\n\
         [[sources]]\ndataset = \"sav\"\nroot = \"{r}/sav\"\nreconstructions = \"{r}/recon/sav/{{video_id}}\"\n\n\
         [[sources]]\ndataset = \"ytvos\"\nroot = \"{r}/ytvos\"\nreconstructions = \"{r}/recon/ytvos/{{video_id}}\"\n\n\
         [[sources]]\ndataset = \"davis\"\nroot = \"{r}/davis\"\nsplit = \"train\"\nreconstructions = \"{r}/recon/davis/{{video_id}}\"\n\n\
         [[sources]]\ndataset = \"tao\"\nroot = \"{r}/tao\"\nsplit = \"train\"\nreconstructions = \"{r}/recon/tao/{{name}}\"\n\n\
         [output]\ndir = \"{}\"\n",
        out.display()
    );
    write(&config, text.as_bytes())?;
    Ok(SyntheticCorpus { config, videos_per_layout })
}

/// TAO: `frames/train/SYN/{video}/frame%04d.jpg` (from 1) and `annotations/train.json` with the
/// moving objects' boxes on every frame.
fn write_tao(root: &Path, count: usize, next_scene: &mut dyn FnMut(&str) -> Result<PathBuf>) -> Result<()> {
    let (mut videos, mut images, mut annotations) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..count {
        let video = format!("tao{i:04}");
        let name = format!("train/SYN/{video}");
        let scene = next_scene(&video)?;
        let frames = write_jpegs(&scene, &root.join("tao/frames").join(&name), |f| format!("frame{:04}.jpg", f + 1))?;
        copy_dir(&scene.join("cam_info"), &root.join("recon/tao").join(&video).join("cam_info"))?;
        let video_id = i as u64 + 1;
        let masks = read_masks(&scene)?;
        let (width, height) = masks[0].dimensions();
        videos.push(serde_json::json!({"id": video_id, "name": name, "width": width, "height": height}));
        for (f, mask) in masks.iter().enumerate().take(frames) {
            let image_id = video_id * 100_000 + f as u64;
            images.push(serde_json::json!({
                "id": image_id, "video_id": video_id, "file_name": format!("{name}/frame{:04}.jpg", f + 1),
                "width": width, "height": height,
            }));
            for object in object_ids(std::slice::from_ref(mask)) {
                let [x0, y0, x1, y1] = bounding_box(mask, object).expect("the object is in the mask");
                annotations.push(serde_json::json!({
                    "image_id": image_id, "track_id": object, "bbox": [x0, y0, x1 - x0 + 1, y1 - y0 + 1],
                }));
            }
        }
    }
    let json = serde_json::json!({"videos": videos, "images": images, "annotations": annotations});
    mkdir(&root.join("tao/annotations"))?;
    write(&root.join("tao/annotations/train.json"), json.to_string().as_bytes())
}

/// The non-zero ids present in any of `masks`, ascending.
fn object_ids(masks: &[GrayImage]) -> Vec<u8> {
    let mut present = [false; 256];
    for mask in masks {
        for &v in mask.as_raw() {
            present[usize::from(v)] = true;
        }
    }
    (1..=u8::MAX).filter(|&v| present[usize::from(v)]).collect()
}

fn bounding_box(mask: &GrayImage, id: u8) -> Option<[u32; 4]> {
    let mut bounds: Option<[u32; 4]> = None;
    for (x, y, p) in mask.enumerate_pixels() {
        if p.0[0] == id {
            let b = bounds.get_or_insert([x, y, x, y]);
            *b = [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)];
        }
    }
    bounds
}

fn write_sav_annotation(scene: &Path, path: &Path, id: &str) -> Result<()> {
    let masks = read_masks(scene)?;
    let (width, height) = masks[0].dimensions();
    let objects = object_ids(&masks);
    let masklet: Vec<Vec<serde_json::Value>> = masks
        .iter()
        .step_by(SAV_ANNOTATION_STEP)
        .map(|mask| {
            objects
                .iter()
                .map(|&object| {
                    let on: Vec<bool> = mask.as_raw().iter().map(|&v| v == object).collect();
                    let counts = encode_counts(&mask_runs(&on, height as usize, width as usize));
                    serde_json::json!({"size": [height, width], "counts": counts})
                })
                .collect()
        })
        .collect();
    let json = serde_json::json!({"video_id": id, "video_frame_count": masks.len() as f64, "masklet": masklet});
    write(path, json.to_string().as_bytes())
}

fn read_masks(scene: &Path) -> Result<Vec<GrayImage>> {
    let dir = scene.join("masks");
    let mut paths: Vec<PathBuf> =
        std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    paths.iter().map(|p| crate::io::annotations::read_id_png(p)).collect()
}

/// The scene's PNG frames as JPEGs named by `name(frame)`; returns the frame count.
fn write_jpegs(scene: &Path, dir: &Path, name: impl Fn(usize) -> String) -> Result<usize> {
    mkdir(dir)?;
    let frames = foundation::frames::read_frames(&sorted_files(&scene.join("frames"))?)?;
    for (f, frame) in frames.iter().enumerate() {
        let path = dir.join(name(f));
        let file = std::fs::File::create(&path).map_err(|e| Error::io(&path, e))?;
        let mut encoder =
            image::codecs::jpeg::JpegEncoder::new_with_quality(std::io::BufWriter::new(file), JPEG_QUALITY);
        encoder
            .encode_image(frame)
            .map_err(|e| Error::Image { context: path.display().to_string(), reason: e.to_string() })?;
    }
    Ok(frames.len())
}

fn copy_masks(scene: &Path, dir: &Path, step: usize) -> Result<()> {
    mkdir(dir)?;
    for path in sorted_files(&scene.join("masks"))?.into_iter().step_by(step) {
        copy(&path, &dir.join(path.file_name().expect("a file")))?;
    }
    Ok(())
}

fn sorted_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut paths: Vec<PathBuf> =
        std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.filter_map(|e| e.ok().map(|e| e.path())).collect();
    paths.sort();
    Ok(paths)
}

fn copy_dir(from: &Path, to: &Path) -> Result<()> {
    mkdir(to)?;
    for path in sorted_files(from)? {
        let target = to.join(path.file_name().expect("a file"));
        if path.is_dir() {
            copy_dir(&path, &target)?;
        } else {
            copy(&path, &target)?;
        }
    }
    Ok(())
}

fn mkdir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))
}

fn copy(from: &Path, to: &Path) -> Result<()> {
    std::fs::copy(from, to).map(|_| ()).map_err(|e| Error::io(from, e))
}

fn write(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}
