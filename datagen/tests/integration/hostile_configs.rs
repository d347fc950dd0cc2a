//! Hostile config values (NaN, inf, negative, zero, absurd, mistyped) in every datagen config are
//! rejected where the config enters, with the file and the key on the error's first line.

use std::path::{Path, PathBuf};
use std::process::Command;

use datagen::config_file::{Validate, load_toml};
use datagen::corpus::build::BuildConfig;
use datagen::pairs::generator::{PairsConfig, TrajectoryRequest, generate_clips};
use datagen::pairs::trajectory::TrajectoryConfig;
use datagen::synth::{SynthConfig, SynthScene, write_sequence};

fn datagen() -> Command {
    Command::new(env!("CARGO_BIN_EXE_datagen"))
}

fn first_line(error: impl std::fmt::Display) -> String {
    error.to_string().lines().next().unwrap_or_default().to_owned()
}

/// Asserts the first line of `error` reads `FILE: key `KEY`: ...` and mentions `value`.
fn assert_names(error: impl std::fmt::Display, file: &Path, key: &str, value: &str) {
    let line = first_line(error);
    let start = format!("{}: key `{key}`: ", file.display());
    assert!(line.starts_with(&start), "expected `{start}...`, got: {line}");
    assert!(line.contains(value), "the value `{value}` is named: {line}");
}

/// Pairs config values outside their documented ranges, each as the key that must be named
/// and the value the message must show.
const BAD_PAIRS: &[(&str, &str, &str)] = &[
    ("[trajectory]\nazimuth_deg = inf\n", "trajectory.azimuth_deg", "inf"),
    ("[trajectory]\nazimuth_deg = nan\n", "trajectory.azimuth_deg", "NaN"),
    ("[trajectory]\nazimuth_deg = 720.0\n", "trajectory.azimuth_deg", "720"),
    ("[trajectory]\nelevation_deg = -inf\n", "trajectory.elevation_deg", "-inf"),
    ("[trajectory]\nelevation_deg = -5.0\n", "trajectory.elevation_deg", "-5"),
    ("[trajectory]\nradius_frac = 2.0\n", "trajectory.radius_frac", "2"),
    ("[trajectory]\nradius_frac = -0.1\n", "trajectory.radius_frac", "-0.1"),
    ("[trajectory]\npivot_scale = 0.0\n", "trajectory.pivot_scale", "0"),
    ("[trajectory]\npivot_scale = -1.0\n", "trajectory.pivot_scale", "-1"),
    ("[trajectory]\nmax_attempts = 0\n", "trajectory.max_attempts", "0"),
    ("[trajectory]\nmax_attempts = 4000000000\n", "trajectory.max_attempts", "4000000000"),
    ("trajectory.pivot_scale = nan\n", "trajectory.pivot_scale", "NaN"),
    ("trajectory = { radius_frac = 1.0 }\n", "trajectory.radius_frac", "1"),
    ("[covisibility]\nepsilon = nan\n", "covisibility.epsilon", "NaN"),
    ("[covisibility]\nepsilon = -1e-4\n", "covisibility.epsilon", "-0.0001"),
    ("[covisibility]\nepsilon = 0.5\n", "covisibility.epsilon", "0.5"),
    ("[covisibility.mesh]\ndiscontinuity_ratio = 0.9\n", "covisibility.mesh.discontinuity_ratio", "0.9"),
    ("[covisibility.mesh]\ndiscontinuity_ratio = inf\n", "covisibility.mesh.discontinuity_ratio", "inf"),
    ("[covisibility.mesh]\noccluder_thickness = -0.05\n", "covisibility.mesh.occluder_thickness", "-0.05"),
    ("[covisibility.mesh]\noccluder_thickness = nan\n", "covisibility.mesh.occluder_thickness", "NaN"),
    ("[covisibility.mesh]\naccelerator = \"octree\"\n", "covisibility.mesh.accelerator", "octree"),
    ("[depth_noise]\ncorrelation_px = 0\n", "depth_noise.correlation_px", "0"),
    ("[depth_noise]\nrelative_sigma = nan\n", "depth_noise.relative_sigma", "NaN"),
    ("[depth_noise]\nedge_relative_sigma = 3.0\n", "depth_noise.edge_relative_sigma", "3"),
    ("[depth_noise]\nedge_width_px = -1.0\n", "depth_noise.edge_width_px", "-1"),
    ("[depth_noise]\nmax_sigmas = 1e300\n", "depth_noise.max_sigmas", "1000000"),
    ("[depth_noise]\nsecond_depth = \"/lidar/{vide_id}\"\n", "depth_noise.second_depth", "{vide_id}"),
    ("[static_background]\nvoxel_relative = 0.0\n", "static_background.voxel_relative", "0"),
    ("[static_background]\nframe_step = 0\n", "static_background.frame_step", "0"),
    ("[static_background]\ndynamic_margin_px = 100000\n", "static_background.dynamic_margin_px", "100000"),
    ("[clip]\nlength = 0\n", "clip.length", "0"),
    ("[clip]\nstride = 0\n", "clip.stride", "0"),
    ("[clip]\nlength = -49\n", "clip.length", "-49"),
    ("[trajectory]\nazimuth_deg = \"wide\"\n", "trajectory.azimuth_deg", "wide"),
    ("[trajectory]\nazimut_deg = 30.0\n", "trajectory.azimut_deg", "azimut_deg"),
    ("[trajectory]\nazimuth_deg = 30x\n", "trajectory.azimuth_deg", "line 2"),
];

#[test]
fn every_bad_pairs_value_is_rejected_at_load_naming_file_key_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pairs.toml");
    for (text, key, value) in BAD_PAIRS {
        std::fs::write(&path, text).unwrap();
        let error = PairsConfig::from_toml_file(&path).expect_err(text);
        assert_names(&error, &path, key, value);
        assert!(first_line(&error).contains("line "), "{text:?}: the line is given: {error}");
    }
}

/// The shipped configs and the defaults are inside the documented ranges.
#[test]
fn shipped_configs_and_defaults_pass() {
    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    BuildConfig::from_toml_file(&configs.join("corpus_example.toml")).unwrap();
    for name in ["synth_default.toml", "synth_paper_size.toml"] {
        load_toml::<SynthConfig>(&configs.join(name)).unwrap();
    }
    PairsConfig::default().validate().unwrap();
    TrajectoryConfig::public_code().validate().unwrap();
    SynthConfig::default().validate().unwrap();
}

fn tiny_sequence(dir: &Path) -> datagen::io::sequence::Sequence {
    let config = SynthConfig { width: 48, height: 32, frames: 3, ..SynthConfig::default() };
    write_sequence(&config, dir, |_| {}).unwrap();
    datagen::io::sequence::read_sequence(dir).unwrap()
}

/// A config built in code gets the same checks from the library functions that take it: a
/// non-finite range used to panic in the sampler, a NaN one was silently read as 0.
#[test]
fn library_entry_points_reject_bad_configs_built_in_code() {
    let dir = tempfile::tempdir().unwrap();
    let sequence = tiny_sequence(&dir.path().join("scene"));
    let request = TrajectoryRequest { sampled: 1, explicit: Vec::new() };
    let bad = |change: fn(&mut PairsConfig)| {
        let mut config = PairsConfig::default();
        change(&mut config);
        config
    };
    for (config, key) in [
        (bad(|c| c.trajectory.azimuth_deg = f64::INFINITY), "trajectory.azimuth_deg"),
        (bad(|c| c.trajectory.azimuth_deg = f64::NAN), "trajectory.azimuth_deg"),
        (bad(|c| c.trajectory.pivot_scale = 0.0), "trajectory.pivot_scale"),
        (bad(|c| c.covisibility.epsilon = f64::NAN), "covisibility.epsilon"),
        (bad(|c| c.covisibility.mesh.occluder_thickness = -1.0), "covisibility.mesh.occluder_thickness"),
        (bad(|c| c.depth_noise.correlation_px = 0), "depth_noise.correlation_px"),
    ] {
        let error = generate_clips(&sequence, "test", &config, &request, 0).expect_err(key);
        assert!(first_line(&error).starts_with(&format!("parameter `{key}`: ")), "{error}");
    }
    let too_many = TrajectoryRequest { sampled: 1_000_000, explicit: Vec::new() };
    let error = generate_clips(&sequence, "test", &PairsConfig::default(), &too_many, 0).unwrap_err();
    assert!(first_line(&error).contains("`trajectories`"), "{error}");

    let config = TrajectoryConfig { elevation_deg: f64::INFINITY, ..TrajectoryConfig::paper() };
    let error = datagen::pairs::trajectory::sample_trajectory(
        &sequence.cameras,
        &sequence.depth[0],
        &config,
        0,
        "s",
        0,
        0,
        None,
    )
    .unwrap_err();
    assert!(first_line(&error).contains("`trajectory.elevation_deg`"), "{error}");
}

/// Synth sizes that cannot be allocated fail with a message naming the key, before any
/// allocation.
#[test]
fn absurd_synth_sizes_fail_with_a_message() {
    let small = SynthConfig { width: 64, height: 48, frames: 3, ..SynthConfig::default() };
    for (config, key) in [
        (SynthConfig { width: 2_000_000, ..small.clone() }, "width"),
        (SynthConfig { height: u32::MAX - 1, ..small.clone() }, "height"),
        (SynthConfig { width: 8192, height: 8192, frames: 1000, ..small.clone() }, "frames"),
        (SynthConfig { frames: u32::MAX, ..small.clone() }, "frames"),
        (SynthConfig { fps: f64::INFINITY, ..small.clone() }, "fps"),
        (SynthConfig { static_objects: 1_000_000_000, ..small.clone() }, "static_objects"),
    ] {
        let error = SynthScene::new(&config).expect_err(key);
        assert!(first_line(&error).starts_with(&format!("parameter `{key}`: ")), "{error}");
    }
}

#[test]
fn bad_build_config_values_name_their_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("corpus.toml");
    let source = "[[sources]]\ndataset = \"sequences\"\nroot = \"/data/seqs\"\n";
    let output = "[output]\ndir = \"/data/out\"\n";
    for (text, key, value) in [
        (format!("trajectories = 0\n{source}{output}"), "trajectories", "0"),
        (format!("trajectories = 100000\n{source}{output}"), "trajectories", "100000"),
        (format!("seed = -1\n{source}{output}"), "seed", "-1"),
        (format!("{source}{output}shard_bytes = 0\n"), "output.shard_bytes", "0"),
        (format!("{source}{output}row_group_bytes = \"big\"\n"), "output.row_group_bytes", "big"),
        (format!("{source}[output]\nshard_bytes = 10\n"), "output.dir", "missing field"),
        (format!("{source}[output]\ndir = \"\"\n"), "output.dir", "empty"),
        (format!("{source}[[sources]]\ndataset = \"davis\"\nroot = \"\"\n{output}"), "sources[1].root", "empty"),
        (format!("{source}split = \"../x\"\n{output}"), "sources[0].split", "../x"),
        (format!("{source}{output}[pairs.trajectory]\nazimuth_deg = inf\n"), "pairs.trajectory.azimuth_deg", "inf"),
        (format!("{source}{output}[pairs.covisibility]\nepsilon = -1.0\n"), "pairs.covisibility.epsilon", "-1"),
        (output.to_owned(), "sources", "missing field"),
    ] {
        std::fs::write(&path, &text).unwrap();
        let error = BuildConfig::from_toml_file(&path).expect_err(&text);
        assert_names(&error, &path, key, value);
    }
}

fn corpus_with_bad_pairs(dir: &Path) -> (PathBuf, PathBuf) {
    let root = dir.join("seqs");
    tiny_sequence(&root.join("scene_a"));
    let out = dir.join("out");
    let config = dir.join("corpus.toml");
    let text = format!(
        "[[sources]]\ndataset = \"sequences\"\nroot = {:?}\n\n[output]\ndir = {:?}\n\n[pairs.trajectory]\n\
         azimuth_deg = inf\n",
        root.display().to_string(),
        out.display().to_string()
    );
    std::fs::write(&config, text).unwrap();
    (config, out)
}

/// A non-finite trajectory range used to panic inside the first input and take the whole build
/// down; it now fails at load, before any input runs, with file and key on the first line.
#[test]
fn datagen_build_with_a_bad_pairs_config_fails_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let (config, out) = corpus_with_bad_pairs(dir.path());
    let run = datagen().args(["build", "--config"]).arg(&config).output().unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "an error, not a panic (101): {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let first = stderr.lines().next().unwrap_or_default();
    assert!(
        first.contains(&config.display().to_string()) && first.contains("key `pairs.trajectory.azimuth_deg`"),
        "{first}"
    );
    let shards = std::fs::read_dir(&out).map(|d| d.count()).unwrap_or(0);
    assert_eq!(shards, 0, "nothing was built");
}

/// The command line's first error line names the file and the key, whatever the error kind
/// (a mistyped value, an out-of-range one), and flags too large to allocate are refused.
#[test]
fn cli_errors_name_file_and_key_on_the_first_line() {
    let dir = tempfile::tempdir().unwrap();
    let synth_toml = dir.path().join("synth.toml");
    for (text, key) in [("width = 64\nheight = \"tall\"\n", "height"), ("width = 64\nframes = 0\n", "frames")] {
        std::fs::write(&synth_toml, text).unwrap();
        let run = datagen()
            .args(["synth", "--out"])
            .arg(dir.path().join("s"))
            .arg("--config")
            .arg(&synth_toml)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(1), "{stderr}");
        let first = stderr.lines().next().unwrap_or_default();
        let expected = format!("error: {}: key `{key}`: ", synth_toml.display());
        assert!(first.starts_with(&expected), "expected `{expected}...`, got: {first}");
    }

    let run = datagen().args(["synth", "--width", "2000000", "--out"]).arg(dir.path().join("s")).output().unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(1), "an error, not an allocation abort: {stderr}");
    assert!(stderr.lines().next().unwrap_or_default().contains("`width`"), "{stderr}");

    let pairs_toml = dir.path().join("pairs.toml");
    std::fs::write(&pairs_toml, "[clip]\nlength = 49\n\n[covisibility]\nepsilon = nan\n").unwrap();
    let run = datagen()
        .args(["pairs", "--out"])
        .arg(dir.path().join("shards"))
        .arg("--config")
        .arg(&pairs_toml)
        .arg(dir.path().join("missing_sequence"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    let first = stderr.lines().next().unwrap_or_default();
    assert!(first.starts_with(&format!("error: {}: key `covisibility.epsilon`: ", pairs_toml.display())), "{first}");
    assert!(first.contains("NaN") && first.contains("line 5"), "{first}");
}
