//! Sequence readers: the three layouts (cog-nvs, MegaSAM, generic) read the same content,
//! resolution changes scale K correctly, and bad input fails naming the file and field.

use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::io::sequence::read_sequence;
use datagen::synth::{SynthConfig, write_sequence};

pub fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures")
}

fn venv_python() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python")
}

/// A small synthetic sequence in the cog-nvs layout.
pub fn synth_sequence(dir: &Path, frames: u32) -> PathBuf {
    let out = dir.join("synth");
    let config = SynthConfig { width: 64, height: 48, frames, ..SynthConfig::default() };
    write_sequence(&config, &out, |_| {}).unwrap();
    out
}

#[test]
fn blender_fixture_reads_with_exact_depth_and_cameras() {
    let dir = fixtures().join("scene_101");
    let sequence = read_sequence(&dir).unwrap();
    assert_eq!((sequence.len(), sequence.size()), (9, (360, 240)));
    let depth = datagen::io::npy::read_npy_f32(&dir.join("cam_info/megasam_depth.npy")).unwrap();
    assert_eq!(sequence.depth[3].values, depth.data[3 * 360 * 240..4 * 360 * 240]);
    let k = datagen::io::npy::read_npy_f64(&dir.join("cam_info/megasam_intrinsics.npy")).unwrap();
    assert!((sequence.cameras[0].intrinsics.z_axis.x - k.data[2]).abs() < 1e-9);
    assert!((sequence.fps - 24.0).abs() < 1e-6);
}

#[test]
fn depth_at_half_resolution_is_resampled_and_k_scaled() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 2);
    let full = read_sequence(&seq).unwrap();
    // Replace depth and K with half-resolution versions (every other pixel, K of the half image).
    let depth = datagen::io::npy::read_npy_f32(&seq.join("cam_info/megasam_depth.npy")).unwrap();
    let half: Vec<f32> = (0..2)
        .flat_map(|f| (0..24).flat_map(move |v| (0..32).map(move |u| (f, v, u))))
        .map(|(f, v, u)| depth.data[f * 48 * 64 + (2 * v) * 64 + 2 * u])
        .collect();
    datagen::io::npy::write_npy(&seq.join("cam_info/megasam_depth.npy"), &[2, 24, 32], &half).unwrap();
    let k = full.cameras[0].resized(32, 24).intrinsics;
    let k_rows: Vec<f32> = foundation::camera::mat3_to_row_major(&k).iter().map(|&v| v as f32).collect();
    datagen::io::npy::write_npy(&seq.join("cam_info/megasam_intrinsics.npy"), &[3, 3], &k_rows).unwrap();
    let read = read_sequence(&seq).unwrap();
    assert_eq!((read.depth[0].width, read.depth[0].height), (64, 48));
    assert!(
        read.cameras[0].intrinsics.abs_diff_eq(full.cameras[0].intrinsics, 1e-4),
        "{} vs {}",
        read.cameras[0].intrinsics,
        full.cameras[0].intrinsics
    );
}

#[test]
fn megasam_npz_and_generic_layouts_read_the_same_scene() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 3);
    let reference = read_sequence(&seq).unwrap();

    // MegaSAM native: float16 depth, images from the lossless PNG frames.
    let npz_dir = dir.path().join("megasam");
    std::fs::create_dir_all(&npz_dir).unwrap();
    let script = r#"
import sys, glob, numpy as np
from PIL import Image
src, out = sys.argv[1], sys.argv[2]
images = np.stack([np.asarray(Image.open(p).convert("RGB")) for p in sorted(glob.glob(src + "/frames/*.png"))])
depth = np.load(src + "/cam_info/megasam_depth.npy").astype(np.float16)
np.savez(out + "/scene_sgd_cvd_hr.npz", images=images, depths=depth,
         intrinsic=np.load(src + "/cam_info/megasam_intrinsics.npy"), cam_c2w=np.load(src + "/cam_info/megasam_c2ws.npy"))
"#;
    let status = Command::new(venv_python()).arg("-c").arg(script).arg(&seq).arg(&npz_dir).status().unwrap();
    assert!(status.success());
    let megasam = read_sequence(&npz_dir).unwrap();
    assert_eq!(megasam.len(), 3);
    assert_eq!(megasam.frames[2], image::open(seq.join("frames/00002.png")).unwrap().to_rgb8());
    for (a, b) in megasam.depth[1].values.iter().zip(&reference.depth[1].values) {
        assert!((a - b).abs() <= 2e-3 * b.abs().max(1e-3), "float16 depth {a} vs {b}");
    }
    assert!(megasam.cameras[2].world_from_camera.abs_diff_eq(reference.cameras[2].world_from_camera, 1e-6));

    // Generic: PNG frames, EXR depth, cameras.json with nested matrices.
    let generic = dir.path().join("generic");
    std::fs::create_dir_all(generic.join("frames")).unwrap();
    std::fs::create_dir_all(generic.join("depth")).unwrap();
    let mut poses = Vec::new();
    for i in 0..3 {
        std::fs::copy(seq.join(format!("frames/{i:05}.png")), generic.join(format!("frames/{i:05}.png"))).unwrap();
        let exr = datagen::io::depth_exr::encode_depth_exr(&reference.depth[i]).unwrap();
        std::fs::write(generic.join(format!("depth/{i:05}.exr")), exr).unwrap();
        let rows = foundation::camera::mat4_to_row_major(&reference.cameras[i].world_from_camera);
        poses.push(rows.chunks(4).map(|r| r.to_vec()).collect::<Vec<_>>());
    }
    let k = foundation::camera::mat3_to_row_major(&reference.cameras[0].intrinsics);
    let json = serde_json::json!({"intrinsics": k.to_vec(), "world_from_camera": poses});
    std::fs::write(generic.join("cameras.json"), json.to_string()).unwrap();
    let read = read_sequence(&generic).unwrap();
    assert_eq!(read.depth, reference.depth);
    assert_eq!(read.frames, megasam.frames);
    assert!(read.cameras[1].world_from_camera.abs_diff_eq(reference.cameras[1].world_from_camera, 1e-12));
}

fn error_of(dir: &Path) -> String {
    read_sequence(dir).err().map(|e| e.to_string()).unwrap_or_else(|| panic!("{} must fail", dir.display()))
}

#[test]
fn bad_sequences_fail_naming_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth_sequence(dir.path(), 3);
    let cam = seq.join("cam_info");
    let depth = datagen::io::npy::read_npy_f32(&cam.join("megasam_depth.npy")).unwrap();
    let poses = datagen::io::npy::read_npy_f32(&cam.join("megasam_c2ws.npy")).unwrap();
    let restore = || {
        datagen::io::npy::write_npy(&cam.join("megasam_depth.npy"), &depth.shape, &depth.data).unwrap();
        datagen::io::npy::write_npy(&cam.join("megasam_c2ws.npy"), &poses.shape, &poses.data).unwrap();
    };
    let check = |what: &str, needles: &[&str]| {
        let error = error_of(&seq);
        for needle in needles {
            assert!(error.contains(needle), "{what}: `{error}` should name `{needle}`");
        }
        restore();
    };

    // NaN/inf/zero regions are fine; an all-invalid frame is not.
    let mut holes = depth.data.clone();
    holes[..500].fill(f32::NAN);
    holes[500..600].fill(0.0);
    holes[600..700].fill(f32::INFINITY);
    datagen::io::npy::write_npy(&cam.join("megasam_depth.npy"), &depth.shape, &holes).unwrap();
    assert!(read_sequence(&seq).is_ok(), "partially invalid depth must work");
    let mut dead = depth.data.clone();
    dead[64 * 48..2 * 64 * 48].fill(f32::NAN);
    datagen::io::npy::write_npy(&cam.join("megasam_depth.npy"), &depth.shape, &dead).unwrap();
    check("all-invalid frame", &["megasam_depth.npy", "depth[1]"]);

    datagen::io::npy::write_npy(&cam.join("megasam_depth.npy"), &[2, 48, 64], &depth.data[..2 * 48 * 64]).unwrap();
    check("frame count mismatch", &["megasam_depth.npy", "3 frames"]);

    let mut nan_pose = poses.data.clone();
    nan_pose[16 + 3] = f32::NAN;
    datagen::io::npy::write_npy(&cam.join("megasam_c2ws.npy"), &poses.shape, &nan_pose).unwrap();
    check("non-finite pose", &["megasam_c2ws.npy", "world_from_camera[1]"]);

    let mut scaled = poses.data.clone();
    scaled[32] *= 2.0;
    datagen::io::npy::write_npy(&cam.join("megasam_c2ws.npy"), &poses.shape, &scaled).unwrap();
    check("non-rigid pose", &["megasam_c2ws.npy", "world_from_camera[2]", "rigid"]);

    let bytes = std::fs::read(cam.join("megasam_depth.npy")).unwrap();
    std::fs::write(cam.join("megasam_depth.npy"), &bytes[..bytes.len() / 2]).unwrap();
    check("truncated npy", &["megasam_depth.npy", "megasam_depth", "truncated"]);

    std::fs::remove_file(cam.join("megasam_depth.npy")).unwrap();
    check("missing depth", &["megasam_depth.npy"]);

    let bytes = std::fs::read(seq.join("gt_rgb.mp4")).unwrap();
    std::fs::write(seq.join("gt_rgb.mp4"), &bytes[..bytes.len() / 3]).unwrap();
    let error = error_of(&seq);
    assert!(error.contains("gt_rgb.mp4"), "truncated video: {error}");

    assert!(error_of(&dir.path().join("nowhere")).contains("nowhere"));
}
