//! Hostile sequence inputs: every documented camera and trajectory
//! form parses; mixed frame sizes, non-rigid poses, bad K, ambiguous image dtypes and transposed
//! depth are errors whose first line names the file and the field or line.

use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::io::sequence::{Sequence, read_sequence};
use datagen::pairs::clip::pivot_distance;
use datagen::pairs::trajectory::{orbit, read_trajectory_file};
use datagen::synth::{SynthConfig, write_sequence};
use foundation::camera::{mat3_to_row_major, mat4_to_row_major};
use foundation::frames::read_frames;
use serde_json::{Value, json};

/// Frames of the synthetic sequences: enough for interpolation, small enough to be fast.
const FRAMES: usize = 5;

/// A small valid cog-nvs sequence (64×48, [`FRAMES`] frames) in `dir/synth`.
fn synth(dir: &Path) -> PathBuf {
    let out = dir.join("synth");
    let config = SynthConfig { width: 64, height: 48, frames: FRAMES as u32, ..SynthConfig::default() };
    write_sequence(&config, &out, |_| {}).unwrap();
    out
}

/// The same scene in the generic layout (PNG frames, EXR depth, `cameras.json` with one flat K
/// and nested poses) in `dir/generic`, with the sequence it must read as.
fn generic(dir: &Path) -> (PathBuf, Sequence) {
    let seq = synth(dir);
    let reference = read_sequence(&seq).unwrap();
    let out = dir.join("generic");
    std::fs::create_dir_all(out.join("frames")).unwrap();
    std::fs::create_dir_all(out.join("depth")).unwrap();
    for i in 0..FRAMES {
        std::fs::copy(seq.join(format!("frames/{i:05}.png")), out.join(format!("frames/{i:05}.png"))).unwrap();
        let exr = datagen::io::depth_exr::encode_depth_exr(&reference.depth[i]).unwrap();
        std::fs::write(out.join(format!("depth/{i:05}.exr")), exr).unwrap();
    }
    write_cameras(&out, json!({"intrinsics": flat_k(&reference), "world_from_camera": nested_poses(&reference)}));
    (out, reference)
}

fn write_cameras(dir: &Path, cameras: Value) {
    std::fs::write(dir.join("cameras.json"), cameras.to_string()).unwrap();
}

fn flat_k(sequence: &Sequence) -> Value {
    json!(mat3_to_row_major(&sequence.cameras[0].intrinsics).to_vec())
}

fn nested_k(sequence: &Sequence) -> Value {
    let rows = mat3_to_row_major(&sequence.cameras[0].intrinsics);
    json!(rows.chunks(3).map(<[f64]>::to_vec).collect::<Vec<_>>())
}

fn pose_rows(sequence: &Sequence) -> Vec<[f64; 16]> {
    sequence.cameras.iter().map(|c| mat4_to_row_major(&c.world_from_camera)).collect()
}

fn nested_poses(sequence: &Sequence) -> Value {
    json!(pose_rows(sequence).iter().map(|p| p.chunks(4).map(<[f64]>::to_vec).collect::<Vec<_>>()).collect::<Vec<_>>())
}

fn flat_poses(sequence: &Sequence) -> Value {
    json!(pose_rows(sequence).iter().map(|p| p.to_vec()).collect::<Vec<_>>())
}

/// The error of reading `dir`, which must fail.
fn error_of(dir: &Path) -> String {
    match read_sequence(dir) {
        Ok(_) => panic!("{} must be rejected", dir.display()),
        Err(e) => e.to_string(),
    }
}

/// Asserts that the first line of `error` names every needle.
fn first_line_names(error: &str, needles: &[&str]) {
    let first = error.lines().next().unwrap_or_default();
    for needle in needles {
        assert!(first.contains(needle), "the first line of `{error}` should name `{needle}`");
    }
}

fn assert_same_cameras(read: &Sequence, reference: &Sequence, what: &str) {
    assert_eq!(read.cameras.len(), reference.cameras.len(), "{what}");
    for (a, b) in read.cameras.iter().zip(&reference.cameras) {
        assert!(a.intrinsics.abs_diff_eq(b.intrinsics, 1e-9), "{what}: {} vs {}", a.intrinsics, b.intrinsics);
        assert!(a.world_from_camera.abs_diff_eq(b.world_from_camera, 1e-9), "{what}: poses differ");
    }
}

fn venv_python() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python")
}

/// Runs a numpy script with `args`.
fn python(script: &str, args: &[&Path]) {
    let status = Command::new(venv_python()).arg("-c").arg(script).args(args).status().unwrap();
    assert!(status.success(), "python failed");
}

// Class 4: every documented input form parses.

#[test]
fn cameras_json_parses_every_documented_form() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, reference) = generic(dir.path());
    let per_frame = |k: Value| json!(vec![k; FRAMES]);
    let intrinsics = [
        ("one flat K", flat_k(&reference)),
        ("one nested K", nested_k(&reference)),
        ("flat K per frame", per_frame(flat_k(&reference))),
        ("nested K per frame", per_frame(nested_k(&reference))),
    ];
    let poses = [("nested 4×4 poses", nested_poses(&reference)), ("flat 16-value poses", flat_poses(&reference))];
    for (k_form, k) in &intrinsics {
        for (pose_form, pose) in &poses {
            write_cameras(&seq, json!({"intrinsics": k, "world_from_camera": pose}));
            let what = format!("{k_form} + {pose_form}");
            let read = read_sequence(&seq).unwrap_or_else(|e| panic!("{what} must parse: {e}"));
            assert_same_cameras(&read, &reference, &what);
        }
    }
}

#[test]
fn generic_layout_reads_a_video_instead_of_frames() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, reference) = generic(dir.path());
    std::fs::remove_dir_all(seq.join("frames")).unwrap();
    std::fs::copy(dir.path().join("synth/gt_rgb.mp4"), seq.join("clip.mp4")).unwrap();
    let read = read_sequence(&seq).unwrap();
    assert_eq!((read.len(), read.size()), (FRAMES, (64, 48)));
    assert!(read.fps > 0.0, "a video carries its frame rate");
    assert_same_cameras(&read, &reference, "video + cameras.json");
}

#[test]
fn trajectory_files_of_every_documented_form_parse() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = read_sequence(&synth(dir.path())).unwrap();
    let read = |path: &Path| {
        read_trajectory_file(path, sequence.len(), &sequence.cameras, &sequence.depth[0])
            .unwrap_or_else(|e| panic!("{} must parse: {e}", path.display()))
    };
    let expected: Vec<_> = sequence.cameras.iter().map(|c| c.world_from_camera).collect();
    let same = |poses: Vec<glam::DMat4>, what: &str| {
        assert_eq!(poses.len(), expected.len(), "{what}");
        for (a, b) in poses.iter().zip(&expected) {
            assert!(a.abs_diff_eq(*b, 1e-9), "{what}");
        }
    };

    let npy = dir.path().join("poses.npy");
    let flat: Vec<f64> = pose_rows(&sequence).concat();
    datagen::io::npy::write_npy(&npy, &[FRAMES, 4, 4], &flat).unwrap();
    same(read(&npy), ".npy (N,4,4)");
    for (name, value) in [
        ("nested.json", nested_poses(&sequence)),
        ("flat.json", flat_poses(&sequence)),
        ("wrapped.json", json!({"world_from_camera": nested_poses(&sequence)})),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, value.to_string()).unwrap();
        same(read(&path), name);
    }

    // trajs/*.txt: azimuth, elevation, radius lines; a single value holds for every frame.
    let txt = dir.path().join("orbit.txt");
    std::fs::write(&txt, "0 20\n5\n0, 0.1\n").unwrap();
    let poses = read(&txt);
    let pivot = pivot_distance(&sequence.depth[0], &sequence.cameras[0], 1.0);
    let last = FRAMES - 1;
    assert!(poses[0].abs_diff_eq(orbit(&expected[0], pivot, 0.0, 5.0, 0.0), 1e-9));
    assert!(poses[last].abs_diff_eq(orbit(&expected[last], pivot, 20.0, 5.0, 0.1), 1e-9));
}

// Class 5: frames of different sizes are rejected, naming the frame and both sizes.

#[test]
fn generic_frames_of_different_sizes_name_the_frame_and_both_sizes() {
    let dir = tempfile::tempdir().unwrap();
    let (seq, _) = generic(dir.path());
    let odd = seq.join("frames/00003.png");
    let small =
        image::imageops::resize(&image::open(&odd).unwrap().to_rgb8(), 62, 46, image::imageops::FilterType::Triangle);
    small.save(&odd).unwrap();
    let error = error_of(&seq);
    first_line_names(&error, &["00003.png", "frame", "62x46", "64x48"]);
}

#[test]
fn image_dataset_frames_of_different_sizes_are_rejected() {
    // A DAVIS-style JPEG folder (the reader the corpus image datasets share).
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("JPEGImages/480p/bear");
    std::fs::create_dir_all(&folder).unwrap();
    let paths: Vec<PathBuf> = (0..3).map(|i| folder.join(format!("{i:05}.jpg"))).collect();
    for (i, path) in paths.iter().enumerate() {
        let (width, height) = if i == 2 { (48, 64) } else { (64, 48) };
        image::RgbImage::from_pixel(width, height, image::Rgb([90, 120, 30])).save(path).unwrap();
    }
    assert_eq!(read_frames(&paths[..2]).unwrap().len(), 2, "equal sizes read");
    let error = read_frames(&paths).expect_err("frames of two sizes must be rejected").to_string();
    first_line_names(&error, &["00002.jpg", "48x64", "64x48"]);
}

// Class 6: one pose check and one K check wherever they come from; ambiguous arrays are errors.

#[test]
fn trajectory_poses_get_the_sequence_pose_checks() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = read_sequence(&synth(dir.path())).unwrap();
    let read = |path: &Path| {
        let result = read_trajectory_file(path, sequence.len(), &sequence.cameras, &sequence.depth[0]);
        result.err().unwrap_or_else(|| panic!("{} must be rejected", path.display())).to_string()
    };
    let mut rows = pose_rows(&sequence);
    rows[2][14] = 0.25; // a projective last row [0, 0, 0.25, 1]
    let npy = dir.path().join("projective.npy");
    datagen::io::npy::write_npy(&npy, &[FRAMES, 4, 4], &rows.concat()).unwrap();
    first_line_names(&read(&npy), &["projective.npy", "world_from_camera[2]", "last row"]);

    let json_path = dir.path().join("projective.json");
    std::fs::write(&json_path, json!(rows.iter().map(|p| p.to_vec()).collect::<Vec<_>>()).to_string()).unwrap();
    first_line_names(&read(&json_path), &["projective.json", "world_from_camera[2]", "last row"]);

    // A mirrored frame (det −1) and a 3×4 matrix.
    let mut rows = pose_rows(&sequence);
    for column in [0, 4, 8] {
        rows[1][column] = -rows[1][column];
    }
    std::fs::write(&json_path, json!(rows.iter().map(|p| p.to_vec()).collect::<Vec<_>>()).to_string()).unwrap();
    first_line_names(&read(&json_path), &["projective.json", "world_from_camera[1]", "determinant"]);
    let mut list: Vec<Vec<f64>> = pose_rows(&sequence).iter().map(|p| p.to_vec()).collect();
    list[4].truncate(12);
    std::fs::write(&json_path, json!(list).to_string()).unwrap();
    first_line_names(&read(&json_path), &["projective.json", "world_from_camera[4]", "found 12 numbers"]);
}

#[test]
fn intrinsics_need_a_pinhole_last_row_and_no_skew() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth(dir.path());
    let k_path = seq.join("cam_info/megasam_intrinsics.npy");
    let k = datagen::io::npy::read_npy_f64(&k_path).unwrap();
    let write = |index: usize, value: f64| {
        let mut data = k.data.clone();
        data[index] = value;
        datagen::io::npy::write_npy(&k_path, &[3, 3], &data).unwrap();
    };
    write(6, 0.5);
    first_line_names(&error_of(&seq), &["megasam_intrinsics.npy", "intrinsics", "last row"]);
    write(8, 2.0);
    first_line_names(&error_of(&seq), &["megasam_intrinsics.npy", "intrinsics", "last row"]);
    write(3, 4.0);
    first_line_names(&error_of(&seq), &["megasam_intrinsics.npy", "intrinsics", "K[1][0]"]);

    // The same check on a per-frame K of cameras.json, and a mirrored pose there.
    let (generic_seq, reference) = generic(dir.path());
    let mut ks = vec![mat3_to_row_major(&reference.cameras[0].intrinsics); FRAMES];
    ks[3][1] = 2.0;
    write_cameras(&generic_seq, json!({"intrinsics": ks, "world_from_camera": nested_poses(&reference)}));
    first_line_names(&error_of(&generic_seq), &["cameras.json", "intrinsics[3]", "skew"]);
}

#[test]
fn megasam_images_of_bool_or_float_dtype_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth(dir.path());
    let script = r#"
import sys, glob, numpy as np
from PIL import Image
src, out, kind = sys.argv[1], sys.argv[2], sys.argv[3]
images = np.stack([np.asarray(Image.open(p).convert("RGB")) for p in sorted(glob.glob(src + "/frames/*.png"))])
images = {"u8": images, "bool": images > 127, "float": images / 255.0, "u16": images.astype(np.uint16) * 257}[kind]
np.savez(out + "/scene_sgd_cvd_hr.npz", images=images, depths=np.load(src + "/cam_info/megasam_depth.npy"),
         intrinsic=np.load(src + "/cam_info/megasam_intrinsics.npy"), cam_c2w=np.load(src + "/cam_info/megasam_c2ws.npy"))
"#;
    let npz_dir = dir.path().join("megasam");
    std::fs::create_dir_all(&npz_dir).unwrap();
    let with = |kind: &str| {
        python(script, &[&seq, &npz_dir, Path::new(kind)]);
        read_sequence(&npz_dir)
    };
    assert_eq!(with("u8").unwrap().len(), FRAMES, "uint8 images read");
    for (kind, needle) in [("bool", "boolean"), ("float", "float"), ("u16", "outside 0–255")] {
        let error = with(kind).err().unwrap_or_else(|| panic!("{kind} images must be rejected")).to_string();
        first_line_names(&error, &["scene_sgd_cvd_hr.npz", "images", needle]);
    }
}

#[test]
fn boolean_depth_is_an_error_naming_the_file_and_member() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth(dir.path());
    let depth_path = seq.join("cam_info/megasam_depth.npy");
    let depth = datagen::io::npy::read_npy_f32(&depth_path).unwrap();
    // cog-nvs: the depth stack saved as `depth > median` (a mask), same shape.
    let mask: Vec<bool> = depth.data.iter().map(|&d| d > 1.0).collect();
    datagen::io::npy::write_npy(&depth_path, &depth.shape, &mask).unwrap();
    first_line_names(&error_of(&seq), &["megasam_depth.npy", "boolean"]);
    // MegaSAM: `depths` of the npz as booleans; float depths of the same folder read.
    let script = r#"
import sys, glob, numpy as np
from PIL import Image
src, out, kind = sys.argv[1], sys.argv[2], sys.argv[3]
images = np.stack([np.asarray(Image.open(p).convert("RGB")) for p in sorted(glob.glob(src + "/frames/*.png"))])
depths = np.load(src + "/cam_info/megasam_depth.npy").astype(np.float32) + 1.0
depths = depths > 1.5 if kind == "bool" else depths
np.savez(out + "/scene_sgd_cvd_hr.npz", images=images, depths=depths,
         intrinsic=np.load(src + "/cam_info/megasam_intrinsics.npy"), cam_c2w=np.load(src + "/cam_info/megasam_c2ws.npy"))
"#;
    let npz_dir = dir.path().join("megasam");
    std::fs::create_dir_all(&npz_dir).unwrap();
    python(script, &[&seq, &npz_dir, Path::new("float")]);
    assert_eq!(read_sequence(&npz_dir).unwrap().len(), FRAMES, "float depths read");
    python(script, &[&seq, &npz_dir, Path::new("bool")]);
    first_line_names(&error_of(&npz_dir), &["scene_sgd_cvd_hr.npz", "depths", "boolean"]);
}

#[test]
fn depth_stored_transposed_is_an_error_naming_both_shapes() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth(dir.path());
    let depth_path = seq.join("cam_info/megasam_depth.npy");
    let depth = datagen::io::npy::read_npy_f32(&depth_path).unwrap();
    // (N, W, H): each map transposed.
    let transposed: Vec<f32> = (0..FRAMES)
        .flat_map(|f| (0..64).flat_map(move |u| (0..48).map(move |v| (f, v, u))))
        .map(|(f, v, u)| depth.data[f * 48 * 64 + v * 64 + u])
        .collect();
    datagen::io::npy::write_npy(&depth_path, &[FRAMES, 64, 48], &transposed).unwrap();
    let error = error_of(&seq);
    first_line_names(&error, &["megasam_depth.npy", "depth", "64x48", "48x64", "transposed"]);

    // The same rule for a second depth source; a legal other resolution still reads.
    datagen::io::npy::write_npy(&depth_path, &depth.shape, &depth.data).unwrap();
    let mut sequence = read_sequence(&seq).unwrap();
    let second = dir.path().join("second.npy");
    datagen::io::npy::write_npy(&second, &[FRAMES, 64, 48], &transposed).unwrap();
    let error = sequence.load_second_depth(&second).unwrap_err().to_string();
    first_line_names(&error, &["second.npy", "depth", "transposed"]);
    let square: Vec<f32> = vec![2.0; FRAMES * 40 * 40];
    datagen::io::npy::write_npy(&second, &[FRAMES, 40, 40], &square).unwrap();
    sequence.load_second_depth(&second).unwrap();
}

// Class 8: messages point at the right thing.

#[test]
fn a_png_named_mp4_is_a_video_error() {
    let dir = tempfile::tempdir().unwrap();
    let seq = synth(dir.path());
    std::fs::copy(seq.join("frames/00000.png"), seq.join("gt_rgb.mp4")).unwrap();
    let error = error_of(&seq);
    first_line_names(&error, &["gt_rgb.mp4", "video", "still image"]);
    assert!(!error.contains("depth"), "not a depth problem: {error}");
}

#[test]
fn bad_trajs_txt_values_name_the_file_line_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = read_sequence(&synth(dir.path())).unwrap();
    let txt = dir.path().join("trajs_loop.txt");
    let error = |text: &str| {
        std::fs::write(&txt, text).unwrap();
        let result = read_trajectory_file(&txt, sequence.len(), &sequence.cameras, &sequence.depth[0]);
        result.err().unwrap_or_else(|| panic!("`{text}` must be rejected")).to_string()
    };
    first_line_names(&error("0 NaN 10\n0 0\n0 0\n"), &["trajs_loop.txt", "`azimuth`", "line 1", "value 2"]);
    // Line numbers are the file's, blank lines included.
    first_line_names(&error("0 10\n\n0 inf\n0 0\n"), &["trajs_loop.txt", "`elevation`", "line 3"]);
    first_line_names(&error("0\n0\n0 abc\n"), &["trajs_loop.txt", "`radius`", "line 3", "not a number"]);
    first_line_names(&error("0\n0\n0 -1.5\n"), &["trajs_loop.txt", "`radius`", "line 3", "pivot"]);
    first_line_names(&error("0\n0\n"), &["trajs_loop.txt", "lines", "found 2"]);
}

/// An I/O error is said once: the CLI prints the whole error chain (`{:#}`), so the OS error must
/// be in the message or be its source, not both.
#[test]
fn an_io_error_is_not_repeated() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no_such_folder");
    let output = Command::new(env!("CARGO_BIN_EXE_datagen")).arg("validate").arg(&missing).output().unwrap();
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    let first = stderr.lines().next().unwrap_or_default();
    assert!(first.contains("no_such_folder") && first.contains("os error 2"), "{first}");
    assert_eq!(first.matches("os error 2").count(), 1, "said once: {first}");
    let error = datagen::error::Error::io(&missing, std::io::Error::other("gone"));
    assert!(std::error::Error::source(&error).is_none(), "the OS error is in the message only");
}
